"""jaxflow.lidar.sweep: the flow of raw sweep pairs, against the generator's truth; bad input."""

import numpy as np
import pytest

from jaxflow import inference
from jaxflow.data import synthetic_sweep as ss
from jaxflow.errors import CheckpointError, DataError
from jaxflow.evaluation import metrics
from jaxflow.lidar import sweep

SMALL = ss.Options(scale=0.3)  # ~30k points a sweep: seconds


def run(s, **kwargs):
  flow, info = sweep.raw_sweep_flow(None, s.pc1, s.pc2, **kwargs)
  assert flow.shape == s.pc1.shape and flow.dtype == np.float32 and np.isfinite(flow).all()
  return flow, info


def test_a_sweep_gets_the_static_world_exact_and_movers_moved():
  s = ss.sweep_pair("val", 2)
  flow, info = run(s)
  epe = metrics.three_way_epe(flow, s.flow, s.ego_flow, s.foreground, s.eval_mask)
  still = metrics.three_way_epe(s.ego_flow, s.flow, s.ego_flow, s.foreground, s.eval_mask)
  assert epe["bs"] < 0.01 and epe["fs"] < 0.02  # the ego-motion, exact
  assert epe["fd"] < 0.3 * still["fd"]  # the moving objects found (the ego-motion alone: 2.3 m)
  ground = np.linalg.norm(flow - s.flow, axis=1)[s.ground]
  assert np.median(ground) < 0.01  # the ground's flow is the ego-motion, not a fit to anything
  assert "PC1 points get the ego-motion flow" in info.note() and not info.notes
  again, _ = run(s)
  np.testing.assert_array_equal(again, flow)  # deterministic


def test_a_parked_sensor_leaves_the_background_still():
  s = ss.sweep_pair("val", 11, ss.Options(speed=(0.0, 0.0), scale=0.5))
  flow, _ = run(s)
  background = s.category == 0
  assert np.median(np.abs(flow[background])) < 0.005
  assert np.percentile(np.linalg.norm(flow[background], axis=1), 95) < 0.02


@pytest.mark.parametrize("options", [ss.Options(ground=False, scale=0.3),
                                     ss.Options(speed=(3.0, 3.0), scale=0.3),
                                     ss.Options(movers=False, scale=0.3),
                                     ss.Options(origin_height=0.33, stacked=True, scale=0.3),
                                     ss.Options(origin_height=0.0, dense=True, scale=0.3),
                                     ss.Options(origin_height=-2.0, scale=0.3)],
                         ids=["no ground", "3 m a frame", "nothing moves",
                              "av2's ego frame, stacked sensors", "vehicle frame, dense city",
                              "origin 2 m below the road"])
def test_hard_sweeps_give_finite_flows_near_the_truth(options):
  s = ss.sweep_pair("val", 12, options)
  flow, info = run(s)
  background = (s.category == 0) & s.eval_mask
  assert np.median(np.linalg.norm(flow - s.flow, axis=1)[background]) < 0.05
  assert not any("perpendicular" in n for n in info.notes)  # no ground is no sign of a wrong up
  np.testing.assert_allclose(info.motion.translation, s.ego_translation, atol=0.05)
  below = options.origin_height is not None and options.origin_height < 0
  assert any("below the origin" in n for n in info.notes) == below  # a note, not a refusal


def test_broken_pairs_give_finite_flows_and_a_note():
  s = ss.sweep_pair("val", 14, SMALL)
  rng = np.random.default_rng(0)
  tiny = ss.SweepPair(**{**s.__dict__, "pc1": s.pc1[rng.choice(len(s.pc1), 100)],
                         "pc2": s.pc2[rng.choice(len(s.pc2), 100)]})
  for pc1, pc2 in ((tiny.pc1, tiny.pc2), (s.pc1, s.pc2 + [100.0, 0.0, 0.0])):
    flow, info = sweep.raw_sweep_flow(None, pc1, pc2)
    assert np.isfinite(flow).all()
    assert any("explains only" in n for n in info.notes)
    assert "explains only" in info.note()


def test_a_wrong_up_axis_is_refused_and_can_be_overridden():
  s = ss.sweep_pair("val", 1, SMALL)
  with pytest.raises(DataError, match="use --up z"):
    sweep.raw_sweep_flow(None, s.pc1, s.pc2, up="y")
  flow, _ = sweep.raw_sweep_flow(None, s.pc1, s.pc2, up="y", ground_limits=False)
  assert np.isfinite(flow).all()


def test_any_up_axis_gives_the_same_flow():
  s = ss.sweep_pair("val", 3, SMALL)
  flow_z, info_z = run(s)
  order = [1, 2, 0]  # z-up -> y-up: (x, y, z) -> (y, z, x), a rotation
  flow_y, info_y = sweep.raw_sweep_flow(None, s.pc1[:, order], s.pc2[:, order], up="y")
  np.testing.assert_allclose(flow_y, flow_z[:, order], atol=1e-3)
  np.testing.assert_allclose(info_y.motion.translation, info_z.motion.translation[order], atol=1e-4)


def test_predict_lidar_gives_the_true_ego_motion():
  """predict --lidar's Python path (the network is not run by default): every static point,
  ground and far points included, moves with the sweep's true ego-motion."""
  s = ss.sweep_pair("val", 5, SMALL)
  predictor = inference.Predictor(None, None, None, False, method="optimise")
  got = predictor.predict(s.pc1, s.pc2, lidar=True, up="z")
  flow, info = got.flow, got.sweep
  static = s.category == 0
  err = np.linalg.norm(flow - s.ego_flow, axis=1)[static]
  assert np.median(err) < 0.005 and np.percentile(err, 90) < 0.02
  np.testing.assert_allclose(info.motion.translation, s.ego_translation, atol=0.01)


def test_a_camera_view_uses_the_given_flow_and_its_rigid_part():
  s = ss.sweep_pair("val", 6, SMALL)
  front1 = np.abs(np.arctan2(s.pc1[:, 1], s.pc1[:, 0])) < np.radians(45)
  front2 = np.abs(np.arctan2(s.pc2[:, 1], s.pc2[:, 0])) < np.radians(45)
  pc1, truth, ego_flow = s.pc1[front1], s.flow[front1], s.ego_flow[front1]
  seen = {}

  def exact(a, b):  # a perfect estimator: the true flow of the points it is given
    seen["rows"] = len(a)
    rows = np.flatnonzero(np.isin(pc1.view("f4,f4,f4"), a.view("f4,f4,f4")).ravel())
    return truth[rows]

  flow, info = sweep.raw_sweep_flow(exact, pc1, s.pc2[front2])
  assert "camera's view" in info.note() and seen["rows"] == info.kept[0]
  static = s.category[front1] == 0  # the given flow where it ran, its rigid part elsewhere
  assert np.median(np.linalg.norm(flow - ego_flow, axis=1)[static]) < 0.01
  np.testing.assert_allclose(info.motion.translation, s.ego_translation, atol=0.02)


def test_a_sweep_loads_no_checkpoint_until_the_method_runs(tmp_path):
  """predict --lidar's predictor (the lidar method running the network): a 360-degree sweep never
  reads the checkpoint (here a missing one, which would raise), a camera's view and a start
  (method.lidar.start) do."""
  missing = str(tmp_path / "no_checkpoint")
  lidar = lambda start: inference.load_predictor(
    missing, method="lidar", method_fields={"method": "network", "start": start})
  s = ss.sweep_pair("val", 5, ss.Options(scale=0.1))
  predictor = lidar(False)
  got = predictor.predict(s.pc1, s.pc2, up="z")
  assert predictor.source == "no checkpoint loaded" and got.flow.shape == s.pc1.shape
  front1 = np.abs(np.arctan2(s.pc1[:, 1], s.pc1[:, 0])) < np.radians(45)
  front2 = np.abs(np.arctan2(s.pc2[:, 1], s.pc2[:, 0])) < np.radians(45)
  for pc1, pc2, start in ((s.pc1[front1], s.pc2[front2], False), (s.pc1, s.pc2, True)):
    with pytest.raises(CheckpointError, match="no_checkpoint: no such checkpoint"):  # load attempted
      lidar(start).predict(pc1, pc2, up="z")


def test_predicts_seed_is_the_pipelines():
  """The lidar method's flow at a seed is the pipeline's at that seed (its ego-motion's starts,
  its groups' random halves); predict's seed once never reached it (every seed gave seed 0's)."""
  s = ss.sweep_pair("val", 0, SMALL)
  zero, _ = run(s, seed=0)
  one, _ = run(s, seed=1)
  api = inference.predict_flow(s.pc1, s.pc2, method="lidar", up="z", seed=1)
  np.testing.assert_array_equal(api, one)
  assert np.abs(zero - one).max() > 0.01  # the seed matters on this pair
