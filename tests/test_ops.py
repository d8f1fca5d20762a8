"""Each numerical operation of the network against the plain NumPy loops of numpy_reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import numpy_reference as ref
from jaxflow.evaluation import metrics
from jaxflow.geometry import neighbours, ops
from jaxflow.network import edges, layers
from jaxflow.network.correlation import (PointVoxelCorrelation, planar, truncated_correlation,
                                         voxel_means)
from jaxflow.network.layers import GCL, SetConv
from jaxflow.network.update import GRUCell, SingleGateCell
from jaxflow.training import losses

SEEDS = (0, 1, 2)


def close(actual, expected, rtol=1e-5):
  """Agreement to rtol relative to the reference's scale (float32 against float64 loops)."""
  actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
  scale = max(np.abs(expected).max(), 1e-12)
  np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * scale)


def cloud(seed, n=40, spread=1.0):
  return np.random.default_rng(seed).normal(size=(n, 3)).astype(np.float32) * spread


def init_apply(module, seed, *args):
  variables = module.init(jax.random.PRNGKey(seed), *args)
  # Non-trivial norm affine parameters, so that scale and bias are exercised.
  variables = jax.tree_util.tree_map_with_path(
    lambda path, x: x + 0.3 * jax.random.normal(jax.random.PRNGKey(len(path) + seed), x.shape)
    if any(getattr(k, "key", "") in ("scale", "negative_slope") for k in path) else x,
    variables,
  )
  return variables, module.apply(variables, *args)


def numpy_params(variables):
  return jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), variables["params"])


@pytest.mark.parametrize("seed", SEEDS)
def test_knn_matches_loop(seed):
  pts = cloud(seed)
  got = np.asarray(neighbours.matmul_knn(jnp.asarray(pts)[None], jnp.asarray(pts)[None], 8))[0]
  want = ref.knn(pts, 8)
  assert all(set(g) == set(w) for g, w in zip(got, want))
  assert np.all(got[:, 0] == np.arange(len(pts)))  # nearest is the point itself


@pytest.mark.parametrize("chunk", [0, 7, 16])
def test_knn_chunked_equals_whole(chunk):
  pts = jnp.asarray(cloud(3, n=50))[None]
  np.testing.assert_array_equal(neighbours.matmul_knn(pts, pts, 6, chunk),
                                neighbours.matmul_knn(pts, pts, 6))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("features", ["8 channels", "the coordinates, 30 m away"])
def test_setconv_matches_loop(seed, features):
  # The second case is an encoder's first layer: the coordinates as features, far (30 m) and dense,
  # where differences of products (p_j W - p_i W) instead of products of differences would fail.
  xyz, width = cloud(seed), 24  # fc1 width (8 + 24) / 2 = 16: a multiple of the 8 norm groups
  f = np.random.default_rng(seed + 10).normal(size=(40, 8)).astype(np.float32)
  if features != "8 channels":
    xyz, width = cloud(seed, spread=0.1) + np.float32(30.0), 32
    f = xyz
  nbr = ref.knn(xyz, 8)
  variables, got = init_apply(SetConv(width), seed, jnp.asarray(f)[None], jnp.asarray(xyz)[None],
                              jnp.asarray(nbr)[None])
  close(got[0], ref.setconv(numpy_params(variables), f, xyz, nbr))


def dense_setconv(p, f_BxNxC, xyz_BxNx3, nbr_BxNxK):
  """SetConv with its edge tensor written out (the reference's form), in jnp for autodiff."""
  def norm(x, q):  # GroupNorm, 8 groups, over every axis but the batch's
    g = x.reshape(*x.shape[:-1], 8, x.shape[-1] // 8)
    axes = tuple(range(1, x.ndim - 1)) + (x.ndim,)
    mean = g.mean(axis=axes, keepdims=True)
    var = jnp.square(g - mean).mean(axis=axes, keepdims=True)
    return ((g - mean) / jnp.sqrt(var + 1e-5)).reshape(x.shape) * q["scale"] + q["bias"]
  leaky = lambda x: jnp.where(x >= 0, x, 0.1 * x)
  edges = jnp.concatenate([ops.gather(f_BxNxC, nbr_BxNxK) - f_BxNxC[:, :, None],
                           ops.gather(xyz_BxNx3, nbr_BxNxK) - xyz_BxNx3[:, :, None]], axis=-1)
  mm = lambda a, w: jnp.matmul(a, w, precision="highest")  # no TF32 on a GPU
  x = leaky(norm(mm(edges, p["fc1"]["kernel"]), p["gn1"])).max(axis=2)
  x = leaky(norm(mm(x, p["fc2"]["kernel"]), p["gn2"]))
  return leaky(norm(mm(x, p["fc3"]["kernel"]), p["gn3"]))


@pytest.mark.parametrize("seed", SEEDS)
def test_setconv_with_negative_norm_scales_and_its_gradient(seed):
  # A negative scale turns the norm's map over: the max of the normalised edges is then the
  # smallest edge's; the gradient must follow it.
  rng = np.random.default_rng(seed)
  xyz = cloud(seed)
  f = rng.normal(size=(40, 16)).astype(np.float32)
  nbr = ref.knn(xyz, 8)
  args = (jnp.asarray(f)[None], jnp.asarray(xyz)[None], jnp.asarray(nbr)[None])
  module = SetConv(32)  # fc1 width 24
  params = module.init(jax.random.PRNGKey(seed), *args)["params"]
  signs = np.where(np.arange(24) % 3 == 0, -1.0, 1.0).astype(np.float32)
  params = {**params, "gn1": {"scale": jnp.asarray(signs * rng.uniform(0.5, 1.5, 24)),
                              "bias": jnp.asarray(rng.normal(size=24), jnp.float32)}}
  got = module.apply({"params": params}, *args)
  close(got[0], ref.setconv(numpy_params({"params": params}), f, xyz, nbr))
  loss = lambda fn: lambda p, feats: jnp.sum(jnp.sin(3.0 * fn(p, feats)))
  ours = jax.grad(loss(lambda p, x: module.apply({"params": p}, x, *args[1:])), (0, 1))(
    params, args[0])
  dense = jax.grad(loss(lambda p, x: dense_setconv(p, x, *args[1:])), (0, 1))(params, args[0])
  for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(dense)):
    close(a, b, rtol=1e-4)


@pytest.mark.parametrize("features", [16, 3])  # the edges' z part, and offsets only (3 -> z None)
def test_setconv_by_blocks_of_points_equals_its_dense_form_with_gradients(features, monkeypatch):
  # Blocks of 7 of the 40 points (the last one padded): the norm's sums, the max over neighbours
  # and their gradients by blocks under lax.map, against autodiff of the written-out edges.
  rng = np.random.default_rng(features)
  xyz = cloud(features) + np.float32(5.0)
  f = np.stack([xyz * 2] * 2)
  if features > 3:
    f = rng.normal(size=(2, 40, features)).astype(np.float32)
  nbr = np.stack([ref.knn(xyz, 8)] * 2)
  args = (jnp.asarray(f), jnp.asarray(np.stack([xyz] * 2)), jnp.asarray(nbr))
  module = SetConv(32)
  params = module.init(jax.random.PRNGKey(0), *args)["params"]
  mid = params["gn1"]["scale"].shape[0]
  params = {**params, "gn1": {"scale": jnp.asarray(rng.uniform(-1.5, 1.5, mid), jnp.float32),
                              "bias": jnp.asarray(rng.normal(size=mid), jnp.float32)}}
  monkeypatch.setattr(edges, "EDGE_BLOCK", 2 * 8 * mid * 7)
  weights = jnp.asarray(rng.normal(size=(2, 40, 32)), jnp.float32)
  loss = lambda fn: lambda p, x: jnp.sum(weights * jnp.sin(fn(p, x)))
  ours = lambda p, x: module.apply({"params": p}, x, *args[1:])
  dense = lambda p, x: dense_setconv(p, x, *args[1:])
  close(jax.jit(ours)(params, args[0]), dense(params, args[0]))
  got = jax.jit(jax.grad(loss(ours), (0, 1)))(params, args[0])
  want = jax.grad(loss(dense), (0, 1))(params, args[0])
  for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
    close(a, b, rtol=1e-4)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("similarity", ["sum", "product"])
def test_gcl_matches_loop(seed, similarity):
  xyz = cloud(seed, n=24)
  f = np.random.default_rng(seed + 20).normal(size=(24, 5)).astype(np.float32)
  nbr = ref.knn(xyz, 6)
  variables, got = init_apply(GCL(8, supports=3, similarity=similarity), seed,
                              jnp.asarray(f)[None], jnp.asarray(xyz)[None], jnp.asarray(nbr)[None])
  close(got[0], ref.gcl(numpy_params(variables), f, xyz, nbr, 3, similarity))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("similarity", ["sum", "product"])
def test_gcl_neighbour_max_gradient_equals_autodiff_of_the_max(seed, similarity):
  # The custom VJP (gradient at the winning neighbour) against autodiff of the dense max, for the
  # support features, the edge directions and the support directions. The self edge (cosine 0)
  # makes ties at 0 in the product form, where both give a zero gradient.
  rng = np.random.default_rng(seed)
  xyz = jnp.asarray(cloud(seed, n=32))[None]
  nbr = neighbours.matmul_knn(xyz, xyz, 6)
  unit_v = layers.safe_normalize(ops.gather(xyz, nbr) - xyz[:, :, None, :])
  support = jnp.asarray(rng.normal(size=(1, 32, 12)), jnp.float32)
  unit_e = layers.safe_normalize(jnp.asarray(rng.normal(size=(12, 3)), jnp.float32)).T
  weights = jnp.asarray(rng.normal(size=(1, 32, 12)), jnp.float32)

  def dense_max(*args):  # autodiff of this is the reference
    return jnp.max(layers.edge_similarity(*args), axis=2)

  def loss(fn):
    return lambda s, v, e: jnp.sum(weights * jnp.sin(fn(s, v, e, nbr, similarity)))

  args = (support, unit_v, unit_e)
  close(layers.neighbour_max(*args, nbr, similarity), dense_max(*args, nbr, similarity))
  got = jax.grad(loss(layers.neighbour_max), argnums=(0, 1, 2))(*args)
  want = jax.grad(loss(dense_max), argnums=(0, 1, 2))(*args)
  for g, w in zip(got, want):
    close(g, w)
  assert np.count_nonzero(np.asarray(got[0])) > 0


def test_gcl_neighbour_max_by_blocks_of_points_equals_the_whole_cloud(monkeypatch):
  # Blocks of 5 of the 32 points (the last padded) against the whole cloud at once: values,
  # winners and gradients the same.
  rng = np.random.default_rng(4)
  xyz = jnp.asarray(np.stack([cloud(4, n=32), cloud(5, n=32)]))
  nbr = neighbours.matmul_knn(xyz, xyz, 6)
  unit_v = layers.safe_normalize(ops.gather(xyz, nbr) - xyz[:, :, None, :])
  support = jnp.asarray(rng.normal(size=(2, 32, 12)), jnp.float32)
  unit_e = layers.safe_normalize(jnp.asarray(rng.normal(size=(12, 3)), jnp.float32)).T
  weights = jnp.asarray(rng.normal(size=(2, 32, 12)), jnp.float32)
  loss = lambda s, v, e: jnp.sum(weights * jnp.sin(layers.neighbour_max(s, v, e, nbr, "sum")))
  whole = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))(support, unit_v, unit_e)
  monkeypatch.setattr(edges, "EDGE_BLOCK", 2 * 6 * 12 * 5)
  blocks = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))(support, unit_v, unit_e)
  for a, b in zip(jax.tree_util.tree_leaves(blocks), jax.tree_util.tree_leaves(whole)):
    np.testing.assert_array_equal(a, b)


def correlation_inputs(seed, n=30, k=40):
  rng = np.random.default_rng(seed)
  coords = rng.normal(size=(n, 3)).astype(np.float32)
  # Candidates around each point at distances spanning the three voxel levels and beyond.
  cand = (coords[:, None, :] + rng.uniform(-2.2, 2.2, size=(n, k, 3))).astype(np.float32)
  corr = rng.normal(size=(n, k)).astype(np.float32) * 3
  return corr, cand, coords


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("scale", [0.25, 0.5, 1.0])
@pytest.mark.parametrize("form", ["compare", "scatter", "auto"])  # GPU/TPU's, CPU's, by device
def test_voxel_cells_match_loop(seed, scale, form):
  # A batch of two pairs: the scatter form numbers the cells of every (pair, point) row apart.
  inputs = [correlation_inputs(seed), correlation_inputs(seed + 100)]
  corr = jnp.asarray(np.stack([c for c, _, _ in inputs]))
  offset = jnp.asarray(np.stack([cand - coords[:, None] for _, cand, coords in inputs]))
  got = voxel_means(corr, offset, scale, form=form)
  grad = jax.grad(lambda c: jnp.sum(voxel_means(c, offset, scale, form=form) ** 2))(corr)
  for b, (corr_b, cand, coords) in enumerate(inputs):
    want = ref.voxel_cells(corr_b, cand, coords, scale)
    close(got[b], want)
    assert np.any(want == 0) and np.any(want != 0)  # both empty and filled cells were exercised
    # Gradient of sum(means^2): d/d corr[i, a] = 2 mean / count of a's cell, 0 outside the cube.
    index = ref.voxel_index(cand, coords, scale)
    counts = np.stack([np.bincount(row[row >= 0], minlength=27) for row in index])
    rows = np.arange(len(index))[:, None]
    cell = np.maximum(index, 0)
    close(grad[b], np.where(index >= 0, 2 * want[rows, cell] / np.maximum(counts[rows, cell], 1),
                            0.0))


def test_voxel_cells_validity_cube_and_empty():
  # One candidate per cell centre of a 5x5x5 grid at spacing 1: only the inner 3x3x3 are inside.
  grid = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), -1).reshape(-1, 3)
  corr = np.arange(len(grid), dtype=np.float32)
  got = np.asarray(voxel_means(jnp.asarray(corr)[None, None], jnp.asarray(grid, jnp.float32)[None, None], 1.0))[0, 0]
  for dx, dy, dz in np.ndindex(3, 3, 3):
    idx = np.where(np.all(grid == [dx - 1, dy - 1, dz - 1], axis=1))[0][0]
    assert got[dx * 9 + dy * 3 + dz] == corr[idx]
  # No candidate inside: every cell is 0.
  far = jnp.full((1, 1, 4, 3), 10.0)
  assert np.all(np.asarray(voxel_means(jnp.ones((1, 1, 4)), far, 0.25)) == 0)


def test_voxel_cells_form_follows_the_device_it_is_compiled_for():
  """"auto" is decided when XLA lowers the program for a platform, not by the process's default
  backend when it is traced: the same trace lowered for the CPU scatters, for a GPU or TPU it
  compares; the explicit forms are what they say everywhere."""
  corr, cand, coords = correlation_inputs(0)
  offset = jnp.asarray(cand - coords[:, None])[None]
  corr = jnp.asarray(corr)[None]

  def lowered(form, platform):
    fn = jax.jit(lambda c, o: voxel_means(c, o, 0.5, form=form))
    return fn.trace(corr, offset).lower(lowering_platforms=(platform,)).as_text()

  for platform in ("cpu", "cuda", "tpu"):
    assert ("scatter" in lowered("auto", platform)) == (platform == "cpu"), platform
    assert "scatter" in lowered("scatter", platform)
    assert "scatter" not in lowered("compare", platform)
  with pytest.raises(ValueError, match="voxel_cells must be one of auto, scatter, compare"):
    voxel_means(corr, offset, 0.5, form="gather")


@pytest.mark.parametrize("seed", SEEDS)
def test_point_branch_matches_loop(seed):
  corr, cand, coords = correlation_inputs(seed)
  module = PointVoxelCorrelation(knn=8, levels=3)
  # The module takes the candidates as three planes (correlation.planar), as the model does.
  cand_3xBxNxK = jnp.stack(planar(jnp.asarray(cand)[None]))
  args = (jnp.asarray(corr)[None], cand_3xBxNxK, jnp.asarray(coords)[None])
  variables, got = init_apply(module, seed, *args)
  p = numpy_params(variables)
  point = ref.point_branch(p, corr, cand, coords, 8)
  cells = np.concatenate([ref.voxel_cells(corr, cand, coords, 0.25 * 2**l) for l in range(3)], -1)
  v = ref.prelu(ref.group_norm(cells @ p["voxel_conv"]["kernel"] + p["voxel_conv"]["bias"],
                               p["voxel_norm"]["scale"], p["voxel_norm"]["bias"]),
                p["voxel_act"]["negative_slope"])
  voxel = v @ p["voxel_out"]["kernel"] + p["voxel_out"]["bias"]
  close(got[0], point + voxel)


@pytest.mark.parametrize("seed", SEEDS)
def test_point_branch_without_its_slot_values_equals_autodiff_of_them(seed):
  # The point branch by v's moments and each channel's two extreme slots against the plain form
  # (dense, GroupNorm, PReLU on every slot, the max), values and gradients; negative norm scales
  # and PReLU slopes (init_apply) turn the norm over and make PReLU convex.
  corr, cand, coords = correlation_inputs(seed)
  module = PointVoxelCorrelation(knn=8, levels=1)
  args = (jnp.asarray(corr)[None], jnp.stack(planar(jnp.asarray(cand)[None])),
          jnp.asarray(coords)[None])
  variables, _ = init_apply(module, seed, *args)

  def plain(p, corr_, coords_):
    offsets = [args[1][a] - coords_[:, :, a, None] for a in range(3)]
    near = jax.lax.top_k(-sum(jax.lax.stop_gradient(o) ** 2 for o in offsets), 8)[1]
    v = jnp.stack([jnp.take_along_axis(x, near, axis=2) for x in (corr_, *offsets)], axis=-1)
    y = jnp.matmul(v, p["knn_conv"]["kernel"], precision="highest") + p["knn_conv"]["bias"]
    g = y.reshape(*y.shape[:-1], 8, 8)
    mean = g.mean(axis=(1, 2, 4), keepdims=True)
    var = jnp.square(g - mean).mean(axis=(1, 2, 4), keepdims=True)
    y = ((g - mean) / jnp.sqrt(var + 1e-5)).reshape(y.shape) * p["knn_norm"]["scale"]
    y = y + p["knn_norm"]["bias"]
    y = jnp.where(y >= 0, y, p["knn_act"]["negative_slope"] * y).max(axis=2)
    return jnp.matmul(y, p["knn_out"]["kernel"], precision="highest") + p["knn_out"]["bias"]

  def ours(p, corr_, coords_):  # the point branch alone: the voxel branch's output less
    voxel = {**p, "knn_out": jax.tree_util.tree_map(jnp.zeros_like, p["knn_out"])}
    return (module.apply({"params": p}, corr_, args[1], coords_)
            - module.apply({"params": voxel}, corr_, args[1], coords_))

  weights = jnp.asarray(np.random.default_rng(seed).normal(size=(1, 30, 64)), jnp.float32)
  loss = lambda fn: lambda *a: jnp.sum(weights * jnp.sin(fn(*a)))
  inputs = (variables["params"], args[0], args[2])
  close(ours(*inputs), plain(*inputs), rtol=1e-4)
  got = jax.jit(jax.grad(loss(ours), (0, 1, 2)))(*inputs)
  want = jax.grad(loss(plain), (0, 1, 2))(*inputs)
  got, want = jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)
  assert len(got) == len(want) and np.any(np.asarray(got[-1]) != 0)
  for a, b in zip(got, want):
    close(a, b, rtol=1e-4)


def test_truncated_correlation_is_topk_of_scaled_products():
  rng = np.random.default_rng(0)
  f1, f2 = rng.normal(size=(1, 20, 16)), rng.normal(size=(1, 30, 16))
  xyz2 = rng.normal(size=(1, 30, 3))
  corr, cand = truncated_correlation(*(jnp.asarray(a, jnp.float32) for a in (f1, f2, xyz2)), k=5)
  full = f1[0] @ f2[0].T / 4.0
  for i in range(20):
    top = np.argsort(-full[i])[:5]
    close(corr[0, i], full[i, top])
    close(cand[0, i], xyz2[0, top])
  chunked = truncated_correlation(*(jnp.asarray(a, jnp.float32) for a in (f1, f2, xyz2)), k=5, chunk=6)
  np.testing.assert_allclose(chunked[0], corr, rtol=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("cell", ["gru", "single_gate"])
def test_recurrent_cells_match_numpy(seed, cell):
  rng = np.random.default_rng(seed)
  h = np.tanh(rng.normal(size=(1, 10, 16))).astype(np.float32)
  x = rng.normal(size=(1, 10, 24)).astype(np.float32)
  module = GRUCell() if cell == "gru" else SingleGateCell()
  variables, got = init_apply(module, seed, jnp.asarray(h), jnp.asarray(x))
  fn = ref.gru if cell == "gru" else ref.single_gate
  close(got[0], fn(numpy_params(variables), h[0], x[0]))


@pytest.mark.parametrize("seed", SEEDS)
def test_losses_match_numpy(seed):
  rng = np.random.default_rng(seed)
  flows = rng.normal(size=(2, 5, 30, 3)).astype(np.float32)
  gt = rng.normal(size=(2, 30, 3)).astype(np.float32)
  mask = rng.random((2, 30)) > 0.3
  per_iter = [np.abs(flows[:, z] - gt)[mask].mean() for z in range(5)]
  want = sum(0.8 ** (4 - z) * per_iter[z] for z in range(5))
  close(losses.sequence_loss(jnp.asarray(flows), jnp.asarray(gt), jnp.asarray(mask)), want)
  close(losses.refinement_loss(jnp.asarray(flows[:, -1]), jnp.asarray(gt), jnp.asarray(mask)),
        per_iter[-1])
  close(losses.total_loss(jnp.asarray(flows), jnp.asarray(flows[:, -1]), jnp.asarray(gt),
                          jnp.asarray(mask)), 0.8 * want + per_iter[-1])


@pytest.mark.parametrize("seed", SEEDS)
def test_metrics_match_loop(seed):
  rng = np.random.default_rng(seed)
  gt = rng.normal(size=(3, 200, 3)).astype(np.float32)
  # Errors spanning every threshold: tiny, relative, absolute and large.
  pred = gt + rng.normal(size=gt.shape).astype(np.float32) * rng.choice([0.01, 0.05, 0.2, 1.0], (3, 200, 1))
  got = metrics.per_pair_metrics(jnp.asarray(pred), jnp.asarray(gt))
  for b in range(3):
    want = ref.metrics(pred[b], gt[b])
    for key in metrics.METRICS:
      close(got[key][b], want[key])
  mean = metrics.scene_flow_metrics(jnp.asarray(pred), jnp.asarray(gt))
  for key in metrics.METRICS:
    close(mean[key], np.mean([ref.metrics(pred[b], gt[b])[key] for b in range(3)]))


def test_metrics_mask_selects_points_and_empty_pair_is_nan():
  rng = np.random.default_rng(5)
  gt = rng.normal(size=(2, 50, 3)).astype(np.float32)
  pred = gt + rng.normal(size=gt.shape).astype(np.float32) * 0.1
  mask = np.zeros((2, 50), bool)
  mask[0, :20] = True
  got = metrics.per_pair_metrics(jnp.asarray(pred), jnp.asarray(gt), jnp.asarray(mask))
  want = ref.metrics(pred[0, :20], gt[0, :20])
  for key in metrics.METRICS:
    close(got[key][0], want[key])
    assert np.isnan(got[key][1])


def test_metrics_perfect_prediction():
  gt = jnp.asarray(np.random.default_rng(1).normal(size=(1, 40, 3)), jnp.float32)
  m = metrics.scene_flow_metrics(gt, gt)
  assert float(m["epe"]) == 0 and float(m["acc_strict"]) == 100 and float(m["outliers"]) == 0
  assert float(m["angle"]) < 1e-3
