"""Forward time of the network (and optionally one training step) on whatever device JAX finds.

    python -m benchmarks.model_speed --points 8192 --iters 32 --configs default_full,pvraft
    python -m benchmarks.model_speed --configs pvraft --train --train-points 2048

Times are medians over --repeats runs after one compile run; the device, jax version, XLA's
temporary memory of the compiled program (memory_analysis: exact, load-independent) and peak
device memory (where the backend reports it) are printed with them. --train adds a training step
(--train-batch pairs of --train-points points, --train-iters iterations, sequence loss, Adam).
"""

import argparse
import platform
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxflow.runtime import host_memory
from jaxflow.configs import ablation, default, pvraft
from jaxflow.network.model import build_model
from jaxflow.training import losses

CONFIGS = {
  "default_full": lambda: ablation.get_config("gcl_rc_sgfi").model,  # the paper's full model
  "default_cpu": lambda: default.get_config().model,  # the main job's small model
  "pvraft": lambda: pvraft.get_config("refine").model,
}


def timed(fn, *args, repeats):
  """Median seconds of a call, after one compile call."""
  return timed_faults(fn, *args, repeats=repeats)[0]


def timed_faults(fn, *args, repeats):
  """(median seconds, median minor page faults) of a call, after one compile call."""
  jax.block_until_ready(fn(*args))  # compile
  times, faults = [], []
  for _ in range(repeats):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - start)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
  return float(np.median(times)), int(np.median(faults))


def temp_mib(jitted, *args):
  """XLA's temporary buffers of the compiled program, MiB."""
  return jitted.lower(*args).compile().memory_analysis().temp_size_in_bytes / 2**20


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


def parse_args():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--points", type=int, default=8192)
  parser.add_argument("--iters", type=int, default=32)
  parser.add_argument("--configs", default="default_full,pvraft")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--train", action="store_true", help="also time a training step")
  parser.add_argument("--train-points", type=int, default=0, help="0: --points")
  parser.add_argument("--train-batch", type=int, default=2)
  parser.add_argument("--train-iters", type=int, default=8)
  parser.add_argument("--inference", type=int, default=1, help="0: time the training step only")
  parser.add_argument("--corr-chunk", type=int, default=0)
  parser.add_argument("--precision", default=None, help="model.precision (default: the config's)")
  parser.add_argument("--host-memory", default=host_memory.KEEP, choices=host_memory.CHOICES,
                      help="malloc keeps freed memory (train.py's default) or releases it")
  return parser.parse_args()


def time_inference(name, cfg, model, variables, pc1, pc2, args):
  """Prints the forward's time, XLA temporary memory, page faults and peak device memory."""
  forward = jax.jit(lambda v, a, b: model.apply(v, a, b, num_iters=args.iters))
  mem = temp_mib(forward, variables, pc1, pc2)
  t, faults = timed_faults(forward, variables, pc1, pc2, repeats=args.repeats)
  peak = peak_memory_gib()
  print(f"{name:>13} ({cfg.precision}): inference 1 pair x {args.points} points x "
        f"{args.iters} iters: {1e3 * t:9.1f} ms, {mem:.0f} MiB temp, {faults} page faults"
        + (f", peak {peak:.2f} GiB" if peak is not None else ""), flush=True)


def time_training(name, model, variables, rng, args):
  """Prints one training step's time (sequence loss, Adam), XLA temporary memory and page
  faults."""
  points, batch = args.train_points or args.points, args.train_batch
  tx = optax.adam(1e-3)
  opt = tx.init(variables["params"])
  one = jnp.asarray(rng.uniform(-10, 10, (1, points, 3)), jnp.float32)
  b1 = jnp.concatenate([one + i for i in range(batch)])
  b2 = b1 + 0.1
  gt = jnp.full(b1.shape, 0.1)

  # The clouds are arguments: as constants, XLA would fold their kNN graphs at compile time.
  @jax.jit
  def step(params, opt, b1, b2, gt):
    def loss_fn(p):
      flows = model.apply({"params": p}, b1, b2, num_iters=args.train_iters,
                          refine=False)["flows"]
      return losses.sequence_loss(flows, gt)
    loss, grads = jax.value_and_grad(loss_fn)(params)
    updates, opt = tx.update(grads, opt, params)
    return optax.apply_updates(params, updates), opt, loss

  batch_args = (variables["params"], opt, b1, b2, gt)
  mem = temp_mib(step, *batch_args)
  t, faults = timed_faults(lambda *a: step(*a)[2], *batch_args, repeats=args.repeats)
  print(f"{name:>13}: train step batch {batch} x {points} points x {args.train_iters} iters: "
        f"{1e3 * t:9.1f} ms, {mem:.0f} MiB temp, {faults} page faults "
        f"({batch / t:.2f} pairs/s)", flush=True)


def main():
  args = parse_args()
  note = host_memory.keep(args.host_memory)
  print(device_line() + f", host memory {args.host_memory}" + (f" ({note})" if note else ""))
  rng = np.random.default_rng(0)
  for name in args.configs.split(","):
    cfg = CONFIGS[name]()
    cfg.corr_chunk = args.corr_chunk
    if args.precision:
      cfg.precision = args.precision
    model = build_model(cfg)
    pc1 = jnp.asarray(rng.uniform(-10, 10, (1, args.points, 3)), jnp.float32)
    pc2 = pc1 + 0.1
    variables = jax.jit(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, num_iters=1))(
      pc1[:, :64], pc2[:, :64])
    if args.inference:
      time_inference(name, cfg, model, variables, pc1, pc2, args)
    if args.train:
      time_training(name, model, variables, rng, args)


if __name__ == "__main__":
  main()
