"""Shared test fixtures: paths to the project's shared samples (absent in a user's clone)."""

import os
import pathlib
import sys
import tempfile

import jax
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("JAXFLOW_SHARED", ROOT.parent / "shared"))

# Compiled programs are shared by the tests, their subprocesses and both xdist workers through jax's
# persistent cache (the models of the tests are few; compiling them is most of the suite's time).
CACHE = os.environ.setdefault(
  "JAX_COMPILATION_CACHE_DIR", os.path.join(tempfile.gettempdir(), "jaxflow-test-xla-cache"))
jax.config.update("jax_compilation_cache_dir", CACHE)

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
  from jaxflow import checkpointing, train_state  # pylint: disable=import-outside-toplevel
  from jaxflow.configs import default  # pylint: disable=import-outside-toplevel
  from jaxflow.model import build_model  # pylint: disable=import-outside-toplevel

  config = default.get_config("smoke")
  model = build_model(config.model)
  state = train_state.create_train_state(train_state.init_params(model, config, jax.random.key(0)),
                                         train_state.make_optimizer(config, 1))
  path = tmp_path_factory.mktemp("smoke_ckpt")
  ckpts = checkpointing.Checkpoints(path / "checkpoints")
  ckpts.save(1, state, config)
  ckpts.close()
  return path
