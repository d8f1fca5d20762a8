"""Batches for training (`BatchLoader`) and evaluation (`eval_batches`), prefetched in the background.

Every batch is a pure function of its arguments: training batch `step` depends only on
(seed, step), so a resumed run sees exactly the batches an uninterrupted one would.
"""

import collections
import concurrent.futures
import itertools
import multiprocessing
import os
import threading
import warnings
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from jaxflow.data.registry import Pair
from jaxflow.data.sampling import augment_pair, check_augment, crop_pair, sample_pair
from jaxflow.errors import ConfigError, DataError


def _stack(pairs: list[Pair]) -> dict:
  batch = {
      "pc1": np.stack([p.pc1 for p in pairs]),
      "pc2": np.stack([p.pc2 for p in pairs]),
      "flow": np.stack([p.flow for p in pairs]),
      "mask": np.stack([p.mask for p in pairs]).astype(np.float32),
  }
  if all(p.has_labels for p in pairs):  # ego-motion flow and labels, for the three-way EPE
    batch["rigid_flow"] = np.stack([p.rigid_flow for p in pairs])
    batch["foreground"] = np.stack([p.foreground for p in pairs])
  if all(p.category is not None for p in pairs):  # Argoverse 2 labels (jaxflow.evaluation.av2_eval)
    batch["category"] = np.stack([p.category for p in pairs])
    batch["ego_xy"] = np.stack([p.ego_xy for p in pairs])
  return batch


def prefetched(fn: Callable, keys: Iterable, depth: int, pool=None) -> Iterator:
  """Yields fn(key) for each key in order, computing up to `depth` results ahead.

  Work runs in `pool` (an Executor, shut down at the end) or in up to `depth` threads. An exception
  raised by fn(key) surfaces when that result is reached; closing the generator cancels the work
  not yet started.
  """
  keys = iter(keys)
  if depth <= 0:
    yield from map(fn, keys)
    return
  if pool is None:
    pool = concurrent.futures.ThreadPoolExecutor(max(1, min(depth, os.cpu_count() or 1)),
                                                 thread_name_prefix="jaxflow-data")
  pending = collections.deque()
  try:
    for key in itertools.islice(keys, depth):
      pending.append(pool.submit(fn, key))
    while pending:
      result = pending.popleft().result()
      for key in itertools.islice(keys, 1):
        pending.append(pool.submit(fn, key))
      yield result
  finally:
    for future in pending:
      future.cancel()
    pool.shutdown(wait=False, cancel_futures=True)


_WORKER_LOADER = None  # the BatchLoader copy of a worker process


def _worker_start(loader):
  global _WORKER_LOADER
  _WORKER_LOADER = loader


def _worker_batch(step: int):
  """batch(step) in a worker process: (batch, newly broken pairs) or ("error", path, problem)."""
  loader = _WORKER_LOADER
  seen = len(loader.broken)
  try:
    with warnings.catch_warnings():
      warnings.simplefilter("ignore")  # the parent warns, once per broken pair
      batch = loader.batch(step)
  except DataError as e:  # sent as its parts: DataError does not unpickle from its message
    return "error", e.path, e.problem
  return batch, loader.broken[seen:]


class BatchLoader:
  """Training batches: B pairs, each sampled to num_points per cloud, shuffled per epoch.

  Batch `step` is deterministic: epoch = step // steps_per_epoch; the pair order is a permutation
  seeded by (seed, epoch); pair `index` is sampled (and augmented) with an rng seeded by
  (seed, epoch, index). The last incomplete batch of an epoch is dropped.
  With skip_broken, a pair raising DataError is reported once (warning + `broken`) and replaced by
  the next pair of the epoch order that reads; otherwise the DataError propagates.
  `iterate` prefetches `prefetch` batches in as many background threads (numpy releases the GIL only
  inside its loops); workers > 0 computes them in that many spawned processes instead, for
  CPU-bound datasets (synthetic scenes) on machines with cores to spare (the loader and its dataset
  are pickled to them, and the calling script needs the usual `if __name__ == "__main__":` guard).
  crop_from > 0 samples each cloud to crop_from points first (the density to learn, e.g. the test's
  8192) and trains on a window of num_points of them (`sampling.crop_pair`); 0 samples num_points.
  crop_mask_outside masks out of a window's loss the points whose flow leaves pc2's window.
  rows (start, stop): only the pairs start .. stop - 1 of each global batch (one process's part of
  it, jaxflow.runtime.distributed.local_rows; the same pairs, sampled the same way, as in the whole batch).
  Batch dict: float32 'pc1', 'pc2', 'flow' (B x N x 3), 'mask' (B x N, 1/0) and 'replaced' (int, the
  clouds sampled with replacement because they had fewer than num_points points).
  """

  def __init__(self, dataset, batch_size: int, num_points: int, seed: int, shuffle: bool = True,
               augment: dict | None = None, skip_broken: bool = False, prefetch: int = 2,
               workers: int = 0, crop_from: int = 0, crop_mask_outside: bool = False,
               rows: tuple[int, int] | None = None):
    if batch_size < 1 or num_points < 1 or seed < 0 or prefetch < 0 or workers < 0:
      raise ConfigError("BatchLoader: need batch_size >= 1, num_points >= 1, seed >= 0, prefetch >= 0, "
                        f"workers >= 0; got {batch_size}, {num_points}, {seed}, {prefetch}, "
                        f"{workers}")
    if crop_from and crop_from < num_points:
      raise ConfigError(f"BatchLoader: crop_from ({crop_from}) must be 0 or >= num_points "
                        f"({num_points})")
    self.dataset = dataset
    self.batch_size = batch_size
    self.num_points = num_points
    self.seed = seed
    self.shuffle = shuffle
    self.augment = check_augment(augment)
    self.skip_broken = skip_broken
    self.prefetch = prefetch
    self.workers = workers
    self.crop_from = crop_from
    self.crop_mask_outside = crop_mask_outside
    self.rows = rows or (0, batch_size)
    if not 0 <= self.rows[0] < self.rows[1] <= batch_size:
      raise ConfigError(f"BatchLoader: rows {self.rows} must lie in 0 .. batch_size {batch_size}")
    self.steps_per_epoch = len(dataset) // batch_size
    if self.steps_per_epoch == 0:
      raise ConfigError(f"{getattr(dataset, 'name', 'dataset')}: {len(dataset)} pairs, fewer than "
                        f"batch_size {batch_size}")
    self.broken: list[str] = []
    self._broken_index: set[int] = set()
    self._lock = threading.Lock()
    self._orders: dict[int, np.ndarray] = {}

  def __getstate__(self):  # for worker processes: no lock, no cached orders
    return {k: v for k, v in self.__dict__.items() if k not in ("_lock", "_orders")}

  def __setstate__(self, state):
    self.__dict__.update(state, _lock=threading.Lock(), _orders={})

  def _report(self, entries):
    with self._lock:
      for entry in entries:
        if entry not in self.broken:
          self.broken.append(entry)
          warnings.warn(f"skipping broken pair: {entry}", stacklevel=3)

  def order(self, epoch: int) -> np.ndarray:
    """Dataset indices in the order epoch `epoch` visits them."""
    with self._lock:
      if epoch not in self._orders:
        n = len(self.dataset)
        rng = np.random.default_rng((self.seed, epoch))
        order = rng.permutation(n) if self.shuffle else np.arange(n)
        if len(self._orders) > 4:
          self._orders.pop(min(self._orders))
        self._orders[epoch] = order
      return self._orders[epoch]

  def _pair_at(self, order, position: int, epoch: int) -> tuple[Pair, int]:
    n = len(order)
    for attempt in range(n):
      index = int(order[(position + attempt) % n])
      if index in self._broken_index:
        continue
      rng = np.random.default_rng((self.seed, epoch, index))
      try:
        pair, replaced = sample_pair(self.dataset[index], self.crop_from or self.num_points, rng)
        if self.crop_from:
          pair = crop_pair(pair, self.num_points, rng, self.crop_mask_outside)
      except DataError as e:
        if not self.skip_broken:
          raise
        with self._lock:
          if index in self._broken_index:
            continue
          self._broken_index.add(index)
        self._report([str(e)])
        continue
      return augment_pair(pair, self.augment, rng), replaced
    raise DataError(getattr(self.dataset, "name", "dataset"), "every pair is broken")

  def batch(self, step: int) -> dict:
    """This process's rows of the batch of global step `step` (deterministic in (seed, step,
    rows))."""
    epoch, k = divmod(step, self.steps_per_epoch)
    order = self.order(epoch)
    pairs, replaced = [], 0
    for position in range(k * self.batch_size + self.rows[0], k * self.batch_size + self.rows[1]):
      pair, rep = self._pair_at(order, position, epoch)
      pairs.append(pair)
      replaced += rep
    return {**_stack(pairs), "replaced": replaced}

  def iterate(self, start_step: int = 0) -> Iterator[tuple[int, dict]]:
    """(step, batch(step)) for step = start_step, start_step + 1, ... prefetched in the background."""
    if not self.workers:
      steps = itertools.count(start_step)
      return prefetched(lambda step: (step, self.batch(step)), steps, self.prefetch)
    return self._iterate_processes(start_step)

  def _iterate_processes(self, start_step):
    context = multiprocessing.get_context("spawn")  # fork would copy the threads of jax and h5py
    pool = concurrent.futures.ProcessPoolExecutor(self.workers, mp_context=context,
                                                  initializer=_worker_start, initargs=(self,))
    depth = max(self.prefetch, self.workers)
    results = prefetched(_worker_batch, itertools.count(start_step), depth, pool)
    try:
      for step, result in zip(itertools.count(start_step), results):
        if result[0] == "error":
          raise DataError(result[1], result[2])
        batch, broken = result
        self._report(broken)
        yield step, batch
    finally:
      results.close()


def eval_batches(dataset, batch_size: int, num_points: int | None, seed: int = 0,
                 prefetch: int = 1, shard: tuple[int, int] = (0, 1)) -> Iterator[dict]:
  """Every pair exactly once, in order; a broken pair raises DataError (evaluation never skips).

  Pair i is sampled with np.random.default_rng((seed, i)), so two runs give identical batches;
  num_points None keeps whole clouds (batch_size must be 1). The last batch is padded by repeating
  its last pair; 'pair_valid' (B, float32) is 1 for real pairs, 0 for padding. Besides the training
  keys the dict holds 'names' (list of B str) and, when every pair has them (`Pair.has_labels`),
  'rigid_flow' (B x N x 3) and 'foreground' (B x N bool), for the three-way EPE. shard (index,
  count): only the batches index, index + count, ... (one process's share; the same batches as
  unsharded).
  """
  index, count = shard
  if not 0 <= index < count:
    raise ConfigError(f"eval_batches: shard index must be in 0 .. count - 1, got {shard}")
  if batch_size < 1 or (num_points is not None and num_points < 1):
    raise ConfigError(f"eval_batches: need batch_size >= 1 and num_points >= 1 or None, "
                      f"got {batch_size}, {num_points}")
  if num_points is None and batch_size != 1:
    raise ConfigError("eval_batches: whole clouds (num_points None) need batch_size 1, "
                      f"got {batch_size}")
  n = len(dataset)

  def make(start):
    pairs, replaced = [], 0
    for i in range(start, min(start + batch_size, n)):
      pair = dataset[i]
      if num_points is not None:
        pair, rep = sample_pair(pair, num_points, np.random.default_rng((seed, i)))
        replaced += rep
      pairs.append(pair)
    real = len(pairs)
    pairs += [pairs[-1]] * (batch_size - real)
    valid = np.zeros(batch_size, np.float32)
    valid[:real] = 1
    return {**_stack(pairs), "replaced": replaced, "pair_valid": valid,
            "names": [p.name for p in pairs]}

  return prefetched(make, range(index * batch_size, n, count * batch_size), prefetch)
