"""Test-time optimisation: nearest points searched every step against every `refresh` steps; one process.

    python -m benchmarks.test_time_refresh --points 8192 --steps 200 --refresh 1,10

On one synthetic_lidar test pair sampled to `--points`, from zero flow (no network, so the rows
time the optimisation alone): the median wall time of `jaxflow.test_time.optimise_flow` after
compilation, the objective reached, and the EPE against the ground truth, for each refresh interval.
"""

import argparse

import jax.numpy as jnp
import numpy as np

from benchmarks.model_speed import device_line, timed
from jaxflow import test_time
from jaxflow.data import eval_batches, open_dataset
from jaxflow.metrics import per_pair_metrics


def main():
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--points", type=int, default=8192)
  parser.add_argument("--steps", type=int, default=200)
  parser.add_argument("--refresh", default="1,10", help="comma-separated refresh intervals")
  parser.add_argument("--repeats", type=int, default=2)
  args = parser.parse_args()

  print(device_line())
  batch = next(eval_batches(open_dataset("synthetic_lidar:1", split="test"), 1, args.points))
  pc1, pc2 = jnp.asarray(batch["pc1"]), jnp.asarray(batch["pc2"])
  gt, mask = jnp.asarray(batch["flow"]), jnp.asarray(batch["mask"])
  print(f"one synthetic_lidar test pair, {args.points} points, {args.steps} steps from zero flow")
  baseline = None
  for refresh in map(int, args.refresh.split(",")):
    settings = test_time.Settings(steps=args.steps, refresh=refresh)
    zero = jnp.zeros_like(pc1)
    t = timed(test_time.optimise_flow, zero, pc1, pc2, settings, repeats=args.repeats)
    flow, before, after = test_time.optimise_flow(zero, pc1, pc2, settings)
    epe = float(per_pair_metrics(flow, gt, mask)["epe"][0])
    baseline = baseline or t
    print(f"refresh {refresh:3d}: {t:7.2f} s ({1000 * t / args.steps:6.1f} ms a step, "
          f"{baseline / t:5.2f}x), objective {float(before[0]):.4f} -> {float(after[0]):.4f}, "
          f"EPE {epe:.4f} m", flush=True)


if __name__ == "__main__":
  main()
