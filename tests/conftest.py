"""Shared test fixtures: paths to the project's shared samples (absent in a user's clone)."""

import hashlib
import os
import pathlib
import sys
import tempfile

import jax
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("JAXFLOW_SHARED", ROOT.parent / "shared"))

# Compiled programs are shared by the tests, their subprocesses and the xdist workers through jax's
# persistent cache (the models of the tests are few; compiling them is most of the suite's time).
# One cache per checkout (its path hashed): another clone's programs are never read.
CACHE = os.environ.setdefault(
  "JAX_COMPILATION_CACHE_DIR", os.path.join(
    tempfile.gettempdir(), f"jaxflow-test-xla-cache-{hashlib.sha1(bytes(ROOT)).hexdigest()[:10]}"))
jax.config.update("jax_compilation_cache_dir", CACHE)
# Every program, however quick to compile (JAX skips those under a second by default): the xdist
# workers compile the same small programs (the smoke model's steps, the methods' stages).
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
# ... and compiled with XLA's backend optimisation off: with no cache (a fresh clone) the suite took
# 18:14 instead of 22:56 (2-core CPU). The programs compute the same up to rounding (LLVM's passes
# only), so tests that compare two processes' numbers give both of them these flags (`xla_flags`).
FAST_COMPILE = "--xla_backend_optimization_level=0"


def xla_flags(*extra: str) -> str:
  """XLA_FLAGS for a test's subprocess: the tests' own and `extra`."""
  return " ".join(filter(None, [os.environ.get("XLA_FLAGS"), *extra]))


if FAST_COMPILE not in os.environ.get("XLA_FLAGS", ""):  # (before any backend starts)
  os.environ["XLA_FLAGS"] = xla_flags(FAST_COMPILE)

# configs/ is imported as a package by the config files and the tests.
if str(ROOT) not in sys.path:
  sys.path.insert(0, str(ROOT))


@pytest.fixture
def shared_dir():
  """../shared, or a clean skip when this clone has none."""
  if not SHARED.is_dir():
    pytest.skip(f"{SHARED} not present")
  return SHARED


@pytest.fixture(scope="session")
def smoke_checkpoint(tmp_path_factory):
  """A stage-1 checkpoint of the smoke model with random weights (for command paths whose numbers
  only have to agree with each other)."""
  from jaxflow.network import checkpointing, train_state  # pylint: disable=import-outside-toplevel
  from jaxflow.configs import default  # pylint: disable=import-outside-toplevel
  from jaxflow.network.model import build_model  # pylint: disable=import-outside-toplevel

  config = default.get_config("smoke")
  model = build_model(config.model)
  state = train_state.create_train_state(train_state.init_params(model, config, jax.random.key(0)),
                                         train_state.make_optimizer(config, 1))
  path = tmp_path_factory.mktemp("smoke_ckpt")
  ckpts = checkpointing.Checkpoints(path / "checkpoints")
  ckpts.save(1, state, config)
  ckpts.close()
  return path


# The test files by their measured time, longest first (2-core CPU). With `--dist loadfile
# --no-loadscope-reorder` (pyproject.toml) the workers take the files in this order, so the
# last files to start are short ones and the workers finish together (xdist's default order, by
# the number of tests in a file, left the few-test files of minutes each for the end).
LONGEST_FIRST = (  # (by their seconds in a whole run, empty cache, 2026-12-07: benchmarks/SUITE.md)
  "test_model.py", "test_method_matrix.py", "test_gpu_round.py", "test_training.py",
  "test_two_stage.py", "test_distributed.py", "test_resume.py", "test_methods.py",
  "test_network_start.py", "test_docs.py", "test_predict.py", "test_ops.py", "test_precision.py",
  "test_gpu_script.py", "test_install.py", "test_pvraft_fidelity.py", "test_compile_cache.py",
  "test_real_sweeps.py", "test_evaluation.py", "test_first_hour.py", "test_submission.py",
  "test_optimise_guard.py", "test_sweep.py", "test_cli.py", "test_gradients.py",
  "test_slow_movers.py", "test_search.py", "test_sweeps_bench.py", "test_yardstick.py")


def pytest_collection_modifyitems(items):
  rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
  items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: files stay whole
