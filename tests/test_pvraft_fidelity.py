"""Fidelity to the official PV-RAFT network: its outputs in tests/data (shipped with the
repository, so every clone runs these), its weights imported by jaxflow.import_pvraft."""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow import inference
from jaxflow.configs import pvraft
from jaxflow.geometry import neighbours
from jaxflow.import_pvraft import convert_state_dict, import_into
from jaxflow.network.model import build_model

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
  fresh = jax.jit(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, num_iters=1))(
    pc1[:, :64], pc2[:, :64])["params"]
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
  fmap1 = jax.jit(lambda p: model.apply({"params": p}, pc1, graphs[0],
                                        method=lambda mdl, x, g: mdl.feature_encoder(x, g)))(params)
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
    ours = np.sort(np.asarray(neighbours.matmul_knn(points, points, 32))[0], axis=-1)
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
  from jaxflow.network import checkpointing
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
  predictor = inference.load_predictor(out, method="network")
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
  # last iteration's flow (methods.registry.model_predict_fn), the only one such a model has.
  predictor = inference.load_predictor(tmp_path / "imported", method="network")
  assert not predictor.refine and predictor.config.train.stage == 1
  assert predictor.config.model.refine == "none" and predictor.model.refine == "none"
