"""jaxflow.lidar.both_ways: movers sought from both sweeps, so a pair predicted backwards finds what
the forward run finds; and the judge between two motions (jaxflow.lidar.judge.better)."""

import dataclasses

import numpy as np
import pytest

import test_objects
from jaxflow.data import synthetic_sweep as ss
from jaxflow.geometry import rigid
from jaxflow.lidar import both_ways, judge, sweep
from jaxflow.lidar.settings import DEFAULTS

ONE_WAY = dataclasses.replace(DEFAULTS, objects=dataclasses.replace(DEFAULTS.objects,
                                                                    both_ways=False))


def test_between_two_motions_significance_decides_and_against_standing_still_the_margins():
  """A paired gain of 0.02 truncations over 400 points (spread 0.01): between two motions it is
  significant (40 standard errors) and wins; against standing still it is under the judge's 0.05
  margin and loses. Noise alone (a gain of 0 +- 0.05) never wins."""
  rng = np.random.default_rng(0)
  base = rng.uniform(0.2, 0.4, 400)
  other = base - 0.02 + rng.normal(0, 0.01, 400)
  objects = DEFAULTS.objects
  assert judge.better(base, other, objects, both_move=True)
  assert not judge.better(base, other, objects, both_move=False)
  assert not judge.better(other, base, objects, both_move=True)
  noise = base + rng.normal(0, 0.05, 400)
  assert not judge.better(base, noise - noise.mean() + base.mean(), objects, both_move=True)
  hidden = np.full(400, np.nan)  # pc2 sees neither placement: no evidence either way
  assert not judge.better(hidden, other, objects, both_move=True)


def test_a_car_pulling_away_from_the_one_behind_it_is_found():
  """Two cars bumper to bumper 0.5 m apart, one group in pc1 (its cells bridge the gap); the front
  one pulls away 1 m along the row. Forward, standing still explains most of the group (and the
  front car's flat side slides along itself: little of it is unexplained), so no motion wins and
  the front car stood still at every sampling; in pc2 it stands apart, its own group, fitted
  against pc1 and offered back: it gets its motion, the parked car, the wall keep theirs."""
  size, faces = np.array([4.5, 1.8, 1.5]), ["-y", "top", "-x", "+x"]
  still = rigid.Motion(np.eye(3), np.zeros(3))
  for seed in range(3):
    rng, rng2 = np.random.default_rng(seed), np.random.default_rng(seed + 100)
    wall = np.c_[rng.uniform(-20, 20, 3000), np.full(3000, 12.0), rng.uniform(0, 4, 3000)]
    parked = lambda r: test_objects._visible_faces(r, (-2.5, 4.0), size, 1500, faces)
    car = lambda r, dx: test_objects._visible_faces(r, (2.5 + dx, 4.0), size, 1500, faces)
    pc1 = np.concatenate([wall, parked(rng), car(rng, 0.0)])
    pc2 = np.concatenate([wall + rng2.normal(0, 0.01, wall.shape), parked(rng2), car(rng2, 1.0)])
    flows = {}
    for name, objects in (("both", DEFAULTS.objects), ("one", ONE_WAY.objects)):
      flows[name], _ = both_ways.object_flow(pc1, pc2, np.zeros(len(pc1), bool),
                                             np.zeros(len(pc2), bool), still, settings=objects)
    front = slice(4500, 6000)
    assert np.linalg.norm(flows["both"][front] - [1.0, 0, 0], axis=1).mean() < 0.02, seed
    np.testing.assert_array_equal(flows["both"][:4500], 0.0)  # the wall and the parked car
    np.testing.assert_array_equal(flows["one"][front], 0.0)  # the step turned off


def _car_error(pair, instance, settings):
  flow, _ = sweep.raw_sweep_flow(None, pair.pc1, pair.pc2, settings=settings)
  mine = pair.instance == instance
  return float(np.linalg.norm(flow[mine] - pair.flow[mine], axis=1).mean())


@pytest.mark.slow
def test_a_car_passing_beside_the_sensor_is_found_backwards_as_forwards():
  """The generator's val pair 1 holds a car passing 3.8 m beside the sensor at 2.1 m a frame
  (instance 23, ~6,000 points). Forwards pc1's side of it fixes its motion; backwards, pc1's
  groups alone slid it 0.18 m along its flat side. Sought from both sweeps, the backward pass
  (the forward run's own) offers its motion, and both sweeps' evidence takes it."""
  forward = ss.sweep_pair("val", 1)
  backward = ss.sweep_pair("val", 1, ss.Options(reverse=True))
  car = 23
  assert np.median(np.linalg.norm(forward.flow - forward.ego_flow, axis=1)[
    forward.instance == car]) > 2.0
  assert _car_error(forward, car, DEFAULTS) < 0.03
  assert _car_error(backward, car, DEFAULTS) < 0.03
  assert _car_error(backward, car, ONE_WAY) > 0.1  # the step turned off
