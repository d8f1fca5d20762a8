"""Nearest neighbours, every search of the package: on the host (NumPy) and inside compiled
programs (jax).

On the host, the one entry point to scipy's k-d tree and the spread of each point's neighbourhood:

    tree = Tree(points_Mx3)
    d_N, j_N = tree.nearest(query_Nx3, reach=0.5)     # inf / M where nothing is within reach
    nbr_NxK = tree.knn(query_Nx3, k)                  # nearest first
    values_NxD, vectors_NxDxD = local_spread(points_NxD, k)   # ascending; vectors[:, :, 0]: normal

Inside compiled programs, batched (B x N x 3):
- `knn` / `nearest` / `nearest_others`: exact nearest points (Euclidean, a constant of the
  gradient), searched where the program runs (`search`, SEARCHES): "host", the k-d tree through a
  callback (O(N log M); the tree of a cloud already searched is reused, `tree_cache_info`);
  "device", a brute-force search in row blocks (O(N x M), memory ~ block x M; coordinate
  differences, no matmul, so no precision setting or TF32 enters and far from the origin nothing
  cancels); "auto", the host on the CPU and the device elsewhere, decided when XLA lowers the
  program for its platform (jax.lax.platform_dependent, as model.voxel_cells), so a GPU or TPU
  program never leaves the device for a search. `knn_now` and co.: the same, outside jit. Costs:
  benchmarks/SEARCH.md.
- `matmul_knn`: the network's kNN graph, distances in the |a|^2 + |b|^2 - 2ab form of the
  reference (one matmul at a chosen precision), rows in chunks.

jax is imported inside the functions that use it: the sweeps (jaxflow.lidar) search on the host
and load no jax.
"""
# pylint: disable=import-outside-toplevel

import collections
import functools
import hashlib
import os
import threading

import numpy as np
from scipy.spatial import cKDTree

# A query of fewer neighbours than this (points x k) runs on one thread: starting threads costs
# more than such a query (an ICP round's 4000 points; 17 of 43 s of three pairs went to
# Thread.start on a loaded 2-core machine when every query used all cores). The answers do not
# depend on the threads.
THREADED_WORK = 100_000
THREADS = max(1, min(4, os.cpu_count() or 1))


class Tree:
  """scipy's cKDTree of `points_MxD` (float64), queried with as many threads as the query is worth."""

  def __init__(self, points_MxD):
    self.points = np.asarray(points_MxD, np.float64)
    self.kd = cKDTree(self.points)

  def _workers(self, queries: int, k: int) -> int:
    return THREADS if queries * k >= THREADED_WORK else 1

  def nearest(self, query_NxD, reach: float = np.inf):
    """(distance N, index N) of each query's nearest point; (inf, M) where none is within `reach`."""
    query = np.asarray(query_NxD, np.float64)
    return self.kd.query(query, distance_upper_bound=reach, workers=self._workers(len(query), 1))

  def knn(self, query_NxD, k: int, reach: float = np.inf, distances: bool = False):
    """Indices N x k' (k' = min(k, M), nearest first; M beyond `reach`), with the distances when
    `distances`."""
    query = np.asarray(query_NxD, np.float64)
    k = min(k, len(self.points))
    d, j = self.kd.query(query, k=list(range(1, k + 1)), distance_upper_bound=reach,
                         workers=self._workers(len(query), k))
    return (d, j) if distances else j


def knn_graph(points_NxD, k: int) -> np.ndarray:
  """Each point's k nearest points of the same cloud (N x min(k, N), itself first)."""
  return Tree(points_NxD).knn(points_NxD, k)


def local_spread(points_NxD, k: int, tree: Tree | None = None):
  """Eigenvalues (N x D, ascending) and eigenvectors (N x D x D, columns) of the scatter matrix of
  each point's k-neighbourhood: vectors[:, :, 0] is a surface's normal (3-D) or the direction
  across a line (2-D); the values say how flat, thin or round the neighbourhood is."""
  points = np.asarray(points_NxD, np.float64)
  nb = points[(Tree(points) if tree is None else tree).knn(points, k)]
  centred = nb - nb.mean(1, keepdims=True)
  return np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))


SEARCHES = ("auto", "host", "device")
# The device search's block: query rows x points compared at once (x 3 float32 differences).
DEVICE_BLOCK_ELEMENTS = 2**22
# k-d trees kept (LRU). A vmapped search calls the host once a pair, each step, and every warped
# cloud's tree is new: the fixed clouds' trees survive for batches of up to 4 pairs with NSFP's
# four searches a step, 8 with two (a larger batch rebuilds them, as before the cache).
TREE_CACHE_SIZE = 16


def check_search(search: str, what: str = "search"):
  if search not in SEARCHES:
    raise ValueError(f"{what} must be one of {', '.join(SEARCHES)}, got {search!r}")


class _TreeCache:
  """k-d trees by the content of their points: a cloud that is searched again (pc2 at every step
  of an optimisation) is not indexed again. Keyed by a hash of the float32 bytes; LRU."""

  def __init__(self, size: int):
    self.size, self.trees, self.lock = size, collections.OrderedDict(), threading.Lock()
    self.hits = self.misses = 0

  def tree(self, points_Mx3: np.ndarray) -> Tree:
    points_Mx3 = np.ascontiguousarray(points_Mx3, np.float32)
    key = (points_Mx3.shape, hashlib.blake2b(points_Mx3.data, digest_size=16).digest())
    with self.lock:
      tree = self.trees.get(key)
      if tree is not None:
        self.trees.move_to_end(key)
        self.hits += 1
        return tree
      self.misses += 1
    tree = Tree(points_Mx3)
    with self.lock:
      self.trees[key] = tree
      while len(self.trees) > self.size:
        self.trees.popitem(last=False)
    return tree

  def clear(self):
    with self.lock:
      self.trees.clear()
      self.hits = self.misses = 0


_TREES = _TreeCache(TREE_CACHE_SIZE)


def tree_cache_info() -> dict:
  """Hits and misses of the host search's tree cache since the last `clear_tree_cache`."""
  return {"hits": _TREES.hits, "misses": _TREES.misses, "size": len(_TREES.trees)}


def clear_tree_cache():
  _TREES.clear()


def host_knn(query_BxNx3, points_BxMx3, k: int):
  """Indices B x N x k' (k' = min(k, M), nearest first) of each query's nearest points, exact
  Euclidean, by scipy's k-d tree on the host inside jit (a constant of the gradient)."""
  import jax
  b, n, _ = query_BxNx3.shape
  k = min(k, points_BxMx3.shape[1])
  shape = jax.ShapeDtypeStruct((b, n, k), jax.numpy.int32)

  return jax.pure_callback(functools.partial(host_search, k=k), shape,
                           jax.lax.stop_gradient(query_BxNx3), jax.lax.stop_gradient(points_BxMx3),
                           vmap_method="sequential")


def host_search(query_BxNx3, points_BxMx3, k: int) -> np.ndarray:
  """`host_knn`'s indices B x N x k (k <= M) in NumPy, outside jit: each batch's k-d tree (cached)."""
  query, points = np.asarray(query_BxNx3, np.float64), np.asarray(points_BxMx3)
  out = np.zeros(query.shape[:2] + (k,), np.int32)
  for i, (q, p) in enumerate(zip(query, points)):
    out[i] = _TREES.tree(p).knn(q, k)
  return out


def squared_differences(a_BxCx3, b_BxMx3):
  """|a - b|^2, B x C x M, summed coordinate by coordinate (no C x M x 3 temporary)."""
  return sum((a_BxCx3[:, :, None, i] - b_BxMx3[:, None, :, i]) ** 2 for i in range(3))


def device_knn(query_BxNx3, points_BxMx3, k: int, block: int = DEVICE_BLOCK_ELEMENTS):
  """`host_knn`'s indices by an exact brute-force search on the device: |q - p|^2 from the
  coordinate differences (not the matmul form of matmul_knn, whose rounding at tens of metres
  can swap close neighbours), `block` // M query rows at a time (memory ~ block)."""
  import jax
  from jaxflow.geometry import ops
  k = min(k, points_BxMx3.shape[1])
  points_BxMx3 = jax.lax.stop_gradient(points_BxMx3)
  m = points_BxMx3.shape[1]

  def select(q_BxCx3):
    d_BxCxM = squared_differences(q_BxCx3, points_BxMx3)
    if k == 1:
      return jax.numpy.argmin(d_BxCxM, axis=-1).astype(jax.numpy.int32)[..., None]
    return jax.lax.top_k(-d_BxCxM, k)[1].astype(jax.numpy.int32)

  rows = max(1, block // max(m, 1))
  return ops.map_row_chunks(select, (jax.lax.stop_gradient(query_BxNx3),), rows)


@functools.cache
def _compiled_device_knn():
  import jax
  return jax.jit(device_knn, static_argnames=("k", "block"))


def knn(query_BxNx3, points_BxMx3, k: int, search: str = "auto"):
  """Indices B x N x k' (k' = min(k, M), nearest first) of each query's exact nearest points, by
  the `search` of SEARCHES (module docstring); a constant of the gradient."""
  import jax
  check_search(search)
  if search == "host":
    return host_knn(query_BxNx3, points_BxMx3, k)
  if search == "device":
    return device_knn(query_BxNx3, points_BxMx3, k)
  return jax.lax.platform_dependent(query_BxNx3, points_BxMx3,
                                    cpu=functools.partial(host_knn, k=k),
                                    default=functools.partial(device_knn, k=k))


def nearest(query_BxNx3, points_BxMx3, search: str = "auto"):
  """Index B x N x 1 of the nearest point of `points` to each query (a constant of the gradient)."""
  return knn(query_BxNx3, points_BxMx3, 1, search)


def nearest_others(pc1_BxNx3, k: int, search: str = "auto"):
  """pc1's k nearest other points, B x N x k' (k' = min(k, N - 1); at least the point itself)."""
  return _others(knn, pc1_BxNx3, k, search)


def _others(knn_of, pc1_BxNx3, k: int, search: str):
  """pc1's k nearest other points by `knn_of` (knn or knn_now): k + 1 with itself, itself dropped."""
  import jax
  n = pc1_BxNx3.shape[1]
  if n == 1:
    return jax.numpy.zeros((pc1_BxNx3.shape[0], 1, 1), jax.numpy.int32)
  return knn_of(pc1_BxNx3, pc1_BxNx3, min(k, n - 1) + 1, search)[:, :, 1:]


def resolved(search: str) -> str:
  """`search` with "auto" resolved for the default backend: "host" on the CPU, else "device"."""
  import jax
  check_search(search)
  if search != "auto":
    return search
  return "host" if jax.default_backend() == "cpu" else "device"


def knn_now(query_BxNx3, points_BxMx3, k: int, search: str = "auto"):
  """`knn`'s indices computed at once, outside jit (no host callback in any compiled program):
  the host's k-d tree (host_search) or the device's search, by `resolved(search)`."""
  import jax
  k = min(k, points_BxMx3.shape[1])
  if resolved(search) == "host":
    return jax.numpy.asarray(host_search(query_BxNx3, points_BxMx3, k))
  return _compiled_device_knn()(query_BxNx3, points_BxMx3, k=k)


def nearest_now(query_BxNx3, points_BxMx3, search: str = "auto"):
  return knn_now(query_BxNx3, points_BxMx3, 1, search)


def nearest_others_now(pc1_BxNx3, k: int, search: str = "auto"):
  """`nearest_others` computed at once, outside jit (knn_now)."""
  return _others(knn_now, pc1_BxNx3, k, search)


def matmul_knn(query_BxNx3, points_BxMx3, k: int, chunk: int = 0, precision: str = "highest",
               selection: str = "auto"):
  """Indices `B x N x k'` of the k' = min(k, M) points nearest to each query (a query in
  `points` finds itself): a cloud smaller than k uses all its points as neighbours.

  With `chunk` > 0 the distance matrix is built `chunk` query rows at a time (memory ~ chunk x M);
  `precision` is that of its matmul (ops.squared_distances); `selection` how the k are selected
  (select.FORMS: the same neighbours in the same order every way).
  """
  import jax
  from jaxflow.geometry import ops, select
  k = min(k, points_BxMx3.shape[1])
  # Centred coordinates keep the |a|^2 + |b|^2 - 2ab form exact enough far from the origin.
  centre_Bx1x3 = jax.numpy.mean(points_BxMx3, axis=1, keepdims=True)
  points_BxMx3 = jax.lax.stop_gradient(points_BxMx3 - centre_Bx1x3)

  def nearest_rows(q_BxCx3):
    d_BxCxM = ops.squared_distances(jax.lax.stop_gradient(q_BxCx3 - centre_Bx1x3), points_BxMx3,
                                    precision)
    return select.top_k(-d_BxCxM, k, selection)[1]

  return ops.map_row_chunks(nearest_rows, (query_BxNx3,), chunk)
