"""The self-supervised objectives of flow optimisation (jaxflow.refine.optimiser: NSFP, test time).

One nearest-point search, one Chamfer term, one smoothness term:
- `knn` / `nearest`: exact nearest points (Euclidean, a constant of the gradient), searched where
  the program runs (`search`, SEARCHES): "host", scipy's k-d tree through a callback (O(N log M);
  the tree of a cloud already searched is reused, `tree_cache_info`); "device", a brute-force
  search in row blocks (O(N x M), memory ~ block x M; coordinate differences, no matmul, so no
  precision setting or TF32 enters and far from the origin nothing cancels); "auto", the host on
  the CPU and the device elsewhere, decided when XLA lowers the program for its platform
  (jax.lax.platform_dependent, as model.voxel_cells), so a GPU or TPU program never leaves the
  device for a search. Costs: benchmarks/SEARCH.md.
- `chamfer_terms`: the truncated two-way Chamfer with the matches held fixed.
- `smoothness`: mean L1 difference of the flow over pc1's k-nearest graph.
- the distance grid of the fast objective: jaxflow.refine.distance_grid.
"""

import collections
import functools
import hashlib
import threading

import jax
import jax.numpy as jnp
import numpy as np

from jaxflow.geometry import ops
from jaxflow.geometry.neighbours import Tree

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
  b, n, _ = query_BxNx3.shape
  k = min(k, points_BxMx3.shape[1])
  shape = jax.ShapeDtypeStruct((b, n, k), jnp.int32)

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


def resolved(search: str) -> str:
  """`search` with "auto" resolved for the default backend: "host" on the CPU, else "device"."""
  check_search(search)
  if search != "auto":
    return search
  return "host" if jax.default_backend() == "cpu" else "device"


def knn_now(query_BxNx3, points_BxMx3, k: int, search: str = "auto"):
  """`knn`'s indices computed at once, outside jit (no host callback in any compiled program):
  the host's k-d tree (host_search) or the device's search, by `resolved(search)`."""
  k = min(k, points_BxMx3.shape[1])
  if resolved(search) == "host":
    return jnp.asarray(host_search(query_BxNx3, points_BxMx3, k))
  return _device_knn(query_BxNx3, points_BxMx3, k=k)


def nearest_now(query_BxNx3, points_BxMx3, search: str = "auto"):
  return knn_now(query_BxNx3, points_BxMx3, 1, search)


def neighbours_now(pc1_BxNx3, k: int, search: str = "auto"):
  """`neighbours` computed at once, outside jit (knn_now)."""
  n = pc1_BxNx3.shape[1]
  if n == 1:
    return jnp.zeros((pc1_BxNx3.shape[0], 1, 1), jnp.int32)
  return knn_now(pc1_BxNx3, pc1_BxNx3, min(k, n - 1) + 1, search)[:, :, 1:]


def squared_differences(a_BxCx3, b_BxMx3):
  """|a - b|^2, B x C x M, summed coordinate by coordinate (no C x M x 3 temporary)."""
  return sum((a_BxCx3[:, :, None, i] - b_BxMx3[:, None, :, i]) ** 2 for i in range(3))


def device_knn(query_BxNx3, points_BxMx3, k: int, block: int = DEVICE_BLOCK_ELEMENTS):
  """`host_knn`'s indices by an exact brute-force search on the device: |q - p|^2 from the
  coordinate differences (not the matmul form of ops.knn, whose rounding at tens of metres
  can swap close neighbours), `block` // M query rows at a time (memory ~ block)."""
  k = min(k, points_BxMx3.shape[1])
  points_BxMx3 = jax.lax.stop_gradient(points_BxMx3)
  m = points_BxMx3.shape[1]

  def select(q_BxCx3):
    d_BxCxM = squared_differences(q_BxCx3, points_BxMx3)
    if k == 1:
      return jnp.argmin(d_BxCxM, axis=-1).astype(jnp.int32)[..., None]
    return jax.lax.top_k(-d_BxCxM, k)[1].astype(jnp.int32)

  rows = max(1, block // max(m, 1))
  return ops.map_row_chunks(select, (jax.lax.stop_gradient(query_BxNx3),), rows)


_device_knn = jax.jit(device_knn, static_argnames=("k", "block"))


def knn(query_BxNx3, points_BxMx3, k: int, search: str = "auto"):
  """Indices B x N x k' (k' = min(k, M), nearest first) of each query's exact nearest points, by
  the `search` of SEARCHES (module docstring); a constant of the gradient."""
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


def matched_sq(query_BxNx3, points_BxMx3, idx_BxNx1):
  """|query - points[idx]|^2, B x N: differentiable in both clouds, the match held fixed."""
  return jnp.sum((query_BxNx3 - ops.gather(points_BxMx3, idx_BxNx1)[:, :, 0]) ** 2, axis=-1)


def truncated_mean(sq_BxN, truncate: float):
  """Mean over points of the squared distances clipped at truncate^2 (a far point stops pulling)."""
  return jnp.mean(jnp.minimum(sq_BxN, truncate**2), axis=1)


def chamfer_terms(a_BxNx3, b_BxMx3, match, truncate: float):
  """Truncated two-way Chamfer (B): a -> b plus b -> a, with `match` = (nearest(a, b),
  nearest(b, a)) held fixed."""
  a_to_b, b_to_a = match
  return (truncated_mean(matched_sq(a_BxNx3, b_BxMx3, a_to_b), truncate)
          + truncated_mean(matched_sq(b_BxMx3, a_BxNx3, b_to_a), truncate))


def chamfer(a_BxNx3, b_BxMx3, truncate: float, search: str = "auto"):
  """Truncated two-way Chamfer distance (B) with the nearest points searched now."""
  match = (nearest(a_BxNx3, b_BxMx3, search), nearest(b_BxMx3, a_BxNx3, search))
  return chamfer_terms(a_BxNx3, b_BxMx3, match, truncate)


def neighbours(pc1_BxNx3, k: int, search: str = "auto"):
  """pc1's k nearest other points, B x N x k' (k' = min(k, N - 1); at least the point itself)."""
  n = pc1_BxNx3.shape[1]
  if n == 1:
    return jnp.zeros((pc1_BxNx3.shape[0], 1, 1), jnp.int32)
  return knn(pc1_BxNx3, pc1_BxNx3, min(k, n - 1) + 1, search)[:, :, 1:]


def smoothness(flow_BxNx3, nbr_BxNxK):
  """Mean L1 difference between each point's flow and its neighbours' (B)."""
  diff = ops.gather(flow_BxNx3, nbr_BxNxK) - flow_BxNx3[:, :, None]
  return jnp.mean(jnp.sum(jnp.abs(diff), axis=-1), axis=(1, 2))
