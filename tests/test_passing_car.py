"""The passing-car pair: its car is where and moves as asked, the world moves as the ego."""

import numpy as np
import pytest

from jaxflow.data import passing_car
from jaxflow.data.synthetic_sweep import REGULAR_VEHICLE, Options


@pytest.mark.parametrize("lateral, oncoming", [(5.0, False), (-4.0, True)])
def test_the_car_passes_beside_the_sensor_at_its_speed(lateral, oncoming):
  speed, ego_speed = 0.8, 0.3
  sweep = passing_car.pair(seed=2, lateral=lateral, speed=speed, ego_speed=ego_speed,
                           oncoming=oncoming, options=Options(beams=32, scale=0.2))
  car = sweep.instance == sweep.instance.max()
  assert car.sum() > 300 and (sweep.category[car] == REGULAR_VEHICLE).all()
  # Its returns are its near side: between the sensor and its lane's centre, beside the sensor.
  centre = sweep.pc1[car].mean(0)
  assert 0 < centre[1] / lateral < 1 and abs(centre[0]) < 2.5
  # The ego drives forward (x) without turning: the world comes back by ego_speed, the car moves
  # by its own speed along x on top of that (z up, x forward).
  np.testing.assert_allclose(sweep.ego_rotation, np.eye(3), atol=1e-6)
  np.testing.assert_allclose(sweep.ego_flow, np.tile([-ego_speed, 0, 0], (len(car), 1)), atol=1e-4)
  direction = -1 if oncoming else 1
  np.testing.assert_allclose(sweep.flow[car] - sweep.ego_flow[car],
                             np.tile([direction * speed, 0, 0], (car.sum(), 1)), atol=1e-4)
  np.testing.assert_allclose(sweep.flow[~sweep.foreground], sweep.ego_flow[~sweep.foreground])


def test_a_seed_draws_one_street():
  a, b = (passing_car.pair(seed=1, options=Options(beams=32, scale=0.1)) for _ in range(2))
  c = passing_car.pair(seed=3, options=Options(beams=32, scale=0.1))
  assert np.array_equal(a.pc1, b.pc1)
  assert a.pc1.shape != c.pc1.shape or not np.array_equal(a.pc1, c.pc1)
