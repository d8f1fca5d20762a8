"""Run-to-run determinism: what repeats bit for bit where, and `--deterministic` (train, evaluate,
predict) for GPUs.

- CPU: every jaxflow program is deterministic given its seeds (the model's initialisation, the
  data's sampling, NSFP's MLP): XLA's CPU backend splits its work the same way at every run of a
  compiled program, and the host's k-d tree search is exact. Two runs on one machine with the
  same thread count give the same bits (tests/test_determinism.py).
- GPU: XLA's scatter-adds (the forward of `voxel_cells: scatter`, the backward of every gather:
  kNN features, `segment_sum` in rigid_clusters, the grid read's gradient) and some reductions
  add in the order the threads arrive, so two runs differ in the last bits, and training
  amplifies that. `enable` (the tools' `--deterministic`) sets XLA's
  `--xla_gpu_deterministic_ops=true`: deterministic scatters (XLA's scatter determinism
  expander, a sort-based fallback where it cannot apply) and autotuning that picks the same
  kernels, at a cost in speed that `scripts/gpu_round.sh determinism` measures (not measured
  yet). TPU programs are deterministic already.
- Either way a different jax/XLA version, thread count or device may change the bits.
XLA reads XLA_FLAGS once, when jax starts its first backend: `enable` must run before any
computation, which the tools do while they parse their flags.
"""

import os
import re

from jaxflow.errors import ConfigError

FLAG = "--xla_gpu_deterministic_ops"


def backend_started() -> bool:
  """Whether jax has started a backend (after which XLA_FLAGS is no longer read)."""
  try:
    from jax._src import xla_bridge  # pylint: disable=import-outside-toplevel
    return bool(xla_bridge.backends_are_initialized())
  except (ImportError, AttributeError):  # a jax without it: assume not, as before any computation
    return False


def enabled() -> bool:
  """Whether XLA_FLAGS asks for deterministic GPU ops."""
  found = re.findall(FLAG + r"(?:=(\S*))?", os.environ.get("XLA_FLAGS", ""))
  return bool(found) and found[-1].lower() in ("", "true", "1")


def enable():
  """Adds `--xla_gpu_deterministic_ops=true` to XLA_FLAGS (replacing a `=false` there); a
  ConfigError once jax has started a backend, since XLA would no longer read it."""
  if enabled():
    return
  if backend_started():
    raise ConfigError("--deterministic must be set before jax starts its backend: XLA reads "
                      "XLA_FLAGS once (set XLA_FLAGS=--xla_gpu_deterministic_ops=true instead)")
  kept = re.sub(FLAG + r"(=\S*)?", "", os.environ.get("XLA_FLAGS", "")).split()
  os.environ["XLA_FLAGS"] = " ".join(kept + [FLAG + "=true"])
