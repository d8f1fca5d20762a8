"""jaxflow.lidar.ego: the sensor's motion between two raw sweeps, against the generator's true motion."""

import numpy as np
import pytest

from jaxflow.data import synthetic_sweep as ss
from jaxflow.geometry import rigid
from jaxflow.lidar import ego, ground
from jaxflow.lidar.settings import DEFAULTS


def errors(motion, sweep):
  """(rotation error in degrees, translation error in metres) against the true ego-motion."""
  d = motion.rotation @ sweep.ego_rotation.T
  angle = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1)))
  return angle, float(np.linalg.norm(motion.translation - sweep.ego_translation))


def fit(sweep, **kwargs):
  s1, s2 = ground.fit_surface(sweep.pc1), ground.fit_surface(sweep.pc2)
  return ego.estimate(sweep.pc1, sweep.pc2, s1.ground(sweep.pc1), s2.ground(sweep.pc2), **kwargs)


@pytest.fixture(scope="module")
def slow_sweep():
  return ss.sweep_pair("val", 0, ss.Options(speed=(0.5, 0.6)))


def test_recovered_to_a_centimetre_from_each_start(slow_sweep):
  s = slow_sweep
  true = rigid.Motion(s.ego_rotation, s.ego_translation)
  c, sn = np.cos(np.radians(1.0)), np.sin(np.radians(1.0))
  off = rigid.Motion(np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ true.rotation,
                     true.translation + [0.3, -0.2, 0.05])  # network-like: 1 deg, 0.4 m off
  result = fit(s, starts={"network": off}, refit_search=True)  # as the raw-sweep pipeline
  fits = {"zero", "zero+gicp", "network+gicp", "search+gicp", "search+trimmed"}
  refined = set(result.starts) - fits
  assert fits <= set(result.starts)  # each start's GICP; the search's refitted on its inliers
  assert len(refined) == 1 and refined.pop().endswith("+trimmed")  # the best, refitted
  for name, (motion, _) in result.starts.items():
    if name == "zero":
      continue
    angle, shift = errors(motion, s)
    assert angle < 0.05 and shift < 0.01, (name, angle, shift)
  assert result.inlier_fraction > 0.7 and result.note is None


def test_a_fast_sensor_is_recovered():
  s = ss.sweep_pair("val", 3, ss.Options(speed=(2.9, 3.0)))
  assert np.linalg.norm(s.ego_translation) > 2.8
  angle, shift = errors(fit(s).motion, s)
  assert angle < 0.05 and shift < 0.01


def test_a_parked_sensor_gives_zero_motion():
  s = ss.sweep_pair("val", 4, ss.Options(speed=(0.0, 0.0)))
  result = fit(s)
  assert np.abs(result.motion.flow(s.pc1)[s.category == 0]).max() < 0.01  # background flow zero


def test_pc2_in_another_frame_is_warned_about(slow_sweep):
  s = slow_sweep
  c, sn = np.cos(np.radians(40)), np.sin(np.radians(40))
  turned = s.pc2 @ np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]).T + [30.0, -12.0, 0.0]
  result = ego.estimate(s.pc1, turned)
  assert result.inlier_fraction < DEFAULTS.ego.plausible_inliers
  assert "explains only" in result.note and "consecutive sweeps" in result.note


def test_traffic_beside_the_sensor_does_not_pull_the_ego_motion():
  """A dense city from Argoverse 2's ego frame, two cars passing 2.5 m beside the sensor (17k of
  its points): GICP of every point lands 0.64 m off from any start, the true motion included, and
  so does its refit on its own inliers; the static residual knows better. GICP refitted on what
  the coarse search's start explains (the raw-sweep pipeline's candidate) finds it."""
  s = ss.sweep_pair("test", 5, ss.FORMS["city"])
  truth = rigid.Motion.of(s.ego_rotation, s.ego_translation)
  assert errors(ego.Registration(s.pc1, s.pc2).gicp(truth), s)[1] > 0.3  # the failure
  assert errors(ego.estimate(s.pc1, s.pc2).motion, s)[1] > 0.3  # without the candidate
  angle, shift = errors(ego.estimate(s.pc1, s.pc2, refit_search=True).motion, s)
  assert angle < 0.05 and shift < 0.02, (angle, shift)
