r"""Where `optimise`'s seconds go, and what a second `predict` run costs: the profile of
benchmarks/SPEED.md.

    python benchmarks/speed.py --json benchmarks/speed.json

1. Stages: the real KITTI and FT3D pairs of ../shared/data (8192 points a cloud, the evaluation
   sampling, seed 0), the shipped checkpoint. Each pair runs twice, the second run is timed stage
   by stage (optimise.optimise_flow's `seconds`: every stage waited for), EPE of the result.
2. Commands: `python -m jaxflow.predict` on KITTI 000002's clouds three times in new processes
   (an empty compilation cache, the same cache again, and `--compilation_cache off`), wall seconds
   of the whole command.
"""

import argparse
import itertools
import json
import os
import pathlib
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxflow.data import eval_batches, open_dataset
from jaxflow.methods import optimise, registry
from jaxflow.network import checkpointing

DATA = pathlib.Path(__file__).absolute().parent.parent.parent / "shared" / "data"
ROOT = pathlib.Path(__file__).absolute().parent.parent


def stages(pairs: int | None):
  model, params, _, _, refine = checkpointing.load_for_inference(None)
  chosen = registry.settings("optimise")
  network = jax.jit(registry.network_for(model, 32, refine)(chosen.start_iters,
                                                            chosen.start_candidates))
  sets = [("KITTI", f"kitti:{DATA / 'KITTI_processed_occ_final'}", ("test",)),
          ("FT3D", f"ft3d:{DATA / 'FlyingThings3D_subset_processed_35m'}", ("train_all", "val"))]
  rows = []
  for name, spec, splits in sets:
    batches = itertools.chain(*(eval_batches(open_dataset(spec, s), 1, 8192, seed=0)
                                for s in splits))
    for batch in itertools.islice(batches, pairs):
      pc1, pc2 = jnp.asarray(batch["pc1"]), jnp.asarray(batch["pc2"])
      for _ in range(2):  # the first compiles
        seconds, clock = {}, time.perf_counter()
        flow0 = jax.block_until_ready(network(params, pc1, pc2))
        seconds["network start"] = time.perf_counter() - clock
        flow, _ = optimise.optimise_flow(flow0, pc1, pc2, chosen, seconds=seconds)
      seconds.pop("start")
      mask = np.asarray(batch["mask"][0]) > 0
      epe = float(np.linalg.norm(np.asarray(flow)[0] - batch["flow"][0], axis=-1)[mask].mean())
      rows.append({"set": name, "pair": batch["names"][0].split("/")[-1], "epe": epe,
                   "seconds": seconds, "total": sum(seconds.values())})
      print(json.dumps(rows[-1]), flush=True)
  return rows


def commands():
  """Wall seconds of predict on KITTI 000002 (all its points sampled to 8192, the default)."""
  kitti = DATA / "KITTI_processed_occ_final" / "000002"
  out = {}
  with tempfile.TemporaryDirectory() as tmp:
    cache = os.path.join(tmp, "xla")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["PYTHONPATH"] = str(ROOT)
    for run, flag in (("first (empty cache)", cache), ("second (same cache)", cache),
                      ("cache off", "off")):
      start = time.perf_counter()
      proc = subprocess.run([sys.executable, "-m", "jaxflow.predict", kitti / "pc1.npy",
                             kitti / "pc2.npy", "--out", os.path.join(tmp, "flow.npy"),
                             "--compilation_cache", flag], env=env, capture_output=True,
                            text=True, check=True)
      out[run] = time.perf_counter() - start
      print(f"predict, {run}: {out[run]:.1f} s ({proc.stderr.strip().splitlines()[-1]})",
            flush=True)
  return out


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--json", default=None)
  parser.add_argument("--pairs", type=int, default=None, help="pairs a dataset (default: all)")
  parser.add_argument("--no-commands", action="store_true")
  args = parser.parse_args()
  rows = stages(args.pairs)
  names = list(rows[0]["seconds"])
  print("\n| stage | median s (KITTI + FT3D pairs) | max s |\n|---|---|---|")
  for stage in names + ["total"]:
    values = [r["seconds"][stage] if stage != "total" else r["total"] for r in rows]
    print(f"| {stage} | {statistics.median(values):.2f} | {max(values):.2f} |")
  for name in ("KITTI", "FT3D"):
    mine = [r for r in rows if r["set"] == name]
    print(f"{name}: {len(mine)} pairs, mean EPE {np.mean([r['epe'] for r in mine]):.4f} m")
  result = {"stages": rows}
  if not args.no_commands:
    result["commands"] = commands()
  if args.json:
    result["machine"] = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                         "processor": platform.processor(), "jax": jax.__version__}
    pathlib.Path(args.json).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
  main()
