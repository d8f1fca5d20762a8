"""jaxflow.ground and jaxflow.rigid: ground removal, range cut, rigid fits, against known truth."""

import numpy as np
import pytest

from jaxflow import ground, rigid
from jaxflow.errors import ConfigError, DataError


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
  truth = true_height < ground.GROUND_MARGIN  # the reference: the true plane and the margin
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


def test_kabsch_recovers_a_known_motion():
  rng = np.random.default_rng(1)
  src = rng.uniform(-20, 20, (500, 3))
  r, t = rotation([0.2, 0.1, 1.0], 7.0), np.array([1.5, -0.3, 0.2])
  m = rigid.kabsch(src, src @ r.T + t)
  np.testing.assert_allclose(m.rotation, r, atol=1e-9)
  np.testing.assert_allclose(m.translation, t, atol=1e-9)
  assert abs(np.linalg.det(rigid.kabsch(src, -src).rotation) - 1) < 1e-9  # never a reflection


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


def test_raw_sweep_flow_gives_every_point_a_flow():
  pts, h, _, _ = street(up=1)  # camera-like: y up
  pts = np.concatenate([pts, [[0, 6, 60], [1, 6, 50]]]).astype(np.float32)  # two far points
  r, t = rotation([0, 1, 0], 1.5), np.array([0.1, 0.0, 1.0])
  ego_Nx3 = (pts @ r.T + t - pts).astype(np.float32)
  seen = {}

  def flow_fn(a, b):  # a perfect estimator of the ego-motion, with one moving box
    seen["n"] = len(a)
    out = (a @ r.T + t - a).astype(np.float32)
    out[a[:, 0] > 12] += [0, 0, 2.0]
    return out

  flow, info = ground.raw_sweep_flow(flow_fn, pts, pts @ r.T + t, up="y", max_range=35)
  assert flow.shape == pts.shape and np.isfinite(flow).all()
  removed = (np.r_[h, 0, 0] < ground.GROUND_MARGIN) | (np.arange(len(pts)) >= len(h))
  assert abs(info.ground[0] + info.far[0] - removed.sum()) <= 0.005 * len(pts)
  assert seen["n"] == info.kept[0] == len(pts) - info.ground[0] - info.far[0]
  assert info.far[0] >= 2
  np.testing.assert_allclose(flow[-2:], ego_Nx3[-2:], atol=1e-3)  # far: the ego-motion
  ground_rows = np.flatnonzero(h < 0.1)
  np.testing.assert_allclose(flow[ground_rows], ego_Nx3[ground_rows], atol=1e-3)
  assert "ego-motion flow of a rigid fit" in info.note()
