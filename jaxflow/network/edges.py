"""Edge reductions of the point-graph layers (jaxflow.network.layers) by blocks of points: the
value of every edge i -> j of a SetConv, their GroupNorm statistics over a cloud and their max over
neighbours, formed EDGE_BLOCK edges at a time where they are reduced, forward and backward, so
that no B x N x K x C tensor is written."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxflow.geometry import ops

# The edges a SetConv or GCL forms at once (elements: 8 MiB of float32). Their reductions over
# the edges (the norm's sums, the max over neighbours, their gradients) run over blocks of points
# this size under lax.map, so that no B x N x K x C tensor is written, forward or backward:
# autodiff of whole-cloud reductions kept every layer's edges for the backward (most of a
# training step's memory on the CPU) and XLA's CPU backend writes them out even in inference.
EDGE_BLOCK = 1 << 21


def edge_values(z_BxMxC, x_BxMxD, w_DxC, nbr_BxRxK, zc_BxRxC=None, xc_BxRxD=None):
  """z_j - z_i + w . (x_j - x_i) of every edge i -> j (z None: 0): B x R x K x C.

  The centres i are the first R points of z and x, or zc and xc where given (a block of them).
  The x part is written out as D products per channel, not a matmul, so that the offsets keep
  their digits (an encoder's first layer: coordinates far from the origin).
  """
  zc_BxRxC = z_BxMxC if zc_BxRxC is None else zc_BxRxC
  xc_BxRxD = x_BxMxD if xc_BxRxD is None else xc_BxRxD
  edges = 0.0 if z_BxMxC is None else ops.gather(z_BxMxC, nbr_BxRxK) - zc_BxRxC[:, :, None, :]
  offsets_BxRxKxD = ops.gather(x_BxMxD, nbr_BxRxK) - xc_BxRxD[:, :, None, :]
  for d in range(x_BxMxD.shape[-1]):
    edges = edges + offsets_BxRxKxD[..., d, None] * w_DxC[d]
  return edges


def _point_blocks(z_BxNxC, x_BxNxD, nbr_BxNxK, channels: int):
  """The points in blocks of R rows (EDGE_BLOCK edges a block): z and x padded to the blocks'
  rows, nbr as blocks x B x R x K, each block's first row and its rows' validity (blocks x R)."""
  b, n, k = nbr_BxNxK.shape
  blocks = -(-n // max(1, EDGE_BLOCK // (b * k * channels)))
  rows = -(-n // blocks)  # the fewest padded rows
  pad = lambda a: None if a is None else jnp.pad(a, ((0, 0), (0, blocks * rows - n), (0, 0)))
  nbr_blocks = jnp.moveaxis(pad(nbr_BxNxK).reshape(b, blocks, rows, k), 1, 0)
  valid = (jnp.arange(blocks * rows) < n).reshape(blocks, rows)
  return pad(z_BxNxC), pad(x_BxNxD), (nbr_blocks, jnp.arange(blocks) * rows, valid)


def _block_edges(z_BxMxC, x_BxMxD, w_DxC, nbr_BxRxK, start):
  """edge_values of the R points from row `start` on."""
  rows = nbr_BxRxK.shape[1]
  # Every edge after the barrier depends on z: neither JAX nor XLA hoists the parts that do not
  # (the offsets' products, of the loop-invariant coordinates) out of the iterations' scan, which
  # would store them for every block of the cloud.
  z_BxMxC, x_BxMxD, w_DxC = jax.lax.optimization_barrier((z_BxMxC, x_BxMxD, w_DxC))
  centre = lambda a: None if a is None else jax.lax.dynamic_slice_in_dim(a, start, rows, axis=1)
  return edge_values(z_BxMxC, x_BxMxD, w_DxC, nbr_BxRxK, centre(z_BxMxC), centre(x_BxMxD))


def _edge_at(k_BxNxC, z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK):
  """edge_values at neighbour slot k of each point and channel: B x N x C."""
  j_BxNxC = jnp.take_along_axis(nbr_BxNxK, k_BxNxC, axis=2)
  edge = 0.0
  if z_BxNxC is not None:
    edge = jnp.take_along_axis(z_BxNxC, j_BxNxC, axis=1) - z_BxNxC
  for d in range(x_BxNxD.shape[-1]):
    x = x_BxNxD[..., d, None]
    edge = edge + (jnp.take_along_axis(jnp.broadcast_to(x, j_BxNxC.shape), j_BxNxC, axis=1)
                   - x) * w_DxC[d]
  return edge


@jax.custom_vjp
def edge_extreme(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, lowest_Bx1xC):
  """max over neighbours of edge_values, min where `lowest`: B x N x C.

  Its gradient goes to the one edge that attains it (the first, in a tie). Autodiff of a max
  finds that edge by comparing the edges with the max, and a GPU that recomputes the edges in
  another fused kernel may round them otherwise and find none.
  """
  return _edge_extreme_fwd(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, lowest_Bx1xC)[0]


def _edge_extreme_fwd(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, lowest_Bx1xC):
  b, n, _ = nbr_BxNxK.shape
  z_pad, x_pad, blocks = _point_blocks(z_BxNxC, x_BxNxD, nbr_BxNxK, w_DxC.shape[-1])

  def block(args):
    nbr_BxRxK, start, _ = args
    edges = _block_edges(z_pad, x_pad, w_DxC, nbr_BxRxK, start)
    signed = jnp.where(lowest_Bx1xC[:, :, None], -edges, edges)
    k_BxRxC = jnp.argmax(signed, axis=2).astype(nbr_BxNxK.dtype)
    return jnp.where(lowest_Bx1xC, jnp.min(edges, axis=2), jnp.max(edges, axis=2)), k_BxRxC

  merge = lambda a: jnp.moveaxis(a, 0, 1).reshape(b, -1, a.shape[-1])[:, :n]
  extreme, k_BxNxC = map(merge, jax.lax.map(block, blocks))
  return extreme, (k_BxNxC, z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, lowest_Bx1xC)


def _edge_extreme_bwd(residuals, g_BxNxC):
  k_BxNxC, z, x, w, nbr, lowest = residuals
  _, vjp = jax.vjp(lambda z_, x_, w_: _edge_at(k_BxNxC, z_, x_, w_, nbr), z, x, w)
  return (*vjp(g_BxNxC), None, np.zeros(lowest.shape, jax.dtypes.float0))


edge_extreme.defvjp(_edge_extreme_fwd, _edge_extreme_bwd)


def _group_sums(edges_BxRxKxC, valid_R, groups: int, mean_BxG=None):
  """Sums B x G over a block's valid edges per group: of the edges, or of their squared
  deviations from mean."""
  b, r, k, c = edges_BxRxKxC.shape
  grouped = edges_BxRxKxC.reshape(b, r, k, groups, c // groups)
  if mean_BxG is not None:
    grouped = jnp.square(grouped - mean_BxG[:, None, None, :, None])
  return jnp.sum(jnp.where(valid_R[:, None, None, None], grouped, 0.0), axis=(1, 2, 4))


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def edge_group_stats(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, groups: int):
  """Mean and (two-pass) variance B x G of edge_values over every edge of a cloud, per group
  of channels, by blocks of points (EDGE_BLOCK); the gradient recomputes each block's edges."""
  return _edge_group_stats_fwd(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, groups)[0]


def _edge_group_stats_fwd(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, groups):
  _, n, k = nbr_BxNxK.shape
  count = n * k * (w_DxC.shape[-1] // groups)
  z_pad, x_pad, blocks = _point_blocks(z_BxNxC, x_BxNxD, nbr_BxNxK, w_DxC.shape[-1])

  def total(mean_BxG=None):
    sums = lambda args: _group_sums(_block_edges(z_pad, x_pad, w_DxC, *args[:2]), args[2],
                                    groups, mean_BxG)
    return jnp.sum(jax.lax.map(sums, blocks), axis=0) / count

  mean_BxG = total()
  return (mean_BxG, total(mean_BxG)), (z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, mean_BxG)


def _edge_group_stats_bwd(groups, residuals, g):
  z, x, w, nbr, mean_BxG = residuals
  _, n, k = nbr.shape
  count = n * k * (w.shape[-1] // groups)
  # Through the barrier the recomputed edges depend on the cotangent: XLA can neither compute
  # them ahead nor merge them with the forward's (which would keep them from forward to backward).
  (z, x, w), g = jax.lax.optimization_barrier(((z, x, w), g))
  g_mean_BxG, g_var_BxG = g
  z_pad, x_pad, blocks = _point_blocks(z, x, nbr, w.shape[-1])

  def block_sums(z_, x_, w_, nbr_BxRxK, start, valid_R):
    # The mean as a constant: the variance's gradient through it is sum(e - mean) = 0.
    edges = _block_edges(z_, x_, w_, nbr_BxRxK, start)
    return (_group_sums(edges, valid_R, groups),
            _group_sums(edges, valid_R, groups, mean_BxG))

  def step(acc, args):
    _, vjp = jax.vjp(lambda *a: block_sums(*a, *args), z_pad, x_pad, w)
    grads = vjp((g_mean_BxG / count, g_var_BxG / count))
    return jax.tree.map(jnp.add, acc, grads), None

  zeros = jax.tree.map(jnp.zeros_like, (z_pad, x_pad, w))
  (g_z, g_x, g_w), _ = jax.lax.scan(step, zeros, blocks)
  unpad = lambda a: None if a is None else a[:, :n]
  return unpad(g_z), unpad(g_x), g_w, None


edge_group_stats.defvjp(_edge_group_stats_fwd, _edge_group_stats_bwd)
