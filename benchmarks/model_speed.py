"""Forward time of the network (and optionally one training step) on whatever device JAX finds.

    python -m benchmarks.model_speed --points 8192 --iters 32 --configs default_full,pvraft

Times are medians over --repeats runs after one compile run; the device, jax version and peak
device memory (where the backend reports it) are printed with them.
"""

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxflow.configs import ablation, default, pvraft
from jaxflow.network.model import build_model
from jaxflow.training import losses

CONFIGS = {
  "default_full": lambda: ablation.get_config("gcl_rc_sgfi").model,  # the paper's full model
  "default_cpu": lambda: default.get_config().model,  # the main job's small model
  "pvraft": lambda: pvraft.get_config("refine").model,
}


def timed(fn, *args, repeats):
  jax.block_until_ready(fn(*args))  # compile
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - start)
  return float(np.median(times))


def device_line():
  dev = jax.devices()[0]
  return (f"device: {dev.device_kind} ({dev.platform}), jax {jax.__version__}, "
          f"host {platform.processor() or platform.machine()}")


def model_parser(doc: str, points: int, candidates: int, iters: int,
                 repeats: int) -> argparse.ArgumentParser:
  """The options of the benchmarks that time one model config (voxel_cells, custom_gradients)."""
  parser = argparse.ArgumentParser(description=doc.splitlines()[0])
  parser.add_argument("--config", default="default_cpu", choices=sorted(CONFIGS))
  parser.add_argument("--points", type=int, default=points)
  parser.add_argument("--candidates", type=int, default=candidates, help="model.truncate_k")
  parser.add_argument("--iters", type=int, default=iters)
  parser.add_argument("--repeats", type=int, default=repeats)
  return parser


def peak_memory_gib():
  stats = jax.devices()[0].memory_stats() or {}
  peak = stats.get("peak_bytes_in_use")
  return None if peak is None else peak / 2**30


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--points", type=int, default=8192)
  parser.add_argument("--iters", type=int, default=32)
  parser.add_argument("--configs", default="default_full,pvraft")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--train", action="store_true", help="also time a batch-2, 8-iteration step")
  parser.add_argument("--corr-chunk", type=int, default=0)
  parser.add_argument("--precision", default=None, help="model.precision (default: the config's)")
  args = parser.parse_args()

  print(device_line())
  rng = np.random.default_rng(0)
  for name in args.configs.split(","):
    cfg = CONFIGS[name]()
    cfg.corr_chunk = args.corr_chunk
    if args.precision:
      cfg.precision = args.precision
    model = build_model(cfg)
    pc1 = jnp.asarray(rng.uniform(-10, 10, (1, args.points, 3)), jnp.float32)
    pc2 = pc1 + 0.1
    variables = jax.jit(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, num_iters=1))(pc1, pc2)
    forward = jax.jit(lambda v, a, b: model.apply(v, a, b, num_iters=args.iters))
    t = timed(forward, variables, pc1, pc2, repeats=args.repeats)
    mem = peak_memory_gib()
    print(f"{name:>13} ({cfg.precision}): inference 1 pair x {args.points} points x {args.iters} iters: "
          f"{1e3 * t:9.1f} ms" + (f", peak {mem:.2f} GiB" if mem is not None else ""))
    if args.train:
      tx = optax.adam(1e-3)
      opt = tx.init(variables["params"])
      b1 = jnp.concatenate([pc1, pc1 + 1.0])
      b2 = b1 + 0.1
      gt = jnp.full(b1.shape, 0.1)

      @jax.jit
      def step(params, opt):
        def loss_fn(p):
          flows = model.apply({"params": p}, b1, b2, num_iters=8, refine=False)["flows"]
          return losses.sequence_loss(flows, gt)
        loss, grads = jax.value_and_grad(loss_fn)(params)
        updates, opt = tx.update(grads, opt, params)
        return optax.apply_updates(params, updates), opt, loss

      t = timed(lambda p, o: step(p, o)[2], variables["params"], opt, repeats=args.repeats)
      print(f"{name:>13}: train step batch 2 x {args.points} points x 8 iters: {1e3 * t:9.1f} ms "
            f"({2 / t:.2f} pairs/s)")


if __name__ == "__main__":
  main()
