"""jaxflow.test_time: the objective against a NumPy loop, recovery of a known motion, independence of
the pairs of a batch, settings from the config."""

import dataclasses

import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from jaxflow.configs import default
from jaxflow import geometry, test_time
from jaxflow.errors import ConfigError


def numpy_objective(flow, pc1, pc2, k, smoothness, truncate):
  """One pair, plain loops: truncated two-way Chamfer + mean L1 flow difference to the k nearest."""
  warped = pc1 + flow
  forward = [min(min(np.sum((w - q) ** 2) for q in pc2), truncate**2) for w in warped]
  backward = [min(min(np.sum((q - w) ** 2) for w in warped), truncate**2) for q in pc2]
  smooth = []
  for i, p in enumerate(pc1):
    order = np.argsort([np.sum((p - q) ** 2) for q in pc1], kind="stable")
    smooth += [np.sum(np.abs(flow[j] - flow[i])) for j in order[1:k + 1]]
  return np.mean(forward) + np.mean(backward) + smoothness * np.mean(smooth)


def test_objective_matches_a_numpy_loop():
  rng = np.random.default_rng(0)
  pc1 = rng.uniform(-2, 2, (40, 3)).astype(np.float32)
  pc2 = (pc1[:35] + rng.normal(0, 0.3, (35, 3))).astype(np.float32)
  flow = rng.normal(0, 0.5, (40, 3)).astype(np.float32)
  settings = test_time.Settings(steps=1, smoothness=0.7, neighbours=5, truncate=0.6)
  args = jnp.asarray(flow[None]), jnp.asarray(pc1[None]), jnp.asarray(pc2[None])
  nbr = geometry.knn(args[1], args[1], settings.neighbours + 1)[:, :, 1:]
  match = test_time.correspondences(*args)
  got = test_time.objective(*args, nbr, match, settings)
  expected = numpy_objective(flow, pc1, pc2, 5, 0.7, 0.6)
  assert got.shape == (1,)
  np.testing.assert_allclose(float(got[0]), expected, rtol=1e-5)
  # The truncation acts here: without it the value is larger.
  assert expected < numpy_objective(flow, pc1, pc2, 5, 0.7, 100.0)


def test_recovers_a_rigid_motion_from_zero_flow():
  rng = np.random.default_rng(1)
  pc1 = rng.uniform(-3, 3, (300, 3)).astype(np.float32)
  motion = np.array([0.25, -0.1, 0.15], np.float32)
  pc2 = pc1[rng.permutation(300)] + motion  # the same points moved, in another order
  settings = test_time.Settings(steps=300, smoothness=1.0)
  flow, before, after = test_time.optimise_flow(jnp.zeros((1, 300, 3)), jnp.asarray(pc1[None]),
                                                jnp.asarray(pc2[None]), settings)
  epe = np.linalg.norm(np.asarray(flow[0]) - motion, axis=-1)
  assert np.mean(epe) < 0.02, np.mean(epe)  # zero flow is 0.31 m off
  assert float(after[0]) < 0.05 * float(before[0])


def test_pairs_of_a_batch_are_optimised_independently():
  rng = np.random.default_rng(2)
  pc1 = rng.uniform(-2, 2, (2, 64, 3)).astype(np.float32)
  pc2 = (pc1 + rng.normal(0, 0.2, (2, 64, 3)) + [[[0.3, 0, 0]], [[0, -0.4, 0]]]).astype(np.float32)
  flow0 = rng.normal(0, 0.1, (2, 64, 3)).astype(np.float32)
  settings = test_time.Settings(steps=25, refresh=4)  # 6 searches and a remainder of 1 step
  both = test_time.optimise_flow(jnp.asarray(flow0), jnp.asarray(pc1), jnp.asarray(pc2), settings)
  for b in range(2):
    alone = test_time.optimise_flow(jnp.asarray(flow0[b:b + 1]), jnp.asarray(pc1[b:b + 1]),
                                    jnp.asarray(pc2[b:b + 1]), settings)
    for x, y in zip(both, alone):
      np.testing.assert_allclose(np.asarray(x[b]), np.asarray(y[0]), rtol=1e-5, atol=1e-6)
  assert not np.allclose(np.asarray(both[0]), flow0, atol=1e-3)  # it moved


def test_zero_steps_leave_the_flow_as_given():
  rng = np.random.default_rng(3)
  pc1 = jnp.asarray(rng.uniform(-2, 2, (1, 32, 3)), jnp.float32)
  flow0 = jnp.asarray(rng.normal(0, 0.1, (1, 32, 3)), jnp.float32)
  flow, before, after = test_time.optimise_flow(flow0, pc1, pc1 + 0.1, test_time.Settings(steps=0))
  np.testing.assert_array_equal(np.asarray(flow), np.asarray(flow0))
  np.testing.assert_array_equal(np.asarray(before), np.asarray(after))


def test_settings_from_config():
  eval_config = default.get_config("eval").eval
  # The config lists every field, with the dataclass's defaults: off.
  assert test_time.settings_from_config(eval_config) == test_time.Settings()
  # Every field but `chunk`, unused since the k-d tree search; older configs that set it still load.
  assert set(eval_config.test_time) == {f.name for f in dataclasses.fields(test_time.Settings)} - {
    "chunk"}
  older = ml_collections.ConfigDict({"test_time": {**eval_config.test_time.to_dict(), "chunk": 64}})
  assert test_time.settings_from_config(older).chunk == 64
  assert test_time.settings_from_config(ml_collections.ConfigDict({"num_points": 8})).steps == 0
  eval_config.test_time.steps = 30
  assert test_time.settings_from_config(eval_config).steps == 30
  # One bad field at a time (neighbours 0: the smoothness term would average over none, NaN).
  for field, bad, message in [("steps", -1, "config.eval.test_time: test-time steps"),
                              ("refresh", 0, "refresh"),
                              ("neighbours", 0, "neighbours must be an integer >= 1")]:
    good = eval_config.test_time[field]
    eval_config.test_time[field] = bad
    with pytest.raises(ConfigError, match=message):
      test_time.settings_from_config(eval_config)
    eval_config.test_time[field] = good
  eval_config.test_time.stepz = 30
  with pytest.raises(ConfigError, match="unknown field.*stepz"):
    test_time.settings_from_config(eval_config)
