"""Scene-flow data: readers, synthetic scenes, HDF5, sampling and batching (DESIGN.md section 2)."""

from jaxflow.data.pipeline import BatchLoader, eval_batches
from jaxflow.data.pointfiles import read_points
from jaxflow.data.readers import Dataset, Pair, open_dataset
from jaxflow.data.sampling import sample_pair
from jaxflow.errors import DataError

__all__ = ["BatchLoader", "DataError", "Dataset", "Pair", "eval_batches", "open_dataset",
           "read_points", "sample_pair"]
