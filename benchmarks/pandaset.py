r"""Every mover on real streets: `predict --lidar`'s method on the PandaSet runs, the generator's
test split and KITTI's halves, both directions, movers by class and speed band beside the false
alarms. Prints markdown tables, writes JSON.

    python -m benchmarks.pandaset [--only pandaset,generator,kitti] [--runs 10-21,30-41]
        [--pairs 8] [--directions forward,backward] [--seed 0] [--json OUT.json]
        [--set objects.judge.evidence=0 --set objects.part.split=False]

- pandaset: the two runs of ../shared/data/real_sweeps/pandaset/val (22 pairs, opensf region=sweep,
  lidar=ego: the pairs `evaluate.py --method lidar --max_points 0` scores) forward, and backward
  (pc1 the later sweep; 20 pairs: a run's last sweep carries no instance ids): a later point of
  track k gets the inverse of k's rigid motion (a Kabsch fit of k's labelled flow at the earlier
  sweep), any other point the ego-motion's inverse; a track without points at the earlier sweep,
  or with fewer than 3, is left out (not scored). The named movers of issue 66 (track 20d13d1d, a
  car creeping 0.14-0.24 m a frame at 4-6 m; d0da2ae7, a walker at 20 m) get a line each pair.
- generator: `--pairs` pairs of synthetic_sweep's test split (untuned: settings are chosen on val),
  forward and backward (its reverse option).
- kitti: the shared raw Velodyne scan split into two disjoint halves, the second moved by a known
  motion (2 deg yaw, (1.0, 0.1, 0.02) m; ../shared/tools/real_sweeps_check.py), and the same
  halves swapped (backward): every point is static.
Readings (scored points: non-ground, |x|, |y| <= 50 m, as the challenge's): the av2 three-way
and bucketed dynamic normalised EPE (jaxflow.evaluation.av2_eval) with movers by class and speed
band; recall: labelled moving points (|label - ego flow| >= 0.05 m) the flow moves (|flow - ego
flow| >= 0.05 m); false alarms: labelled static points the flow moves more than 5 cm from the ego
flow, on static objects (a class other than background) and on the background apart.
`--set FIELD=VALUE`: a setting of the lidar method (as predict's --method.lidar.FIELD=VALUE; the
slow movers' step off above); `--seed`: the method's sampling seed (its groups' random halves).
Seconds: the method's wall time a pair in this process (the machine is
shared: the JSON and the closing line give the load).
"""

import argparse
import json
import os
import pathlib
import platform
import time

import h5py
import numpy as np

from jaxflow import inference
from jaxflow.data import open_dataset
from jaxflow.data import synthetic_sweep as ss
from jaxflow.evaluation import av2_eval, movers
from jaxflow.geometry import rigid

SHARED = pathlib.Path(__file__).resolve().parents[2] / "shared/data/real_sweeps"
PANDASET = f"opensf:{SHARED / 'pandaset'},region=sweep,lidar=ego"
NAMED = {"20d13d1d": "creeping car", "d0da2ae7": "walker", "8ea9144b": "car passing close"}
MOVING = av2_eval.DYNAMIC_THRESHOLD  # m a frame: av2's dynamic threshold, and the false alarm's
KITTI_MOTION = rigid.Motion.of(
  [[np.cos(np.radians(2.0)), -np.sin(np.radians(2.0)), 0],
   [np.sin(np.radians(2.0)), np.cos(np.radians(2.0)), 0], [0, 0, 1]], [1.0, 0.1, 0.02])


class Tally:
  """One row's sums over its pairs: the official readings, recall and false alarms, seconds."""

  def __init__(self):
    self.breakdown, self.buckets = 0.0, 0.0
    self.counts = dict.fromkeys(("moving", "moved", "static_objects", "static_objects_moved",
                                 "background", "background_moved"), 0)
    self.pairs, self.seconds = 0, 0.0

  def add(self, flow, gt, rigid_flow, category, ego_xy, scored, seconds):
    args = (flow, gt, rigid_flow, category, ego_xy, scored)
    self.breakdown = self.breakdown + av2_eval.breakdown_sums(av2_eval.pair_labels(*args))
    self.buckets = self.buckets + av2_eval.bucketed_sums(*args)
    moving = np.linalg.norm(gt - rigid_flow, axis=1) >= MOVING
    moved = np.linalg.norm(flow - rigid_flow, axis=1) >= MOVING
    parts = {"moving": scored & moving, "static_objects": scored & ~moving & (category != 0),
             "background": scored & ~moving & (category == 0)}
    for name, points in parts.items():
      self.counts[name] += int(points.sum())
      self.counts[name + "_moved" if name != "moving" else "moved"] += int((points & moved).sum())
    self.pairs += 1
    self.seconds += seconds

  def results(self) -> dict:
    c = self.counts
    share = lambda a, b: c[a] / c[b] if c[b] else float("nan")
    out = {"pairs": self.pairs, "seconds_a_pair": self.seconds / max(self.pairs, 1),
           "recall": share("moved", "moving"),
           "false_alarms_static_objects": share("static_objects_moved", "static_objects"),
           "false_alarms_background": share("background_moved", "background"), "counts": c}
    if c["moving"] or c["background"]:
      av2 = av2_eval.breakdown_results(self.breakdown)
      bucketed = av2_eval.bucketed_results(self.buckets)
      out.update(three_way=av2["EPE 3-Way Average"], fd=av2["EPE/Foreground/Dynamic"],
                 dynamic_iou=av2["Dynamic IoU"], dynamic_norm=bucketed["dynamic_norm_epe"],
                 static_epe=bucketed["static_epe"],
                 classes={k: v["dynamic_norm_epe"] for k, v in bucketed["classes"].items()},
                 speeds=av2_eval.bucketed_by_speed(self.buckets))
    return out


def backward_pair(dataset, i):
  """Pair i of the opensf dataset taken backwards with its derived labels (module docstring), or
  None where the later sweep carries no instance ids: (pc1, pc2, flow, rigid flow, category,
  scored, ids, table)."""
  path, k0, k1 = dataset.pairs[i]
  forward = dataset[i]
  ids0, table = dataset.instances(i)
  with h5py.File(path, "r") as f:
    later = f[k1]
    if "flow_instance_id" not in later:
      return None
    pc1 = later["lidar"][()][:, :3].astype(np.float32)
    ids = later["flow_instance_id"][()].astype(np.int64)
    category = later["flow_category_indices"][()].astype(np.uint8)
    valid, ground = later["flow_is_valid"][()].astype(bool), later["ground_mask"][()].astype(bool)
    ego_motion = f[k0]["ego_motion"][()].astype(np.float64)
  keep = np.isfinite(pc1).all(1)  # region=sweep: every finite point
  pc1, ids, category = pc1[keep], ids[keep], category[keep]
  valid, ground = valid[keep], ground[keep]
  ego_back = rigid.Motion.of(ego_motion[:3, :3], ego_motion[:3, 3]).inverse()
  rigid_flow = ego_back.flow(pc1)
  flow = rigid_flow.copy()
  for track in np.unique(ids[ids > 0]):
    earlier = ids0 == track
    later_points = ids == track
    if earlier.sum() < 3:
      valid &= ~later_points  # no motion to invert: not scored
      continue
    motion = rigid.kabsch(forward.pc1[earlier], forward.pc1[earlier] + forward.flow[earlier])
    flow[later_points] = motion.inverse().flow(pc1[later_points])
  scored = valid & ~ground & (np.abs(pc1[:, :2]) <= 50.0).all(1)  # the challenge's points
  return pc1, forward.pc1, flow, rigid_flow, category, scored, ids, table


def run_pandaset(args, predictor, tallies, named_rows):
  dataset = open_dataset(PANDASET, "val")
  runs = args.runs.split(",")
  for i, (path, k0, _) in enumerate(dataset.pairs):
    if not any(run in pathlib.Path(path).stem for run in runs):
      continue
    for direction in args.directions.split(","):
      if direction == "forward":
        pair = dataset[i]
        ids, table = dataset.instances(i)
        clouds = (pair.pc1, pair.pc2, pair.flow, pair.rigid_flow, pair.category, pair.mask, ids,
                  table)
      else:
        clouds = backward_pair(dataset, i)
        if clouds is None:
          continue
      pc1, pc2, gt, rigid_flow, category, scored, ids, table = clouds
      flow, seconds = timed_flow(predictor, pc1, pc2, args.seed)
      tallies.setdefault(f"pandaset, {direction}", Tally()).add(
        flow, gt, rigid_flow, category, pc1[:, :2], scored, seconds)
      name = f"{pathlib.Path(path).stem}:{k0}"
      rows = movers.pair_movers(pc1, pc2, flow, gt, rigid_flow, scored, ids, table, name=name)
      for row in rows:
        row["direction"] = direction
      named_rows += rows
      print(f"{name} {direction}: {seconds:.1f} s; " + "; ".join(
        f"{NAMED[r['track'][:8]]} {r['track'][:8]} {r['points']} points {r['range']:.1f} m "
        f"speed {r['speed']:.2f} predicted {r['pred_speed']:.2f} EPE {r['epe']:.3f}"
        for r in rows if r["track"][:8] in NAMED), flush=True)


def run_generator(args, predictor, tallies):
  for i in range(args.pairs):
    for direction in args.directions.split(","):
      s = ss.sweep_pair("test", i, ss.Options(reverse=direction == "backward"))
      flow, seconds = timed_flow(predictor, s.pc1, s.pc2, args.seed)
      tallies.setdefault(f"generator test, {direction}", Tally()).add(
        flow, s.flow, s.ego_flow, s.category.astype(np.uint8), s.pc1[:, :2], s.eval_mask, seconds)
      print(f"{s.name}: {seconds:.1f} s", flush=True)


def run_kitti(args, predictor, tallies):
  scan = np.fromfile(SHARED / "kitti_velodyne_000002.bin", np.float32).reshape(-1, 4)[:, :3]
  half = np.random.default_rng(0).random(len(scan)) < 0.5
  first, second = scan[half], KITTI_MOTION.apply(scan[~half]).astype(np.float32)
  for direction in args.directions.split(","):
    if direction == "forward":
      pc1, pc2, motion = first, second, KITTI_MOTION
    else:
      pc1, pc2, motion = second, first, KITTI_MOTION.inverse()
    flow, seconds = timed_flow(predictor, pc1, pc2, args.seed)
    truth = motion.flow(pc1)
    scored = (np.abs(pc1[:, :2]) <= 50.0).all(1)
    category = np.zeros(len(pc1), np.uint8)  # all static: every moved point is a false alarm
    tallies.setdefault(f"KITTI halves, {direction}", Tally()).add(
      flow, truth, truth, category, pc1[:, :2], scored, seconds)
    print(f"KITTI halves {direction}: {seconds:.1f} s", flush=True)


def timed_flow(predictor, pc1, pc2, seed=0):
  start = time.perf_counter()
  flow = predictor.predict(pc1, pc2, up="z", seed=seed).flow
  return np.asarray(flow, np.float32), time.perf_counter() - start


def print_tables(results, named_rows):
  print("\n| row | pairs | three-way | FD | Dynamic IoU | dynamic normalised | recall | false "
        "alarms: static objects | background | s / pair |\n" + "|---" * 10 + "|")
  fmt = lambda r, k, f=".4f": format(r[k], f) if k in r else "-"
  for name, r in results.items():
    print(f"| {name} | {r['pairs']} | {fmt(r, 'three_way')} | {fmt(r, 'fd')} | "
          f"{fmt(r, 'dynamic_iou', '.3f')} | {fmt(r, 'dynamic_norm', '.3f')} | "
          f"{r['recall']:.3f} | {r['false_alarms_static_objects']:.4f} | "
          f"{r['false_alarms_background']:.4f} | {r['seconds_a_pair']:.1f} |")
  bands = [f"{lo:g}-{hi:g}" for lo, hi in zip(av2_eval.SPEED_BANDS, av2_eval.SPEED_BANDS[1:])]
  print("\nmovers by class and speed (m a frame): normalised EPE (points)\n| row | class | "
        + " | ".join(bands) + " |\n" + "|---" * (len(bands) + 2) + "|")
  for name, r in results.items():
    for c, band in r.get("speeds", {}).items():
      if c != "BACKGROUND" and any(b["points"] for b in band):
        print(f"| {name} | {c} | " + " | ".join(
          f"{b['dynamic_norm_epe']:.3f} ({b['points']})" if b["points"] else "-" for b in band)
          + " |")
  for direction in ("forward", "backward"):
    rows = [r for r in named_rows if r["direction"] == direction and r["track"][:8] in NAMED]
    for track, what in NAMED.items():
      mine = [r for r in rows if r["track"][:8] == track]
      if mine:
        got = sum(r["pred_speed"] >= r["speed"] / 2 for r in mine)
        print(f"{what} {track} {direction}: moved (predicted >= half its labelled speed) in {got} "
              f"of {len(mine)} pairs; EPE {np.mean([r['epe'] for r in mine]):.3f} m")


def parse_args(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--only", default="pandaset,generator,kitti",
                      help="which of pandaset, generator, kitti to run (comma separated)")
  parser.add_argument("--runs", default="10-21,30-41", help="PandaSet runs (file name parts)")
  parser.add_argument("--pairs", type=int, default=8, help="generator test pairs")
  parser.add_argument("--directions", default="forward,backward")
  parser.add_argument("--seed", type=int, default=0, help="the method's sampling seed")
  parser.add_argument("--json", default=None)
  parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                      help="a lidar method setting, as predict's --method.lidar.FIELD=VALUE")
  args = parser.parse_args(argv)
  if any("=" not in field for field in args.set):
    parser.error("--set takes FIELD=VALUE, e.g. objects.judge.evidence=150")
  unknown = set(args.only.split(",")) - {"pandaset", "generator", "kitti"}
  if unknown or not set(args.directions.split(",")) <= {"forward", "backward"}:
    parser.error("--only: pandaset, generator, kitti; --directions: forward, backward")
  return args


def main(argv=None):
  args = parse_args(argv)
  fields = dict(field.split("=", 1) for field in args.set)  # (checked and typed by the settings)
  predictor = inference.load_predictor(method="lidar", method_fields=fields)  # predict --lidar's
  tallies, named_rows, start = {}, [], time.perf_counter()
  only = args.only.split(",")
  if "pandaset" in only:
    run_pandaset(args, predictor, tallies, named_rows)
  if "generator" in only:
    run_generator(args, predictor, tallies)
  if "kitti" in only:
    run_kitti(args, predictor, tallies)
  results = {name: t.results() for name, t in tallies.items()}
  print_tables(results, named_rows)
  machine = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
             "load_average": os.getloadavg(), "seconds": time.perf_counter() - start}
  print(f"\n{machine['seconds']:.0f} s in all on {machine['cpu_count']} cores, load average "
        + " ".join(f"{v:.1f}" for v in machine["load_average"]))
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(
      {"args": vars(args), "machine": machine, "rows": results, "movers": named_rows},
      indent=2, default=float) + "\n")


if __name__ == "__main__":
  main()
