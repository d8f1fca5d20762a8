"""jaxflow.lidar.both_ways: movers sought from both sweeps, so a mover pc1's groups hide is found
from pc2's, and a pair predicted backwards finds what the forward run finds."""

import dataclasses

import numpy as np
import pytest

import test_objects
from jaxflow.geometry import rigid
from jaxflow.lidar import both_ways
from jaxflow.lidar.settings import DEFAULTS

ONE_WAY = dataclasses.replace(DEFAULTS.objects, both_ways=False)
SIZE, FACES = np.array([4.5, 1.8, 1.5]), ["-y", "top", "-x", "+x"]


def _row(seed: int):
  """(pc1, pc2): a wall, a car parked 0.5 m behind another (one group from above: the cells bridge
  the gap), the front one pulling away 1 m along the row; each sweep sampled anew."""
  clouds = []
  for rng, shift in ((np.random.default_rng(seed), 0.0), (np.random.default_rng(seed + 100), 1.0)):
    wall = np.c_[rng.uniform(-20, 20, 3000), np.full(3000, 12.0), rng.uniform(0, 4, 3000)]
    clouds.append(np.concatenate([
      wall + rng.normal(0, 0.01, wall.shape) * (shift > 0),
      test_objects._visible_faces(rng, (-2.5, 4.0), SIZE, 1500, FACES),
      test_objects._visible_faces(rng, (2.5 + shift, 4.0), SIZE, 1500, FACES)]))
  return clouds


def _flow(pc1, pc2, settings):
  still = rigid.Motion(np.eye(3), np.zeros(3))
  return both_ways.object_flow(pc1, pc2, np.zeros(len(pc1), bool), np.zeros(len(pc2), bool),
                               still, settings=settings)[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_car_pulling_away_from_the_one_behind_it_is_found_both_ways(seed):
  """Forward, pc1's group holds both cars; standing still explains most of it and the front car's
  flat side slides along itself (little of it is unexplained): it stood still at every sampling.
  In pc2 it stands apart, its own group, fitted against pc1 and offered back: it gets its motion,
  and the parked car and the wall keep theirs. Backwards (pc2 first) its group is its own
  already: the same motion, undone."""
  pc1, pc2 = _row(seed)
  front = slice(4500, 6000)
  forward = _flow(pc1, pc2, DEFAULTS.objects)
  assert np.linalg.norm(forward[front] - [1.0, 0, 0], axis=1).mean() < 0.02
  np.testing.assert_array_equal(forward[:4500], 0.0)  # the wall and the parked car
  np.testing.assert_array_equal(_flow(pc1, pc2, ONE_WAY)[front], 0.0)  # the step turned off
  backward = _flow(pc2, pc1, DEFAULTS.objects)
  assert np.linalg.norm(backward[front] - [-1.0, 0, 0], axis=1).mean() < 0.02
  np.testing.assert_array_equal(backward[:4500], 0.0)
