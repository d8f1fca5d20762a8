"""Many processes on JAX's own runtime: `jax.distributed.initialize` (from the flags that
`cli.define_process_flags` defines) and the few helpers training and evaluation need (the global
mesh, each process's rows of a global batch, reductions).

One process per host (or per GPU) runs the same command with its own `--process_id`:

    python train.py --config ... --workdir SHARED_DIR \
        --coordinator HOST0:1234 --num_processes 2 --process_id 0     # and 1 on the other host

With none of the three flags, SLURM (more than one task), Open MPI (more than one rank) and
multi-host TPU slices are detected from their environment and `jax.distributed.initialize()` finds
the rest itself; otherwise the run is a plain single process. On the CPU, cross-process collectives
need gloo (set here), which makes two local processes a faithful test of the multi-host path.
"""

import os

import jax
import numpy as np
from absl import flags
from jax.experimental import multihost_utils
from jax.sharding import Mesh

from jaxflow.errors import ConfigError

def detected_cluster() -> str | None:
  """The multi-process launcher found in the environment (that `jax.distributed.initialize()`
  reads by itself), or None. A single-task SLURM job or one-host TPU stays single-process."""
  env = os.environ
  if int(env.get("SLURM_NTASKS", "1") or 1) > 1 and "SLURM_JOB_ID" in env:
    return "SLURM"
  if int(env.get("OMPI_COMM_WORLD_SIZE", "1") or 1) > 1:
    return "Open MPI"
  if len([h for h in env.get("TPU_WORKER_HOSTNAMES", "").split(",") if h]) > 1:
    return "TPU pod"
  return None


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> int:
  """Joins the run of `num_processes` processes (or the one the environment describes); returns
  the number of processes. Must run before anything touches a device."""
  given = [coordinator is not None, num_processes is not None, process_id is not None]
  if any(given) and not all(given):
    raise ConfigError("--coordinator, --num_processes and --process_id go together (got "
                      f"{coordinator!r}, {num_processes!r}, {process_id!r})")
  if all(given):
    if num_processes < 1 or not 0 <= process_id < num_processes:
      raise ConfigError(f"--process_id must be in 0 .. {num_processes - 1} and --num_processes "
                        f">= 1, got {process_id} of {num_processes}")
    if ":" not in coordinator:
      raise ConfigError(f"--coordinator must be HOST:PORT, got {coordinator!r}")
  elif detected_cluster() is None:
    return 1
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(coordinator, num_processes, process_id)
  return jax.process_count()


def initialize_from_flags() -> int:
  """`initialize` with --coordinator, --num_processes and --process_id (train.py, evaluate.py)."""
  f = flags.FLAGS
  return initialize(f.coordinator, f.num_processes, f.process_id)


def is_primary() -> bool:
  """Process 0: the one that writes config.json, metrics, eval.json and pictures."""
  return jax.process_index() == 0


def global_mesh() -> Mesh:
  """A 1-D mesh over every process's devices: batches split over 'data', parameters replicated."""
  # Process-major order: each process's devices, hence its rows of a batch, are contiguous.
  devices = sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
  return Mesh(np.asarray(devices), ("data",))


def local_rows(sharding, rows: int) -> tuple[int, int]:
  """[start, stop) of the leading-axis rows of a `rows`-row global array that this process's
  devices hold under `sharding` (contiguous for a 1-D mesh over `jax.devices()`)."""
  index = sharding.addressable_devices_indices_map((rows,))
  starts = sorted({s[0].indices(rows)[0] for s in index.values()})
  stops = sorted({s[0].indices(rows)[1] for s in index.values()})
  start, stop = starts[0], stops[-1]
  if stop - start != sum(b - a for a, b in zip(starts, stops)):
    raise ValueError(f"this process's rows of the batch are not contiguous: {index}")
  return start, stop


def global_batch(local: dict, sharding, rows: int) -> dict:
  """Global arrays of `rows` rows from this process's rows (`local_rows`) of each array."""
  return {k: jax.make_array_from_process_local_data(sharding, v, (rows, *v.shape[1:]))
          for k, v in local.items()}


def local_copy(tree):
  """A replicated global tree as arrays on this process's first device, for work each process
  does on its own (evaluating its share of the pairs)."""
  if jax.process_count() == 1:
    return tree
  return jax.tree.map(lambda x: x.addressable_data(0), tree)


def sum_over_processes(values) -> np.ndarray:
  """The element-wise sum over processes of a float64 vector (every process must call it)."""
  values = np.asarray(values, np.float64)
  if jax.process_count() == 1:
    return values
  # jax computes in float32 (x64 off), which would round the sums: gather the float64 bytes as
  # int32 words and add them up here.
  raw = np.frombuffer(values.tobytes(), np.int32)
  gathered = np.asarray(multihost_utils.process_allgather(raw))
  return np.frombuffer(gathered.astype(np.int32).tobytes(), np.float64).reshape(
    jax.process_count(), -1).sum(axis=0)


def barrier(name: str):
  """Waits until every process reaches `name` (before reading what process 0 wrote)."""
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices(name)
