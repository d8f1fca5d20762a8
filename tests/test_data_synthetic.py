"""Synthetic scenes: ray-casting kernels against independent implicit surfaces, flow consistency
with a dense rendering of frame 2, conventions of the readers, determinism and splits."""

import math

import numpy as np
import pytest

from jaxflow.data import open_dataset
from jaxflow.data import synthetic as S
from jaxflow.data.readers import GROUND_Y


# Independent definitions of each primitive: inside test and distance-like surface residual (local
# frame).
def _inside(kind, p, size):
  x, y, z = p
  if kind == S.BOX:
    return (np.abs(p) < size[:, None]).all(0)
  if kind == S.ELLIPSOID:
    return ((p / size[:, None]) ** 2).sum(0) < 1
  if kind == S.CYLINDER:
    return (x * x + z * z < size[0] ** 2) & (np.abs(y) < size[1])
  if kind == S.TORUS:
    return np.hypot(np.hypot(x, z) - size[0], y) < size[1]
  raise ValueError(kind)


def _on_surface(kind, p, size, tol=1e-6):
  x, y, z = p
  if kind == S.BOX:
    return np.abs((np.abs(p) / size[:, None]).max(0) - 1) < tol
  if kind == S.ELLIPSOID:
    return np.abs(np.sqrt(((p / size[:, None]) ** 2).sum(0)) - 1) < tol
  if kind == S.CYLINDER:
    r = np.hypot(x, z)
    side = (np.abs(r - size[0]) < tol) & (np.abs(y) <= size[1] + tol)
    cap = (np.abs(np.abs(y) - size[1]) < tol) & (r <= size[0] + tol)
    return side | cap
  if kind == S.TORUS:
    return np.abs(np.hypot(np.hypot(x, z) - size[0], y) - size[1]) < tol
  if kind == S.SHELL:
    rb, half_angle, hh = size
    return ((np.abs(np.hypot(x, z + rb) - rb) < tol) & (np.abs(y) <= hh + tol)
            & (np.abs(np.arctan2(x, z + rb)) <= half_angle + tol))
  if kind == S.PLANE:
    return (np.abs(y) < tol) & (np.abs(x) <= size[0]) & (np.abs(z) <= size[2])
  raise ValueError(kind)


@pytest.mark.parametrize("kind, size", [
    (S.BOX, (1.0, 0.5, 2.0)), (S.ELLIPSOID, (1.0, 0.6, 1.5)), (S.CYLINDER, (0.7, 1.2, 0)),
    (S.TORUS, (1.2, 0.35, 0)), (S.SHELL, (1.5, 1.0, 0.8)), (S.PLANE, (2.0, 0, 1.0))])
def test_kernels_hit_the_surface_first(kind, size):
  rng = np.random.default_rng(kind)
  size = np.array(size, float)
  o = rng.normal(size=3)
  o = o / np.linalg.norm(o) * 6
  targets = rng.uniform(-1, 1, (3, 400)) * np.maximum(size, 0.5)[:, None] * 1.3
  d = (targets - o[:, None]) * rng.uniform(0.5, 2.0, 400)  # any scale of d: t is in units of |d|
  t = S._KERNELS[kind](o, d, size)
  hit = np.isfinite(t)
  assert 0.15 < hit.mean() < 0.95  # the test rays hit and miss
  points = o[:, None] + t[hit] * d[:, hit]
  assert _on_surface(kind, points, size).all()
  if kind in (S.SHELL, S.PLANE):
    return
  fractions = np.linspace(0, 1, 300)[:-1]
  shrink = size * (1 - 1e-3)
  if kind == S.TORUS:  # rays grazing the tube by less than ~1% of its radius count as misses
    shrink[1] = size[1] * 0.99
  before = o[:, None, None] + d[:, hit, None] * (t[hit, None] * fractions)  # 3 x hits x samples
  assert not _inside(kind, before.reshape(3, -1), shrink).any()  # nothing solid before the hit
  ts = np.linspace(0, 3, 3000)
  missed = o[:, None, None] + d[:, ~hit, None] * ts
  assert not _inside(kind, missed.reshape(3, -1), shrink).any()  # and misses miss


def test_camera_and_object_motion_compose_by_hand():
  """Static world under a camera translation c: flow = -c; an object translated by m: flow = m - c."""
  builder = S.Builder(np.eye(3), (0.3, -0.2, 1.0))
  builder.add([(S.PLANE, S._ROT_X90, S.ZERO, (50, 0, 50), None)], np.eye(3), (0, 0, 20))
  builder.add([(S.BOX, np.eye(3), S.ZERO, (1, 1, 1), None)], np.eye(3), (0, 0, 10), None, (0.5, 0.0, -0.25))
  turn = S.rotation((0, 1, 0), math.radians(10))
  builder.add([(S.ELLIPSOID, np.eye(3), S.ZERO, (1, 1, 1), None)], np.eye(3), (3, 0, 12), turn)
  scene = builder.scene()
  points, prim = S.render(scene, 0, S.things_grid(np.random.default_rng(0)))
  flow = S.warp(scene, points, prim) - points
  wall, box, ball = (prim == 0), (prim == 1), (prim == 2)
  assert wall.any() and box.any() and ball.any()
  np.testing.assert_allclose(flow[:, wall], np.tile([[-0.3], [0.2], [-1.0]], wall.sum()), atol=1e-12)
  np.testing.assert_allclose(flow[:, box], np.tile([[0.2], [0.2], [-1.25]], box.sum()), atol=1e-12)
  expected = turn @ (points[:, ball] - [[3], [0], [12]]) + [[3], [0], [12]] - [[0.3], [-0.2], [1.0]]
  np.testing.assert_allclose(flow[:, ball] + points[:, ball], expected, atol=1e-12)
  np.testing.assert_allclose(S.warp(scene, S.warp(scene, points, prim), prim, inverse=True), points, atol=1e-12)


@pytest.mark.parametrize("kind", ["synthetic_things", "synthetic_lidar"])
def test_warped_points_lie_on_their_primitive_in_frame2(kind):
  """Exact: every frame-1 hit, moved by the flow, satisfies its primitive's frame-2 surface equation."""
  scene, rng = S.make_scene(kind, "test", 5)
  points, prim = S.render(scene, 0, (S.things_grid if kind == "synthetic_things" else S.lidar_grid)(rng))
  warped = S.warp(scene, points, prim)
  rot2, pos2 = scene.frame_pose(1)
  checked = 0
  for p in np.unique(prim):
    if p in scene.bumps:  # rocks: displaced ellipsoids, covered by the dense test below
      continue
    local = rot2[p].T @ (warped[:, prim == p] - pos2[p][:, None])
    assert _on_surface(scene.kind_P[p], local, scene.size_Px3[p], tol=1e-6).all(), (p, scene.kind_P[p])
    checked += local.shape[1]
  assert checked > 0.8 * len(prim)


def _wide_grid(pinhole: bool, rows: int, cols: int):
  """A dense grid wider than the sensor's field of view (points may leave it in frame 2)."""
  if pinhole:
    v, u = np.meshgrid(np.linspace(-1, 1, rows), np.linspace(-1.5, 1.5, cols), indexing="ij")
    dirs = np.stack([u, v, np.ones_like(u)])
    rv, cu = v[:, 0], u[0]
  else:
    el, az = np.meshgrid(np.radians(np.linspace(-30, 20, rows)), np.radians(np.linspace(-80, 80, cols)),
                         indexing="ij")
    dirs = np.stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    rv, cu = el[:, 0], az[0]
  return S.Grid(dirs, rv, rv, cu, cu, pinhole=pinhole)


@pytest.mark.parametrize("kind", ["synthetic_things", "synthetic_lidar"])
def test_flow_moves_pc1_onto_the_frame2_surfaces(kind):
  spatial = pytest.importorskip("scipy.spatial")
  pinhole = kind == "synthetic_things"
  near_1cm, near_none, spacing = [], [], []
  for i in range(2):
    pair = S.synthetic_pair(kind, "test", i)
    scene, _ = S.make_scene(kind, "test", i)
    dense, _ = S.render(scene, 1, _wide_grid(pinhole, 700, 1400) if pinhole else _wide_grid(False, 500, 2500))
    tree = spatial.cKDTree(dense.T)
    target = pair.pc1 + pair.flow
    dist = tree.query(target)[0] / np.linalg.norm(target, axis=1)  # relative to range: the grid is angular
    near_1cm.append(np.mean(dist < 0.004))
    near_none.append(np.mean(tree.query(pair.pc1)[0] / np.linalg.norm(pair.pc1, axis=1) < 0.004))
    spacing.append(np.median(spatial.cKDTree(target).query(pair.pc2)[0]))
  # Most warped points lie on a frame-2 surface (the rest are occluded in frame 2); without the flow
  # they do not.
  assert min(near_1cm) > 0.9 and max(near_none) < 0.35
  # pc2 samples the surfaces independently: its points are not the warped pc1 points.
  assert min(spacing) > 1e-3


@pytest.mark.parametrize("kind", ["synthetic_things", "synthetic_lidar"])
def test_conventions_and_statistics(kind):
  pairs = [S.synthetic_pair(kind, "val", i) for i in range(4)]
  for pair in pairs:
    assert pair.pc1.dtype == pair.pc2.dtype == pair.flow.dtype == np.float32 and pair.mask.all()
    assert len(pair.pc1) > 6000 and len(pair.pc2) > 6000
    for cloud in (pair.pc1, pair.pc1 + pair.flow, pair.pc2):
      assert (cloud[:, 2] > 0).all() and (cloud[:, 2] < 35).all()
    if kind == "synthetic_things":  # FT3D's field of view
      assert (np.abs(pair.pc1[:, 0] / pair.pc1[:, 2]) < 0.4572 * 1.05).all()
      assert (np.abs(pair.pc1[:, 1] / pair.pc1[:, 2]) < 0.2572 * 1.05).all()
    else:  # KITTI cut: no point is below the ground threshold in both frames
      warped = pair.pc1 + pair.flow
      assert not ((pair.pc1[:, 1] < GROUND_Y) & (warped[:, 1] < GROUND_Y)).any()
      assert pair.pc1[:, 1].min() < -1.0 and pair.pc1[:, 1].max() > 0.5  # y up: objects above the ground
  mean_flow = np.mean([np.linalg.norm(p.flow, axis=1).mean() for p in pairs])
  assert 0.2 < mean_flow < 1.8  # the real FT3D samples' range of mean |flow|


def test_ground_is_near_minus_1_6_before_removal():
  scene, rng = S.make_scene("synthetic_lidar", "train", 0)
  points, prim = S.render(scene, 0, S.lidar_grid(rng))
  ground = points[1, prim == 0]
  assert (ground.size > 1000) and -1.8 < np.median(ground[ground < -1.4]) < -1.5


def test_determinism_and_disjoint_splits():
  a, b = S.synthetic_pair("synthetic_things", "train", 3), S.synthetic_pair("synthetic_things", "train", 3)
  assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("pc1", "pc2", "flow", "mask"))
  assert a.name == "synthetic_things/train/3"
  others = [S.synthetic_pair("synthetic_things", "val", 3), S.synthetic_pair("synthetic_things", "train", 4)]
  assert all(not np.array_equal(a.pc1[:100], o.pc1[:100]) for o in others)
  mix = open_dataset("synthetic_mix:4", "val")
  assert mix[3].name == "synthetic_lidar/val/1" and np.array_equal(mix[2].pc2, S.synthetic_pair("synthetic_things", "val", 1).pc2)
  assert len(open_dataset("synthetic_lidar")) == S.DEFAULT_COUNT["train"]
  assert "4 pairs" in mix.describe()
