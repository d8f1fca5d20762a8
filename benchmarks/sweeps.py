r"""Raw LiDAR sweeps: jaxflow.lidar.sweep on the synthetic 360-degree sweeps' TEST split and
the raw shared KITTI frame, and what each piece gains. Prints markdown tables, writes JSON.

    PYTHONPATH=. python benchmarks/sweeps.py --pairs 10 [--network-pairs 3] --json OUT.json

Rows (three-way EPE of the AV2 challenge over each pair's eval mask: non-ground, |x|, |y| <= 50 m;
FD / FS / BS averaged over the pairs that have such points, "mean" over the pairs' means):
- zero flow; the ego-motion alone (jaxflow.lidar.ego; every point static); the default pipeline
  (ego + moving objects); the same on 8192-point samples of each sweep (the network's input size);
- with --nsfp-pairs: NSFP (published settings) on the same 8192-point samples, their true ground
  points left out (the field's protocol removes the ground first; ground points are not scored),
  on the first pairs only (30-90 s a pair on the 2-core CPU);
- with --network-pairs: the pipeline with the shipped network's flow as a start, and the previous
  `predict --lidar` (a255f3d: the network on the non-ground points within 35 m, every other point
  the rigid motion fitted to its static part), both with the network alone (8192 points, 32
  iterations), on the first pairs only (a network call takes 5-80 s on a loaded 2-core CPU).
Seconds: wall time a pair in this process (the machine may be shared; the JSON says how loaded).
Both directions: with `--directions forward,backward` (the default) the default pipeline runs on
each pair taken backwards too (pc1 the later sweep: `synthetic_sweep`'s reverse option), its rows
named "..., backward". Then the official readings of the same flows (jaxflow.evaluation.av2_eval,
equal to av2's evaluator): the av2 breakdown count-weighted over the split (EPE 3-Way Average) and
the 2024 bucketed normalised EPE, overall, by class, and by class and speed band.
"""

import argparse
import json
import os
import pathlib
import platform
import time

import numpy as np

from jaxflow.data import synthetic_sweep as ss
from jaxflow.evaluation import av2_eval, metrics
from jaxflow.geometry import rigid
from jaxflow.lidar import sweep

KITTI = pathlib.Path(__file__).resolve().parents[2] / "shared/data/KITTI_processed_occ_final/000002"


def three_way(flow, s):
  return metrics.three_way_epe(flow, s.flow, s.ego_flow, s.foreground, s.eval_mask)


def subsample(s, n, seed=0):
  rng = np.random.default_rng(seed)
  i = np.sort(rng.choice(len(s.pc1), min(n, len(s.pc1)), replace=False))
  j = np.sort(rng.choice(len(s.pc2), min(n, len(s.pc2)), replace=False))
  return ss.SweepPair(s.pc1[i], s.pc2[j], s.flow[i], s.ego_flow[i], s.category[i], s.instance[i],
                      s.ground[i], s.ground2[j], s.ego_rotation, s.ego_translation, s.name)


def old_lidar(network, s):
  """The previous --lidar: network on the non-ground points within 35 m (one RANSAC plane per
  sweep), the rigid fit to its static part for the rest."""
  from jaxflow.lidar import ground  # pylint: disable=import-outside-toplevel
  k1 = ~ground.fit_ground(s.pc1).ground(s.pc1) & ground.within_range(s.pc1)
  k2 = ~ground.fit_ground(s.pc2).ground(s.pc2) & ground.within_range(s.pc2)
  kept = network(s.pc1[k1], s.pc2[k2])
  motion = rigid.fit_static_motion(s.pc1[k1], kept)
  flow = motion.flow(s.pc1)
  flow[k1] = kept
  return flow


def table(rows):
  out = ["| method | pairs | EPE FD | EPE FS | EPE BS | three-way | EPE all | s / pair |",
         "|---|---|---|---|---|---|---|---|"]
  for name, r in rows.items():
    out.append(f"| {name} | {r['pairs']} | {r['fd']:.4f} | {r['fs']:.4f} | {r['bs']:.4f} | "
               f"{r['mean']:.4f} | {r['epe']:.4f} | {r['seconds']:.1f} |")
  return "\n".join(out)


def parse_args():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--pairs", type=int, default=10)
  parser.add_argument("--network-pairs", type=int, default=0)
  parser.add_argument("--nsfp-pairs", type=int, default=0)
  parser.add_argument("--split", default="test")
  parser.add_argument("--directions", default="forward,backward",
                      help="forward, backward or both: backward runs the default pipeline on each "
                      "pair taken backwards")
  parser.add_argument("--json", default=None)
  return parser.parse_args()


def methods_of(args):
  """{row: (flow of a SweepPair, on its 8192-point sample?, how many pairs it runs on)}, in the
  tables' order."""
  default = lambda s: sweep.raw_sweep_flow(None, s.pc1, s.pc2)[0]
  methods = {
    "zero flow": (lambda s: np.zeros_like(s.pc1), False, args.pairs),
    "ego-motion alone": (lambda s: sweep.raw_sweep_flow(None, s.pc1, s.pc2,
                                                        moving_objects=False)[0], False, args.pairs),
    "ego + objects (default)": (default, False, args.pairs),
    "ego + objects, 8192-point sweeps": (default, True, args.pairs),
  }
  if args.network_pairs:
    from jaxflow import inference  # pylint: disable=import-outside-toplevel
    predictor = inference.load_predictor(method="network")
    network = lambda a, b: predictor(a, b)
    methods["ego + objects, network start"] = (lambda s: sweep.raw_sweep_flow(
      network, s.pc1, s.pc2, use_network=True)[0], False, args.network_pairs)
    methods["previous --lidar (network, rigid fit)"] = (lambda s: old_lidar(network, s), False,
                                                        args.network_pairs)
  if args.nsfp_pairs:
    from jaxflow import inference  # pylint: disable=import-outside-toplevel
    nsfp = inference.load_predictor(method="nsfp")

    def nsfp_flow(pair):  # ground points get zero flow: they are not scored
      flow = np.zeros_like(pair.pc1)
      flow[~pair.ground] = nsfp(pair.pc1[~pair.ground], pair.pc2[~pair.ground2])
      return flow

    methods["nsfp, 8192-point sweeps, ground left out"] = (nsfp_flow, True, args.nsfp_pairs)
  return methods


BACKWARD = ", backward"  # the suffix of a row run on the pairs taken backwards


def score_pairs(args, methods):
  """({row: [three-way EPE, EPE and seconds of each pair]}, {row: [summed av2 breakdown, summed
  buckets]}) over the split's first args.pairs pairs, each printed as it is done."""
  directions = args.directions.split(",")
  if not set(directions) <= {"forward", "backward"} or not directions:
    raise SystemExit(f"--directions: forward, backward or both, got {args.directions!r}")
  rows = {}
  if "forward" in directions:
    rows.update({name: (m, ss.Options()) for name, m in methods.items()})
  if "backward" in directions:
    rows["ego + objects (default)" + BACKWARD] = (methods["ego + objects (default)"],
                                                   ss.Options(reverse=True))
  per = {k: [] for k in rows}
  official = {k: [0.0, 0.0] for k in rows}
  for i in range(args.pairs):
    built = {}
    for name, ((fn, sampled, pairs), options) in rows.items():
      if i >= pairs:
        continue
      s = built.setdefault(options.reverse, ss.sweep_pair(args.split, i, options))
      pair = subsample(s, 8192) if sampled else s
      start = time.perf_counter()
      flow = fn(pair)
      seconds = time.perf_counter() - start
      r = three_way(flow, pair)
      r["epe"] = float(np.linalg.norm(flow - pair.flow, axis=1).mean())
      r["seconds"] = seconds
      per[name].append(r)
      args_av2 = (flow, pair.flow, pair.ego_flow, pair.category, pair.pc1[:, :2], pair.eval_mask)
      official[name][0] += av2_eval.breakdown_sums(av2_eval.pair_labels(*args_av2))
      official[name][1] += av2_eval.bucketed_sums(*args_av2)
      print(f"{s.name} {len(s.pc1)} points, {name}: "
            + " ".join(f"{k} {v:.4f}" for k, v in r.items()), flush=True)
  return per, official


def official_table(per, official):
  """Prints the official readings (av2 breakdown, bucketed overall and by class) of each row;
  returns them."""
  av2_rows = {}
  print("\n| method | pairs | av2 EPE 3-Way Average | FD | FS | BS | Dynamic IoU | bucketed static "
        "EPE | bucketed dynamic normalised EPE |\n|---|---|---|---|---|---|---|---|---|")
  for name, (breakdown, buckets) in official.items():
    if not per[name]:
      continue
    r, b = av2_eval.breakdown_results(breakdown), av2_eval.bucketed_results(buckets)
    av2_rows[name] = {"av2": r, "bucketed": b}
    print(f"| {name} | {len(per[name])} | {r['EPE 3-Way Average']:.4f} | "
          f"{r['EPE/Foreground/Dynamic']:.4f} | {r['EPE/Foreground/Static']:.4f} | "
          f"{r['EPE/Background/Static']:.4f} | {r['Dynamic IoU']:.3f} | {b['static_epe']:.4f} | "
          f"{b['dynamic_norm_epe']:.4f} |")
  classes = [c for c in av2_eval.META_CLASSES if c != "BACKGROUND"]
  print("\nbucketed dynamic normalised EPE by class (points)\n| method | "
        + " | ".join(classes) + " |\n" + "|---" * (len(classes) + 1) + "|")
  for name, rows in av2_rows.items():
    by = rows["bucketed"]["classes"]
    print(f"| {name} | " + " | ".join(f"{by[c]['dynamic_norm_epe']:.3f} ({by[c]['points']})"
                                      for c in classes) + " |")
  speed_table(official, av2_rows, classes)
  return av2_rows


def speed_table(official, av2_rows, classes):
  """Prints each row's movers by class and speed band (av2_eval.bucketed_by_speed), stored in
  av2_rows[row]["speeds"]."""
  bands = [f"{lo:g}-{hi:g}" for lo, hi in zip(av2_eval.SPEED_BANDS, av2_eval.SPEED_BANDS[1:])]
  print("\nmovers by class and speed (m a frame): normalised EPE / EPE m (points)\n| method | "
        "class | " + " | ".join(bands) + " |\n" + "|---" * (len(bands) + 2) + "|")
  for name in av2_rows:
    by = av2_eval.bucketed_by_speed(official[name][1])
    av2_rows[name]["speeds"] = {c: by[c] for c in classes}
    for c in classes:
      if any(b["points"] for b in by[c]):
        print(f"| {name} | {c} | " + " | ".join(
          f"{b['dynamic_norm_epe']:.3f} / {b['epe']:.3f} ({b['points']})" if b["points"] else "-"
          for b in by[c]) + " |")


def kitti_frame():
  """The pipeline on the shared raw KITTI frame (up y), printed; {} where it is not there."""
  if not (KITTI / "pc1.npy").exists():
    return {}
  from jaxflow.data.readers import kitti_keep  # pylint: disable=import-outside-toplevel
  raw1, raw2 = np.load(KITTI / "pc1.npy"), np.load(KITTI / "pc2.npy")  # camera axes, rows match
  keep = kitti_keep(raw1, raw2)
  start = time.perf_counter()
  flow, info = sweep.raw_sweep_flow(None, raw1, raw2, up="y")
  kitti = {"epe_loader_points": float(np.linalg.norm(flow - (raw2 - raw1), axis=1)[keep].mean()),
           "seconds": time.perf_counter() - start, "points": len(raw1), "note": info.note()}
  print(f"\nKITTI 000002 raw frame (up y): EPE on the loader's {keep.sum()} points "
        f"{kitti['epe_loader_points']:.4f} m, {kitti['seconds']:.1f} s\n{info.note()}")
  return kitti


def main():
  args = parse_args()
  per, official = score_pairs(args, methods_of(args))
  rows = {}
  for name, rs in per.items():
    if rs:
      rows[name] = {k: float(np.nanmean([r[k] for r in rs])) for k in rs[0]}
      rows[name]["pairs"] = len(rs)
  print(f"\nsynthetic_sweep {args.split} pairs 0-{args.pairs - 1}\n" + table(rows))
  av2_rows = official_table(per, official)
  kitti = kitti_frame()
  if args.json:
    machine = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
               "load_average": os.getloadavg()}
    pathlib.Path(args.json).write_text(json.dumps(
      {"machine": machine, "split": args.split, "rows": rows, "per_pair": per, "kitti": kitti,
       "official": av2_rows},
      indent=2) + "\n")


if __name__ == "__main__":
  main()
