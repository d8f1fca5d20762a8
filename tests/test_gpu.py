"""Checks that need a GPU (marked `gpu`, skipped elsewhere; `bash scripts/gpu_round.sh device` runs
them on a lent one): the "auto" search stays on the device and finds the host's neighbours, exact
float32 matmuls at precision "highest", and XLA's deterministic ops repeat scatter-adds."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow.geometry import neighbours
from jaxflow.refine import optimiser
from tests.test_search import reference, sweep_like

REPO = Path(__file__).absolute().parent.parent
pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(jax.default_backend() != "gpu", reason="needs a GPU")]


def test_auto_search_stays_on_the_gpu_and_finds_the_hosts_neighbours():
  pc1, pc2 = sweep_like(8192, seed=11)
  warped = pc1 + np.float32([0.7, 0.0, 0.0])
  fn = jax.jit(lambda a, b: neighbours.knn(a, b, 1))
  assert "callback" not in fn.lower(warped[None], pc2[None]).as_text()
  got = np.asarray(fn(warped[None], pc2[None]))[0, :, 0]
  want, sq = reference(warped, pc2, 1)
  clear = (sq[:, 1] - sq[:, 0]) > 1e-5 * sq[:, 1] + 1e-9
  np.testing.assert_array_equal(got[clear], want[clear, 0])
  host = np.asarray(jax.jit(lambda a, b: neighbours.knn(a, b, 1, "host"))(warped[None], pc2[None]))
  np.testing.assert_array_equal(got[clear], host[0, clear, 0])


def test_highest_precision_matmuls_match_float64_on_the_gpu():
  """NSFP's MLP on pc1 at tens of metres: "highest" is float32 (~1e-6 relative); "default" is
  TF32 on Hopper (~1e-3), printed for the record."""
  pc1, _ = sweep_like(8192, seed=12)
  layers = optimiser.init_mlp(jax.random.key(0), 128, 8)
  x = jnp.asarray(pc1)
  errors = {}
  for precision in ("highest", "default"):
    got = np.asarray(jax.jit(lambda l, x: optimiser.apply_mlp(l, x, precision))(layers, x))
    h = pc1.astype(np.float64)
    for w, b in layers[:-1]:
      h = np.maximum(h @ np.asarray(w, np.float64) + np.asarray(b, np.float64), 0)
    want = h @ np.asarray(layers[-1][0], np.float64) + np.asarray(layers[-1][1], np.float64)
    errors[precision] = float(np.max(np.abs(got - want)) / np.max(np.abs(want)))
  print("relative error of the MLP on the GPU:", errors)
  assert errors["highest"] < 1e-5, errors


DETERMINISM = """
  import hashlib, jax, jax.numpy as jnp, numpy as np
  idx = jnp.asarray(np.random.default_rng(0).integers(0, 8192, 2**22), jnp.int32)
  x = jnp.asarray(np.random.default_rng(1).normal(size=(8192, 64)), jnp.float32)
  grad = jax.jit(jax.grad(lambda x: jnp.sum(jnp.sin(x[idx]) ** 2)))
  seg = jax.jit(lambda x: jax.ops.segment_sum(x[idx], idx % 1000, num_segments=1000))
  digest = lambda a: hashlib.sha256(np.asarray(a).tobytes()).hexdigest()
  print(len({digest(grad(x)) for _ in range(5)}), len({digest(seg(x)) for _ in range(5)}))
"""


@pytest.mark.parametrize("deterministic", [True, False])
def test_deterministic_ops_repeat_scatter_adds(deterministic):
  """Five runs of a gather's gradient and a segment_sum (scatter-adds of 4M values into 8192 and
  1000 rows): one result with XLA's deterministic ops; without them the count is printed."""
  flags = "--xla_gpu_deterministic_ops=true" if deterministic else ""
  env = {**os.environ, "PYTHONPATH": str(REPO), "XLA_FLAGS": flags}
  proc = subprocess.run([sys.executable, "-c", textwrap.dedent(DETERMINISM)], env=env, cwd=REPO,
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-3000:]
  distinct = proc.stdout.split()
  print(f"deterministic ops {deterministic}: distinct results of 5 (gradient, segment_sum):",
        distinct)
  if deterministic:
    assert distinct == ["1", "1"]
