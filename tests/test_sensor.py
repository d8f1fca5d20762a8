"""jaxflow.lidar.sensor: a spinning lidar's position in its frame, found from its rings."""

import dataclasses

import numpy as np
import pytest

from jaxflow.lidar import sensor
from jaxflow.lidar.settings import DEFAULTS


def ring_sweep(position, beams=32, seed=0):
  """The non-ground points of a spinning lidar at `position` (z up) in a street: 32 beams from
  -25 to +15 deg, every 0.4 deg of azimuth, each ray's first hit on the road (z = 0, left out),
  the facades (y = +-9 m) or the street's ends (x = +-40 m), with 2 cm of range noise."""
  rng = np.random.default_rng(seed)
  elevation = np.radians(np.linspace(-25, 15, beams))[:, None]
  azimuth = np.radians(np.arange(0, 360, 0.4))[None]
  direction = np.stack(np.broadcast_arrays(np.cos(elevation) * np.cos(azimuth),
                                           np.cos(elevation) * np.sin(azimuth),
                                           np.sin(elevation)), -1).reshape(-1, 3)
  def to_plane(axis, at):  # along each ray to the plane coordinate[axis] = +-at (inf: never)
    d = direction[:, axis]
    with np.errstate(divide="ignore", invalid="ignore"):
      t = (np.sign(d) * at - position[axis]) / d
    return np.where(np.isfinite(t) & (t > 0), t, np.inf)

  to_road = np.where(direction[:, 2] < 0, -position[2] / np.minimum(direction[:, 2], -1e-9), np.inf)
  reach = np.minimum.reduce([to_road, to_plane(1, 9.0), to_plane(0, 40.0)])
  points = position + direction * (reach + rng.normal(0, 0.02, len(direction)))[:, None]
  return points[points[:, 2] > 0.1]


@pytest.mark.parametrize("position", [(1.35, 0.0, 1.9), (0.0, 0.0, 1.7), (-0.8, 0.3, 1.2)])
def test_the_sensor_of_a_ring_sweep_is_found(position):
  """Argoverse 2's roof sensors above and ahead of the rear axle, a sensor at the origin's x,
  one behind and aside."""
  found, gain = sensor.sensor_position(ring_sweep(np.array(position)), DEFAULTS.sensor)
  assert gain > DEFAULTS.sensor.min_gain
  np.testing.assert_allclose(found[:2], position[:2], atol=0.15)
  np.testing.assert_allclose(found[2], position[2], atol=0.05)


def test_no_rings_or_find_off_is_the_origin():
  cloud = np.random.default_rng(1).normal(0, 15, (20000, 3))  # no beams: nothing sharpens
  found, gain = sensor.sensor_position(cloud, DEFAULTS.sensor)
  assert gain < DEFAULTS.sensor.min_gain and not found.any()
  off = dataclasses.replace(DEFAULTS.sensor, find=False)
  assert not sensor.sensor_position(ring_sweep(np.array([1.0, 0, 1.8])), off)[0].any()
