"""jaxflow.lidar.ground and jaxflow.geometry.rigid: ground removal, range cut, rigid fits, against known truth."""

import dataclasses

import numpy as np
import pytest

from jaxflow.errors import ConfigError, DataError
from jaxflow.geometry import rigid
from jaxflow.lidar import ground
from jaxflow.lidar.settings import DEFAULTS

MARGIN = DEFAULTS.ground.margin  # metres above the ground still ground


def rotation(axis_3, degrees):
  """Rodrigues' formula, written out (independent of the code under test)."""
  k = np.asarray(axis_3, float) / np.linalg.norm(axis_3)
  a = np.radians(degrees)
  kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
  return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def street(seed=0, up=2, tilt_deg=3.0, height=-1.7, noise=0.02):
  """A tilted ground plane with noise, boxes standing on it and a floating sign, up axis `up`.

  Returns points N x 3 and their true height above the plane (from the construction)."""
  rng = np.random.default_rng(seed)
  normal = rotation([1.0, 0.3, 0.0], tilt_deg) @ np.array([0.0, 0.0, 1.0])
  # ground: uniform in a 60 m square, lifted onto the plane normal . p = height
  xy = rng.uniform(-30, 30, (3000, 2))
  z = (height - normal[0] * xy[:, 0] - normal[1] * xy[:, 1]) / normal[2]
  g = np.c_[xy, z] + normal * rng.normal(0, noise, (3000, 1))
  parts, heights = [g], [(g @ normal) - height]
  for cx, cy, size in ((8, 3, 2.0), (-12, -6, 3.0), (15, -10, 1.5), (-5, 14, 2.5)):
    local = rng.uniform(0, 1, (400, 3)) * [size, size, 1.8] + [cx, cy, 0]
    base = (height - normal[0] * local[:, 0] - normal[1] * local[:, 1]) / normal[2]
    box = np.c_[local[:, :2], base + local[:, 2]]  # 0 .. 1.8 m above the plane along z
    parts.append(box)
    heights.append(box @ normal - height)
  sign = rng.uniform(0, 1, (200, 3)) * [1, 1, 0.5] + [3, -3, 2.0]
  parts.append(sign)
  heights.append(sign @ normal - height)
  pts, h = np.concatenate(parts), np.concatenate(heights)
  order = {0: [2, 0, 1], 1: [0, 2, 1], 2: [0, 1, 2]}[up]  # the construction's z moves to `up`
  return pts[:, order].astype(np.float32), h, normal[order], height


@pytest.mark.parametrize("up", ["z", "y"])
def test_ground_plane_and_removal_match_the_known_plane(up):
  points, true_height, true_normal, offset = street(up="xyz".index(up))
  plane = ground.fit_ground(points, up=up, max_range=None)
  assert np.degrees(np.arccos(plane.normal @ true_normal)) < 0.5
  assert abs(-plane.offset - offset) < 0.02
  removed = plane.ground(points)
  truth = true_height < MARGIN  # the reference: the true plane and the margin
  assert (removed != truth).mean() < 0.005
  assert not removed[-200:].any()  # the floating sign stays


def test_range_cut_is_horizontal_distance_about_the_up_axis():
  pts = np.array([[30, 20, 0], [10, 0, 50], [0, 40, 1]], np.float32)
  np.testing.assert_array_equal(ground.within_range(pts, "z", 35), [False, True, False])
  np.testing.assert_array_equal(ground.within_range(pts, "y", 35), [True, False, True])
  assert ground.within_range(pts, "z", 0).all()
  with pytest.raises(ConfigError, match="up must be"):
    ground.within_range(pts, "w", 35)


def test_no_ground_is_an_error_naming_the_cloud():
  wall = np.random.default_rng(0).uniform(0, 10, (500, 3)) * [0, 1, 1] + [5, 0, 0]  # x = 5 plane
  with pytest.raises(DataError, match="sweep.ply: no ground plane within 20"):
    ground.fit_ground(wall.astype(np.float32), up="z", name="sweep.ply")


def test_static_fit_ignores_moving_objects():
  rng = np.random.default_rng(2)
  pts = rng.uniform(-30, 30, (2000, 3))
  r, t = rotation([0, 0, 1], 2.0), np.array([1.2, 0.1, 0.0])
  flow = pts @ r.T + t - pts
  movers = rng.choice(2000, 600, replace=False)  # 30% on moving objects
  flow[movers] += rng.uniform(-3, 3, (600, 3))
  flow += rng.normal(0, 0.01, flow.shape)
  m = rigid.fit_static_motion(pts, flow)
  assert np.degrees(np.arccos((np.trace(m.rotation.T @ r) - 1) / 2)) < 0.02
  np.testing.assert_allclose(m.translation, t, atol=0.01)
  static = np.ones(2000, bool)
  static[movers] = False
  assert (m.inliers == static).mean() > 0.99


def hilly_street(seed=0):
  """Points of a crowned road (0.15 m crown over 8 m) that starts climbing 7% at x = 15 m, boxes
  on it; returns the points and their true height above the ground (a closed form)."""
  rng = np.random.default_rng(seed)

  def height(x, y):
    return -1.9 + 0.15 * np.clip(1 - np.abs(y) / 8, 0, 1) + 0.07 * np.maximum(x - 15, 0)

  xy = rng.uniform(-60, 60, (30000, 2))
  g = np.c_[xy, height(*xy.T) + rng.normal(0, 0.01, len(xy))]
  boxes = []
  for cx, cy in ((8, 3), (30, -4), (45, 5), (-20, 2), (-35, -5)):
    local = rng.uniform(0, 1, (500, 3)) * [4, 1.8, 1.5] + [cx, cy, 0.3]
    boxes.append(np.c_[local[:, :2], height(local[:, 0], local[:, 1]) + local[:, 2]])
  pts = np.concatenate([g, *boxes])
  return pts.astype(np.float32), pts[:, 2] - height(pts[:, 0], pts[:, 1])


def test_local_ground_follows_slopes_and_crowns_where_one_plane_cannot():
  pts, true_height = hilly_street()
  surface = ground.fit_surface(pts, "z")
  on_ground = np.abs(true_height) < 0.05
  error = np.abs(surface.height(pts[on_ground]) - true_height[on_ground])
  assert np.percentile(error, 99) < 0.03 and error.max() < 0.1  # the crest and the crown's ridge
  truth = true_height < MARGIN
  assert (surface.ground(pts) != truth).mean() < 0.01
  plane = ground.fit_ground(pts, "z", None)
  assert (plane.ground(pts) != truth).mean() > 0.1  # one plane misses the climbing road
  assert surface.sensor_height == pytest.approx(1.9 - 0.15, abs=0.05)


def test_find_ground_is_the_surface_from_the_near_plane_and_its_points():
  pts, true_height = hilly_street()
  surface, ground_N = ground.find_ground(pts, "z")
  plane = ground.fit_ground(pts, "z", 20.0)  # the RANSAC plane near the sensor, then the cells
  np.testing.assert_array_equal(surface.coef_HxWx3, ground.fit_surface(pts, "z", plane).coef_HxWx3)
  np.testing.assert_array_equal(ground_N, surface.ground(pts))
  assert (ground_N != (true_height < MARGIN)).mean() < 0.01
  wall = np.random.default_rng(0).uniform(0, 10, (500, 3)) * [0, 1, 1] + [5, 0, 0]
  with pytest.raises(DataError, match="wall.ply: no ground plane"):
    ground.find_ground(wall, "z", "wall.ply")


def test_a_wall_taken_for_the_ground_is_refused_with_the_way_out():
  pts, _ = hilly_street()
  with pytest.raises(DataError, match=r"--up z"):
    ground.check_up_axis(pts, "y", "sweep.bin", 0.3)
  ground.check_up_axis(pts, "z", "sweep.bin", 0.8)  # the right axis passes
  surface = ground.fit_surface(pts, "z")
  half = np.arange(len(pts)) < len(pts) // 2
  assert ground.check_ground(surface, half, "sweep.bin", "z", pts) is None
  far = dataclasses.replace(surface, coef_HxWx3=surface.coef_HxWx3 - [0, 0, 8.0])
  assert "9.8 m below the origin" in ground.check_ground(far, np.zeros(len(pts), bool),
                                                         "sweep.bin", "z", pts)
  assert "holds 90% of the points" in ground.check_ground(surface, np.arange(100) < 90,
                                                          "sweep.bin", "z", pts)
  with pytest.raises(DataError, match=r"--up z"):  # a problem under a wrong up names the axis
    ground.check_ground(far, np.zeros(len(pts), bool), "sweep.bin", "y", pts)
