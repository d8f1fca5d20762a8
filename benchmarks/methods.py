r"""The three methods (network, nsfp, optimise) on real and synthetic pairs: the paper's Tables 4
and 7, our way. Prints a markdown table (EPE, AccS, AccR, outliers, seconds a pair) and writes JSON.

    python benchmarks/methods.py --json benchmarks/methods.json [--synthetic 4] [--nsfp-steps N]

Pairs: the real KITTI and FT3D samples of ../shared/data (skipped when absent) and the first
--synthetic val pairs of synthetic_things and synthetic_lidar, 8192 points a cloud (the evaluation
sampling, seed 0). The network is the shipped checkpoint. Seconds a pair are the wall time of the
compiled method (compilation excluded; for optimise the network's time is included) on this machine.
"""

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import time

import jax

from jaxflow import checkpointing, evaluation, methods
from jaxflow.data import eval_batches, open_dataset

DATA = pathlib.Path(__file__).absolute().parent.parent.parent / "shared" / "data"


def datasets(synthetic: int):
  sets = []
  kitti, ft3d = DATA / "KITTI_processed_occ_final", DATA / "FlyingThings3D_subset_processed_35m"
  if kitti.is_dir():
    sets.append(("KITTI real", f"kitti:{kitti}", "test", None))
  if ft3d.is_dir():
    sets.append(("FT3D real", f"ft3d:{ft3d}", "train_all", None))
  if synthetic:
    sets += [("synthetic_things", f"synthetic_things:{synthetic}", "val", None),
             ("synthetic_lidar", f"synthetic_lidar:{synthetic}", "val", None)]
  return sets


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--json", default=None)
  parser.add_argument("--synthetic", type=int, default=4, help="val pairs of each synthetic kind")
  parser.add_argument("--nsfp-steps", type=int, default=None, help="cap NSFP's 5000 steps")
  parser.add_argument("--methods", default="network,nsfp,optimise")
  parser.add_argument("--num-points", type=int, default=8192)
  args = parser.parse_args()
  model, params, _, _, refine = checkpointing.load_for_inference(None)
  rows, results = [], {}
  for method in args.methods.split(","):
    chosen = methods.settings(method, args.nsfp_steps if method == "nsfp" else None)
    predict = evaluation.model_predict_fn(model, 32, refine, method=method, method_settings=chosen,
                                          with_info=method != "network")
    compiled = {}  # one compilation for every dataset (same shapes)
    for name, spec, split, _ in datasets(args.synthetic):
      batches = eval_batches(open_dataset(spec, split), 1, args.num_points, seed=0)
      start = time.perf_counter()
      # pylint: disable-next=protected-access
      r = evaluation._run(predict, (params,), batches, compiled=compiled)
      r["wall_s"] = time.perf_counter() - start
      r.update(methods.describe(method, chosen))
      results[f"{method} / {name}"] = r
      rows.append((method, name, r))
      print(f"{method:8s} {name:16s} EPE {r['epe']:.4f} AccS {r['acc_strict']:.1f} "
            f"AccR {r['acc_relax']:.1f} Out {r['outliers']:.1f} "
            f"{r['ms_per_pair'] / 1000:.1f} s/pair ({r['pairs']} pairs)", flush=True)
  print("\n| method | pairs | EPE (m) | AccS (%) | AccR (%) | Outliers (%) | s / pair |")
  print("|---|---|---|---|---|---|---|")
  for method, name, r in rows:
    print(f"| {method} | {name} ({r['pairs']}) | {r['epe']:.4f} | {r['acc_strict']:.1f} | "
          f"{r['acc_relax']:.1f} | {r['outliers']:.1f} | {r['ms_per_pair'] / 1000:.1f} |")
  if args.json:
    machine = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
               "processor": platform.processor(), "jax": jax.__version__}
    pathlib.Path(args.json).write_text(json.dumps(
      {"machine": machine, "num_points": args.num_points, "results": results}, indent=2,
      default=lambda o: dataclasses.asdict(o) if dataclasses.is_dataclass(o) else str(o)) + "\n")


if __name__ == "__main__":
  main()
