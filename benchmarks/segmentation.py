r"""The raw-sweep pipeline's object segmentation beside scikit-learn's DBSCAN and HDBSCAN.

    PYTHONPATH=.:/tmp/sklsite python benchmarks/segmentation.py --split val --pairs 10 \
        --jobs 2 --json val.json                  # the grid; its choice in val.json["choice"]
    PYTHONPATH=.:/tmp/sklsite python benchmarks/segmentation.py --split test --pairs 10 \
        --choice val.json --json test.json        # the chosen settings (default: CHOSEN below)
    python benchmarks/segmentation.py --split val --pairs 1 --scale 0.05 --segmenters own

Pairs: `jaxflow.data.synthetic_sweep.sweep_pair(split, i, FORMS[form])` for i < --pairs and each
form of --forms (generated, city). Each pair's pc1 is segmented as
`jaxflow.lidar.objects.object_flow` does it, with the pipeline's own ground (not the labels):
each sweep's ground (ground.find_ground), the ego-motion (ego.estimate), the joint ground of both
sweeps in pc1's frame (sweep._joint_ground), the heights above that surface. Every segmenter gets
the same points, pc1's points within the AV2 challenge's box (|x|, |y| <= 50 m):
  own      objects.object_groups(points, where(ground, -1, height)).without(ground): the default
           settings (8-connected 0.3 m cells seen from above of the points 0 - object_top above the
           ground, a cell's gap bridged; higher points in those cells join the object), on val
           also other cells / bridging, and on test the default always;
  dbscan   sklearn.cluster.DBSCAN on the same seed points (non-ground, 0 < height < object_top),
           on x, y, z or on x, y; the others get no group;
  hdbscan  sklearn.cluster.HDBSCAN on the same seed points (x, y, z).
Scores, per labelled instance (`instance` > 0) with at least MIN_POINTS points in the box (its
points in the box): best IoU (of the groups, over the box's points), matched (best IoU >= 0.5),
merged (the instance's dominant group, the one holding most of its points, holds >= 20% and >= 3
points of another instance, or more background points than the instance's own), split (that
group holds < 70% of the instance: points given no group count against it); by class (vehicles,
pedestrians, cyclists), by size (points) and by form. Seconds per pair of each segmenter: wall
clock of the segmentation call alone (the ground is shared), the segmenters alternating in turn
within one process (--jobs 1; timings under --jobs > 1 are not comparable).
"""

import argparse
import dataclasses
import json
import multiprocessing
import pathlib
import sys
import time

import numpy as np

if __package__ in (None, ""):  # run as a script: the repository on the path
  sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from jaxflow.data import synthetic_sweep as ss  # noqa: E402
from jaxflow.lidar import ego, ground, objects, sweep  # noqa: E402
from jaxflow.lidar.settings import DEFAULTS  # noqa: E402

BOX = ss.EVAL_BOX
MIN_POINTS = 10  # instances with fewer points in the box are not scored (counted)
CLASSES = {"vehicle": ss.REGULAR_VEHICLE, "pedestrian": ss.PEDESTRIAN, "cyclist": ss.BICYCLIST}
SIZES = ((10, 50), (50, 200), (200, 1000), (1000, None))
MATCH_IOU, SPLIT_SHARE, MERGE_SHARE, MERGE_MIN = 0.5, 0.7, 0.2, 3

# The val grid (--split val); CHOSEN: its choice (benchmarks/SEGMENTATION.md), used on test.
GRID = [("own", {})] + [("own", {"cell": c, "bridge": b}) for c in (0.2, 0.3, 0.4)
                       for b in (True, False) if (c, b) != (0.3, True)]
GRID += [("dbscan", {"eps": e, "min_samples": m, "dims": d})
         for d in (3, 2) for e in (0.5, 0.8, 1.2) for m in (3, 8)]
GRID += [("hdbscan", {"min_cluster_size": c, "min_samples": s})
         for c, s in ((10, None), (20, None), (20, 5))]
CHOSEN = [("own", {"cell": 0.2, "bridge": True}),
          ("dbscan", {"eps": 0.8, "min_samples": 3, "dims": 2}),
          ("hdbscan", {"min_cluster_size": 10, "min_samples": None})]


@dataclasses.dataclass
class Scene:
  """One pair's input to the segmenters: pc1's points in the box and their labels."""
  points: np.ndarray  # K x 3 float64
  height: np.ndarray  # K: above the pipeline's ground surface
  ground: np.ndarray  # K bool: the pipeline's ground
  instance: np.ndarray  # K (0 background)
  category: np.ndarray  # K


def pipeline_ground(pc1_Nx3, pc2_Mx3, settings=DEFAULTS):
  """(height N, ground N bool) of pc1 as raw_sweep_flow gives them to object_flow (z up)."""
  pc1, pc2 = np.asarray(pc1_Nx3, np.float64), np.asarray(pc2_Mx3, np.float64)
  surf1, g1 = ground.find_ground(pc1, "z", "pc1", settings.ground)
  surf2, g2 = ground.find_ground(pc2, "z", "pc2", settings.ground)
  fit = ego.estimate(pc1, pc2, g1, g2, {}, 0, settings=settings.ego,
                     frame_rate_hz=settings.frame_rate_hz)
  surface, g1, _ = sweep._joint_ground(pc1, pc2, fit.motion, surf1, surf2, g1, g2, "pc1",
                                       settings.ground)
  return surface.height(pc1), g1


def scene_of(split, index, form, scale=1.0) -> Scene:
  options = dataclasses.replace(ss.FORMS[form], scale=scale)
  pair = ss.sweep_pair(split, index, options)
  height, grd = pipeline_ground(pair.pc1, pair.pc2)
  box = (np.abs(pair.pc1[:, :2]) <= BOX).all(1)
  return Scene(pair.pc1[box].astype(np.float64), height[box], grd[box],
               pair.instance[box].astype(np.int64), pair.category[box].astype(np.int64))


def seeds(scene: Scene, settings=DEFAULTS.objects) -> np.ndarray:
  """What object_groups groups: the non-ground points between 0 and object_top."""
  return ~scene.ground & (scene.height > 0) & (scene.height < settings.object_top)


def segment(scene: Scene, name: str, params: dict) -> np.ndarray:
  """The group of each point (-1: none)."""
  if name == "own":
    found = objects.object_groups(scene.points, np.where(scene.ground, -1.0, scene.height),
                                  **params)
    return found.without(scene.ground).label
  low = seeds(scene)
  label = np.full(len(scene.points), -1)
  if low.sum() < 2:
    return label
  from sklearn import cluster  # noqa: PLC0415 (optional: not a dependency)
  if name == "dbscan":
    p = dict(params)
    x = scene.points[low, :p.pop("dims")]
    label[low] = cluster.DBSCAN(**p).fit_predict(x)
  elif name == "hdbscan":
    label[low] = cluster.HDBSCAN(copy=True, **params).fit_predict(scene.points[low])
  else:
    raise ValueError(f"unknown segmenter {name!r}")
  return label


def score(instance_K, category_K, label_K) -> list[dict]:
  """Per scored instance: class, points, best IoU, matched, merged, split (module docstring)."""
  instance_K, label_K = np.asarray(instance_K, np.int64), np.asarray(label_K, np.int64)
  ids, n_inst = np.unique(instance_K, return_counts=True)
  size = dict(zip(ids.tolist(), n_inst.tolist()))
  grouped = label_K >= 0
  groups, n_group = np.unique(label_K[grouped], return_counts=True)
  group_size = dict(zip(groups.tolist(), n_group.tolist()))
  pairs, inter = np.unique(np.stack([instance_K[grouped], label_K[grouped]]), axis=1,
                           return_counts=True)
  by_group = {}  # group -> {instance: points}
  for (i, g), c in zip(pairs.T.tolist(), inter.tolist()):
    by_group.setdefault(g, {})[i] = c
  out = []
  for k in ids.tolist():
    if k <= 0 or size[k] < MIN_POINTS:
      continue
    n = size[k]
    mine = {g: c[k] for g, c in by_group.items() if k in c}
    cat = int(np.bincount(category_K[instance_K == k]).argmax())
    row = {"instance": k, "category": cat, "points": n, "iou": 0.0, "matched": False,
           "merged": False, "merged_instance": False, "merged_background": False, "split": True}
    if mine:
      row["iou"] = max(c / (n + group_size[g] - c) for g, c in mine.items())
      dom = max(mine, key=mine.get)
      held = by_group[dom]
      others = any(c >= max(MERGE_MIN, MERGE_SHARE * size[j])
                   for j, c in held.items() if j not in (0, k))
      background = held.get(0, 0) > mine[dom]
      row.update(matched=row["iou"] >= MATCH_IOU, split=mine[dom] < SPLIT_SHARE * n,
                 merged=bool(others or background), merged_instance=bool(others),
                 merged_background=bool(background))
    out.append(row)
  return out


def summary(rows) -> dict:
  if not rows:
    return {"instances": 0}
  return {"instances": len(rows),
          "matched": float(np.mean([r["matched"] for r in rows])),
          "mean_iou": float(np.mean([r["iou"] for r in rows])),
          "merged": float(np.mean([r["merged"] for r in rows])),
          "merged_instance": float(np.mean([r["merged_instance"] for r in rows])),
          "merged_background": float(np.mean([r["merged_background"] for r in rows])),
          "split": float(np.mean([r["split"] for r in rows]))}


def breakdown(rows) -> dict:
  """All, by class, by size and by form."""
  out = {"all": summary(rows)}
  for name, cat in CLASSES.items():
    out[name] = summary([r for r in rows if r["category"] == cat])
  for lo, hi in SIZES:
    out[f"{lo}-{hi - 1}" if hi else f">={lo}"] = summary(
      [r for r in rows if r["points"] >= lo and (hi is None or r["points"] < hi)])
  for form in sorted({r["form"] for r in rows if "form" in r}):
    out[form] = summary([r for r in rows if r.get("form") == form])
  return out


def config_name(name, params) -> str:
  return name + "".join(f" {k}={v}" for k, v in params.items())


def run_pair(job):
  """Every config on one pair: (rows per config, seconds per config, unscored instances)."""
  split, index, form, scale, configs = job
  if any(n != "own" for n, _ in configs):
    import sklearn.cluster  # noqa: F401, PLC0415 (imported before any timing)
  scene = scene_of(split, index, form, scale)
  rows, seconds = {}, {}
  order = configs[index % len(configs):] + configs[:index % len(configs)]  # alternating
  for name, params in order:
    key = config_name(name, params)
    start = time.perf_counter()
    label = segment(scene, name, params)
    seconds[key] = time.perf_counter() - start
    rows[key] = [dict(r, form=form, pair=index) for r in
                 score(scene.instance, scene.category, label)]
  ids, n = np.unique(scene.instance[scene.instance > 0], return_counts=True)
  return rows, seconds, int((n < MIN_POINTS).sum())


def main(argv=None):
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--split", choices=ss.SPLITS, default="val")
  ap.add_argument("--pairs", type=int, default=10, help="pairs per form")
  ap.add_argument("--forms", default="generated,city")
  ap.add_argument("--scale", type=float, default=1.0, help="synthetic_sweep Options.scale")
  ap.add_argument("--segmenters", default="own,dbscan,hdbscan")
  ap.add_argument("--choice", help="a val run's JSON: its choice (test; default CHOSEN)")
  ap.add_argument("--jobs", type=int, default=1, help="pairs at once (timings: --jobs 1)")
  ap.add_argument("--json", help="write the results here")
  args = ap.parse_args(argv)
  wanted = args.segmenters.split(",")
  if args.split == "val":
    configs = GRID
  elif args.choice:
    configs = [tuple(c) for c in json.loads(pathlib.Path(args.choice).read_text())["choice"]]
  else:
    configs = CHOSEN
  if args.split == "test" and ("own", {}) not in configs:  # the pipeline's own, always
    configs = [("own", {})] + configs
  configs = [(n, p) for n, p in configs if n in wanted]
  if any(n != "own" for n, _ in configs):
    import sklearn.cluster  # noqa: F401, PLC0415 (imported before any timing)
  jobs = [(args.split, i, form, args.scale, configs)
          for form in args.forms.split(",") for i in range(args.pairs)]
  if args.jobs > 1:
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
      done = pool.map(run_pair, jobs, chunksize=1)
  else:
    done = [run_pair(j) for j in jobs]
  result = {"split": args.split, "pairs_per_form": args.pairs, "forms": args.forms.split(","),
            "scale": args.scale, "jobs": args.jobs, "min_points": MIN_POINTS,
            "unscored_small": sum(d[2] for d in done), "configs": {}}
  for name, params in configs:
    key = config_name(name, params)
    rows = [r for d in done for r in d[0][key]]
    seconds = [d[1][key] for d in done]
    result["configs"][key] = {"name": name, "params": params, "scores": breakdown(rows),
                              "seconds_per_pair": float(np.mean(seconds)),
                              "seconds_max": float(np.max(seconds))}
  if args.split == "val":  # the best of each segmenter: matched, then mean IoU
    choice = []
    for name in wanted:
      mine = [(c["scores"]["all"].get("matched", 0), c["scores"]["all"].get("mean_iou", 0),
               c["name"], c["params"]) for c in result["configs"].values() if c["name"] == name]
      if mine:
        best = max(mine, key=lambda m: m[:2])
        choice.append([best[2], best[3]])
    result["choice"] = choice
  for key, c in result["configs"].items():
    a = c["scores"]["all"]
    print(f"{key:45s} n={a['instances']:4d} matched {a.get('matched', 0):.3f} "
          f"iou {a.get('mean_iou', 0):.3f} merged {a.get('merged', 0):.3f} "
          f"split {a.get('split', 0):.3f}  {c['seconds_per_pair']:.3f} s/pair")
  if args.split == "val":
    print("choice:", result["choice"])
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(result, indent=1))
  return result


if __name__ == "__main__":
  main()
