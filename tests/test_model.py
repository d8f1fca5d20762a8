"""The whole network: parameter counts, shapes, the scan, symmetries and gradients (fidelity to the
official PV-RAFT outputs: tests/test_pvraft_fidelity.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow.configs import ablation, default, pvraft
from jaxflow.geometry import ops
from jaxflow.network.model import build_model
from jaxflow.summary import parameter_counts
from jaxflow.training import losses


def small_config(**overrides):
  m = default.model_config()
  m.widths = (16, 16, 32, 32)
  m.knn, m.truncate_k, m.corr_knn = 8, 24, 8
  for k, v in overrides.items():
    m[k] = v
  return m


def init_fn(model):
  """model.init, compiled (eagerly it runs op by op: several times slower)."""
  return jax.jit(lambda pc1, pc2: model.init(jax.random.PRNGKey(0), pc1, pc2, num_iters=1))


def random_pair(seed, n=64, m=80):
  rng = np.random.default_rng(seed)
  pc1 = rng.uniform(-2, 2, size=(1, n, 3)).astype(np.float32)
  pc2 = rng.uniform(-2, 2, size=(1, m, 3)).astype(np.float32)
  return jnp.asarray(pc1), jnp.asarray(pc2)


def test_pvraft_parameter_count_is_official():
  counts = parameter_counts(pvraft.get_config().model)
  assert sum(counts.values()) == 192034
  assert "refine" not in counts
  assert parameter_counts(pvraft.get_config("refine").model)["refine"] == 47187


def test_every_variant_config_builds_and_counts():
  totals = {row: sum(parameter_counts(ablation.get_config(row).model).values())
            for row in ablation.ROWS}
  # Each of the two encoders gains projections of 64*128 + 128*256 weights; GRU has 2 more gates.
  assert totals["gcl_rc"] - totals["gcl"] == 2 * (64 * 128 + 128 * 256)
  assert totals["gcl_rc"] > totals["gcl_rc_sgfi"]


@pytest.mark.parametrize("n,m,batch", [(48, 72, 2), (90, 33, 1)])
@pytest.mark.parametrize("variant", ["graph", "pvraft"])
def test_shapes(n, m, batch, variant):
  cfg = small_config() if variant == "graph" else small_config(
    encoder="setconv", widths=(16, 16, 32), cell="gru", refine="setconv", residual=False)
  model = build_model(cfg)
  rng = np.random.default_rng(0)
  pc1 = jnp.asarray(rng.normal(size=(batch, n, 3)), jnp.float32)
  pc2 = jnp.asarray(rng.normal(size=(batch, m, 3)), jnp.float32)
  variables = init_fn(model)(pc1, pc2)
  out = jax.jit(lambda v, a, b: model.apply(v, a, b, num_iters=3))(variables, pc1, pc2)
  assert out["flows"].shape == (batch, 3, n, 3)
  assert out["refined"].shape == (batch, n, 3)
  assert np.all(np.isfinite(out["flows"]))


def test_jit_compiles_once_per_shape():
  model = build_model(small_config())
  pc1, pc2 = random_pair(0)
  variables = init_fn(model)(pc1, pc2)
  traces = []

  @jax.jit
  def run(v, a, b):
    traces.append(1)
    return model.apply(v, a, b, num_iters=2)["flows"]

  run(variables, pc1, pc2)
  run(variables, pc1 + 1.0, pc2)
  assert len(traces) == 1
  run(variables, *random_pair(1, n=50))
  assert len(traces) == 2


@pytest.mark.slow  # op by op, the first such network test: ~20 s of small compilations
@pytest.mark.parametrize("cell", ["single_gate", "gru"])
def test_scan_equals_python_loop(cell):
  model = build_model(small_config(cell=cell))
  pc1, pc2 = random_pair(2)
  variables = model.init(jax.random.PRNGKey(1), pc1, pc2, num_iters=1)
  scanned = model.apply(variables, pc1, pc2, num_iters=4, refine=False)["flows"]

  # The same step as a Python loop: the scan's carry, broadcast parameters and output order.
  # (Op by op: compiled, the unrolled loop costs more than it runs.)
  looped = model.apply(variables, pc1, pc2, num_iters=4, refine=False, unroll=True)["flows"]
  np.testing.assert_allclose(scanned, looped, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_recomputed_iterations_give_the_same_gradient_with_fewer_stored_activations():
  pc1, pc2 = random_pair(7, n=96, m=96)
  gt = pc2 - pc1
  params = init_fn(build_model(small_config()))(pc1, pc2)["params"]

  def compiled_grad(remat):
    model = build_model(small_config(remat_iterations=remat))
    loss = lambda p: losses.sequence_loss(
      model.apply({"params": p}, pc1, pc2, num_iters=6, refine=False)["flows"], gt)
    return jax.jit(jax.grad(loss)).lower(params).compile()

  stored, recomputed = compiled_grad(False), compiled_grad(True)
  for a, b in zip(jax.tree.leaves(recomputed(params)), jax.tree.leaves(stored(params))):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6 * float(np.max(np.abs(b))))
  temp = lambda f: f.memory_analysis().temp_size_in_bytes
  assert temp(recomputed) < 0.8 * temp(stored), (temp(recomputed), temp(stored))


@pytest.mark.slow
def test_memory_grows_linearly_in_the_points_with_the_automatic_chunk(monkeypatch):
  # corr_chunk 0 builds the kNN graphs and the correlation in chunks of rows once a B x N x M
  # matrix outgrows ops.chunk_budget() (1 MiB here, a few hundred points): XLA's temporaries at
  # twice the points stay near twice. Whole matrices (a budget they fit) grow them ~4x.
  model = build_model(small_config(refine="none"))
  params = init_fn(model)(*random_pair(0))

  def temp(n, budget):
    monkeypatch.setattr(ops, "chunk_budget", lambda: budget)
    forward = jax.jit(lambda v, a, b: model.apply(v, a, b, num_iters=2))
    return forward.lower(params, *random_pair(0, n, n)).compile().memory_analysis(
      ).temp_size_in_bytes

  chunked = temp(2048, 1 << 20), temp(4096, 1 << 20)
  assert chunked[1] < 2.3 * chunked[0], chunked
  whole = temp(2048, 1 << 30), temp(4096, 1 << 30)
  assert whole[1] > 3.0 * whole[0] and whole[1] > 2 * chunked[1], (whole, chunked)


def test_automatic_chunk_rows():
  budget = 64 << 20  # the CPU's (ops.CHUNK_BYTES)
  assert ops.auto_chunk(1, 8192, 8192, 512, budget) == 512  # a given chunk is kept
  assert ops.auto_chunk(1, 2048, 2048, 0, budget) == 0  # 16 MiB: whole
  assert ops.auto_chunk(1, 8192, 8192, 0, budget) == 2048  # 64 MiB a chunk
  assert ops.auto_chunk(2, 100_000, 100_000, 0, budget) == 64
  assert ops.auto_chunk(4, 10**7, 10**7, 0, budget) == 16  # at least 16 rows


def test_permuting_pc1_permutes_flow_and_pc2_order_does_not_matter():
  model = build_model(small_config())
  pc1, pc2 = random_pair(3)
  variables = init_fn(model)(pc1, pc2)
  run = jax.jit(lambda a, b: model.apply(variables, a, b, num_iters=3)["refined"])
  base = run(pc1, pc2)
  perm1 = np.random.default_rng(0).permutation(pc1.shape[1])
  perm2 = np.random.default_rng(1).permutation(pc2.shape[1])
  np.testing.assert_allclose(run(pc1[:, perm1], pc2), base[:, perm1], rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(run(pc1, pc2[:, perm2]), base, rtol=1e-4, atol=1e-5)


def finite_loss_and_grads(cfg, pc1, pc2):
  model = build_model(cfg)
  variables = init_fn(model)(pc1, pc2)
  gt = jnp.full(pc1.shape, 0.1)

  def loss_fn(params):
    out = model.apply({"params": params}, pc1, pc2, num_iters=2)
    return losses.total_loss(out["flows"], out["refined"], gt)

  loss, grads = jax.jit(jax.value_and_grad(loss_fn))(variables["params"])  # as training runs it
  return np.isfinite(loss) and all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))


@pytest.mark.slow
def test_gradients_finite_on_degenerate_input():
  """One batch, one case per pair: duplicate points, all points identical, a cloud 1e4 m away."""
  pc1, pc2 = random_pair(4, n=40, m=40)
  dup1 = pc1.at[:, 20:].set(pc1[:, :20])
  dup2 = pc2.at[:, 10:30].set(pc2[:, :20])
  same = jnp.full_like(pc1, 0.5)
  batch1 = jnp.concatenate([dup1, same, pc1 + 1e4])
  batch2 = jnp.concatenate([dup2, same, pc2 + 1e4])
  assert finite_loss_and_grads(small_config(), batch1, batch2)


@pytest.mark.slow
def test_gradients_finite_with_fewer_points_than_k():
  cfg = small_config()
  cfg.knn, cfg.truncate_k, cfg.corr_knn = 8, 64, 32  # more than the 8 points each cloud holds
  pc1, pc2 = random_pair(6, n=8, m=8)
  assert finite_loss_and_grads(cfg, pc1, pc2)


@pytest.mark.slow  # op by op: seconds after the scan test (its operations compiled), ~20 s alone
def test_far_cloud_gives_the_same_flow_as_near():
  """Translation invariance: the network sees only relative positions (up to float32 rounding)."""
  model = build_model(small_config())
  pc1, pc2 = random_pair(5)
  # Op by op, as the scan test before it (whose compiled operations it reuses): faster than jit.
  variables = model.init(jax.random.PRNGKey(4), pc1, pc2, num_iters=1)
  near = model.apply(variables, pc1, pc2, num_iters=2)["flows"]
  far = model.apply(variables, pc1 + 1000.0, pc2 + 1000.0, num_iters=2)["flows"]
  np.testing.assert_allclose(far, near, atol=5e-3)
