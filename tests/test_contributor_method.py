"""A new method is one module (docs/contributing.md): a toy one, a constant flow, defined here and
registered from here only, runs through predict and evaluate.py (their `run`, so their `main`, at
toy size) with no other file touched."""

import dataclasses
import json
import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np

from jaxflow.methods import registry
from jaxflow.methods.interface import Method

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@dataclasses.dataclass(frozen=True)
class Constant:
  """The toy method's settings: one flow for every point."""
  flow: tuple = (0.5, 0.0, -0.25)  # m: every point's flow, in the method's frame (y up)


def _build(network_for, settings: Constant):
  del network_for  # no network

  def run(params, pc1_BxNx3, pc2_BxMx3):
    del params, pc2_BxMx3
    return jnp.broadcast_to(jnp.asarray(settings.flow, pc1_BxNx3.dtype), pc1_BxNx3.shape), None

  return run


METHOD = Method("constant", "every point moves by one vector (a test's toy)", up="y",
                needs_network=False, defaults=lambda steps, iters, objective: Constant(),
                build=_build, compiles=False)


def _run(tool: str, *args) -> subprocess.CompletedProcess:
  """`tool`'s command line (jaxflow.predict or jaxflow.evaluate) with the toy method registered."""
  script = (f"import sys; from jaxflow.methods import registry; from jaxflow import {tool}; "
            "from tests import test_contributor_method as toy; registry.register(toy.METHOD); "
            f"sys.argv[0] = {tool!r}; {tool}.run()")
  return subprocess.run([sys.executable, "-c", script, *map(str, args)], cwd=ROOT,
                        capture_output=True, text=True, timeout=300,
                        env={**os.environ, "JAX_PLATFORMS": "cpu"})


def test_the_toy_method_runs_through_predict(tmp_path):
  rng = np.random.default_rng(0)
  pc1, pc2 = (rng.normal(size=(200, 3)).astype(np.float32) for _ in range(2))
  np.save(tmp_path / "pc1.npy", pc1)
  np.save(tmp_path / "pc2.npy", pc2)
  out = tmp_path / "flow.npy"
  done = _run("predict", tmp_path / "pc1.npy", tmp_path / "pc2.npy", "--method", "constant",
              "--method.constant.flow=(1.0, 2.0, 3.0)", "--up", "y", "--noground_limits",
              "--out", out)
  assert done.returncode == 0, done.stderr[-3000:]
  np.testing.assert_array_equal(np.load(out), np.broadcast_to(np.float32([1, 2, 3]), pc1.shape))
  assert "method constant" in done.stderr, done.stderr
  listed = _run("predict", "a", "b", "--method", "constant", "--print_config")
  assert "method.constant.flow = (0.5, 0.0, -0.25)  # m: every point's flow" in listed.stdout


def test_the_toy_method_runs_through_evaluate(tmp_path):
  out = tmp_path / "results.json"
  done = _run("evaluate", "--dataset", "synthetic_lidar:2", "--split", "val", "--method",
              "constant", "--max_points", 64, "--json", out)
  assert done.returncode == 0, done.stderr[-3000:]
  results = json.loads(out.read_text())
  assert results["method"] == "constant" and results["pairs"] == 2
  assert results["method_settings"] == {"flow": [0.5, 0.0, -0.25]} and np.isfinite(results["epe"])


def test_the_toy_method_is_not_registered_outside_its_test():
  assert "constant" not in registry.METHODS
