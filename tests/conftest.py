"""Shared test fixtures: paths to the project's shared samples (absent in a user's clone)."""

import os
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("JAXFLOW_SHARED", ROOT.parent / "shared"))

# configs/ is imported as a package by the config files and the tests.
if str(ROOT) not in sys.path:
  sys.path.insert(0, str(ROOT))


@pytest.fixture
def shared_dir():
  """../shared, or a clean skip when this clone has none."""
  if not SHARED.is_dir():
    pytest.skip(f"{SHARED} not present")
  return SHARED
