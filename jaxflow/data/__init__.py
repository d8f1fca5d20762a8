"""Scene-flow data: readers, synthetic scenes, HDF5, sampling and batching.

    from jaxflow.data import open_dataset, read_points, eval_batches, BatchLoader

The names are loaded on first use (importing `jaxflow.data.pointfiles` does not import h5py or the
synthetic scene generator). `open_dataset` and `formats` import every reader module first, each of
which registers its formats with `jaxflow.data.registry`.
"""

import importlib

READER_MODULES = ("hdf5", "opensf", "readers", "synthetic", "synthetic_sweep")  # each registers its formats
_NAMES = {"BatchLoader": "pipeline", "eval_batches": "pipeline", "read_points": "pointfiles",
          "Dataset": "registry", "Pair": "registry", "sample_pair": "sampling"}

__all__ = ["BatchLoader", "DataError", "Dataset", "Pair", "eval_batches", "formats", "open_dataset",
           "read_points", "sample_pair"]


def _register_readers():
  for name in READER_MODULES:
    importlib.import_module(f"jaxflow.data.{name}")


def open_dataset(spec: str, split: str | None = None):
  """registry.open_dataset("FORMAT:ARG", split) with every reader's format registered."""
  _register_readers()
  from jaxflow.data import registry  # pylint: disable=import-outside-toplevel
  return registry.open_dataset(spec, split)


def formats() -> tuple[str, ...]:
  """The registered dataset formats (every reader's)."""
  _register_readers()
  from jaxflow.data import registry  # pylint: disable=import-outside-toplevel
  return registry.formats()


def __getattr__(name: str):
  if name == "DataError":
    from jaxflow.errors import DataError  # pylint: disable=import-outside-toplevel
    return DataError
  if name in _NAMES:
    return getattr(importlib.import_module(f"jaxflow.data.{_NAMES[name]}"), name)
  raise AttributeError(f"module 'jaxflow.data' has no attribute {name!r}")
