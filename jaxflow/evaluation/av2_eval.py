"""The Argoverse 2 scene-flow numbers as the official evaluators compute them.

1. The av2 breakdown (`av2.evaluation.scene_flow.eval`: `compute_metrics` per example, then
   `results_to_dict`): EPE, Accuracy Strict / Relax, Angle Error per Background/Foreground x
   Dynamic/Static x Close/Far (and per class x motion), each averaged over the split weighted by
   point COUNT (every point counts once, whatever its pair); "Dynamic IoU"; "EPE 3-Way Average" =
   the mean of EPE/Foreground/Dynamic, EPE/Foreground/Static and EPE/Background/Static (the 2023
   ranking). Points: the pair's evaluated points with valid flow. Foreground: av2 category != 0;
   dynamic: |gt - ego-motion flow| >= 0.05 m; Close: |x|, |y| <= 35 m in the ego frame. As the
   challenge's files do, the flows are rounded to float16 first (predictions and annotations), so
   av2's evaluator on `jaxflow.evaluation.submission`'s export gives the same numbers.
2. The bucketed normalised EPE of the 2024 challenge (`bucketed-scene-flow-eval`,
   `BucketedEPEEvaluator` with its av2 meta-classes): points with valid flow and
   max(|x|, |y|) < 35 m; speed = |gt - ego-motion flow| (m a frame) in 51 buckets (edges
   linspace(0, 2, 51) and infinity); per meta-class and bucket the mean EPE and mean speed over
   the split (count-weighted); a class's static EPE is its first bucket's mean EPE, its dynamic
   error the mean over its other non-empty buckets of mean EPE / mean speed; the split's numbers are
   the means over the classes that have them. Categories outside the meta-classes (road signs,
   animals) are left out, as there. Computed on the flows as given (no float16).

OpenSceneFlow's local reading (35 m disc, per-frame means) is
`jaxflow.evaluation.metrics.three_way_epe`.
"""

import numpy as np

# av2's CATEGORY_TO_INDEX: the index of a name is its position ("NONE" = 0, background).
CATEGORIES = (
  "NONE", "ANIMAL", "ARTICULATED_BUS", "BICYCLE", "BICYCLIST", "BOLLARD", "BOX_TRUCK", "BUS",
  "CONSTRUCTION_BARREL", "CONSTRUCTION_CONE", "DOG", "LARGE_VEHICLE", "MESSAGE_BOARD_TRAILER",
  "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MOTORCYCLE", "MOTORCYCLIST", "OFFICIAL_SIGNALER",
  "PEDESTRIAN", "RAILED_VEHICLE", "REGULAR_VEHICLE", "SCHOOL_BUS", "SIGN", "STOP_SIGN",
  "STROLLER", "TRAFFIC_LIGHT_TRAILER", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER", "WHEELCHAIR",
  "WHEELED_DEVICE", "WHEELED_RIDER")
DYNAMIC_THRESHOLD = 0.05  # m a frame
CLOSE_M = 35.0  # Close: |x|, |y| <= this (av2); the bucketed distance: max(|x|, |y|) < this
TIME_DELTA = 0.1  # s between sweeps: the time axis of av2's space-time angle
EPS = 1e-10  # av2's relative-error epsilon

# (class, motion, distance) in the order av2's compute_metrics lists them.
SUBSETS = tuple((c, m, d) for c in ("Background", "Foreground") for m in ("Dynamic", "Static")
                for d in ("Close", "Far"))
METRICS = (("EPE", "EPE"), ("ACCURACY_STRICT", "Accuracy Strict"),
           ("ACCURACY_RELAX", "Accuracy Relax"), ("ANGLE_ERROR", "Angle Error"))
_SUMS = ("count", *(m for m, _ in METRICS), "TP", "TN", "FP", "FN")  # columns of breakdown sums

# bucketed-scene-flow-eval's BUCKETED_METACATAGORIES for av2 (its "BACKGROUND" is index 0).
META_CLASSES = {
  "BACKGROUND": ("NONE",),
  "CAR": ("REGULAR_VEHICLE",),
  "OTHER_VEHICLES": ("BOX_TRUCK", "LARGE_VEHICLE", "RAILED_VEHICLE", "TRUCK", "TRUCK_CAB",
                     "VEHICULAR_TRAILER", "ARTICULATED_BUS", "BUS", "SCHOOL_BUS"),
  "PEDESTRIAN": ("PEDESTRIAN", "STROLLER", "WHEELCHAIR", "OFFICIAL_SIGNALER"),
  "WHEELED_VRU": ("BICYCLE", "BICYCLIST", "MOTORCYCLE", "MOTORCYCLIST", "WHEELED_DEVICE",
                  "WHEELED_RIDER"),
}
BUCKET_EDGES = np.concatenate([np.linspace(0.0, 2.0, 51), [np.inf]])  # 51 buckets
_META_OF = np.full(len(CATEGORIES), -1)  # category index -> meta-class row (-1: left out)
for _row, _names in enumerate(META_CLASSES.values()):
  _META_OF[[CATEGORIES.index(n) for n in _names]] = _row


def point_metrics(pred_Nx3, gt_Nx3) -> dict:
  """av2's per-point EPE, strict / relaxed accuracy (0/1) and space-time angle (rad), float64."""
  pred, gt = np.asarray(pred_Nx3, np.float64), np.asarray(gt_Nx3, np.float64)
  err = np.linalg.norm(pred - gt, axis=-1)
  rel = err / (np.linalg.norm(gt, axis=-1) + EPS)
  st_pred = np.pad(pred, ((0, 0), (0, 1)), constant_values=TIME_DELTA)
  st_gt = np.pad(gt, ((0, 0), (0, 1)), constant_values=TIME_DELTA)
  cos = np.einsum("nd,nd->n", st_pred / np.linalg.norm(st_pred, axis=-1, keepdims=True),
                  st_gt / np.linalg.norm(st_gt, axis=-1, keepdims=True))
  return {"EPE": err, "ACCURACY_STRICT": ((err < 0.05) | (rel < 0.05)).astype(np.float64),
          "ACCURACY_RELAX": ((err < 0.1) | (rel < 0.1)).astype(np.float64),
          "ANGLE_ERROR": np.arccos(np.clip(cos, -1.0, 1.0))}


def pair_labels(pred_Nx3, gt_Nx3, rigid_Nx3, category_N, ego_xy_Nx2, valid_N) -> dict:
  """What av2's files hold for one pair: `pred` and `gt` (float16), `pred_dynamic` (|pred - rigid|
  >= 0.05: the prediction's own motion segmentation), `is_dynamic`, `is_close`, `category`
  (uint8) and `is_valid`, one entry per point."""
  rigid = np.asarray(rigid_Nx3, np.float64)
  gt = np.asarray(gt_Nx3, np.float32)
  pred = np.asarray(pred_Nx3, np.float32)
  return {"pred": pred.astype(np.float16), "gt": gt.astype(np.float16),
          "pred_dynamic": np.linalg.norm(pred - rigid, axis=-1) >= DYNAMIC_THRESHOLD,
          "is_dynamic": np.linalg.norm(gt - rigid, axis=-1) >= DYNAMIC_THRESHOLD,
          "is_close": (np.abs(np.asarray(ego_xy_Nx2)) <= CLOSE_M).all(-1),
          "category": np.asarray(category_N).astype(np.uint8),
          "is_valid": np.asarray(valid_N).astype(bool)}


def breakdown_sums(labels: dict) -> np.ndarray:
  """len(SUBSETS) x len(_SUMS): per subset its point count, the sums of the four metrics and the
  TP / TN / FP / FN of the dynamic segmentation, over the valid points of one pair
  (`pair_labels`)."""
  v = labels["is_valid"]
  per_point = point_metrics(labels["pred"][v], labels["gt"][v])
  fg, dyn, close = labels["category"][v] != 0, labels["is_dynamic"][v], labels["is_close"][v]
  pred_dyn = labels["pred_dynamic"][v]
  out = np.zeros((len(SUBSETS), len(_SUMS)))
  for s, (c, m, d) in enumerate(SUBSETS):
    sel = ((fg if c == "Foreground" else ~fg) & (dyn if m == "Dynamic" else ~dyn)
           & (close if d == "Close" else ~close))
    p, g = pred_dyn[sel], dyn[sel]
    out[s] = [sel.sum(), *(per_point[k][sel].sum() for k, _ in METRICS),
              (p & g).sum(), (~p & ~g).sum(), (p & ~g).sum(), (~p & g).sum()]
  return out


def breakdown_results(sums: np.ndarray) -> dict:
  """av2's `results_to_dict` from the summed `breakdown_sums`: the same keys, count-weighted."""
  col = {k: i for i, k in enumerate(_SUMS)}
  out = {}

  def mean(rows, metric):
    count = sums[rows, 0].sum()
    return float(sums[rows, col[metric]].sum() / count) if count else float("nan")

  for metric, title in METRICS:
    for s, subset in enumerate(SUBSETS):
      if subset[:2] != ("Background", "Dynamic"):
        out[f"{title}/{'/'.join(subset)}"] = mean([s], metric)
  for metric, title in METRICS:
    for c, m in sorted({s[:2] for s in SUBSETS} - {("Background", "Dynamic")}):
      rows = [i for i, s in enumerate(SUBSETS) if s[:2] == (c, m)]
      out[f"{title}/{c}/{m}"] = mean(rows, metric)
  tp, fp, fn = (sums[:, col[k]].sum() for k in ("TP", "FP", "FN"))
  out["Dynamic IoU"] = float(tp / (tp + fp + fn)) if tp + fp + fn else float("nan")
  out["EPE 3-Way Average"] = (out["EPE/Foreground/Dynamic"] + out["EPE/Foreground/Static"]
                              + out["EPE/Background/Static"]) / 3
  return out


def bucketed_sums(pred_Nx3, gt_Nx3, rigid_Nx3, category_N, ego_xy_Nx2, valid_N) -> np.ndarray:
  """len(META_CLASSES) x 51 x 3: per meta-class and speed bucket the count, the sum of EPE and the
  sum of speeds |gt - rigid| over one pair's valid points with max(|x|, |y|) < 35 m."""
  pred, gt = np.asarray(pred_Nx3, np.float64), np.asarray(gt_Nx3, np.float64)
  meta = _META_OF[np.asarray(category_N, np.int64)]
  keep = (np.asarray(valid_N).astype(bool) & (meta >= 0)
          & (np.abs(np.asarray(ego_xy_Nx2)).max(-1) < CLOSE_M))
  speed = np.linalg.norm(gt - np.asarray(rigid_Nx3, np.float64), axis=-1)[keep]
  err = np.linalg.norm(pred - gt, axis=-1)[keep]
  bucket = np.searchsorted(BUCKET_EDGES, speed, side="right") - 1  # edges[b] <= speed < edges[b+1]
  out = np.zeros((len(META_CLASSES), len(BUCKET_EDGES) - 1, 3))
  np.add.at(out, (meta[keep], bucket), np.stack([np.ones_like(err), err, speed], -1))
  return out


def bucketed_results(sums: np.ndarray) -> dict:
  """{"classes": {meta-class: {"static_epe", "dynamic_norm_epe", "points"}}, "static_epe",
  "dynamic_norm_epe"} from the summed `bucketed_sums` (NaN where a class has no such points)."""
  count = sums[..., 0]
  with np.errstate(invalid="ignore", divide="ignore"):
    epe, speed = sums[..., 1] / count, sums[..., 2] / count  # NaN where empty
    norm = epe[:, 1:] / speed[:, 1:]
  classes = {}
  for row, name in enumerate(META_CLASSES):
    dyn = norm[row][~np.isnan(norm[row])]
    classes[name] = {"static_epe": float(epe[row, 0]),
                     "dynamic_norm_epe": float(dyn.mean()) if len(dyn) else float("nan"),
                     "points": int(count[row].sum())}

  def nanmean(key):
    values = [c[key] for c in classes.values() if not np.isnan(c[key])]
    return float(np.mean(values)) if values else float("nan")

  return {"classes": classes, "static_epe": nanmean("static_epe"),
          "dynamic_norm_epe": nanmean("dynamic_norm_epe")}


SPEED_BANDS = (0.04, 0.32, 1.0, 2.0, np.inf)  # m a frame: bands of whole buckets, slowest first


def bucketed_by_speed(sums: np.ndarray, bands=SPEED_BANDS) -> dict:
  """{meta-class: [{"speeds": (lo, hi), "points", "epe", "dynamic_norm_epe"}, ...]}: the summed
  `bucketed_sums` of each class's moving points in coarser speed bands (edges on the buckets'),
  so the slow movers the metric weighs most are seen apart: a band's mean EPE, and its normalised
  EPE as the metric takes it (the mean over its non-empty buckets of mean EPE / mean speed; NaN
  where the band is empty)."""
  out = {}
  for row, name in enumerate(META_CLASSES):
    out[name] = []
    for lo, hi in zip(bands[:-1], bands[1:]):
      inside = (BUCKET_EDGES[:-1] >= lo - 1e-9) & (BUCKET_EDGES[:-1] < hi - 1e-9)
      count, err, speed = sums[row, inside].T
      full = count > 0
      out[name].append({
        "speeds": (float(lo), float(hi)), "points": int(count.sum()),
        "epe": float(err.sum() / count.sum()) if full.any() else float("nan"),
        "dynamic_norm_epe": (float(np.mean(err[full] / speed[full])) if full.any()
                             else float("nan"))})
  return out


class Official:
  """Both official readings over the pairs of evaluation batches: `add(pred, batch)` per batch (a
  batch without av2 labels, 'category' and 'ego_xy', is ignored), `reduce(sum_fn)` in a run over
  many processes, `results()` at the end: {"av2": {results_to_dict's keys..., "pairs", "points"},
  "bucketed": bucketed_results(...)}, or {} when no batch had labels. `on_pair(name, labels)`, if
  given, receives every real pair's `pair_labels` (jaxflow.evaluation.submission writes them)."""

  def __init__(self, on_pair=None):
    self.breakdown = np.zeros((len(SUBSETS), len(_SUMS)))
    self.buckets = np.zeros((len(META_CLASSES), len(BUCKET_EDGES) - 1, 3))
    self.pairs = 0
    self.on_pair = on_pair

  def add(self, pred_BxNx3, batch: dict):
    if "category" not in batch or "rigid_flow" not in batch:
      return
    pred = np.asarray(pred_BxNx3)
    for i, real in enumerate(np.asarray(batch["pair_valid"])):
      if not real:
        continue
      args = (pred[i], batch["flow"][i], batch["rigid_flow"][i], batch["category"][i],
              batch["ego_xy"][i], np.asarray(batch["mask"][i]) > 0)
      labels = pair_labels(*args)
      self.breakdown += breakdown_sums(labels)
      self.buckets += bucketed_sums(*args)
      self.pairs += 1
      if self.on_pair is not None:
        self.on_pair(batch["names"][i], labels)

  def reduce(self, sum_fn):
    """Replaces the sums by `sum_fn` of them (the sum over processes)."""
    flat = sum_fn([*self.breakdown.ravel(), *self.buckets.ravel(), self.pairs])
    flat = np.asarray(flat, np.float64)
    n = self.breakdown.size
    self.breakdown = flat[:n].reshape(self.breakdown.shape)
    self.buckets = flat[n:n + self.buckets.size].reshape(self.buckets.shape)
    self.pairs = int(flat[-1])

  def results(self) -> dict:
    if not self.pairs:
      return {}
    av2 = {**breakdown_results(self.breakdown), "pairs": self.pairs,
           "points": int(self.breakdown[:, 0].sum())}
    return {"av2": av2, "bucketed": {**bucketed_results(self.buckets), "pairs": self.pairs,
                                     "speeds": bucketed_by_speed(self.buckets)}}


def challenge_points(dataset) -> bool:
  """Whether a dataset is scored on the Argoverse 2 challenge's points: opensf's region=challenge
  and region=sweep, and any reader without that option (synthetic_sweep's mask is those points)."""
  return getattr(dataset, "options", {}).get("region", "challenge") in ("challenge", "sweep")


def format_results(results: dict, dataset=None) -> str:
  """The av2 breakdown (count-weighted over the split), the bucketed EPE of `results`
  (Official.results()) and its movers by class and speed band as tables; a last line says when `dataset` is not read on the
  challenge's points (opensf without region=challenge)."""
  from jaxflow.evaluation import tables  # pylint: disable=import-outside-toplevel

  r, rows = results["av2"], []
  for c, m in (("Foreground", "Dynamic"), ("Foreground", "Static"), ("Background", "Static")):
    rows.append((f"{c}/{m}", *(f"{r[f'EPE/{c}/{m}{d}']:.4f}" for d in ("", "/Close", "/Far")),
                 f"{r[f'Accuracy Strict/{c}/{m}']:.4f}", f"{r[f'Accuracy Relax/{c}/{m}']:.4f}",
                 f"{r[f'Angle Error/{c}/{m}']:.4f}"))
  rows.append(("EPE 3-Way Average", f"{r['EPE 3-Way Average']:.4f}", "", "", "", "", ""))
  rows.append(("Dynamic IoU", f"{r['Dynamic IoU']:.4f}", "", "", "", "", ""))
  head = (f"av2 official: {r['pairs']} pairs, {r['points']} points", "EPE", "EPE Close",
          "EPE Far", "AccS", "AccR", "Angle")
  b = results["bucketed"]
  brows = [(k, f"{v['static_epe']:.4f}", f"{v['dynamic_norm_epe']:.4f}", str(v["points"]))
           for k, v in b["classes"].items()]
  brows.append(("mean", f"{b['static_epe']:.4f}", f"{b['dynamic_norm_epe']:.4f}", ""))
  bhead = ("bucketed 2024 (35 m box)", "static EPE", "dynamic normalised EPE", "points")
  text = tables.markdown_table(head, rows) + "\n" + tables.markdown_table(bhead, brows)
  if "speeds" in b:  # the movers by speed band: what a class's dynamic figure is made of
    bands = SPEED_BANDS
    shead = ("movers by speed (m a frame)",
             *(f"{lo:g}-{hi:g}: norm. EPE (points)" for lo, hi in zip(bands, bands[1:])))
    srows = [(k, *(f"{c['dynamic_norm_epe']:.3f} ({c['points']})" if c["points"] else "-"
                   for c in v)) for k, v in b["speeds"].items()
             if k != "BACKGROUND" and any(c["points"] for c in v)]
    if srows:
      text += "\n" + tables.markdown_table(shead, srows)
  on_challenge = r.get("challenge_points", True) if dataset is None else challenge_points(dataset)
  if not on_challenge:
    text += ("\nnote: on the reader's points (ground removed, the max_range disc), not the "
             "challenge's: open the dataset with region=challenge (region=sweep: whole raw sweeps "
             "in, scored on the challenge's points) for those")
  return text
