"""jaxflow.runtime.determinism: XLA_FLAGS gets XLA's deterministic GPU ops before the backend starts (and
XLA honours XLA_FLAGS set then), a started backend is refused, and on the CPU two fresh processes
give the same bits for the order-sensitive programs (scatter-add gradients, NSFP)."""

import hashlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from jaxflow.runtime import determinism
from jaxflow.errors import ConfigError

REPO = Path(__file__).absolute().parent.parent


def python(code: str, **env) -> str:
  env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(REPO), **env}
  proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-3000:]
  return proc.stdout.strip()


def test_enable_sets_the_flag_before_the_backend_and_xla_reads_it(tmp_path):
  # A probe flag beside it (an HLO dump) shows that XLA reads XLA_FLAGS as set after import.
  out = python(f"""
    import os
    import jax, jax.numpy as jnp
    from jaxflow.runtime import determinism
    os.environ["XLA_FLAGS"] = "--xla_gpu_deterministic_ops=false --xla_dump_to={tmp_path}"
    assert not determinism.enabled()
    determinism.enable()
    print(os.environ["XLA_FLAGS"])
    print(determinism.enabled(), float(jax.jit(lambda x: x.sum())(jnp.ones(3))))
    try:
      os.environ["XLA_FLAGS"] = ""
      determinism.enable()
    except Exception as e:
      print(type(e).__name__, e)
  """)
  flags, ran, refused = out.splitlines()
  assert flags == f"--xla_dump_to={tmp_path} --xla_gpu_deterministic_ops=true"
  assert ran == "True 3.0"  # the CPU accepts the GPU flag
  assert any(tmp_path.iterdir())  # the dump: XLA_FLAGS was read after `import jax`
  assert refused.startswith("ConfigError --deterministic must be set before jax starts")


def test_enabled_reads_the_last_setting(monkeypatch):
  for flags, want in (("", False), ("--xla_gpu_deterministic_ops", True),
                      ("--xla_gpu_deterministic_ops=true --xla_gpu_deterministic_ops=false", False),
                      ("--xla_cpu_x=1 --xla_gpu_deterministic_ops=TRUE", True)):
    monkeypatch.setenv("XLA_FLAGS", flags)
    assert determinism.enabled() == want, flags
  monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_deterministic_ops=true")
  determinism.enable()  # already on: nothing to do, also after the backend started
  monkeypatch.setenv("XLA_FLAGS", "")
  if determinism.backend_started():
    with pytest.raises(ConfigError, match="before jax starts its backend"):
      determinism.enable()


PROGRAM = """
  import hashlib
  import jax, jax.numpy as jnp, numpy as np
  from jaxflow.refine import optimiser, rigid_clusters
  rng = np.random.default_rng(0)
  pc1 = rng.uniform(-20, 20, (1, 300, 3)).astype(np.float32)
  pc2 = pc1 + rng.normal(0.5, 0.1, pc1.shape).astype(np.float32)
  labels = jnp.asarray(rng.integers(0, 7, (1, 300)), jnp.int32)
  # Scatter-adds in the backward: a gather's gradient and segment_sum's.
  def loss(x):
    r, c, t = rigid_clusters.fit(x, pc2 - x, labels, 3)
    return jnp.sum(jnp.sin(x[:, rng.integers(0, 300, 900)]) ** 2) + jnp.sum(c ** 2) + jnp.sum(t)
  grad = jax.jit(jax.grad(loss))(jnp.asarray(pc1))
  chosen = optimiser.Settings(model="mlp", objective="exact", steps=20, width=16, depth=2,
                              smoothness=0.5)
  flow = optimiser.optimise(jnp.zeros_like(pc1), pc1, pc2, chosen)[0]
  print(hashlib.sha256(np.asarray(grad).tobytes() + np.asarray(flow).tobytes()).hexdigest())
"""


@pytest.mark.slow
def test_the_cpu_gives_the_same_bits_in_two_fresh_processes():
  first, second = python(PROGRAM), python(PROGRAM)
  assert len(first) == 64 and first == second
  assert first != hashlib.sha256(b"").hexdigest()


def test_the_tools_flag_turns_it_on_before_main():
  """train, evaluate and predict parse their flags with jaxflow.cli.run, which defines
  --deterministic: main then finds the flag in XLA_FLAGS and no backend started yet."""
  code = """
    import os, sys
    from jaxflow import cli
    from jaxflow.runtime import determinism
    sys.argv = ["tool"] + sys.argv[1:]
    cli.run(lambda argv: print(os.environ.get("XLA_FLAGS"), determinism.backend_started()))
  """
  env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(REPO), "XLA_FLAGS": ""}
  run = lambda *args: subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], cwd=REPO,
                                     env=env, capture_output=True, text=True, timeout=120)
  on, off = run("--deterministic"), run()
  assert on.returncode == 0 and off.returncode == 0, on.stderr + off.stderr
  assert on.stdout.split() == ["--xla_gpu_deterministic_ops=true", "False"]
  assert off.stdout.split() == ["False"]
