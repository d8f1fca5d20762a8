"""Point-graph layers: SetConv (PV-RAFT / FLOT) and the graph convolutional layer (GCL)."""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxflow.geometry import ops

# GroupNorm as in the reference: 8 groups, epsilon 1e-5, exact (two-pass) variance.
GroupNorm = functools.partial(nn.GroupNorm, num_groups=8, epsilon=1e-5, use_fast_variance=False)

# model.precision: the precision of every matmul of the network and its kNN (jax.lax.Precision
# names and their aliases). "highest" (= "float32"): exact float32 on every backend (CPU always;
# no TF32 on GPUs; 6 bfloat16 passes on TPUs). "high" (= "tensorfloat32"): TF32 on Ampere/Hopper
# GPUs, 3 bfloat16 passes on TPUs. "default" (= "bfloat16"): the backend's fastest (TF32 on
# A100/H100, one bfloat16 pass on TPUs). The CPU computes float32 at every setting.
PRECISIONS = ("highest", "float32", "high", "tensorfloat32", "default", "bfloat16")


def lax_precision(name: str) -> jax.lax.Precision:
  """The jax.lax.Precision of a model.precision name; ValueError naming the choices otherwise."""
  if name not in PRECISIONS:
    raise ValueError(f"model.precision must be one of {', '.join(PRECISIONS)}, got {name!r}")
  return jax.lax.Precision(name)


def dense(features: int, precision: str, **kwargs) -> nn.Dense:
  """nn.Dense at the model's matmul precision (its gradient's matmuls inherit it)."""
  return nn.Dense(features, precision=lax_precision(precision), **kwargs)


def leaky_relu(x):
  return nn.leaky_relu(x, negative_slope=0.1)


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


class EdgeNormMax(nn.Module):
  """max over neighbours j of GroupNorm(edge i -> j) per point and channel (`edge_values`).

  GroupNorm as `GroupNorm` (8 groups, its parameters "scale" and "bias", exact two-pass variance)
  over every edge of a cloud. The edges are formed a block of points at a time where they are
  reduced (EDGE_BLOCK), forward and backward: no B x N x K x C tensor is written. The norm is an
  increasing (scale >= 0) or decreasing affine map of each channel, so the max of the normalised
  edges is the normalised max (or min) of the edges, to the bit (`edge_extreme`).
  """

  groups: int = 8
  epsilon: float = 1e-5

  @nn.compact
  def __call__(self, z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK):
    c = w_DxC.shape[-1]
    scale = self.param("scale", nn.initializers.ones, (c,))
    bias = self.param("bias", nn.initializers.zeros, (c,))
    mean_BxG, var_BxG = edge_group_stats(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, self.groups)
    per_channel = lambda v_BxG: jnp.repeat(v_BxG, c // self.groups, axis=-1)[:, None, :]
    mul_Bx1xC = per_channel(jax.lax.rsqrt(var_BxG + self.epsilon)) * scale
    extreme_BxNxC = edge_extreme(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK,
                                 jax.lax.stop_gradient(mul_Bx1xC < 0))
    return (extreme_BxNxC - per_channel(mean_BxG)) * mul_Bx1xC + bias


class Kernel(nn.Module):
  """A bias-free nn.Dense's parameter alone ("kernel", D x C, nn.Dense's initialiser)."""

  features: int

  @nn.compact
  def __call__(self, inputs: int):
    return self.param("kernel", nn.linear.default_kernel_init, (inputs, self.features))


class DenseParams(nn.Module):
  """nn.Dense's parameters alone ("kernel" D x C, "bias" C; nn.Dense's initialisers)."""

  features: int

  @nn.compact
  def __call__(self, inputs: int):
    return (self.param("kernel", nn.linear.default_kernel_init, (inputs, self.features)),
            self.param("bias", nn.initializers.zeros, (self.features,)))


class NormParams(nn.Module):
  """nn.GroupNorm's parameters alone ("scale" ones, "bias" zeros, C each)."""

  features: int

  @nn.compact
  def __call__(self):
    return (self.param("scale", nn.initializers.ones, (self.features,)),
            self.param("bias", nn.initializers.zeros, (self.features,)))


class SetConv(nn.Module):
  """PointNet-style graph layer: per-edge MLP, max over neighbours, then two point-wise layers.

  Edge feature of i -> j: concat(f_j - f_i, p_j - p_i) -> fc1 -> GroupNorm over all points and
  neighbours (the reference's 2D GroupNorm) -> LeakyReLU -> max over neighbours. fc1 has no bias,
  so fc1 of an edge is W_f f_j - W_f f_i + W_p (p_j - p_i): the feature part is one matmul per
  point (K times fewer flops), the offsets' part a few products per edge, and no edge tensor is
  stored (EdgeNormMax).
  """

  features: int
  precision: str = "highest"

  @nn.compact
  def __call__(self, f_BxNxC, xyz_BxNx3, nbr_BxNxK):
    c_in = f_BxNxC.shape[-1]
    mid = (c_in + self.features) // 2 if c_in % 2 == 0 else self.features // 2
    w_DxM = Kernel(mid, name="fc1")(c_in + 3)
    if c_in <= 3:  # coordinates or a flow: every part as offsets, which keep their digits
      z_BxNxM = None
      x_BxNxD = jnp.concatenate([f_BxNxC, xyz_BxNx3], axis=-1)
    else:
      z_BxNxM = jnp.einsum("bnc,cm->bnm", f_BxNxC, w_DxM[:c_in],
                           precision=lax_precision(self.precision))
      x_BxNxD, w_DxM = xyz_BxNx3, w_DxM[c_in:]
    fc = lambda width, name: dense(width, self.precision, use_bias=False, name=name)
    x = leaky_relu(EdgeNormMax(name="gn1")(z_BxNxM, x_BxNxD, w_DxM, nbr_BxNxK))
    x = leaky_relu(GroupNorm(name="gn2")(fc(self.features, "fc2")(x)))
    x = leaky_relu(GroupNorm(name="gn3")(fc(self.features, "fc3")(x)))
    return x


def safe_normalize(v, eps: float = 1e-8):
  """v / |v| with 0 for v = 0 and finite gradients there (the self edge of a graph has v = 0)."""
  sq = jnp.sum(v * v, axis=-1, keepdims=True)
  return v * jax.lax.rsqrt(jnp.maximum(sq, eps * eps)) * (sq > 0)


def _uniform_pm1(key, shape, dtype=jnp.float32):
  return jax.random.uniform(key, shape, dtype, -1.0, 1.0)


def _similarity(support, cos, similarity: str):
  return support + cos if similarity == "sum" else nn.relu(cos) * support


def cosines(unit_v_Xx3, unit_e_3xC, precision="highest"):
  """unit_v . unit_e for every row of unit_v and column of unit_e: X x C.

  On the CPU one matmul (XLA's CPU backend stores the B x N x K x LC result either way, and a
  matmul's is the only copy); elsewhere three products, which XLA fuses with the gathers into
  the max over neighbours, so that no such tensor is stored (benchmarks/NETWORK_GPU.md). Decided
  when XLA lowers the program for its device.
  """
  matmul = lambda v, e: jnp.einsum("...d,dc->...c", v, e, precision=lax_precision(precision))
  products = lambda v, e: sum(v[..., d, None] * e[d] for d in range(3))
  return jax.lax.platform_dependent(unit_v_Xx3, unit_e_3xC, cpu=matmul, default=products)


def edge_similarity(support_BxMxLC, unit_v_BxNxKx3, unit_e_3xLC, nbr_BxNxK, similarity,
                    precision="highest"):
  """sim(j, l) of every neighbour j, per point and channel: B x N x K x LC."""
  cos_BxNxKxLC = cosines(unit_v_BxNxKx3, unit_e_3xLC, precision)
  return _similarity(ops.gather(support_BxMxLC, nbr_BxNxK), cos_BxNxKxLC, similarity)


def _best_at(k_BxNxLC, support_BxMxLC, unit_v_BxNxKx3, unit_e_3xLC, nbr_BxNxK, similarity,
             precision):
  """sim(j, l) at the given neighbour slot k of each point and channel: B x N x LC."""
  j_BxNxLC = jnp.take_along_axis(nbr_BxNxK, k_BxNxLC, axis=2)
  support = jnp.take_along_axis(support_BxMxLC, j_BxNxLC, axis=1)
  unit_v_BxNxLCx3 = jnp.take_along_axis(unit_v_BxNxKx3, k_BxNxLC[..., None], axis=2)
  cos = jnp.einsum("bncd,dc->bnc", unit_v_BxNxLCx3, unit_e_3xLC,
                   precision=lax_precision(precision))
  return _similarity(support, cos, similarity)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5))
def neighbour_max(support_BxMxLC, unit_v_BxNxKx3, unit_e_3xLC, nbr_BxNxK, similarity: str,
                  precision: str = "highest"):
  """GCL's max over neighbours, whose gradient is taken at the winning neighbour only.

  Autodiff of the max would carry B x N x K x LC cotangents through the gather and the cosines
  (most of a training step's encoder time on the CPU); at the argmax they are B x N x LC. Same
  value and, away from ties, the same gradient (tests/test_ops.py). The similarities are formed
  a block of points at a time (EDGE_BLOCK of them), which XLA's CPU backend would write out for
  the whole cloud at once (B x N x K x LC, 1.5 GiB for a GCL of 256 channels at 8192 points).
  """
  return _neighbour_max_fwd(support_BxMxLC, unit_v_BxNxKx3, unit_e_3xLC, nbr_BxNxK, similarity,
                            precision)[0]


def _neighbour_max_fwd(support_BxMxLC, unit_v_BxNxKx3, unit_e_3xLC, nbr_BxNxK, similarity,
                       precision):
  b, n, k = nbr_BxNxK.shape
  blocks = -(-n // max(1, EDGE_BLOCK // (b * k * support_BxMxLC.shape[-1])))

  def block(unit_v_BxRxKx3, nbr_BxRxK):
    sim = edge_similarity(support_BxMxLC, unit_v_BxRxKx3, unit_e_3xLC, nbr_BxRxK, similarity,
                          precision)
    return jnp.max(sim, axis=2), jnp.argmax(sim, axis=2).astype(nbr_BxRxK.dtype)

  best_BxNxLC, k_BxNxLC = ops.map_row_chunks(block, (unit_v_BxNxKx3, nbr_BxNxK),
                                             -(-n // blocks) if blocks > 1 else 0)
  residuals = (k_BxNxLC, support_BxMxLC, unit_v_BxNxKx3, unit_e_3xLC, nbr_BxNxK)
  return best_BxNxLC, residuals


def _neighbour_max_bwd(similarity, precision, residuals, g_BxNxLC):
  k_BxNxLC, support, unit_v, unit_e, nbr = residuals
  _, vjp = jax.vjp(lambda s, v, e: _best_at(k_BxNxLC, s, v, e, nbr, similarity, precision),
                   support, unit_v, unit_e)
  return (*vjp(g_BxNxLC), None)


neighbour_max.defvjp(_neighbour_max_fwd, _neighbour_max_bwd)


class GCL(nn.Module):
  """Graph convolutional layer (paper eq. 1-5, after 3D-GCN).

  out_i = <f_i, w(e')> + b + sum_l max_j sim(j, l), with
  sim = <f_j, w(e_l)> + cos(p_j - p_i, e_l)                  (similarity="sum", the paper's)
  sim = ReLU(cos(p_j - p_i, e_l)) * <f_j, w(e_l)>           (similarity="product", 3D-GCN's)
  Each output channel has its own L support directions e_l. f @ [w(e'), w(e_1..L)] is one matmul
  over all points; only its support part is gathered per neighbour.
  """

  features: int
  supports: int = 3
  similarity: str = "sum"
  precision: str = "highest"

  @nn.compact
  def __call__(self, f_BxNxC, xyz_BxNx3, nbr_BxNxK):
    if self.similarity not in ("sum", "product"):
      raise ValueError(f"GCL similarity must be 'sum' or 'product', got {self.similarity!r}")
    l, c = self.supports, self.features
    w = dense((l + 1) * c, self.precision, use_bias=False, name="kernel")(f_BxNxC)
    centre_BxNxC, support_BxNxLC = w[..., :c], w[..., c:]
    # 3D-GCN initialises directions uniformly in [-1, 1]^3 (per channel and support).
    directions_3xLC = self.param("directions", _uniform_pm1, (3, l * c))
    v_BxNxKx3 = ops.gather(xyz_BxNx3, nbr_BxNxK) - xyz_BxNx3[:, :, None, :]
    unit_e_3xLC = safe_normalize(directions_3xLC.T).T
    best_BxNxLC = neighbour_max(support_BxNxLC, safe_normalize(v_BxNxKx3), unit_e_3xLC,
                                nbr_BxNxK, self.similarity, self.precision)
    b, n = best_BxNxLC.shape[:2]
    summed_BxNxC = jnp.sum(best_BxNxLC.reshape(b, n, l, c), axis=2)
    bias = self.param("bias", nn.initializers.zeros, (c,))
    return centre_BxNxC + summed_BxNxC + bias
