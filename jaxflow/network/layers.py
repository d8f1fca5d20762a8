"""Point-graph layers: SetConv (PV-RAFT / FLOT) and the graph convolutional layer (GCL)."""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxflow.geometry import ops
from jaxflow.network import edges

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


class EdgeNormMax(nn.Module):
  """max over neighbours j of GroupNorm(edge i -> j) per point and channel
  (jaxflow.network.edges.edge_values).

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
    mean_BxG, var_BxG = edges.edge_group_stats(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK, self.groups)
    per_channel = lambda v_BxG: jnp.repeat(v_BxG, c // self.groups, axis=-1)[:, None, :]
    mul_Bx1xC = per_channel(jax.lax.rsqrt(var_BxG + self.epsilon)) * scale
    extreme_BxNxC = edges.edge_extreme(z_BxNxC, x_BxNxD, w_DxC, nbr_BxNxK,
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
  blocks = -(-n // max(1, edges.EDGE_BLOCK // (b * k * support_BxMxLC.shape[-1])))

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
