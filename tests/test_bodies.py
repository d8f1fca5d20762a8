"""jaxflow.refine.bodies: a scene's rigid bodies found in a flow and fitted to pc2."""

import numpy as np
import pytest

from jaxflow.methods import optimise
from jaxflow.refine import bodies


def _rotation(axis, degrees):
  axis = np.asarray(axis, float) / np.linalg.norm(axis)
  k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  a = np.radians(degrees)
  return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def _box_surface(centre, size, n, rng):
  """n points uniform on the faces of an axis-aligned box."""
  size = np.asarray(size, float)
  u = rng.uniform(-0.5, 0.5, (n, 3)) * size
  face = rng.integers(0, 3, n)
  u[np.arange(n), face] = np.where(rng.random(n) < 0.5, -0.5, 0.5) * size[face]
  return u + centre


def _room(n, rng):
  """A floor and two walls (the static world), 2 boxes inside: (points, body of each point)."""
  floor = np.c_[rng.uniform(-6, 6, n), np.full(n, -1.5), rng.uniform(2, 14, n)]
  back = np.c_[rng.uniform(-6, 6, n // 2), rng.uniform(-1.5, 3, n // 2), np.full(n // 2, 14.0)]
  side = np.c_[np.full(n // 2, -6.0), rng.uniform(-1.5, 3, n // 2), rng.uniform(2, 14, n // 2)]
  box_a = _box_surface([-2.0, 0.0, 7.0], [1.5, 1.2, 1.0], n // 2, rng)
  box_b = _box_surface([2.5, 0.5, 9.0], [1.0, 2.0, 1.4], n // 2, rng)
  points = np.concatenate([floor, back, side, box_a, box_b])
  body = np.repeat([0, 0, 0, 1, 2], [n, n // 2, n // 2, n // 2, n // 2])
  return points, body


# The camera turns 3 degrees and moves 0.4 m; box A flies 0.6 m and turns; box B moves sideways.
MOTIONS = [(_rotation([0, 1, 0], 3.0), np.array([0.1, 0.0, -0.4])),
           (_rotation([1, 1, 0], 8.0), np.array([0.6, 0.2, -0.3])),
           (_rotation([0, 1, 0], -5.0), np.array([-0.5, 0.0, 0.2]))]


def _pair(seed=0, n=2000):
  """Two independent samplings of the moved scene (no point has an exact counterpart), the true
  flow of pc1."""
  rng = np.random.default_rng(seed)
  pc1, body1 = _room(n, rng)
  pc2, body2 = _room(n, rng)
  for b, (r, t) in enumerate(MOTIONS):
    pc2[body2 == b] = pc2[body2 == b] @ r.T + t
  truth = np.zeros_like(pc1)
  for b, (r, t) in enumerate(MOTIONS):
    truth[body1 == b] = pc1[body1 == b] @ r.T + t - pc1[body1 == b]
  return pc1.astype(np.float32), pc2.astype(np.float32), truth.astype(np.float32), body1


def _stuck_start(pc1, truth, body, seed=1):
  """The truth with 2 cm noise, and the usual failure of a Chamfer optimiser: a third of each box
  stuck to the world's motion."""
  rng = np.random.default_rng(seed)
  start = truth + rng.normal(0, 0.02, truth.shape).astype(np.float32)
  for b in (1, 2):
    idx = np.flatnonzero(body == b)
    wrong = idx[pc1[idx, 0] < np.quantile(pc1[idx, 0], 0.33)]
    start[wrong] = pc1[wrong] @ MOTIONS[0][0].T + MOTIONS[0][1] - pc1[wrong]
  return start


def test_a_flow_wrong_on_part_of_each_box_becomes_the_bodies_motions():
  pc1, pc2, truth, body = _pair()
  start = _stuck_start(pc1, truth, body)
  before = np.linalg.norm(start - truth, axis=1)
  flow, found = bodies.rigid_bodies(pc1, pc2, start)
  after = np.linalg.norm(flow - truth, axis=1)
  assert before.mean() > 0.09 and found.bodies >= 3
  assert after.mean() < 0.025
  for b in (0, 1, 2):  # each body's points carry its motion, to 2 cm at the 90th percentile
    assert np.quantile(after[body == b], 0.9) < 0.02, b


def test_a_rigid_flow_that_fits_stays_and_the_result_is_the_same_twice():
  pc1, pc2, truth, _ = _pair(seed=2)
  flow, _ = bodies.rigid_bodies(pc1, pc2, truth)
  error = np.linalg.norm(flow - truth, axis=1)
  assert error.mean() < 0.005 and np.quantile(error, 0.99) < 0.02  # the ICP's sampling noise
  assert error.max() < 0.1  # no point took another body's motion (they differ by >= 0.3 m)
  again, _ = bodies.rigid_bodies(pc1, pc2, truth)
  np.testing.assert_array_equal(flow, again)


def test_where_no_rigid_motion_fits_the_starting_flow_is_kept():
  """A cloth-like sheet bent between the frames: per-point freedom where no rigid motion fits."""
  rng = np.random.default_rng(3)
  u = rng.uniform(-2, 2, (3000, 2))
  pc1 = np.c_[u, np.zeros(3000)]
  bend = lambda p: np.c_[p[:, :2], 0.4 * np.sin(2.0 * p[:, 0])]
  pc2 = bend(np.c_[rng.uniform(-2, 2, (3000, 2)), np.zeros(3000)])
  truth = bend(pc1) - pc1
  flow, found = bodies.rigid_bodies(pc1, pc2, truth)
  assert found.free_points > 0  # and elsewhere small rigid pieces: a quarter of the flow at most
  assert np.linalg.norm(flow - truth, axis=1).mean() < 0.25 * np.linalg.norm(truth, axis=1).mean()


VIEW = 0.6  # |x / z| the camera of the street pairs sees
STREET_WORLD = (_rotation([0, 1, 0], 1.0), np.array([0.0, 0.0, -1.5]))
BOX_MOVE = np.array([-1.2, 0.0, 1.5])  # seen from the world: across the view and along it


def _street(n, rng):
  """A street before a forward camera (x left, y up, z forward): two facades along it, a far
  wall, two poles and a box near the left edge of the view; (points, 0 world / 1 box)."""
  along = lambda x: np.c_[np.full(n, x), rng.uniform(-1.4, 2.5, n), rng.uniform(2.5, 30, n)]
  far = np.c_[rng.uniform(-4, 4, n // 2), rng.uniform(-1.4, 2.5, n // 2), np.full(n // 2, 30.0)]
  poles = []
  for x, z in ((1.5, 12.0), (-2.0, 18.0)):
    a = rng.uniform(0, 2 * np.pi, n // 8)
    poles.append(np.c_[x + 0.15 * np.cos(a), rng.uniform(-1.4, 2.5, n // 8),
                       z + 0.15 * np.sin(a)])
  box = _box_surface([2.6, -0.6, 4.5], [1.0, 1.2, 1.0], n // 2, rng)
  points = np.concatenate([along(4.0), along(-4.0), far, *poles, box])
  return points, np.repeat([0, 1], [len(points) - len(box), len(box)])


def _street_pair(seed=0, n=3000):
  """Independent samplings of the street in each frame, each cut to the camera's view; the
  camera moves 1.5 m forward and turns 1 degree, the box moves by BOX_MOVE besides."""
  rng = np.random.default_rng(seed)
  (r, t), (pc1, part1), (pc2, part2) = STREET_WORLD, _street(n, rng), _street(n, rng)
  pc2 = pc2 @ r.T + t + np.outer(part2 == 1, BOX_MOVE)
  truth = pc1 @ r.T + t - pc1 + np.outer(part1 == 1, BOX_MOVE)
  in1, in2 = np.abs(pc1[:, 0]) <= VIEW * pc1[:, 2], np.abs(pc2[:, 0]) <= VIEW * pc2[:, 2]
  return pc1[in1], pc2[in2], truth[in1], part1[in1]


def test_a_facade_dragged_along_itself_out_of_the_view_takes_the_world_motion():
  """The near end of a facade leaves the camera's view; a Chamfer optimiser drags it 4 m along
  the facade onto what pc2 still sees, where it fits perfectly. Nothing pc2 saw refutes the
  world's motion there, and the departure is a slide: the world's motion it is."""
  pc1, pc2, truth, part = _street_pair()
  moved = pc1 + truth
  dragged = (np.abs(moved[:, 0]) > VIEW * moved[:, 2]) & (part == 0)
  start = truth + np.outer(dragged, [0.0, 0.0, 4.0])
  flow, _ = bodies.rigid_bodies(pc1, pc2, start)
  error = np.linalg.norm(flow - truth, axis=1)
  assert dragged.sum() > 200
  assert error[dragged].mean() < 0.15  # the world's motion, as fitted (was 3.98: the drag kept)
  assert error[part == 1].mean() < 0.02


def test_a_box_out_of_the_view_only_under_the_world_motion_keeps_its_own():
  """The box comes into view by its own motion: the world's motion would take all of it out of
  pc2's view, where nothing refutes it, but the box's motion is no slide of the world's."""
  pc1, pc2, truth, part = _street_pair()
  r, t = STREET_WORLD
  still = pc1[part == 1] @ r.T + t
  assert np.all(np.abs(still[:, 0]) > VIEW * still[:, 2])  # every box point off the view
  flow, _ = bodies.rigid_bodies(pc1, pc2, truth)
  assert np.linalg.norm(flow - truth, axis=1)[part == 1].mean() < 0.02
  # Every departure taken for a slide: the box joins the world (the check above is what holds it)
  flow, _ = bodies.rigid_bodies(pc1, pc2, truth, bodies.Settings(slide=1.01))
  assert np.linalg.norm(flow - truth, axis=1)[part == 1].mean() > 1.0


@pytest.mark.parametrize("case", ["nan", "few", "empty_support"])
def test_bad_input_returns_the_flow_unchanged_with_a_note(case):
  pc1, pc2, truth, _ = _pair(n=200)
  if case == "nan":
    truth = truth.copy()
    truth[5] = np.nan
  elif case == "few":
    pc1, pc2, truth = pc1[:12], pc2[:12], truth[:12]
  else:  # every point moves its own random way: no hypothesis has 30 supporters
    truth = np.random.default_rng(4).normal(0, 3.0, truth.shape).astype(np.float32)
  flow, found = bodies.rigid_bodies(pc1, pc2, truth)
  np.testing.assert_array_equal(flow, truth)
  assert found.bodies == 0 and found.note and "unchanged" in found.note


def test_bad_settings_are_refused():
  with pytest.raises(ValueError, match="bodies local"):
    bodies.Settings(local=2)
  with pytest.raises(ValueError, match="bodies truncate"):
    bodies.Settings(truncate=0.0)


def test_optimise_ends_with_the_bodies_stage_of_each_pair():
  pc1, pc2, truth, body = _pair(n=1000)
  start = _stuck_start(pc1, truth, body)
  other = (pc1, pc2, np.zeros_like(start))  # the second pair of the batch: a zero start
  flow, motion_of = optimise.rigid_bodies_flow(*map(np.stack, zip((pc1, pc2, start), other)),
                                               bodies.Settings())
  assert flow.shape == (2, *pc1.shape) and motion_of.shape == (2, len(pc1))
  for i, (a, b, f) in enumerate(((pc1, pc2, start), other)):  # each pair gets its own bodies
    np.testing.assert_allclose(np.asarray(flow[i]), bodies.rigid_bodies(a, b, f)[0], atol=1e-6)
  assert not np.allclose(np.asarray(flow[0]), np.asarray(flow[1]), atol=1e-3)
  assert np.linalg.norm(np.asarray(flow[0]) - truth, axis=1).mean() < \
    0.5 * np.linalg.norm(start - truth, axis=1).mean()
