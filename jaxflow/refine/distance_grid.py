"""The distance to a cloud sampled once per pair on a voxel grid and read by trilinear
interpolation at any point: the fast objective of jaxflow.refine.optimiser (the FNSF idea: a step
costs O(N), not O(N x M)).

The grid covers pc2's box plus `margin` metres (beyond it every point is farther than `margin`
from pc2, so a term truncated at <= margin is constant there) and holds at most `max_cells` nodes:
cells grow for large extents, so memory stays bounded for whole sweeps. It is built once per
pair where `search` says: scipy's distance transform on the host, or the exact distances by
brute force on the device.
"""

import functools
import typing

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from jaxflow.geometry import ops
from jaxflow.geometry.neighbours import (DEVICE_BLOCK_ELEMENTS, check_search, resolved,
                                         squared_differences)


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
  holder = holder.reshape(tuple(dims))
  nearest = ndimage.distance_transform_edt(holder < 0, return_distances=False, return_indices=True)
  held = holder[tuple(nearest)]  # the point of each node's nearest occupied node
  # Axis by axis, each node's coordinate broadcast from its axis: no G x 3 array of nodes (2.6x
  # faster at 2^22 nodes, the same values).
  sq = np.zeros(tuple(dims), np.float64)
  for a in range(3):
    own = (np.arange(dims[a]) * cell + origin[a]).reshape([-1 if i == a else 1 for i in range(3)])
    sq += (own - np.asarray(points_Mx3[:, a], np.float64)[held]) ** 2
  values = np.sqrt(sq).reshape(-1)
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
    return jnp.min(squared_differences(n_BxCx3, pc2_BxMx3), axis=-1)

  sq_BxG = ops.map_row_chunks(nearest_sq, (nodes_BxGx3,), max(1, block // max(m, 1)))
  inside_BxG = g_G[None] < jnp.prod(dims_Bx3, axis=1)[:, None]
  return Grid(origin_Bx3, cell_B, dims_Bx3, jnp.where(inside_BxG, jnp.sqrt(sq_BxG), 0.0))


def _grid_shapes(b: int, max_cells: int):
  return (jax.ShapeDtypeStruct((b, 3), jnp.float32), jax.ShapeDtypeStruct((b,), jnp.float32),
          jax.ShapeDtypeStruct((b, 3), jnp.int32),
          jax.ShapeDtypeStruct((b, max_cells), jnp.float32))


def _host_grids(pc2_BxMx3, cell: float, max_cells: int, margin: float):
  """The fields of the batch's Grid in NumPy (distance_grid_np of each cloud, padded)."""
  pc2 = np.asarray(pc2_BxMx3, np.float64)
  out = [np.zeros(s.shape, s.dtype) for s in _grid_shapes(len(pc2), max_cells)]
  for i, points in enumerate(pc2):
    origin, c, dims, values = distance_grid_np(points, cell, max_cells, margin)
    out[0][i], out[1][i], out[2][i] = origin, c, dims
    out[3][i, :len(values)] = values
  return tuple(out)


def host_distance_grid(pc2_BxMx3, cell: float, max_cells: int, margin: float) -> Grid:
  """The distance grid of each cloud of the batch, built on the host (scipy) inside jit."""
  build = functools.partial(_host_grids, cell=cell, max_cells=max_cells, margin=margin)
  return Grid(*jax.pure_callback(build, _grid_shapes(pc2_BxMx3.shape[0], max_cells),
                                 jax.lax.stop_gradient(pc2_BxMx3), vmap_method="sequential"))


_device_grid = jax.jit(device_distance_grid, static_argnums=(1, 2, 3))


def distance_grid_now(pc2_BxMx3, cell: float, max_cells: int, margin: float,
                      search: str = "auto") -> Grid:
  """`distance_grid` built at once, outside jit (no host callback in any compiled program)."""
  if resolved(search) == "host":
    return Grid(*map(jnp.asarray, _host_grids(pc2_BxMx3, cell, max_cells, margin)))
  return _device_grid(pc2_BxMx3, cell, max_cells, margin)


def _trilinear(origin, cell, dims, values, pts_Nx3):
  """The trilinear read at the points (N) and its gradient in the points (N x 3), both from the
  8 corners: written out, the gradient costs a few multiplies (autodiff of the read built a
  backward pass 6x the forward's time on the CPU). Points outside are clamped to the box, where the
  gradient across the clamped axis is 0."""
  top = (dims - 1).astype(jnp.float32)
  u_Nx3 = (pts_Nx3 - origin) / cell
  inside_Nx3 = (u_Nx3 > 0.0) & (u_Nx3 < top)
  u_Nx3 = jnp.clip(u_Nx3, 0.0, top)
  i0_Nx3 = jnp.minimum(jnp.floor(u_Nx3), jnp.maximum(top - 1, 0)).astype(jnp.int32)
  t_Nx3 = u_Nx3 - i0_Nx3
  corner = {}
  for a in (0, 1):
    for b in (0, 1):
      for c in (0, 1):
        idx_Nx3 = jnp.minimum(i0_Nx3 + jnp.array([a, b, c], jnp.int32), dims - 1)
        corner[a, b, c] = values[(idx_Nx3[:, 0] * dims[1] + idx_Nx3[:, 1]) * dims[2]
                                 + idx_Nx3[:, 2]]
  tx, ty, tz = t_Nx3[:, 0], t_Nx3[:, 1], t_Nx3[:, 2]
  lerp = lambda lo, hi, t: lo + t * (hi - lo)
  # Along z, then y, then x; each partial derivative is the difference across its axis.
  z = {(a, b): lerp(corner[a, b, 0], corner[a, b, 1], tz) for a in (0, 1) for b in (0, 1)}
  y = {a: lerp(z[a, 0], z[a, 1], ty) for a in (0, 1)}
  value = lerp(y[0], y[1], tx)
  d_tx = y[1] - y[0]
  d_ty = lerp(z[0, 1] - z[0, 0], z[1, 1] - z[1, 0], tx)
  d_tz = lerp(lerp(corner[0, 0, 1] - corner[0, 0, 0], corner[0, 1, 1] - corner[0, 1, 0], ty),
              lerp(corner[1, 0, 1] - corner[1, 0, 0], corner[1, 1, 1] - corner[1, 1, 0], ty), tx)
  grad_Nx3 = jnp.stack([d_tx, d_ty, d_tz], -1) * inside_Nx3 / cell
  return value, grad_Nx3


@jax.custom_vjp
def _grid_read(grid: Grid, points_BxNx3):
  return jax.vmap(_trilinear)(*grid, points_BxNx3)[0]


def _grid_read_fwd(grid, points_BxNx3):
  value, grad = jax.vmap(_trilinear)(*grid, points_BxNx3)
  return value, (grid, grad)


def _grid_read_bwd(saved, cotangent_BxN):
  grid, grad_BxNx3 = saved
  zeros = jax.tree.map(lambda a: jnp.zeros(a.shape, jax.dtypes.float0) if jnp.issubdtype(
    a.dtype, jnp.integer) else jnp.zeros_like(a), grid)  # the grid is data, not a parameter
  return zeros, cotangent_BxN[..., None] * grad_BxNx3


_grid_read.defvjp(_grid_read_fwd, _grid_read_bwd)


def grid_distance(grid: Grid, points_BxNx3):
  """Trilinear read of the grid at the points (B x N); points outside are clamped to the box.
  Differentiable in the points (not in the grid)."""
  return _grid_read(grid, points_BxNx3)


def grid_chamfer(grid: Grid, warped_BxNx3, truncate: float):
  """The warped -> pc2 Chamfer term through the grid: mean of min(d, truncate)^2 (B)."""
  return jnp.mean(jnp.minimum(grid_distance(grid, warped_BxNx3), truncate) ** 2, axis=1)

