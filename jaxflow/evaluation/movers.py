"""Movers by name: each labelled moving object of an OpenSceneFlow log that carries instance ids
(`flow_instance_id`, the PandaSet files), its flow's error and where its points land.

    movers = Movers(dataset)            # evaluate.py's on_batch callback: movers.add(batch, flow)
    ... evaluate ...
    print(movers.table()); results["movers"] = movers.results()

A mover of a pair: a track whose labelled points (the pair's scored mask) move, by the median of
|label flow - ego-motion flow|, at least av2's dynamic threshold (0.05 m a frame). Its row: the
track (uuid), class (the file's label), points, range (median horizontal distance from the ego
origin, m), speed (that median, m a frame), the predicted speed, EPE (mean over its points, m) and
where its points land in the next sweep: the median distance from pc1 + flow to pc2's nearest
point for the predicted flow, the label's and the ego-motion's alone (not moved). How to read it:
a mover whose label lands close and whose prediction lands far (near the ego-motion's) was missed;
one whose prediction lands as close as its label, or closer, with a large EPE, has a label that
does not follow its points (boxes that jitter or lag); each track's summary counts both (`tracks`:
missed, label_off). The summary is printed; every pair's row is in the JSON ("movers": {"tracks":
..., "pairs": ...}).
Whole clouds only (--max_points 0; sampled ones get a note): a sampled cloud's points no longer
match the file's ids.
"""

import sys

import numpy as np
from scipy.spatial import cKDTree

from jaxflow.errors import ConfigError
from jaxflow.evaluation import av2_eval, tables


def for_spec(spec, split, num_points):
  """for_dataset of evaluate.py's --dataset SPEC (only an opensf one is opened here), or None."""
  if not spec or not str(spec).startswith("opensf:"):
    return None
  from jaxflow.data import open_dataset  # pylint: disable=import-outside-toplevel
  return for_dataset(open_dataset(spec, split=split), num_points)


def for_dataset(dataset, num_points):
  """A Movers for `dataset` if it is an opensf log whose files carry instance ids, else None; with
  sampled clouds (num_points: config.eval.num_points) None and a note on stderr saying why."""
  if not hasattr(dataset, "instances") or not len(dataset):
    return None
  if dataset.instances(0) is None:
    return None
  if num_points:
    print(f"note: {dataset.name}: its files carry instance ids; the movers by name need whole "
          "clouds (--max_points 0: a sampled cloud's points no longer match the ids), not listed",
          file=sys.stderr)
    return None
  return Movers(dataset)


def pair_movers(pc1_Nx3, pc2_Mx3, pred_Nx3, gt_Nx3, rigid_Nx3, mask_N, ids_N, table,
                ego_xy_Nx2=None, name="", threshold=av2_eval.DYNAMIC_THRESHOLD) -> list[dict]:
  """The rows of one pair's movers (the module docstring), slowest last."""
  ego_xy = pc1_Nx3[:, :2] if ego_xy_Nx2 is None else ego_xy_Nx2
  scored = np.asarray(mask_N, bool) & (ids_N > 0)
  rows, tree = [], None
  for track in np.unique(ids_N[scored]):
    points = scored & (ids_N == track)
    speed = float(np.median(np.linalg.norm(gt_Nx3[points] - rigid_Nx3[points], axis=1)))
    if speed < threshold:
      continue
    if tree is None:  # built once a pair, only where a mover is
      tree = cKDTree(pc2_Mx3)
    p = pc1_Nx3[points]
    land = {what: float(np.median(tree.query(p + flow[points])[0]))
            for what, flow in (("land_pred", pred_Nx3), ("land_label", gt_Nx3),
                               ("land_static", rigid_Nx3))}
    uuid, label, category = table[int(track) - 1]
    rows.append({
      "pair": name, "track": uuid, "label": label, "category": category,
      "points": int(points.sum()),
      "range": float(np.median(np.hypot(*ego_xy[points].T))),
      "speed": speed,
      "pred_speed": float(np.median(np.linalg.norm(pred_Nx3[points] - rigid_Nx3[points], axis=1))),
      "epe": float(np.linalg.norm(pred_Nx3[points] - gt_Nx3[points], axis=1).mean()),
      **land})
  return sorted(rows, key=lambda r: -r["speed"])


class Movers:
  """evaluate.py's on_batch callback (batch, flow B x N x 3): the movers of every real pair."""

  def __init__(self, dataset):
    self.dataset = dataset
    self.index = {f"{path}:{k0}": i for i, (path, k0, _) in enumerate(dataset.pairs)}
    self.rows = []

  def add(self, batch, pred_BxNx3):
    for b, name in enumerate(batch["names"]):
      if not batch["pair_valid"][b]:
        continue
      ids, table = self.dataset.instances(self.index[name])
      pc1 = np.asarray(batch["pc1"][b])
      if len(ids) != len(pc1):
        raise ConfigError(f"{name}: {len(pc1)} points evaluated, {len(ids)} instance ids: movers "
                          "by name need whole clouds (--max_points 0)")
      self.rows += pair_movers(pc1, np.asarray(batch["pc2"][b]), np.asarray(pred_BxNx3[b]),
                               np.asarray(batch["flow"][b]), np.asarray(batch["rigid_flow"][b]),
                               np.asarray(batch["mask"][b]) > 0, ids, table,
                               np.asarray(batch["ego_xy"][b]), name)

  def tracks(self) -> list[dict]:
    """Each track's summary over the pairs it moves in: medians of its rows (EPE: the mean),
    fastest first; `missed`: its pairs where the prediction moves it at most half its labelled
    speed and lands farther from the next sweep than the label (by over 5 mm); `label_off`: its
    pairs where the prediction lands closer than the label by 2 cm or more with an EPE of 0.1 m or
    more (the label, not the flow, is off the points)."""
    by = {}
    for row in self.rows:
      by.setdefault(row["track"], []).append(row)
    out = []
    for track, rows in by.items():
      median = lambda k, rows=rows: float(np.median([r[k] for r in rows]))
      out.append({
        "track": track, "label": rows[0]["label"], "category": rows[0]["category"],
        "pairs": len(rows), **{k: median(k) for k in ("points", "range", "speed", "pred_speed",
                                                      "land_pred", "land_label", "land_static")},
        "epe": float(np.mean([r["epe"] for r in rows])),
        "missed": sum(r["pred_speed"] <= r["speed"] / 2 and r["land_pred"] > r["land_label"] + 0.005
                      for r in rows),
        "label_off": sum(r["land_pred"] <= r["land_label"] - 0.02 and r["epe"] >= 0.1
                         for r in rows)})
    return sorted(out, key=lambda t: -t["speed"])

  def results(self) -> dict:
    return {"tracks": self.tracks(), "pairs": self.rows}

  def table(self) -> str:
    """The tracks' summary as markdown."""
    header = ("track", "class", "pairs", "points", "range m", "speed m/frame", "predicted",
              "EPE m", "lands: pred", "label", "static", "missed", "label off")
    return ("movers by name (medians over the pairs each moves in; lands: median distance of its "
            "points + flow to the next sweep; missed, label off: pairs, jaxflow.evaluation."
            "movers)\n" + tables.markdown_table(header, [(
              t["track"][:8], t["label"], str(t["pairs"]), f"{t['points']:.0f}",
              f"{t['range']:.1f}", f"{t['speed']:.3f}", f"{t['pred_speed']:.3f}",
              f"{t['epe']:.3f}", f"{t['land_pred']:.3f}", f"{t['land_label']:.3f}",
              f"{t['land_static']:.3f}", str(t["missed"]), str(t["label_off"]))
              for t in self.tracks()]))
