"""optimise's start (the shipped network, 8 iterations, 64 or 128 candidates) on real-size pairs:
the production network, whose SetConv, GCL and point-branch reductions and whose kNN and
correlation rows run in blocks, against the same parameters computed plainly, every B x N x K x C
tensor written out and each cloud's rows at once.

The plain network takes the production run's discrete choices: its candidates (the top-k of the
correlations) and the estimate entering each iteration (which picks the point branch's nearest
candidates and the voxel cells). Left free, float32 rounding of ~1e-6 flips such a choice at a
point or two (a last candidate, a cell boundary), and the flow head carries the jump to its
neighbours and theirs over the iterations: the four cases' start flows were 2.8e-4 to 0.13 m apart
(on 11 to 1550 points), with no error in either computation. Pinned, only the order of the float32
sums differs, and the flows agree to 3.8e-6 m."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import SHARED
from jaxflow.data import eval_batches, open_dataset
from jaxflow.geometry import ops
from jaxflow.methods import registry
from jaxflow.network import checkpointing, correlation, edges, encoder, layers, model as network
from jaxflow.network import refine, update
from test_ops import dense_setconv

NUM_POINTS = 8192  # the test density: the edges and the correlation rows run in several blocks
# float32 sums in another order through 8 iterations (the rewrite moved these flows by <= 3.8e-6 m).
ATOL = 2e-5
PLAIN_CALLS = []  # the plain modules' names as they are traced: proof that they stood in


def group_norm(x, scale, bias, groups=8, eps=1e-5):
  """GroupNorm over every axis but the batch's (two-pass variance), written out."""
  g = x.reshape(*x.shape[:-1], groups, x.shape[-1] // groups)
  axes = tuple(range(1, x.ndim - 1)) + (x.ndim,)
  mean = g.mean(axis=axes, keepdims=True)
  var = jnp.square(g - mean).mean(axis=axes, keepdims=True)
  return ((g - mean) / jnp.sqrt(var + eps)).reshape(x.shape) * scale + bias


def norm_params(width, name):
  return dict(zip(("scale", "bias"), layers.NormParams(width, name=name)()))


class PlainSetConv(nn.Module):
  """SetConv's parameters, its edges B x N x K x C written out (test_ops.dense_setconv: the
  concatenated differences through fc1, GroupNorm and LeakyReLU on every edge, then the max)."""

  features: int
  precision: str = "highest"

  @nn.compact
  def __call__(self, f_BxNxC, xyz_BxNx3, nbr_BxNxK):
    c_in = f_BxNxC.shape[-1]
    mid = (c_in + self.features) // 2 if c_in % 2 == 0 else self.features // 2
    p = {"fc1": {"kernel": layers.Kernel(mid, name="fc1")(c_in + 3)},
         "fc2": {"kernel": layers.Kernel(self.features, name="fc2")(mid)},
         "fc3": {"kernel": layers.Kernel(self.features, name="fc3")(self.features)},
         "gn1": norm_params(mid, "gn1"), "gn2": norm_params(self.features, "gn2"),
         "gn3": norm_params(self.features, "gn3")}
    PLAIN_CALLS.append("SetConv")
    return dense_setconv(p, f_BxNxC, xyz_BxNx3, nbr_BxNxK)


class PlainGCL(nn.Module):
  """GCL's parameters, every neighbour's similarity B x N x K x LC written out, then the max
  (paper eq. 4-5: cosines as v.e / (|v| |e|), 0 for the self edge)."""

  features: int
  supports: int = 3
  similarity: str = "sum"
  precision: str = "highest"

  @nn.compact
  def __call__(self, f_BxNxC, xyz_BxNx3, nbr_BxNxK):
    l, c = self.supports, self.features
    w_CxW = layers.Kernel((l + 1) * c, name="kernel")(f_BxNxC.shape[-1])
    e_3xLC = self.param("directions", nn.initializers.zeros, (3, l * c))
    bias = self.param("bias", nn.initializers.zeros, (c,))
    w = jnp.matmul(f_BxNxC, w_CxW, precision="highest")
    v_BxNxKx3 = ops.gather(xyz_BxNx3, nbr_BxNxK) - xyz_BxNx3[:, :, None, :]
    dot = jnp.einsum("bnkd,dc->bnkc", v_BxNxKx3, e_3xLC, precision="highest")
    lengths = jnp.linalg.norm(v_BxNxKx3, axis=-1, keepdims=True) * jnp.linalg.norm(e_3xLC, axis=0)
    cos = jnp.where(lengths > 0, dot / jnp.where(lengths > 0, lengths, 1.0), 0.0)
    support = ops.gather(w[..., c:], nbr_BxNxK)
    sim = support + cos if self.similarity == "sum" else nn.relu(cos) * support
    b, n = f_BxNxC.shape[:2]
    PLAIN_CALLS.append("GCL")
    return w[..., :c] + sim.max(axis=2).reshape(b, n, l, c).sum(axis=2) + bias


class PlainCorrelation(nn.Module):
  """PointVoxelCorrelation's parameters; its point branch with the B x N x Q x 64 values written
  out (dense, GroupNorm and PReLU on every slot, then the max), its voxel branch by the
  all-cells comparison (no scatter)."""

  knn: int = 32
  levels: int = 3
  base_scale: float = 0.25
  features: int = 64
  precision: str = "highest"
  voxel_cells: str = "auto"

  @nn.compact
  def __call__(self, corr_BxNxK, xyz_3xBxNxK, coords_BxNx3):
    offsets = [xyz_3xBxNxK[a] - coords_BxNx3[:, :, a, None] for a in range(3)]
    # The distances summed in the production's order: a near tie then ranks the same candidates.
    dist_BxNxK = offsets[0] ** 2 + offsets[1] ** 2 + offsets[2] ** 2
    near = jax.lax.top_k(-dist_BxNxK, min(self.knn, corr_BxNxK.shape[-1]))[1]
    v = jnp.stack([jnp.take_along_axis(x, near, axis=2) for x in (corr_BxNxK, *offsets)], -1)
    w, b = layers.DenseParams(64, name="knn_conv")(4)
    y = jnp.matmul(v, w, precision="highest") + b
    y = nn.PReLU(negative_slope_init=0.25, name="knn_act")(
      group_norm(y, **norm_params(64, "knn_norm")))
    point = layers.dense(self.features, self.precision, name="knn_out")(y.max(axis=2))
    cells = [correlation.planar_voxel_means(corr_BxNxK, offsets, self.base_scale * 2**level,
                                            form="compare") for level in range(self.levels)]
    v = layers.dense(128, self.precision, name="voxel_conv")(jnp.concatenate(cells, axis=-1))
    v = nn.PReLU(negative_slope_init=0.25, name="voxel_act")(
      group_norm(v, **norm_params(128, "voxel_norm")))
    PLAIN_CALLS.append("correlation")
    return point + layers.dense(self.features, self.precision, name="voxel_out")(v)


def pinned_correlation(idx_BxNxK):
  """truncated_correlation with the candidates `idx` (B x N x K rows of pc2): the whole N x M
  correlation matrix, its values there, and their xyz."""

  def pinned(f1_BxNxC, f2_BxMxC, xyz2_BxMx3, k, chunk=0, precision="highest", selection="auto"):
    del chunk, precision, selection
    assert idx_BxNxK.shape[-1] == min(k, f2_BxMxC.shape[1])
    PLAIN_CALLS.append("candidates")
    corr = jnp.einsum("bnc,bmc->bnm", f1_BxNxC, f2_BxMxC, precision="highest")
    corr = corr / jnp.sqrt(jnp.float32(f1_BxNxC.shape[-1]))
    return jnp.take_along_axis(corr, idx_BxNxK, axis=2), ops.gather(xyz2_BxMx3, idx_BxNxK)

  return pinned


def capturing_correlation(captured):
  """The production truncated_correlation, which also puts its candidates' rows of pc2 in
  `captured` (pc2 given a fourth column, its row numbers: the same top-k and the same xyz)."""
  production = correlation.truncated_correlation

  def truncated(f1_BxNxC, f2_BxMxC, xyz2_BxMx3, *args):
    b, m, _ = xyz2_BxMx3.shape
    rows = jnp.broadcast_to(jnp.arange(m, dtype=jnp.float32)[None, :, None], (b, m, 1))
    corr, cand = production(f1_BxNxC, f2_BxMxC, jnp.concatenate([xyz2_BxMx3, rows], -1), *args)
    captured["idx"] = cand[..., 3].astype(jnp.int32)  # exact: M < 2^24
    return corr, cand[..., :3]

  return truncated


@pytest.fixture(scope="module")
def shipped():
  """The shipped checkpoint as optimise loads it: (model, params, refine)."""
  model, params, _, _, refine_flow = checkpointing.load_for_inference(None)
  return model, params, refine_flow


def first_pair(spec, split):
  return next(eval_batches(open_dataset(spec, split), 1, NUM_POINTS, seed=0))


@pytest.fixture(scope="module")
def pairs():
  """{"ft3d": the first pair of the shared FT3D sample's train split (0001435; None without
  ../shared), "lidar": the generator's first LiDAR test pair}, as evaluation samples them."""
  root = SHARED / "data" / "FlyingThings3D_subset_processed_35m"
  ft3d = first_pair(f"ft3d:{root}", "train") if root.is_dir() else None
  return {"ft3d": ft3d, "lidar": first_pair("synthetic_lidar:1", "test")}


@pytest.mark.slow
@pytest.mark.parametrize("candidates", [64, 128])
@pytest.mark.parametrize("data", ["ft3d", "lidar"])
def test_optimise_start_by_blocks_equals_the_plain_network(shipped, pairs, data, candidates,
                                                          monkeypatch):
  if pairs[data] is None:
    pytest.skip(f"{SHARED / 'data'} has no FlyingThings3D_subset_processed_35m")
  model, params, refine_flow = shipped
  assert not refine_flow  # a stage-1 checkpoint: the start is the last iteration's flow
  chosen = registry.settings("optimise")
  assert chosen.start_iters == 8 and chosen.start_candidates == 64  # optimise's start
  iters = chosen.start_iters
  pc1, pc2 = (jnp.asarray(pairs[data][k]) for k in ("pc1", "pc2"))
  # The production path blocks here (else the comparison proves nothing): the kNN and correlation
  # rows in chunks (ops.auto_chunk) and a GCL's similarities (64 channels, 3 supports) in blocks.
  assert 0 < ops.auto_chunk(1, NUM_POINTS, NUM_POINTS, model.corr_chunk) < NUM_POINTS
  assert edges.EDGE_BLOCK < NUM_POINTS * model.knn * 3 * 64
  # The clouds go in as arguments, as optimise's: XLA folds a kNN of clouds captured as constants
  # with another rounding (802 of 8192 rows in another order, 21 with other neighbours).
  start = jax.jit(registry.network_for(model, 32, refine_flow)(iters, candidates))
  got = np.asarray(start(params, pc1, pc2))

  # The same network with every iteration's flow and its candidates: optimise's start to the bit.
  blocked = model.clone(truncate_k=min(candidates, model.truncate_k))  # as network_for's

  def production(p, x, y):
    captured = {}
    monkeypatch.setattr(network, "truncated_correlation", capturing_correlation(captured))
    flows = blocked.apply({"params": p}, x, y, num_iters=iters, refine=False)["flows"]
    return flows, captured["idx"]

  flows, idx = jax.jit(production)(params, pc1, pc2)
  np.testing.assert_array_equal(flows[:, -1], got)
  # The estimate entering each iteration (Z x B x N x 3): pc1, then pc1 + the previous flow.
  entering = jnp.concatenate([pc1[None], pc1[None] + jnp.moveaxis(flows[:, :-1], 1, 0)])

  # The plain network: the same parameters through the modules above and each kNN matrix whole (a
  # chunk of every row: ops.map_row_chunks calls its function once), given those choices.
  for module in (encoder, update, refine):
    monkeypatch.setattr(module, "SetConv", PlainSetConv)
  for module in (encoder, refine):
    monkeypatch.setattr(module, "GCL", PlainGCL)
  monkeypatch.setattr(network, "PointVoxelCorrelation", PlainCorrelation)
  whole = blocked.clone(corr_chunk=NUM_POINTS)

  def plain(p, x, y, entering_ZxBxNx3, idx_BxNxK):
    monkeypatch.setattr(network, "truncated_correlation", pinned_correlation(idx_BxNxK))
    return whole.apply({"params": p}, x, y, num_iters=iters, refine=False,
                       entering=entering_ZxBxNx3)["flows"]

  PLAIN_CALLS.clear()
  want = np.asarray(jax.jit(plain)(params, pc1, pc2, entering, idx))
  assert set(PLAIN_CALLS) == {"SetConv", "GCL", "correlation", "candidates"}

  assert want.shape == flows.shape == (1, iters, NUM_POINTS, 3) and np.isfinite(want).all()
  worst = np.abs(np.asarray(flows) - want).max(axis=(0, 2, 3))
  print(f"{data}, {candidates} candidates: largest difference by iteration (m) "
        f"{np.array2string(worst, precision=1)}")
  assert worst.max() <= ATOL, (f"{data}, {candidates} candidates: flows differ by up to "
                               f"{worst.max():.2e} m (by iteration: {worst})")
