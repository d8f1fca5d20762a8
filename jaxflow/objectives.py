"""The self-supervised objectives of flow optimisation (jaxflow.optimiser: NSFP, test time).

One nearest-point search, one Chamfer term, one smoothness term, one distance transform:
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
- `distance_grid` / `grid_distance`: the distance to pc2 sampled once per pair on a voxel grid and
  read by trilinear interpolation at any point (the FNSF idea: a step costs O(N), not O(N x M)).
  The grid covers pc2's box plus `margin` metres (beyond it every point is farther than `margin`
  from pc2, so a term truncated at <= margin is constant there) and holds at most `max_cells` nodes:
  cells grow for large extents, so memory stays bounded for whole sweeps. It is built once per
  pair where `search` says: scipy's distance transform on the host, or the exact distances by
  brute force on the device.
"""

import collections
import functools
import hashlib
import threading
import typing

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage, spatial

from jaxflow import geometry

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

  def tree(self, points_Mx3: np.ndarray) -> spatial.cKDTree:
    points_Mx3 = np.ascontiguousarray(points_Mx3, np.float32)
    key = (points_Mx3.shape, hashlib.blake2b(points_Mx3.data, digest_size=16).digest())
    with self.lock:
      tree = self.trees.get(key)
      if tree is not None:
        self.trees.move_to_end(key)
        self.hits += 1
        return tree
      self.misses += 1
    tree = spatial.cKDTree(points_Mx3.astype(np.float64))
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

  def search(query, points):
    out = np.zeros(shape.shape, np.int32)
    for i, (q, p) in enumerate(zip(np.asarray(query, np.float64), np.asarray(points))):
      out[i] = _TREES.tree(p).query(q, k=[*range(1, k + 1)], workers=-1)[1]
    return out

  return jax.pure_callback(search, shape, jax.lax.stop_gradient(query_BxNx3),
                           jax.lax.stop_gradient(points_BxMx3), vmap_method="sequential")


def _squared_differences(a_BxCx3, b_BxMx3):
  """|a - b|^2, B x C x M, summed coordinate by coordinate (no C x M x 3 temporary)."""
  return sum((a_BxCx3[:, :, None, i] - b_BxMx3[:, None, :, i]) ** 2 for i in range(3))


def device_knn(query_BxNx3, points_BxMx3, k: int, block: int = DEVICE_BLOCK_ELEMENTS):
  """`host_knn`'s indices by an exact brute-force search on the device: |q - p|^2 from the
  coordinate differences (not the matmul form of geometry.knn, whose rounding at tens of metres
  can swap close neighbours), `block` // M query rows at a time (memory ~ block)."""
  k = min(k, points_BxMx3.shape[1])
  points_BxMx3 = jax.lax.stop_gradient(points_BxMx3)
  m = points_BxMx3.shape[1]

  def select(q_BxCx3):
    d_BxCxM = _squared_differences(q_BxCx3, points_BxMx3)
    if k == 1:
      return jnp.argmin(d_BxCxM, axis=-1).astype(jnp.int32)[..., None]
    return jax.lax.top_k(-d_BxCxM, k)[1].astype(jnp.int32)

  rows = max(1, block // max(m, 1))
  return geometry.map_row_chunks(select, (jax.lax.stop_gradient(query_BxNx3),), rows)


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
  return jnp.sum((query_BxNx3 - geometry.gather(points_BxMx3, idx_BxNx1)[:, :, 0]) ** 2, axis=-1)


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
  diff = geometry.gather(flow_BxNx3, nbr_BxNxK) - flow_BxNx3[:, :, None]
  return jnp.mean(jnp.sum(jnp.abs(diff), axis=-1), axis=(1, 2))


# The distance transform.


class Grid(typing.NamedTuple):
  """Distances to a cloud at the nodes of a regular grid: node (i, j, k) sits at
  origin + cell * (i, j, k); `values` is the flat C-order grid padded to a fixed length."""
  origin_Bx3: jax.Array
  cell_B: jax.Array
  dims_Bx3: jax.Array  # int32 nodes per axis
  values_BxG: jax.Array


def grid_layout(points_Mx3: np.ndarray, cell: float, max_cells: int, margin: float):
  """(origin 3, cell, dims 3): pc's box plus `margin`, cells of `cell` m or larger so that the
  node count stays <= max_cells."""
  lo = points_Mx3.min(axis=0).astype(np.float64) - margin
  extent = points_Mx3.max(axis=0).astype(np.float64) + margin - lo
  cell = max(float(cell), float(np.prod(extent) / max_cells) ** (1 / 3), 1e-6)
  dims = np.floor(extent / cell).astype(np.int64) + 2
  while np.prod(dims) > max_cells:  # the cube-root estimate ignores the +2 nodes per axis
    cell *= 1.02
    dims = np.floor(extent / cell).astype(np.int64) + 2
  return lo, cell, dims


def distance_grid_np(points_Mx3: np.ndarray, cell: float, max_cells: int, margin: float):
  """(origin, cell, dims, values): at each node the distance to the pc2 point held by its nearest
  occupied node (each point occupies its nearest node; the exact Euclidean distance transform of the
  occupancy finds that node). It equals the distance to the nearest point up to about one cell."""
  origin, cell, dims = grid_layout(points_Mx3, cell, max_cells, margin)
  node_Mx3 = np.clip(np.rint((points_Mx3 - origin) / cell).astype(np.int64), 0, dims - 1)
  flat_M = np.ravel_multi_index(node_Mx3.T, dims)
  holder = np.full(int(np.prod(dims)), -1, np.int64)
  holder[flat_M[::-1]] = np.arange(len(points_Mx3))[::-1]  # the first point of a node holds it
  empty = (holder < 0).reshape(tuple(dims))
  nearest_3xG = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
  nearest_G = np.ravel_multi_index(nearest_3xG.reshape(3, -1), dims)
  nodes_Gx3 = np.stack(np.unravel_index(np.arange(int(np.prod(dims))), dims), -1) * cell + origin
  values = np.linalg.norm(nodes_Gx3 - points_Mx3[holder[nearest_G]], axis=-1)
  return origin, cell, dims, values.astype(np.float32)


def distance_grid(pc2_BxMx3, cell: float, max_cells: int, margin: float,
                  search: str = "auto") -> Grid:
  """The distance grid of each cloud of the batch, built where `search` says (SEARCHES): on the
  host (`host_distance_grid`) or on the device (`device_distance_grid`)."""
  check_search(search)
  host = functools.partial(host_distance_grid, cell=cell, max_cells=max_cells, margin=margin)
  device = functools.partial(device_distance_grid, cell=cell, max_cells=max_cells, margin=margin)
  if search == "host":
    return host(pc2_BxMx3)
  if search == "device":
    return device(pc2_BxMx3)
  return jax.lax.platform_dependent(pc2_BxMx3, cpu=host, default=device)


def device_distance_grid(pc2_BxMx3, cell: float, max_cells: int, margin: float,
                         block: int = 8 * DEVICE_BLOCK_ELEMENTS) -> Grid:
  """`grid_layout`'s grid with the EXACT distance to the nearest point at each node, by brute force
  on the device (all max_cells nodes against all points, `block` // M nodes at a time: O(max_cells
  x M), tens of ms on a GPU at 2^22 nodes and 8192 points; the host's distance transform is
  within a cell of it)."""
  pc2_BxMx3 = jax.lax.stop_gradient(pc2_BxMx3).astype(jnp.float32)
  m = pc2_BxMx3.shape[1]

  def layout(points_Mx3):  # grid_layout in float32 (the host's is float64: a hair apart)
    lo_3 = jnp.min(points_Mx3, axis=0) - margin
    extent_3 = jnp.max(points_Mx3, axis=0) + margin - lo_3
    size = jnp.maximum(jnp.maximum(cell, (jnp.prod(extent_3) / max_cells) ** (1 / 3)), 1e-6)
    dims_of = lambda size: jnp.floor(extent_3 / size) + 2  # float: no int32 overflow
    size = jax.lax.while_loop(lambda c: jnp.prod(dims_of(c)) > max_cells, lambda c: c * 1.02, size)
    return lo_3, size, dims_of(size).astype(jnp.int32)

  origin_Bx3, cell_B, dims_Bx3 = jax.vmap(layout)(pc2_BxMx3)
  g_G = jnp.arange(max_cells, dtype=jnp.int32)

  def nodes(origin_3, size, dims_3):  # node (i, j, k) of each flat C-order index
    ijk_Gx3 = jnp.stack([g_G // (dims_3[1] * dims_3[2]), (g_G // dims_3[2]) % dims_3[1],
                         g_G % dims_3[2]], -1)
    return origin_3 + size * ijk_Gx3.astype(jnp.float32)

  nodes_BxGx3 = jax.vmap(nodes)(origin_Bx3, cell_B, dims_Bx3)

  def nearest_sq(n_BxCx3):
    return jnp.min(_squared_differences(n_BxCx3, pc2_BxMx3), axis=-1)

  sq_BxG = geometry.map_row_chunks(nearest_sq, (nodes_BxGx3,), max(1, block // max(m, 1)))
  inside_BxG = g_G[None] < jnp.prod(dims_Bx3, axis=1)[:, None]
  return Grid(origin_Bx3, cell_B, dims_Bx3, jnp.where(inside_BxG, jnp.sqrt(sq_BxG), 0.0))


def host_distance_grid(pc2_BxMx3, cell: float, max_cells: int, margin: float) -> Grid:
  """The distance grid of each cloud of the batch, built on the host (scipy) inside jit."""
  b = pc2_BxMx3.shape[0]
  shapes = (jax.ShapeDtypeStruct((b, 3), jnp.float32), jax.ShapeDtypeStruct((b,), jnp.float32),
            jax.ShapeDtypeStruct((b, 3), jnp.int32),
            jax.ShapeDtypeStruct((b, max_cells), jnp.float32))

  def build(pc2):
    out = [np.zeros(s.shape, s.dtype) for s in shapes]
    for i, points in enumerate(np.asarray(pc2, np.float64)):
      origin, c, dims, values = distance_grid_np(points, cell, max_cells, margin)
      out[0][i], out[1][i], out[2][i] = origin, c, dims
      out[3][i, :len(values)] = values
    return tuple(out)

  return Grid(*jax.pure_callback(build, shapes, jax.lax.stop_gradient(pc2_BxMx3),
                                 vmap_method="sequential"))


def grid_distance(grid: Grid, points_BxNx3):
  """Trilinear read of the grid at the points (B x N); points outside are clamped to the box."""

  def one(origin, cell, dims, values, pts_Nx3):
    top = (dims - 1).astype(jnp.float32)
    u_Nx3 = jnp.clip((pts_Nx3 - origin) / cell, 0.0, top)
    i0_Nx3 = jnp.minimum(jnp.floor(u_Nx3), jnp.maximum(top - 1, 0)).astype(jnp.int32)
    t_Nx3 = u_Nx3 - i0_Nx3
    total = 0.0
    for corner in range(8):
      bit_3 = jnp.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], jnp.int32)
      idx_Nx3 = jnp.minimum(i0_Nx3 + bit_3, dims - 1)
      flat_N = (idx_Nx3[:, 0] * dims[1] + idx_Nx3[:, 1]) * dims[2] + idx_Nx3[:, 2]
      weight_N = jnp.prod(jnp.where(bit_3 == 1, t_Nx3, 1.0 - t_Nx3), axis=-1)
      total = total + weight_N * values[flat_N]
    return total

  return jax.vmap(one)(*grid, points_BxNx3)


def grid_chamfer(grid: Grid, warped_BxNx3, truncate: float):
  """The warped -> pc2 Chamfer term through the grid: mean of min(d, truncate)^2 (B)."""
  return jnp.mean(jnp.minimum(grid_distance(grid, warped_BxNx3), truncate) ** 2, axis=1)

