"""Scene-flow data: readers, synthetic scenes, HDF5, sampling and batching (DESIGN.md section 2).

Importing the package imports every reader module, each of which registers its formats with
`jaxflow.data.registry`.
"""

from jaxflow.data import hdf5, opensf, readers, synthetic, synthetic_sweep  # noqa: F401  (register)
from jaxflow.data.pipeline import BatchLoader, eval_batches
from jaxflow.data.pointfiles import read_points
from jaxflow.data.registry import Dataset, Pair, formats, open_dataset
from jaxflow.data.sampling import sample_pair
from jaxflow.errors import DataError

__all__ = ["BatchLoader", "DataError", "Dataset", "Pair", "eval_batches", "formats", "open_dataset",
           "read_points", "sample_pair"]
