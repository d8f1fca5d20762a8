"""Issue 57 (item 3): a car passing beside the sensor shows it mostly its flat side, which matches
itself slid along its length; its ends fix it there (jaxflow.lidar.along)."""

import numpy as np
import pytest

from jaxflow.data import passing_car
from jaxflow.data.synthetic_sweep import Options
from jaxflow.lidar import along, sweep
from jaxflow.lidar.settings import DEFAULTS


def share_of_its_motion(seed: int, ego_speed: float, reverse: bool) -> float:
  """1 - the mean error over the car's points / the mean of its motion in the world (--lidar)."""
  pair = passing_car.pair(seed=seed, lateral=5.0, speed=0.8, ego_speed=ego_speed,
                          options=Options(beams=32, scale=0.2, reverse=reverse))
  car = pair.instance == pair.instance.max()
  flow, _ = sweep.raw_sweep_flow(None, pair.pc1, pair.pc2)
  error = np.linalg.norm(flow[car] - pair.flow[car], axis=1).mean()
  return 1 - error / np.linalg.norm(pair.flow[car] - pair.ego_flow[car], axis=1).mean()


# Hard cases of 32 beams, 8 m/s, 5 m beside the sensor (issue 57): without the vote
# (along.min_length out of reach) seed 3's car is left still both ways (share 0: only its ends are
# unexplained, too few points to make it a candidate) and seed 4's, the ego driving 3 m/s, slides
# short along its side (0.81 forward, 0.67 backward); with it 0.98-1.00 (0.977 at the least).
@pytest.mark.parametrize("reverse", [False, True], ids=["forward", "backward"])
@pytest.mark.parametrize("seed, ego_speed", [(3, 0.0), (4, 0.3)])
def test_a_car_passing_5_m_beside_the_sensor_gets_its_motion(seed, ego_speed, reverse):
  assert share_of_its_motion(seed, ego_speed, reverse) >= 0.9


def test_the_ends_vote_for_the_shift_along_a_flat_side():
  """A side 4 m long moved 0.8 m along itself, sampled as a sensor beside it samples (denser where
  it is nearest, in both sweeps): its ends' cells say 0.8 m."""
  rng = np.random.default_rng(0)
  x = np.tan(rng.uniform(np.arctan(-2.6 / 5), np.arctan(2.2 / 5), 4000)) * 5  # returns of a side
  side = np.c_[x, np.full_like(x, 5.0), rng.uniform(-1, 0.5, len(x))]
  first, second = side[x < 1.4], side[x > -1.8]  # the side at -2.6 .. 1.4, then -1.8 .. 2.2
  shift, support = along.vote(first, second, np.array([1.0, 0.0]), 3.5, DEFAULTS.objects)
  assert shift == pytest.approx(0.8, abs=0.03) and support > 0.9
  assert along.vote(first, first, np.array([1.0, 0.0]), 3.5, DEFAULTS.objects)[0] == 0.0
