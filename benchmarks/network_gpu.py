"""The network's figures on an accelerator, beside the official PV-RAFT's (issue table's rows).

    python -m benchmarks.network_gpu                  # 8192 points, as on a lent GPU
    python -m benchmarks.network_gpu --points 256 --iters 2 --train_iters 1   # toy size, any CPU

Rows: PV-RAFT's config and the paper's full model, inference (B=1, --iters) and a training step
(B=2, --train_iters, sequence loss, Adam): median time of --repeats calls after compilation,
XLA's temporaries, the device's peak memory so far (programs run from the smallest to the
largest, so it is each one's own where it grew), and the compilation time. The official PV-RAFT
(PyTorch) was timed on an H200 on 2026-12-04 in one run with jaxflow's code of that day
(REFERENCE); its ratios are against those figures, not this run's.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from benchmarks.model_speed import CONFIGS, device_line, peak_memory_gib, timed
from jaxflow.network.model import build_model
from jaxflow.training import losses

# The official PV-RAFT on one H200 (torch 2.11, float32, 8192 points; benchmarks/NETWORK_GPU.md).
REFERENCE = {"inference": (262.5, 2.38), "train": (201.0, 11.64)}  # ms, peak GiB


def programs(name, points, iters, train_iters, overrides):
  """The config's inference (B=1) and training step (B=2) as (jitted function, arguments)."""
  cfg = CONFIGS[name]()
  cfg.update(overrides)
  model = build_model(cfg)
  rng = np.random.default_rng(0)
  one = jnp.asarray(rng.uniform(-10, 10, (1, points, 3)), jnp.float32)
  variables = jax.jit(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, num_iters=1))(
    one[:, :64], one[:, :64] + 0.1)
  forward = jax.jit(lambda v, a, b: model.apply(v, a, b, num_iters=iters))
  tx = optax.adam(1e-3)
  params = variables["params"]
  b1 = jnp.concatenate([one, one + 1.0])

  def step(params, opt, b1, b2, gt):
    def loss_fn(p):
      flows = model.apply({"params": p}, b1, b2, num_iters=train_iters, refine=False)["flows"]
      return losses.sequence_loss(flows, gt)
    loss, grads = jax.value_and_grad(loss_fn)(params)
    updates, opt = tx.update(grads, opt, params)
    return optax.apply_updates(params, updates), opt, loss

  return ((forward, (variables, one, one + 0.1)),
          (jax.jit(step), (params, tx.init(params), b1, b1 + 0.1, jnp.full(b1.shape, 0.1))))


def run(name, points, iters, train_iters, repeats, overrides):
  (forward, forward_args), (step, step_args) = programs(name, points, iters, train_iters,
                                                        overrides)
  start = time.perf_counter()
  forward = forward.lower(*forward_args).compile()
  compile_s = time.perf_counter() - start
  yield ("inference", f"B=1, {iters} iterations", timed(forward, *forward_args, repeats=repeats),
         forward.memory_analysis().temp_size_in_bytes, peak_memory_gib(), compile_s)
  start = time.perf_counter()
  train = step.lower(*step_args).compile()
  compile_s = time.perf_counter() - start
  yield ("train", f"B=2, {train_iters} iterations, Adam",
         timed(lambda *a: train(*a)[2], *step_args, repeats=repeats),
         train.memory_analysis().temp_size_in_bytes, peak_memory_gib(), compile_s)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--points", type=int, default=8192)
  parser.add_argument("--iters", type=int, default=32)
  parser.add_argument("--train_iters", type=int, default=8)
  parser.add_argument("--repeats", type=int, default=5)
  parser.add_argument("--configs", default="pvraft,default_full")
  parser.add_argument("--set", action="append", default=[],
                      help="a model field for every config, e.g. --set selection=sort")
  args = parser.parse_args()
  overrides = {}
  for item in args.set:
    key, _, value = item.partition("=")
    overrides[key] = {"true": True, "false": False}.get(value.lower(), value)
  print(device_line() + (f", model {overrides}" if overrides else ""))
  print(f"{args.points} points a cloud. PV-RAFT (PyTorch): REFERENCE, same GPU kind, another run.")
  print("| config | work | ms | XLA temporaries (GiB) | peak so far (GiB) | compile (s) | "
        "vs PV-RAFT (PyTorch) |")
  print("|---|---|---|---|---|---|---|")
  for name in args.configs.split(","):
    for work, shape, seconds, temp, peak, compile_s in run(
        name, args.points, args.iters, args.train_iters, args.repeats, overrides):
      ref_ms, ref_peak = REFERENCE[work]
      versus = (f"{ref_ms / (1e3 * seconds):.1f}x faster" + (
        f", {ref_peak / peak:.1f}x less memory" if peak else "")
        if name == "pvraft" and args.points == 8192 else "-")
      print(f"| {name} | {work}, {shape} | {1e3 * seconds:.1f} | {temp / 2**30:.2f} | "
            + (f"{peak:.2f}" if peak is not None else "-")
            + f" | {compile_s:.1f} | {versus} |", flush=True)


if __name__ == "__main__":
  main()
