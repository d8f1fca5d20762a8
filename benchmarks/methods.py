r"""The three methods (network, nsfp, optimise) on real and synthetic pairs: the paper's Tables 4
and 7, our way. Prints a markdown table (EPE, AccS, AccR, outliers, seconds a pair) and writes JSON.

    python benchmarks/methods.py --json benchmarks/methods.json [--synthetic 4] [--nsfp-steps N]

Pairs: the real KITTI and FT3D samples of ../shared/data (skipped when absent; FT3D's 21 pairs are
its "train_all" and "val" splits read one after the other, each pair's EPE in the JSON) and the
first --synthetic val pairs of synthetic_things and synthetic_lidar, 8192 points a cloud (the
evaluation sampling, seed 0). The network is the shipped checkpoint. Seconds a pair are the wall
time of the compiled method (compilation excluded; for optimise the network's time is included) on
this machine. `--no-bodies`: optimise without its rigid bodies (what jaxflow.refine.bodies gains).
"""

import argparse
import dataclasses
import itertools
import json
import os
import pathlib
import platform
import time

import jax
import numpy as np

from jaxflow.runtime import host_memory
from jaxflow.data import eval_batches, open_dataset
from jaxflow.evaluation import evaluator
from jaxflow.methods import registry
from jaxflow.network import checkpointing

DATA = pathlib.Path(__file__).absolute().parent.parent.parent / "shared" / "data"


def datasets(synthetic: int):
  sets = []
  kitti, ft3d = DATA / "KITTI_processed_occ_final", DATA / "FlyingThings3D_subset_processed_35m"
  if kitti.is_dir():
    sets.append(("KITTI real", f"kitti:{kitti}", "test", None))
  if ft3d.is_dir():
    sets.append(("FT3D real", f"ft3d:{ft3d}", ("train_all", "val"), None))
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
  parser.add_argument("--no-bodies", action="store_true",
                      help="optimise without its rigid bodies (jaxflow.refine.bodies): their gain")
  parser.add_argument("--host-memory", default=host_memory.RELEASE, choices=host_memory.CHOICES,
                      help="malloc releases freed memory (evaluate.py's default) or keeps it")
  args = parser.parse_args()
  host_memory.keep(args.host_memory)
  model, params, _, _, refine = checkpointing.load_for_inference(None)
  rows, results = [], {}
  for method in args.methods.split(","):
    chosen = registry.settings(method, args.nsfp_steps if method == "nsfp" else None)
    if method == "optimise" and args.no_bodies:
      chosen = dataclasses.replace(chosen, bodies=None)
    predict = registry.model_predict_fn(model, 32, refine, method=method, method_settings=chosen,
                                          with_info=method != "network")
    compiled = {}  # one compilation for every dataset (same shapes)
    for name, spec, splits, _ in datasets(args.synthetic):
      splits = splits if isinstance(splits, tuple) else (splits,)
      per_pair = {}

      def record(batch, flow, per_pair=per_pair):  # each pair's EPE (batches of one pair)
        error = np.linalg.norm(flow[0] - batch["flow"][0], axis=-1)
        per_pair[batch["names"][0]] = float(np.mean(error, where=batch["mask"][0] > 0))

      batches = itertools.chain(*(eval_batches(open_dataset(spec, split), 1, args.num_points,
                                               seed=0) for split in splits))
      start = time.perf_counter()
      # pylint: disable-next=protected-access
      r = evaluator._run(predict, (params,), batches, compiled=compiled, on_batch=(record,))
      r["wall_s"] = time.perf_counter() - start
      r["per_pair_epe"] = per_pair
      r.update(registry.describe(method, chosen))
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
