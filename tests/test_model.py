"""The whole network: parameter counts, shapes, the scan, symmetries, gradients, and fidelity to
the official PV-RAFT outputs in tests/data (shipped with the repository, so every clone runs it)."""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow.configs import ablation, default, pvraft
from jaxflow import geometry, inference, losses
from jaxflow.import_pvraft import convert_state_dict, import_into
from jaxflow.model import build_model
from jaxflow.summary import parameter_counts


def small_config(**overrides):
  m = default.model_config()
  m.widths = (16, 16, 32, 32)
  m.knn, m.truncate_k, m.corr_knn = 8, 24, 8
  for k, v in overrides.items():
    m[k] = v
  return m


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
  variables = model.init(jax.random.PRNGKey(0), pc1, pc2, num_iters=1)
  out = model.apply(variables, pc1, pc2, num_iters=3)
  assert out["flows"].shape == (batch, 3, n, 3)
  assert out["refined"].shape == (batch, n, 3)
  assert np.all(np.isfinite(out["flows"]))


def test_jit_compiles_once_per_shape():
  model = build_model(small_config())
  pc1, pc2 = random_pair(0)
  variables = model.init(jax.random.PRNGKey(0), pc1, pc2, num_iters=1)
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


@pytest.mark.parametrize("cell", ["single_gate", "gru"])
def test_scan_equals_python_loop(cell):
  model = build_model(small_config(cell=cell))
  pc1, pc2 = random_pair(2)
  variables = model.init(jax.random.PRNGKey(1), pc1, pc2, num_iters=1)
  scanned = model.apply(variables, pc1, pc2, num_iters=4, refine=False)["flows"]

  # The same step as a Python loop: the scan's carry, broadcast parameters and output order.
  looped = model.apply(variables, pc1, pc2, num_iters=4, refine=False, unroll=True)["flows"]
  np.testing.assert_allclose(scanned, looped, rtol=1e-5, atol=1e-6)


def test_recomputed_iterations_give_the_same_gradient_with_fewer_stored_activations():
  pc1, pc2 = random_pair(7, n=96, m=96)
  gt = pc2 - pc1
  params = build_model(small_config()).init(jax.random.PRNGKey(5), pc1, pc2, num_iters=1)["params"]

  def compiled_grad(remat):
    model = build_model(small_config(remat_iterations=remat))
    loss = lambda p: losses.sequence_loss(
      model.apply({"params": p}, pc1, pc2, num_iters=6, refine=False)["flows"], gt)
    return jax.jit(jax.grad(loss)).lower(params).compile()

  stored, recomputed = compiled_grad(False), compiled_grad(True)
  for a, b in zip(jax.tree.leaves(recomputed(params)), jax.tree.leaves(stored(params))):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6 * float(jnp.max(jnp.abs(b))))
  temp = lambda f: f.memory_analysis().temp_size_in_bytes
  assert temp(recomputed) < 0.8 * temp(stored), (temp(recomputed), temp(stored))


def test_permuting_pc1_permutes_flow_and_pc2_order_does_not_matter():
  model = build_model(small_config())
  pc1, pc2 = random_pair(3)
  variables = model.init(jax.random.PRNGKey(2), pc1, pc2, num_iters=1)
  run = jax.jit(lambda a, b: model.apply(variables, a, b, num_iters=3)["refined"])
  base = run(pc1, pc2)
  perm1 = np.random.default_rng(0).permutation(pc1.shape[1])
  perm2 = np.random.default_rng(1).permutation(pc2.shape[1])
  np.testing.assert_allclose(run(pc1[:, perm1], pc2), base[:, perm1], rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(run(pc1, pc2[:, perm2]), base, rtol=1e-4, atol=1e-5)


def finite_loss_and_grads(cfg, pc1, pc2):
  model = build_model(cfg)
  variables = model.init(jax.random.PRNGKey(3), pc1, pc2, num_iters=1)
  gt = jnp.full(pc1.shape, 0.1)

  def loss_fn(params):
    out = model.apply({"params": params}, pc1, pc2, num_iters=2)
    return losses.total_loss(out["flows"], out["refined"], gt)

  loss, grads = jax.value_and_grad(loss_fn)(variables["params"])
  return np.isfinite(loss) and all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))


def test_gradients_finite_on_degenerate_input():
  """One batch, one case per pair: duplicate points, all points identical, a cloud 1e4 m away."""
  pc1, pc2 = random_pair(4, n=40, m=40)
  dup1 = pc1.at[:, 20:].set(pc1[:, :20])
  dup2 = pc2.at[:, 10:30].set(pc2[:, :20])
  same = jnp.full_like(pc1, 0.5)
  batch1 = jnp.concatenate([dup1, same, pc1 + 1e4])
  batch2 = jnp.concatenate([dup2, same, pc2 + 1e4])
  assert finite_loss_and_grads(small_config(), batch1, batch2)


def test_gradients_finite_with_fewer_points_than_k():
  cfg = small_config()
  cfg.knn, cfg.truncate_k, cfg.corr_knn = 8, 64, 32  # more than the 8 points each cloud holds
  pc1, pc2 = random_pair(6, n=8, m=8)
  assert finite_loss_and_grads(cfg, pc1, pc2)


def test_far_cloud_gives_the_same_flow_as_near():
  """Translation invariance: the network sees only relative positions (up to float32 rounding)."""
  model = build_model(small_config())
  pc1, pc2 = random_pair(5)
  variables = model.init(jax.random.PRNGKey(4), pc1, pc2, num_iters=1)
  near = model.apply(variables, pc1, pc2, num_iters=2)["flows"]
  far = model.apply(variables, pc1 + 1000.0, pc2 + 1000.0, num_iters=2)["flows"]
  np.testing.assert_allclose(far, near, atol=5e-3)


# --- Fidelity to the official PV-RAFT network --------------------------------------------------
# tests/data/pvraft_seed5_n2048_it12.npz holds the official PV-RAFT network's outputs for seeded
# weights (tests/data/README.md), with its own kNN graphs (nbr1, nbr2): given them, the network is
# compared with no emulation of the official float32 neighbour ranking (whose rounding picks another
# 32nd neighbour than an exact kNN on a few rows). It is in the repository: no clone skips these.

PVRAFT_REFERENCE = pathlib.Path(__file__).resolve().parent / "data" / "pvraft_seed5_n2048_it12.npz"


@pytest.fixture(scope="module")
def pvraft_reference():
  with np.load(PVRAFT_REFERENCE) as data:  # a missing file fails: the repository ships it
    return {k: data[k] for k in data.files}


def imported_pvraft(ref):
  imported, has_refine = convert_state_dict({k: v for k, v in ref.items() if "/" in k})
  assert has_refine
  model = build_model(pvraft.get_config("refine").model)
  pc1, pc2 = jnp.asarray(ref["pc1"]), jnp.asarray(ref["pc2"])
  fresh = model.init(jax.random.PRNGKey(0), pc1[:, :64], pc2[:, :64], num_iters=1)["params"]
  return model, import_into(jax.tree_util.tree_map(np.asarray, fresh), imported)


@pytest.mark.slow
def test_pvraft_reproduces_official_outputs_given_its_graphs(pvraft_reference):
  ref = pvraft_reference
  model, params = imported_pvraft(ref)
  pc1, pc2 = jnp.asarray(ref["pc1"]), jnp.asarray(ref["pc2"])
  graphs = (jnp.asarray(ref["nbr1"]), jnp.asarray(ref["nbr2"]))
  num_iters = ref["flows"].shape[1]
  out = jax.jit(lambda p: model.apply({"params": p}, pc1, pc2, num_iters=num_iters,
                                      graphs=graphs))(params)
  fmap1 = model.apply({"params": params}, pc1, graphs[0],
                      method=lambda mdl, p, g: mdl.feature_encoder(p, g))
  want = ref["fmap1"].transpose(0, 2, 1)
  assert np.abs(np.asarray(fmap1) - want).max() <= 1e-5 * np.abs(want).max()
  err = np.linalg.norm(np.asarray(out["flows"][0]) - ref["flows"][0], axis=-1)  # Z x N
  for z in range(num_iters):  # the README's tolerances, at every iteration
    assert np.median(err[z]) < 5e-6, (z, np.median(err[z]))
    assert np.mean(err[z] < 1e-3) >= 0.995, (z, np.mean(err[z] < 1e-3))
  refined_err = np.linalg.norm(np.asarray(out["refined"][0]) - ref["refined"][0], axis=-1)
  assert np.median(refined_err) < 1e-5 and np.mean(refined_err < 1e-3) >= 0.995


def test_exact_knn_differs_from_the_official_graphs_on_a_few_rows_only(pvraft_reference):
  """Our exact kNN and the official float32 one choose the same 32 neighbours (as sets) on all but
  a handful of the 2048 rows (README: 1-3, where float32 rounding exceeds the 32nd/33rd gap)."""
  for cloud, nbr in (("pc1", "nbr1"), ("pc2", "nbr2")):
    points = jnp.asarray(pvraft_reference[cloud])
    ours = np.sort(np.asarray(geometry.knn(points, points, 32))[0], axis=-1)
    theirs = np.sort(pvraft_reference[nbr][0], axis=-1)
    differing = int(np.sum(np.any(ours != theirs, axis=-1)))
    assert differing <= 5, (cloud, differing)


def test_import_rejects_foreign_weights():
  from jaxflow.errors import CheckpointError
  with pytest.raises(CheckpointError, match="matches no jaxflow parameter"):
    convert_state_dict({"backbone.layer1.weight": np.zeros((3, 3))})


@pytest.mark.slow
def test_import_cli_writes_a_checkpoint_that_restores_the_weights(pvraft_reference, tmp_path):
  import subprocess
  import sys

  from conftest import ROOT
  from jaxflow import checkpointing
  source = tmp_path / "weights.npz"
  np.savez(source, **{k: v for k, v in pvraft_reference.items() if "/" in k})
  out = tmp_path / "imported"
  done = subprocess.run(
    [sys.executable, "-m", "jaxflow.import_pvraft", str(source), "--out", str(out)],
    cwd=ROOT, capture_output=True, text=True)
  assert done.returncode == 0, done.stderr
  state, config, step = checkpointing.restore_checkpoint(out)
  # With refinement weights: a trained stage 2, which evaluate.py and predict run refined.
  assert config.model.refine == "setconv" and config.train.stage == 2 and step == 0
  kernel = pvraft_reference["rsf/update_block.gru.convz.weight"][:, :, 0].T
  np.testing.assert_array_equal(state.params["update"]["gru"]["convz"]["kernel"], kernel)
  fc = pvraft_reference["refine/fc.weight"].T
  np.testing.assert_array_equal(state.params["refine"]["fc"]["kernel"], fc)

  # jaxflow.predict on it returns the refined flow: the official refined flow up to the few-row kNN
  # difference (our exact kNN, not the official graphs), far from the official coarse flow (the
  # refinement of these random weights moves points by a median 0.57 m).
  ref = pvraft_reference
  predictor = inference.load_predictor(out)
  assert predictor.refine
  flow = inference.predict_flow(ref["pc1"][0], ref["pc2"][0], num_iters=ref["flows"].shape[1],
                                predictor=predictor)
  to_refined = np.linalg.norm(flow - ref["refined"][0], axis=-1)
  to_coarse = np.linalg.norm(flow - ref["flows"][0, -1], axis=-1)
  assert np.median(to_refined) < 1e-2 and np.median(to_coarse) > 0.2, (
    np.median(to_refined), np.median(to_coarse))


def test_import_without_refinement_predicts_the_coarse_flow(pvraft_reference, tmp_path):
  from jaxflow import import_pvraft
  source = tmp_path / "rsf.npz"
  np.savez(source, **{k: v for k, v in pvraft_reference.items() if k.startswith("rsf/")})
  import_pvraft.main([str(source), "--out", str(tmp_path / "imported")])
  # A stage-1 checkpoint of the network without refinement: predict and evaluate.py return the
  # last iteration's flow (evaluation.model_predict_fn), the only one such a model has.
  predictor = inference.load_predictor(tmp_path / "imported")
  assert not predictor.refine and predictor.config.train.stage == 1
  assert predictor.config.model.refine == "none" and predictor.model.refine == "none"
