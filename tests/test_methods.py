"""jaxflow.refine.optimiser / rigid / nsfp / methods: NSFP recovers a rigid motion, early stopping stops
with the best-loss flow, the cluster fit against NumPy, degenerate clouds stay finite, and the
methods through evaluate.py, jaxflow.predict and jaxflow.nsfp at toy size."""

import dataclasses
import json
import os

import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow import evaluate, nsfp, predict
from jaxflow.geometry import rigid
from jaxflow.methods import optimise, registry
from jaxflow.refine import optimiser, rigid_clusters

import commands

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _rotation(angle):
  c, s = np.cos(angle), np.sin(angle)
  return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float32)


@pytest.mark.slow
def test_nsfp_recovers_a_rigid_motion():
  rng = np.random.default_rng(0)
  pc1 = rng.uniform(-2, 2, (128, 3)).astype(np.float32)
  gt = pc1 @ _rotation(0.05).T + [0.3, -0.1, 0.2] - pc1
  pc2 = (pc1 + gt)[rng.permutation(128)]  # the same points moved, in another order
  chosen = registry.settings("nsfp", steps=600, objective="exact")
  flow, info = registry.flow_fn("nsfp", chosen=chosen, with_info=True)(None, pc1[None], pc2[None])
  flow, info = np.asarray(flow[0]), {k: np.asarray(v)[0] for k, v in info.items()}
  assert np.mean(np.linalg.norm(flow - gt, axis=1)) < 0.02  # zero flow is 0.37 m off
  assert info["finite"] and info["loss_best"] < 0.01 * info["loss_start"]


def _numpy_chamfer(a, b, truncate):
  d = np.sum((a[:, None] - b[None]) ** 2, axis=-1)
  return np.mean(np.minimum(d.min(1), truncate**2)) + np.mean(np.minimum(d.min(0), truncate**2))


def test_early_stopping_stops_and_returns_the_best_loss_flow():
  rng = np.random.default_rng(1)
  pc1 = rng.uniform(-1, 1, (64, 3)).astype(np.float32)
  pc2 = (pc1 + [0.2, 0.0, 0.1]).astype(np.float32)
  chosen = optimiser.Settings(objective="exact", steps=3000, learning_rate=0.05, patience=20,
                              min_delta=1e-4, refresh=1)
  flow, info = optimiser.optimise(jnp.zeros((1, 64, 3)), pc1[None], pc2[None], chosen)
  steps = int(info["steps"][0])
  assert bool(info["stopped"][0]) and 20 < steps < 3000
  # The loss recorded is that of the flow returned (nearest points searched at every step).
  best = _numpy_chamfer(pc1 + np.asarray(flow[0]), pc2, chosen.truncate)
  np.testing.assert_allclose(float(info["loss_best"][0]), best, rtol=1e-3, atol=1e-7)
  assert best < 0.05 * _numpy_chamfer(pc1, pc2, chosen.truncate)  # it optimised
  # Without early stopping every step runs.
  _, info = optimiser.optimise(jnp.zeros((1, 64, 3)), pc1[None], pc2[None],
                               dataclasses.replace(chosen, patience=0, steps=steps + 7))
  assert int(info["steps"][0]) == steps + 7 and not bool(info["stopped"][0])


@pytest.mark.slow
def test_clusters_and_their_rigid_motions():
  rng = np.random.default_rng(2)
  a = rng.uniform(0, 1, (40, 3))
  b = rng.uniform(0, 1, (30, 3)) + [5.0, 0.0, 0.0]  # far from a: its own cluster
  pc1 = np.concatenate([a, b]).astype(np.float32)
  moves = [(_rotation(0.2), np.array([0.5, 0, 0])), (_rotation(-0.1), np.array([0, 0.3, 0]))]
  flow = np.concatenate([p @ r.T + t - p for p, (r, t) in zip((a, b), moves)]).astype(np.float32)
  chosen = rigid_clusters.Settings(radius=2.0, flow_tolerance=0.5, min_points=4)
  labels = np.asarray(rigid_clusters.clusters(pc1[None], flow[None], chosen)[0])
  np.testing.assert_array_equal(labels, [0] * 40 + [40] * 30)
  r, cen, t = (np.asarray(x[0]) for x in rigid_clusters.fit(pc1[None], flow[None], labels[None], 4))
  for label, p, (r_true, t_true) in ((0, a, moves[0]), (40, b, moves[1])):
    np.testing.assert_allclose(r[label], r_true, atol=1e-4)
    np.testing.assert_allclose(cen[label], p.mean(0), atol=1e-5)
    moved = (p - cen[label]) @ r[label].T + cen[label] + t[label]
    np.testing.assert_allclose(moved, p @ r_true.T + t_true, atol=1e-4)
  got = rigid_clusters.rigid_flow(jnp.asarray(pc1), jnp.asarray(labels), *map(jnp.asarray, (r, cen, t)))
  np.testing.assert_allclose(np.asarray(got), flow, atol=1e-4)
  # The rotation vector's matrix (the rigid model's, jax) against the closed form about y.
  turned = rigid.rotations_from_vectors(jnp.asarray([[0, 0.3, 0]]))[0]
  np.testing.assert_allclose(np.asarray(turned), _rotation(0.3), atol=1e-6)


_TINY = optimise.Optimise(
  descent=dataclasses.replace(optimise.Optimise().descent, steps=30, max_cells=2**15),
  rigid_steps=20)
_TINY_NSFP = dataclasses.replace(optimiser.NSFP, steps=20, max_cells=2**15, width=16, depth=2)
_ZERO_NETWORK = lambda params, a, b: jnp.zeros_like(a)


def _degenerate_pairs():
  """identical points, a plane, far from the origin, pc2 100x smaller: one batch (one compile)."""
  rng = np.random.default_rng(3)
  pc1 = rng.uniform(-1, 1, (4, 48, 3)).astype(np.float32)
  pc1[0] = 1.0
  pc1[1, :, 1] = 0.0
  pc1[2] += 1e5
  pc2 = pc1 + [0.1, 0.0, 0.05]
  pc2[3] = pc1[3] / 100.0
  return pc1, pc2


@pytest.mark.slow
@pytest.mark.parametrize("method, chosen", [
  ("nsfp", _TINY_NSFP), ("nsfp", dataclasses.replace(_TINY_NSFP, objective="grid")),
  ("optimise", _TINY)])
def test_degenerate_clouds_give_finite_flows(method, chosen):
  fn = registry.flow_fn(method, _ZERO_NETWORK, chosen, with_info=True)
  pc1, pc2 = _degenerate_pairs()
  flow, info = fn(None, pc1, pc2)
  assert np.isfinite(np.asarray(flow)).all() and np.asarray(info["finite"]).all()
  # The centring keeps the centimetres far from the origin: the translation is recovered there as
  # well as from the same cloud at the origin, up to float32's spacing at 1e5 m (0.0078 m).
  near1, near2 = pc1.copy(), pc2.copy()
  near1[2], near2[2] = pc1[2] - 1e5, pc2[2] - 1e5
  error = lambda f: np.mean(np.linalg.norm(np.asarray(f[2]) - [0.1, 0.0, 0.05], axis=-1))
  assert error(flow) < error(fn(None, near1, near2)[0]) + np.spacing(np.float32(1e5)), method
  assert error(flow) < (0.01 if method == "optimise" else 0.05), (method, error(flow))
  # Deterministic: the same call gives the same flow.
  np.testing.assert_array_equal(np.asarray(fn(None, pc1, pc2)[0]), np.asarray(flow))
  # Fewer points than the neighbourhoods (8) and the clusters' minimum.
  flow, info = fn(None, pc1[:1, :3], pc2[:1, :3])
  assert np.isfinite(np.asarray(flow)).all() and np.asarray(info["finite"]).all()


def test_settings_reject_bad_values():
  with pytest.raises(ValueError, match="optimiser model"):
    optimiser.Settings(model="tree")
  with pytest.raises(ValueError, match="patience"):
    optimiser.Settings(patience=-1)
  with pytest.raises(registry.ConfigError, match="--method"):
    registry.settings("icp")
  capped = registry.settings("optimise", steps=5)
  assert capped.descent.steps == capped.polish.steps == capped.rigid_steps == 5
  assert registry.settings("nsfp").model == "mlp" and registry.settings("network") is None


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  """The command lines at toy size, run in this process one after another (tests/commands.py)."""
  d = tmp_path_factory.mktemp("methods")
  rng = np.random.default_rng(5)
  pc1 = rng.uniform(-2, 2, (120, 3)).astype(np.float32)
  np.save(d / "pc1.npy", pc1)
  np.save(d / "pc2.npy", pc1 + [0.2, 0.0, 0.1])
  np.save(d / "bad.npy", pc1[:, :2])
  toy = ["--config.eval.num_points=64", "--config.eval.num_iters=2", "--steps", "15"]
  eval_args = ["--dataset", "synthetic_lidar:1", "--split", "val", *toy]
  cases = {
    "eval_nsfp": (evaluate.run, *eval_args, "--method", "nsfp", "--json", d / "nsfp.json"),
    # (optimise: the same dispatch, jaxflow.methods.registry, with the network of the predict case)
    "predict_optimise": (predict.run, d / "pc1.npy", d / "pc2.npy", "--out", d / "p_opt.npy",
                         "--iters", "2", "--steps", "15"),
    "nsfp": (nsfp.run, d / "pc1.npy", d / "pc2.npy", "--out", d / "n.npy", "--steps", "15"),
    "nsfp_bad": (nsfp.run, d / "pc1.npy", d / "bad.npy", "--out", d / "x.npy"),
    "nsfp_bad_objective": (nsfp.run, d / "pc1.npy", d / "pc2.npy", "--out", d / "y.npy",
                           "--objective", "fast"),
  }
  done = {k: commands.run(*v, cwd=ROOT) for k, v in cases.items()}
  return d, {k: (p.returncode, p.stdout, p.stderr) for k, p in done.items()}


@pytest.mark.slow
def test_methods_run_from_both_command_lines(runs):
  d, out = runs
  for case in ("eval_nsfp", "predict_optimise", "nsfp"):
    assert out[case][0] == 0, (case, out[case][2][-2000:])
  results = json.loads((d / "nsfp.json").read_text())
  assert results["method"] == "nsfp" and results["method_settings"]["model"] == "mlp"
  for key in ("epe", "acc_strict", "acc_relax", "outliers", "angle", "pairs", "ms_per_pair"):
    assert np.isfinite(results[key])
  assert results["checkpoint"] is None  # no network loaded
  # 15 steps cannot let early stopping (patience 100) fire: the JSON and stderr say so.
  assert results["convergence"] == {"pairs": 1, "non_finite": 0, "early_stopped": 0,
                                    "mean_steps": 15.0}
  assert "early stopping did not fire on 1 of 1 pairs" in out["eval_nsfp"][2]
  for name in ("p_opt", "n"):
    flow = np.load(d / f"{name}.npy")
    assert flow.shape == (120, 3) and np.isfinite(flow).all()
  assert "method optimise" in out["predict_optimise"][2]  # the default method
  # 15 steps do not let NSFP's early stopping fire: the user is told.
  assert "did not fire within 15 steps" in out["nsfp"][2]
  assert "(exact objective)" in out["nsfp"][2]  # the grid's: tests/test_predict.py


@pytest.mark.slow
def test_nsfp_command_errors_are_one_line(runs):
  _, out = runs
  for case, words in (("nsfp_bad", ["bad.npy", "expected N x 3"]),
                      ("nsfp_bad_objective", ["--objective", "fast"])):
    rc, stdout, stderr = out[case]
    lines = stderr.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert all(w in lines[0] for w in words), lines[0]


@pytest.mark.parametrize("chosen", [
  dataclasses.replace(_TINY_NSFP, patience=3, min_delta=1.0),  # early stopping fires at once
  dataclasses.replace(optimise.Optimise().polish, steps=30),
  dataclasses.replace(_TINY_NSFP, objective="grid")])
def test_the_loop_driven_from_python_gives_the_compiled_loop_result(chosen):
  """optimiser.optimise_host_loop (searches between compiled blocks, what the methods run) and
  optimiser.optimise (one compiled loop, searches by host callback) take the same steps."""
  rng = np.random.default_rng(5)
  pc1 = rng.uniform(-2, 2, (2, 200, 3)).astype(np.float32)
  pc2 = pc1 + rng.normal(0, 0.05, pc1.shape).astype(np.float32) + [0.2, 0.0, 0.1]
  start = jnp.asarray(rng.normal(0, 0.1, pc1.shape), jnp.float32)
  flow, info = optimiser.optimise(start, pc1, pc2, chosen)
  host_flow, host_info = optimiser.optimise_host_loop(start, pc1, pc2, chosen)
  np.testing.assert_allclose(np.asarray(host_flow), np.asarray(flow), atol=1e-5)
  for key in ("steps", "stopped", "finite"):
    np.testing.assert_array_equal(np.asarray(host_info[key]), np.asarray(info[key]), key)
  np.testing.assert_allclose(np.asarray(host_info["loss_best"]), np.asarray(info["loss_best"]),
                             rtol=1e-5)
  assert (np.asarray(info["steps"]) < chosen.steps).all() == (chosen.patience == 3)


def test_a_long_optimisation_shows_its_steps_loss_and_time_left(capsys):
  """NSFP's host loop draws a bar of steps with the lowest loss on stderr when asked (by default
  only on a terminal: none here)."""
  rng = np.random.default_rng(0)
  pc1 = jnp.asarray(rng.normal(size=(1, 64, 3)), jnp.float32)
  pc2 = pc1 + 0.1
  chosen = dataclasses.replace(optimiser.NSFP, steps=12, width=16, depth=2, max_cells=2**15)
  optimiser.optimise_host_loop(jnp.zeros_like(pc1), pc1, pc2, chosen)
  assert "optimisation" not in capsys.readouterr().err  # not a terminal
  optimiser.optimise_host_loop(jnp.zeros_like(pc1), pc1, pc2, chosen, progress=True)
  err = capsys.readouterr().err
  assert "mlp optimisation" in err and "12/12" in err and "loss=" in err, err
