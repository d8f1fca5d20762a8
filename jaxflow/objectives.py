"""The self-supervised objectives of flow optimisation (jaxflow.optimiser: NSFP, test time).

One Chamfer term, one smoothness term, one distance transform:
- `nearest` / `chamfer_terms`: the exact nearest-point squared distances, the points found by a
  k-d tree on the host (`host_knn`, scipy: O(N log M), ~4 ms for 8192 x 8192 points on a 2-core
  CPU against ~100 ms for the network's brute-force `geometry.knn`).
- `smoothness`: mean L1 difference of the flow over pc1's k-nearest graph.
- `distance_grid` / `grid_distance`: the distance to pc2 sampled once per pair on a voxel grid and
  read by trilinear interpolation at any point (the FNSF idea: a step costs O(N), not O(N x M)).
  The grid covers pc2's box plus `margin` metres (beyond it every point is farther than `margin`
  from pc2, so a term truncated at <= margin is constant there) and holds at most `max_cells` nodes:
  cells grow for large extents, so memory stays bounded for whole sweeps.
"""

import typing

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage, spatial

from jaxflow import geometry


def host_knn(query_BxNx3, points_BxMx3, k: int):
  """Indices B x N x k' (k' = min(k, M), nearest first) of each query's nearest points, exact
  Euclidean, by scipy's k-d tree on the host inside jit (a constant of the gradient)."""
  b, n, _ = query_BxNx3.shape
  k = min(k, points_BxMx3.shape[1])
  shape = jax.ShapeDtypeStruct((b, n, k), jnp.int32)

  def search(query, points):
    out = np.zeros(shape.shape, np.int32)
    for i, (q, p) in enumerate(zip(np.asarray(query, np.float64), np.asarray(points, np.float64))):
      out[i] = spatial.cKDTree(p).query(q, k=[*range(1, k + 1)], workers=-1)[1]
    return out

  return jax.pure_callback(search, shape, jax.lax.stop_gradient(query_BxNx3),
                           jax.lax.stop_gradient(points_BxMx3), vmap_method="sequential")


def nearest(query_BxNx3, points_BxMx3):
  """Index B x N x 1 of the nearest point of `points` to each query (a constant of the gradient)."""
  return host_knn(query_BxNx3, points_BxMx3, 1)


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


def chamfer(a_BxNx3, b_BxMx3, truncate: float):
  """Truncated two-way Chamfer distance (B) with the nearest points searched now."""
  match = (nearest(a_BxNx3, b_BxMx3), nearest(b_BxMx3, a_BxNx3))
  return chamfer_terms(a_BxNx3, b_BxMx3, match, truncate)


def neighbours(pc1_BxNx3, k: int):
  """pc1's k nearest other points, B x N x k' (k' = min(k, N - 1); at least the point itself)."""
  n = pc1_BxNx3.shape[1]
  if n == 1:
    return jnp.zeros((pc1_BxNx3.shape[0], 1, 1), jnp.int32)
  return host_knn(pc1_BxNx3, pc1_BxNx3, min(k, n - 1) + 1)[:, :, 1:]


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


def distance_grid(pc2_BxMx3, cell: float, max_cells: int, margin: float) -> Grid:
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

