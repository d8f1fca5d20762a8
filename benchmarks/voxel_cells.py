"""The voxel branch's forms (jaxflow.network.correlation.voxel_means) in the whole model, one process.

    python -m benchmarks.voxel_cells --points 8192 --candidates 512 --iters 32

"all cells" compares every candidate with the 27 cells at once (the default off the CPU); "one cell
at a time" loops over the cells (the CPU's default until 2026-11-25, kept here as the baseline);
"scatter" adds every candidate into its cell in one scatter (the CPU's default now). For each: the
compiled program's temporary memory (XLA's memory_analysis, the same on every run), the median wall
time after compilation, and the same for a training step (batch 2, 8 iterations, sequence loss)
with --train.
"""

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.model_speed import CONFIGS, device_line, model_parser, timed
from jaxflow.network import correlation
from jaxflow.network.model import build_model
from jaxflow.training import losses


def one_cell_at_a_time(corr_BxNxK, index_BxNxK, cells, scatter):
  """The former CPU form of `correlation._cell_sums`: a loop over the cells."""
  def sums_of(r):
    member_BxNxK = index_BxNxK == r
    return (jnp.sum(jnp.where(member_BxNxK, corr_BxNxK, 0.0), axis=2),
            jnp.sum(member_BxNxK, axis=2).astype(corr_BxNxK.dtype))
  sums_RxBxN, counts_RxBxN = jax.lax.map(sums_of, jnp.arange(cells, dtype=index_BxNxK.dtype))
  return jnp.moveaxis(sums_RxBxN, 0, -1), jnp.moveaxis(counts_RxBxN, 0, -1)


# name: (model.voxel_cells, the cell sums it runs)
FORMS = {"all cells": ("compare", correlation._cell_sums),
         "one cell at a time": ("scatter", one_cell_at_a_time),
         "scatter": ("scatter", correlation._cell_sums)}


def temp_mib(jitted, *args):
  return jitted.lower(*args).compile().memory_analysis().temp_size_in_bytes / 2**20


def main():
  parser = model_parser(__doc__, points=8192, candidates=512, iters=32, repeats=2)
  parser.add_argument("--train", action="store_true")
  args = parser.parse_args()

  print(device_line())
  cfg = CONFIGS[args.config]()
  cfg.truncate_k = args.candidates
  model = build_model(cfg)
  rng = np.random.default_rng(0)
  pc1 = jnp.asarray(rng.uniform(-10, 10, (1, args.points, 3)), jnp.float32)
  pc2 = pc1 + 0.1
  variables = jax.jit(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, num_iters=1))(pc1, pc2)
  b1 = jnp.concatenate([pc1, pc1 + 1.0])
  gt = jnp.full(b1.shape, 0.1)
  originals = correlation._cell_sums
  base = model
  print(f"{args.config}, {args.points} points, {args.candidates} candidates")
  try:
    for name, (form, cell_sums) in FORMS.items():
      # The model calls the cell sums by name: pin them for this trace.
      model = base.clone(voxel_cells=form)
      correlation._cell_sums = cell_sums
      forward = jax.jit(lambda v, a, b: model.apply(v, a, b, num_iters=args.iters)["flows"])
      mem, t = temp_mib(forward, variables, pc1, pc2), timed(forward, variables, pc1, pc2,
                                                             repeats=args.repeats)
      line = f"{name:>18}: inference ({args.iters} iters) {mem:7.0f} MiB temp, {t:7.2f} s"
      if args.train:
        def loss(p):
          flows = model.apply({"params": p}, b1, b1 + 0.1, num_iters=8, refine=False)["flows"]
          return losses.sequence_loss(flows, gt)
        grad = jax.jit(jax.grad(loss))
        mem, t = temp_mib(grad, variables["params"]), timed(grad, variables["params"],
                                                           repeats=args.repeats)
        line += f" | training step (batch 2, 8 iters) {mem:7.0f} MiB temp, {t:7.2f} s"
      print(line, flush=True)
  finally:
    correlation._cell_sums = originals


if __name__ == "__main__":
  main()
