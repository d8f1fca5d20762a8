"""A training step's gradient: plain autodiff, two custom VJPs, recomputed iterations; one process.

    python -m benchmarks.custom_gradients --points 2048 --candidates 128 --iters 16

Rows add, in turn, `jaxflow.network.layers.neighbour_max` (GCL: gradient at the winning neighbour
only) and `jaxflow.network.correlation.cell_means` (voxel cells: gradient from the cell index and
counts), then `model.remat_iterations` (the backward recomputes each iteration from its carry). For
each: the compiled gradient's temporary memory (XLA's memory_analysis, the same on every run), the
median wall time after compilation, and the largest difference of any gradient from plain
autodiff's, relative to that parameter's largest gradient.
"""

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.model_speed import CONFIGS, device_line, model_parser, timed
from benchmarks.voxel_cells import temp_mib
from jaxflow.network import correlation, layers
from jaxflow.network.model import build_model
from jaxflow.training import losses


def plain_neighbour_max(support, unit_v, unit_e, nbr, similarity):
  return jnp.max(layers.edge_similarity(support, unit_v, unit_e, nbr, similarity), axis=2)


def plain_cell_means(corr, index, cells, scatter):
  sums, counts = correlation._cell_sums(corr, index, cells, scatter)
  return sums / jnp.maximum(counts, 1.0)


ROWS = {  # name: (GCL max, voxel cell means, model.remat_iterations)
  "plain autodiff": (plain_neighbour_max, plain_cell_means, False),
  "+ GCL neighbour_max": (layers.neighbour_max, plain_cell_means, False),
  "+ voxel cell_means": (layers.neighbour_max, correlation.cell_means, False),
  "+ remat_iterations": (layers.neighbour_max, correlation.cell_means, True),
}


def main():
  parser = model_parser(__doc__, points=2048, candidates=128, iters=16, repeats=3)
  parser.add_argument("--batch", type=int, default=2)
  args = parser.parse_args()

  print(device_line())
  cfg = CONFIGS[args.config]()
  cfg.truncate_k = args.candidates
  model = build_model(cfg)  # parameters: the same with and without remat_iterations
  rng = np.random.default_rng(0)
  pc1 = jnp.asarray(rng.uniform(-10, 10, (args.batch, args.points, 3)), jnp.float32)
  pc2 = pc1 + jnp.asarray(rng.normal(0, 0.3, pc1.shape), jnp.float32)
  gt = pc2 - pc1
  params = jax.jit(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, num_iters=1))(
    pc1[:1], pc2[:1])["params"]
  print(f"{args.config}, training step gradient: batch {args.batch} x {args.points} points, "
        f"{args.candidates} candidates, {args.iters} iterations, sequence loss")
  originals = layers.neighbour_max, correlation.cell_means
  reference, baseline = None, None
  try:
    for name, (gcl_max, cell_means, remat) in ROWS.items():
      # The model calls both by module attribute: pin this row's forms for the trace.
      layers.neighbour_max, correlation.cell_means = gcl_max, cell_means
      row_model = model.clone(remat_iterations=remat)

      def loss(p, a, b, flow):
        flows = row_model.apply({"params": p}, a, b, num_iters=args.iters, refine=False)["flows"]
        return losses.sequence_loss(flows, flow)

      grad = jax.jit(jax.grad(loss))
      inputs = params, pc1, pc2, gt
      mem, t = temp_mib(grad, *inputs), timed(grad, *inputs, repeats=args.repeats)
      g = grad(*inputs)
      if reference is None:
        reference, baseline, diff = g, t, 0.0
      else:
        diff = max(float(jnp.max(jnp.abs(a - b)) / jnp.maximum(jnp.max(jnp.abs(b)), 1e-30))
                   for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(reference)))
      print(f"{name:>20}: {mem:7.0f} MiB temp, {t:7.2f} s ({baseline / t:4.2f}x), "
            f"gradient differs by {diff:.1e}", flush=True)
  finally:
    layers.neighbour_max, correlation.cell_means = originals


if __name__ == "__main__":
  main()
