"""PV-RAFT's point-voxel correlation.

Once per pair, `truncated_correlation` keeps for every pc1 point the `truncate_k` largest
feature correlations with pc2 and the xyz of those candidates. At every iteration,
`PointVoxelCorrelation` looks them up (their xyz as three B x N x K planes, `planar`) around the
current estimate y = pc1 + flow:
- point branch: the `knn` candidates nearest to y, [corr, xyz - y] -> MLP -> max;
- voxel branch: per level, 3x3x3 cells of size base_scale * 2**level centred on y, each holding
  the MEAN correlation of the candidates inside it (0 when empty) -> MLP.
Candidate selection and cell membership carry no gradient; correlation values do.
"""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxflow.geometry import ops, select
from jaxflow.network.layers import DenseParams, GroupNorm, NormParams, dense, lax_precision

# model.voxel_cells: how the voxel branch adds candidates into their cells (same values, the sums
# in another order). "scatter": one scatter-add (B x N x K temporaries; XLA's CPU backend runs it
# in one pass). "compare": every candidate compared with every cell (B x N x K x 27; fused on
# GPUs and TPUs, where a scatter adds in a varying order). "auto": "scatter" where the program is
# compiled for the CPU, "compare" elsewhere, decided when XLA lowers it for its device
# (jax.lax.platform_dependent), not by jax.default_backend() when it is traced.
VOXEL_CELLS = ("auto", "scatter", "compare")


def truncated_correlation(f1_BxNxC, f2_BxMxC, xyz2_BxMx3, k: int, chunk: int = 0,
                          precision: str = "highest", selection: str = "auto"):
  """Top-k of corr = F1 F2^T / sqrt(C) per pc1 point (sorted, largest first).

  Returns (corr_BxNxK, xyz_BxNxKx3). With `chunk` > 0 the N x M matrix is built `chunk` rows at a
  time, so memory grows with N (not N x M). `precision`: the matmul's (model.precision);
  `selection`: how the k are selected (select.FORMS: the same candidates in the same order).
  """
  c = f1_BxNxC.shape[-1]
  k = min(k, f2_BxMxC.shape[1])

  def candidates(f1_chunk):
    corr = jnp.einsum("bnc,bmc->bnm", f1_chunk, f2_BxMxC, precision=lax_precision(precision))
    corr = corr / jnp.sqrt(jnp.float32(c))
    values, idx = select.top_k(corr, k, selection)
    return values, ops.gather(xyz2_BxMx3, idx)

  return ops.map_row_chunks(candidates, (f1_BxNxC,), chunk)


def planar(xyz_BxNxKx3):
  """Candidates' xyz as three B x N x K planes (x, y, z).

  The iterations' elementwise work (offsets, distances, cells) then runs along K, which XLA's CPU
  backend vectorises; along the trailing axis of 3 it ran ~2x slower (benchmarks/MODEL.md).
  """
  return tuple(xyz_BxNxKx3[..., a] for a in range(3))


def voxel_means(corr_BxNxK, offset_BxNxKx3, scale: float, resolution: int = 3,
                form: str = "auto"):
  """Mean correlation of the candidates in each of the resolution^3 cells around the estimate.

  offset = candidate xyz - estimate. cell = round(offset / scale); a candidate is inside when
  every |cell| <= resolution // 2; cells are numbered (dx * R + dy) * R + dz with d = cell + R // 2.
  `form` (VOXEL_CELLS) is how candidates are added into their cells.
  """
  return planar_voxel_means(corr_BxNxK, planar(offset_BxNxKx3), scale, resolution, form)


def planar_voxel_means(corr_BxNxK, offsets_3xBxNxK, scale: float, resolution: int = 3,
                       form: str = "auto"):
  """voxel_means of the offsets given as three B x N x K planes (`planar`)."""
  if form not in VOXEL_CELLS:
    raise ValueError(f"model.voxel_cells must be one of {', '.join(VOXEL_CELLS)}, got {form!r}")
  half = resolution // 2
  cells_3xBxNxK = [jnp.round(jax.lax.stop_gradient(o) / scale) for o in offsets_3xBxNxK]
  inside_BxNxK = functools.reduce(jnp.logical_and, [jnp.abs(c) <= half for c in cells_3xBxNxK])
  dx, dy, dz = [(c + half).astype(jnp.int32) for c in cells_3xBxNxK]
  index_BxNxK = (dx * resolution + dy) * resolution + dz
  # The index is what the gradient keeps of every iteration: int8 where the cells fit.
  index_BxNxK = jnp.where(inside_BxNxK, index_BxNxK, -1).astype(
    jnp.int8 if resolution**3 < 128 else jnp.int32)
  scatter = {"auto": None, "scatter": True, "compare": False}[form]
  return cell_means(corr_BxNxK, index_BxNxK, resolution**3, scatter)


def _cell_sums(corr_BxNxK, index_BxNxK, cells: int, scatter: bool | None):
  """Sums and counts B x N x cells of the values in each cell; scatter None: by the platform."""
  if scatter is None:
    # XLA's CPU backend materialises the all-cells comparison (2.7 GB of temporaries for one
    # 8192-point pair with 512 candidates), and runs its scatter in one pass; other backends fuse
    # the comparison, and a GPU scatter adds in a varying order (benchmarks/MODEL.md).
    form = lambda flag: functools.partial(_cell_sums, cells=cells, scatter=flag)
    return jax.lax.platform_dependent(corr_BxNxK, index_BxNxK, cpu=form(True), default=form(False))
  if scatter:
    b, n, k = corr_BxNxK.shape
    # Row (b, n) owns slots (b * N + n) * (cells + 1) + cell; the last slot takes the outsiders.
    slot_BxNxK = jnp.where(index_BxNxK >= 0, index_BxNxK.astype(jnp.int32), cells)
    slot_BxNxK = slot_BxNxK + (cells + 1) * jnp.arange(b * n, dtype=jnp.int32).reshape(b, n, 1)
    # Value and count in one scatter: half the passes of two.
    values_Px2 = jnp.stack([corr_BxNxK.reshape(-1), jnp.ones(b * n * k, corr_BxNxK.dtype)], -1)
    sums = jnp.zeros((b * n * (cells + 1), 2), corr_BxNxK.dtype).at[slot_BxNxK.reshape(-1)].add(
      values_Px2).reshape(b, n, cells + 1, 2)
    return sums[..., :cells, 0], sums[..., :cells, 1]
  member_BxNxKxR = index_BxNxK[..., None] == jnp.arange(cells, dtype=index_BxNxK.dtype)
  sums_BxNxR = jnp.sum(jnp.where(member_BxNxKxR, corr_BxNxK[..., None], 0.0), axis=2)
  return sums_BxNxR, jnp.sum(member_BxNxKxR, axis=2).astype(corr_BxNxK.dtype)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def cell_means(corr_BxNxK, index_BxNxK, cells: int, scatter: bool):
  """Mean of the values in each cell (0 when empty): B x N x cells; index -1 is in no cell.

  The gradient of a candidate's value is its cell's cotangent / count, so it keeps only the index
  and the counts; autodiff of the sums would keep the B x N x K x cells memberships of every
  iteration.
  """
  return _cell_means_fwd(corr_BxNxK, index_BxNxK, cells, scatter)[0]


def _cell_means_fwd(corr_BxNxK, index_BxNxK, cells, scatter):
  sums_BxNxR, counts_BxNxR = _cell_sums(corr_BxNxK, index_BxNxK, cells, scatter)
  return sums_BxNxR / jnp.maximum(counts_BxNxR, 1.0), (index_BxNxK, counts_BxNxR)


def _cell_means_bwd(cells, scatter, residuals, g_BxNxR):
  index_BxNxK, counts_BxNxR = residuals
  per_value_BxNxR = g_BxNxR / jnp.maximum(counts_BxNxR, 1.0)
  g_BxNxK = jnp.take_along_axis(per_value_BxNxR, jnp.maximum(index_BxNxK, 0).astype(jnp.int32),
                                axis=2)
  return jnp.where(index_BxNxK >= 0, g_BxNxK, 0.0), None


cell_means.defvjp(_cell_means_fwd, _cell_means_bwd)


def affine_group_stats(v_BxNxQxD, w_DxC, b_C, groups: int, precision: str = "highest"):
  """Mean and variance B x G of y = v w + b over every point, slot and channel of each group
  of channels, from the mean and covariance of v (centred first: two-pass, as GroupNorm)."""
  b, n, q, _ = v_BxNxQxD.shape
  c = w_DxC.shape[-1]
  mm = functools.partial(jnp.einsum, precision=lax_precision(precision))
  mean_v_BxD = jnp.mean(v_BxNxQxD, axis=(1, 2))
  centred = v_BxNxQxD - mean_v_BxD[:, None, None, :]
  cov_BxDxD = mm("bnqd,bnqe->bde", centred, centred) / (n * q)
  grouped = lambda a_BxC: a_BxC.reshape(b, groups, c // groups)
  mean_BxGxS = grouped(mm("bd,dc->bc", mean_v_BxD, w_DxC) + b_C)
  var_BxGxS = grouped(mm("bde,dc,ec->bc", cov_BxDxD, w_DxC, w_DxC))
  mean_BxG = jnp.mean(mean_BxGxS, axis=-1)
  return mean_BxG, jnp.mean(var_BxGxS + jnp.square(mean_BxGxS - mean_BxG[..., None]), axis=-1)


def _slot_values(k_BxNxC, v_BxNxQxD, w_DxC, b_C):
  """v w + b at slot k of each point and channel: B x N x C."""
  y = b_C
  for d in range(v_BxNxQxD.shape[-1]):
    y = y + jnp.take_along_axis(v_BxNxQxD[..., d], k_BxNxC, axis=2) * w_DxC[d]
  return y


@jax.custom_vjp
def slot_extremes(v_BxNxQxD, w_DxC, b_C):
  """(max, min) over the Q slots of y = v w + b, per point and channel: two B x N x C.

  The D products are written out, so that XLA fuses them into the reductions (no B x N x Q x C
  tensor); the gradient goes to the slot that attains each (the first, in a tie).
  """
  return _slot_extremes_fwd(v_BxNxQxD, w_DxC, b_C)[0]


def _slot_extremes_fwd(v_BxNxQxD, w_DxC, b_C):
  y = b_C
  for d in range(v_BxNxQxD.shape[-1]):
    y = y + v_BxNxQxD[..., d, None] * w_DxC[d]
  slots = [jnp.argmax(y, axis=2), jnp.argmin(y, axis=2)]
  ends = tuple(_slot_values(k, v_BxNxQxD, w_DxC, b_C) for k in slots)
  return ends, (slots, v_BxNxQxD, w_DxC, b_C)


def _slot_extremes_bwd(residuals, g):
  slots, v, w, b = residuals
  _, vjp = jax.vjp(lambda *a: tuple(_slot_values(k, *a) for k in slots), v, w, b)
  return vjp(g)


slot_extremes.defvjp(_slot_extremes_fwd, _slot_extremes_bwd)


class PointVoxelCorrelation(nn.Module):
  """Correlation feature J (B x N x 64) of the candidates around the current estimate."""

  knn: int = 32
  levels: int = 3
  base_scale: float = 0.25
  features: int = 64
  precision: str = "highest"
  voxel_cells: str = "auto"

  @nn.compact
  def __call__(self, corr_BxNxK, xyz_3xBxNxK, coords_BxNx3):
    """corr_BxNxK and the candidates' xyz as three B x N x K planes (`planar`)."""
    offsets_3xBxNxK = [xyz_3xBxNxK[a] - coords_BxNx3[:, :, a, None] for a in range(3)]
    # Point branch.
    dist_BxNxK = sum(jax.lax.stop_gradient(o) ** 2 for o in offsets_3xBxNxK)
    knn = min(self.knn, corr_BxNxK.shape[-1])
    near_BxNxQ = jax.lax.top_k(-dist_BxNxK, knn)[1]
    near_corr = jnp.take_along_axis(corr_BxNxK, near_BxNxQ, axis=2)
    near_offset = [jnp.take_along_axis(o, near_BxNxQ, axis=2) for o in offsets_3xBxNxK]
    v_BxNxQx4 = jnp.stack([near_corr, *near_offset], axis=-1)
    # max over the Q of PReLU(GroupNorm(dense(v))) without the B x N x Q x 64 values: the norm's
    # statistics follow from v's mean and covariance (dense is affine), and the norm is a monotone
    # map of each channel and PReLU convex or increasing, so the max over the Q is that of the
    # two ends of each channel's range (`slot_extremes`).
    w_4xC, b_C = DenseParams(64, name="knn_conv")(v_BxNxQx4.shape[-1])
    scale_C, shift_C = NormParams(64, name="knn_norm")()
    mean_BxG, var_BxG = affine_group_stats(v_BxNxQx4, w_4xC, b_C, 8, self.precision)
    per_channel = lambda v_BxG: jnp.repeat(v_BxG, 64 // 8, axis=-1)[:, None, :]
    mul_Bx1xC = per_channel(jax.lax.rsqrt(var_BxG + 1e-5)) * scale_C
    act = nn.PReLU(negative_slope_init=0.25, name="knn_act")
    ends = [act((y - per_channel(mean_BxG)) * mul_Bx1xC + shift_C)
            for y in slot_extremes(v_BxNxQx4, w_4xC, b_C)]
    point_BxNxF = dense(self.features, self.precision, name="knn_out")(jnp.maximum(*ends))
    # Voxel branch.
    cells = [
      planar_voxel_means(corr_BxNxK, offsets_3xBxNxK, self.base_scale * 2**level,
                         form=self.voxel_cells)
      for level in range(self.levels)
    ]
    v = dense(128, self.precision, name="voxel_conv")(jnp.concatenate(cells, axis=-1))
    v = nn.PReLU(negative_slope_init=0.25, name="voxel_act")(GroupNorm(name="voxel_norm")(v))
    voxel_BxNxF = dense(self.features, self.precision, name="voxel_out")(v)
    return point_BxNxF + voxel_BxNxF
