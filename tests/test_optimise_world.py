"""optimise's last stage, the world (jaxflow.methods.optimise.World): a static world seen as walls
that the descent slid along them gets the scene's registered motion back, and a mover keeps its
flow."""

import dataclasses

import numpy as np
import pytest

from jaxflow.methods import optimise, registry
from jaxflow.refine import rigid_clusters


def _yaw(deg):
  c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
  return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # about the model frame's y (up)


def _corridor(rng, n):
  """Points of a street in the model frame (y up, the sensor at the origin): two walls along x at
  z = +-5 with a post every 3 m standing out of each, the ground between them."""
  ground = n // 4
  ground = np.stack([rng.uniform(-15, 15, ground), np.full(ground, -1.5),
                     rng.uniform(-5, 5, ground)], 1)
  n -= len(ground)
  wall = n * 3 // 4
  x = rng.uniform(-15, 15, wall)
  side = rng.choice([-5.0, 5.0], wall)
  walls = np.stack([x, rng.uniform(-1.5, 2.5, wall), side], 1)
  posts = n - wall
  at = rng.integers(-5, 6, posts) * 3.0
  angle = rng.uniform(0, 2 * np.pi, posts)
  side = rng.choice([-1.0, 1.0], posts)
  posts = np.stack([at + 0.2 * np.cos(angle), rng.uniform(-1.5, 2.5, len(at)),
                    side * (4.8 + 0.2 * np.sin(angle))], 1)
  return np.concatenate([ground, walls, posts])


def _box(rng, n):
  """A 4 x 1.5 x 1.8 m box's surface in the middle of the street."""
  size = np.array([4.0, 1.5, 1.8])
  p = rng.uniform(-0.5, 0.5, (n, 3))
  face = rng.integers(0, 3, n)
  p[np.arange(n), face] = rng.choice([-0.5, 0.5], n)
  return p * size + np.array([3.0, -0.75, 0.0])


def _scene(seed=0):
  """pc1, pc2, the true flow, the mover's mask: the sensor moved 0.6 m along the street and turned
  2 degrees; the box drove 0.8 m across it besides. Each cloud samples the surfaces anew."""
  rng = np.random.default_rng(seed)
  R, t = _yaw(2.0), np.array([-0.6, 0.0, 0.05])  # pc1's frame to pc2's
  world1, box1 = _corridor(rng, 16000), _box(rng, 800)
  world2, box2 = _corridor(rng, 16000), _box(rng, 800)
  drive = np.array([0.0, 0.0, 0.8])
  pc1 = np.concatenate([world1, box1])
  pc2 = np.concatenate([world2, box2 + drive]) @ R.T + t
  truth = np.concatenate([world1, box1 + drive]) @ R.T + t - pc1
  mover = np.arange(len(pc1)) >= len(world1)
  return pc1.astype(np.float32), pc2.astype(np.float32), truth.astype(np.float32), mover


def _stage(pc1, pc2, flow, world=optimise.World()):
  """The stage as optimise runs it: on the rigid clusters of the flow, then guarded."""
  labels = rigid_clusters.clusters(pc1[None], flow[None], rigid_clusters.Settings())
  taken, to = optimise.world_flow(pc1[None], pc2[None], flow[None], labels,
                                  optimise.registered_world(pc1[None], pc2[None]), world)
  guarded = optimise.Guarded(pc1[None], pc2[None], optimise.Guard())
  return np.asarray(guarded(np.where(taken, 0, -1), to, flow[None]))[0]


def test_a_world_slid_along_its_walls_gets_the_registered_motion():
  pc1, pc2, truth, mover = _scene()
  slid = truth.copy()
  slid[~mover] += np.float32([0.3, 0.0, 0.0])  # along the walls: their planes do not object
  error = lambda f: np.linalg.norm(f - truth, axis=1)
  assert error(slid)[~mover].mean() > 0.29  # what the stage is given
  out = _stage(pc1, pc2, slid)
  assert error(out)[~mover].mean() < 0.04, error(out)[~mover].mean()
  np.testing.assert_array_equal(out[mover], slid[mover])  # the world's motion misplaces the box


def test_a_world_already_right_stays_right_and_a_mover_keeps_its_flow():
  pc1, pc2, truth, mover = _scene(seed=1)
  out = _stage(pc1, pc2, truth)
  assert np.linalg.norm(out - truth, axis=1).mean() < 0.015
  np.testing.assert_array_equal(out[mover], truth[mover])


def test_world_settings_are_checked_and_set_from_the_command_line():
  with pytest.raises(ValueError, match="world.tie"):
    optimise.World(tie=-1.0)
  chosen = registry.settings("optimise", fields={"world.tie": 0.02})
  assert chosen.world == dataclasses.replace(optimise.World(), tie=0.02)
  assert registry.settings("optimise", fields={"world": None}).world is None
