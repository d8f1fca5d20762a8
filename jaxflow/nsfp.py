r"""Neural Scene Flow Prior (Li, Kooi Pontes, Lucey, NeurIPS 2021): per-pair flow with no training.

    python -m jaxflow.nsfp PC1 PC2 --out FLOW.npy [--objective exact|grid] [--steps 5000]
        [--max-points 8192] [--seed 0]

    flow_Nx3, info = nsfp_flow(pc1_Nx3, pc2_Mx3)          # from Python

A coordinate MLP (8 x 128, ReLU, linear output) maps each pc1 point to its flow; it and a backward
MLP (pc1 + flow back to pc1, the cycle term) are optimised from scratch with Adam (lr 0.008, weight
decay 1e-4) on the truncated Chamfer distance, up to 5000 steps with early stopping (patience 100,
min delta 1e-4), and the flow of the lowest loss is returned (jaxflow.optimiser.NSFP). The
objective is NSFP's exact two-way one by default (`exact`: nearest points by k-d tree every step,
~60 ms a step at 8192 points on a 2-core CPU) or the one-way terms read from distance grids of pc2
and pc1 (`grid`, the FNSF idea: faster, less accurate on FT3D). Files and errors are those of
jaxflow.predict (any format read_points reads; clouds above --max-points are sampled and the flow
mapped back to every PC1 point; broken input is one line and exit code 2). A run whose early
stopping did not fire within the steps says so on stderr.
"""

import dataclasses
import pathlib
import sys

import jax.numpy as jnp
import numpy as np

from jaxflow import cli, export, optimiser, predict
from jaxflow.errors import ConfigError


def settings(objective: str = "exact", steps: int | None = None, seed: int = 0):
  """NSFP's published settings with the given objective, steps cap and initial weights' seed."""
  if objective not in optimiser.OBJECTIVES:
    raise ConfigError(f"--objective must be one of {', '.join(optimiser.OBJECTIVES)}, "
                      f"got {objective!r}")
  if steps is not None and steps < 0:
    raise ConfigError(f"--steps must be >= 0, got {steps}")
  chosen = dataclasses.replace(optimiser.NSFP, objective=objective, seed=seed)
  return chosen if steps is None else dataclasses.replace(chosen, steps=steps)


def nsfp_flow(pc1_Nx3, pc2_Mx3, chosen: optimiser.Settings | None = None):
  """(flow N x 3 float32, info dict of numpy values) of one pair, the clouds used whole."""
  pc1_Nx3 = predict._cloud(pc1_Nx3, "pc1", 1)  # pylint: disable=protected-access
  pc2_Mx3 = predict._cloud(pc2_Mx3, "pc2", 1)  # pylint: disable=protected-access
  flow, info = optimiser.optimise(jnp.zeros((1, *pc1_Nx3.shape), jnp.float32), pc1_Nx3[None],
                                  pc2_Mx3[None], chosen or settings())
  return np.asarray(flow[0]), {k: np.asarray(v)[0] for k, v in info.items()}


def main(argv):
  import argparse  # pylint: disable=import-outside-toplevel

  parser = argparse.ArgumentParser(prog="python -m jaxflow.nsfp",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("pc1")
  parser.add_argument("pc2")
  parser.add_argument("--out", required=True, help="the flow, a row per PC1 point: .npy (float32), .txt or .csv")
  parser.add_argument("--objective", default="exact", help="exact (default, NSFP's) or grid")
  parser.add_argument("--steps", type=int, default=None, help="at most (default 5000)")
  parser.add_argument("--max-points", type=int, default=predict.DEFAULT_MAX_POINTS,
                      help="larger clouds are sampled to this size (0: whole clouds)")
  parser.add_argument("--seed", type=int, default=0, help="sampling and initial weights")
  parser.add_argument("--columns", type=int, default=None, help=".bin: float32 values a point (4)")
  parser.error = cli.fail  # one line and exit code 2, as the other tools
  args = parser.parse_args(argv)
  if args.max_points < 0:
    raise ConfigError(f"--max-points must be >= 0, got {args.max_points}")
  out = pathlib.Path(args.out)
  export.check_flow_path(out)
  chosen = settings(args.objective, args.steps, args.seed)
  pc1, note1 = predict.read_cloud(args.pc1, args.columns)
  pc2, note2 = predict.read_cloud(args.pc2, args.columns)
  runner = predict.load_predictor(method="nsfp")
  runner = dataclasses.replace(runner, method_settings=chosen)
  flow = runner(pc1, pc2, max_points=args.max_points, seed=args.seed,
                names=(args.pc1, args.pc2)).astype(np.float32)
  export.save_flow(out, flow)
  for note in [note1, note2] + runner.notes:
    if note:
      print(f"note: {note}", file=sys.stderr)
  print(f"{out}: NSFP flow of {len(pc1)} points ({chosen.objective} objective)", file=sys.stderr)


if __name__ == "__main__":
  cli.guard(main, sys.argv[1:])
