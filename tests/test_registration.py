"""The host geometry the sweeps and the rigid bodies share: the k-d tree entry point against brute
force, the neighbourhood spread against planes and lines, the one robust registration core
(point-to-plane 6 dof, point-to-line yaw_xy) recovering known motions despite outliers."""

import numpy as np
import pytest

from jaxflow.geometry import neighbours, registration, rigid


def rotation_z(angle):
  c, s = np.cos(angle), np.sin(angle)
  return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_tree_nearest_and_knn_match_brute_force_with_reach():
  rng = np.random.default_rng(0)
  points, query = rng.uniform(-5, 5, (300, 3)), rng.uniform(-6, 6, (50, 3))
  dist = np.linalg.norm(query[:, None] - points[None], axis=-1)
  tree = neighbours.Tree(points)
  d, j = tree.nearest(query, reach=1.0)
  near = dist.min(1) < 1.0
  np.testing.assert_array_equal(j[near], dist.argmin(1)[near])
  assert np.all(np.isinf(d[~near])) and np.all(j[~near] == len(points)) and (~near).any()
  nbr = tree.knn(query, 7)
  np.testing.assert_array_equal(nbr, np.argsort(dist, 1)[:, :7])
  # k beyond the cloud: every point, nearest first; a graph starts with each point itself.
  assert neighbours.Tree(points[:5]).knn(query, 9).shape == (50, 5)
  np.testing.assert_array_equal(neighbours.knn_graph(points, 4)[:, 0], np.arange(300))
  # The threaded query (a large one) answers the same as one thread.
  big = rng.uniform(-6, 6, (neighbours.THREADED_WORK // 2, 3))
  assert tree._workers(len(big), 2) == neighbours.THREADS
  np.testing.assert_array_equal(tree.knn(big, 2), tree.kd.query(big, 2, workers=1)[1])


def test_local_spread_gives_a_planes_normal_and_a_lines_across_direction():
  rng = np.random.default_rng(1)
  u, v = rng.uniform(-2, 2, (2, 400))
  normal = np.array([1.0, 2.0, 2.0]) / 3.0
  a = np.cross(normal, [0, 0, 1.0])
  a /= np.linalg.norm(a)
  b = np.cross(normal, a)
  plane = u[:, None] * a + v[:, None] * b + 3.0
  values, vectors = neighbours.local_spread(plane, 10)
  assert np.allclose(np.abs(vectors[:, :, 0] @ normal), 1.0, atol=1e-9)
  assert np.all(values[:, 0] < 1e-12 * np.maximum(values[:, 1], 1.0))
  line = np.c_[np.linspace(0, 10, 200), 0.5 * np.linspace(0, 10, 200)]  # 2-D, along (2, 1)
  across = neighbours.local_spread(line, 5)[1][:, :, 0]
  np.testing.assert_allclose(np.abs(across @ [1.0, -2.0]) / np.sqrt(5), 1.0, atol=1e-9)


def box_faces(rng, n=3000):
  """Points on the six faces of a 4 x 3 x 2 m box, centred 10 m from the origin."""
  face = rng.integers(0, 6, n)
  p = rng.uniform(-1, 1, (n, 3))
  axis, sign = face // 2, np.where(face % 2, 1.0, -1.0)
  p[np.arange(n), axis] = sign
  return p * [2.0, 1.5, 1.0] + [10.0, 2.0, 0.5]


def test_point_to_plane_fit_recovers_a_known_motion_despite_outliers():
  rng = np.random.default_rng(2)
  target_pts = box_faces(rng)
  truth = rigid.Motion(rigid.rotations_from_vectors(np.array([[0.02, -0.03, 0.08]]))[0],
                       np.array([0.3, -0.2, 0.1]))
  src = truth.inverse().apply(box_faces(rng))  # other samples of the same surfaces
  src = np.r_[src, rng.uniform(0, 20, (150, 3))]  # clutter that matches nothing well
  target = registration.PlaneTarget(target_pts)
  got = registration.robust_fit(src, rigid.Motion.of(np.eye(3), np.zeros(3)), target.plane_rows,
                                [0.3] * 10 + [0.05] * 15, point_weight=0.1)
  np.testing.assert_allclose(got.rotation, truth.rotation, atol=2e-3)
  np.testing.assert_allclose(got.translation, truth.translation, atol=2e-2)
  # The plane distance: a NumPy loop over the points, truncated, 'truncate' where nothing is near.
  moved = got.apply(src[:200])
  want = []
  for q in moved:
    d = np.linalg.norm(target_pts - q, axis=1)
    j = int(np.argmin(d))
    gap = abs((q - target_pts[j]) @ target.normals[j])
    want.append(min(gap, 0.2) if d[j] < 0.5 else 0.2)
  np.testing.assert_allclose(target.plane_distance(moved, 0.2, reach=0.5), want, atol=1e-12)


def test_yaw_xy_fit_of_point_to_line_rows_recovers_a_cars_motion():
  """Seen from above: a car's outline (two sides and a back) moved by a yaw and a shift; its rows
  are the distances across the outline's sides (a line's normal, horizontal)."""
  rng = np.random.default_rng(3)
  side = np.linspace(-2, 2, 80)
  outline = np.r_[np.c_[side, np.full(80, -0.9)], np.c_[side, np.full(80, 0.9)],
                  np.c_[np.full(40, -2.0), np.linspace(-0.9, 0.9, 40)]]
  outline = np.c_[outline + [20.0, 5.0], rng.uniform(0.2, 1.5, len(outline))]
  normals = np.r_[np.tile([0, 1.0], (160, 1)), np.tile([1.0, 0], (40, 1))]
  yaw, centre = rotation_z(np.radians(4.0)), np.array([20.0, 5.0, 0.0])
  truth = rigid.Motion(yaw, centre - yaw @ centre + [0.8, 0.3, 0.0])  # about the car's centre
  pc2 = truth.apply(outline)
  n2 = np.c_[normals @ truth.rotation[:2, :2].T, np.zeros(len(normals))]
  tree = neighbours.Tree(pc2[:, :2])

  def rows_of(moved, scale):
    _, j = tree.nearest(moved[:, :2])
    diff = moved - pc2[j]
    diff[:, 2] = 0
    return registration.Rows(np.sum(diff * n2[j], 1), n2[j], np.arange(len(moved)))

  start = rigid.Motion.of(np.eye(3), [0.6, 0.2, 0.0])  # the shift roughly, no yaw
  got = registration.robust_fit(outline[::3], start, rows_of, [0.3] * 20, dof="yaw_xy",
                                about_centroid=True, damping=1e-3)
  np.testing.assert_allclose(got.rotation, truth.rotation, atol=1e-3)
  np.testing.assert_allclose(got.translation, truth.translation, atol=3e-2)
  assert got.rotation[2, 2] == 1.0 and got.translation[2] == 0.0  # yaw_xy: no tilt, no rise


def test_bad_dof_is_refused():
  still = rigid.Motion.of(np.eye(3), np.zeros(3))
  with pytest.raises(ValueError, match="dof must be one of"):
    registration.robust_fit(np.zeros((3, 3)), still, None, [0.1], dof="5")
  with pytest.raises(ValueError, match="point_weight needs dof '6'"):
    registration.robust_fit(np.zeros((3, 3)), still, None, [0.1], dof="yaw_xy", point_weight=0.1)
