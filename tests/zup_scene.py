"""A raw z-up LiDAR sweep pair for the frame and picture tests (x forward, y left, z up, metres).

    scene = sweep_pair(seed=0)   # scene.pc1, pc2, flow (true), ego_flow, ground1, moving1, ...

A flat ground 1.8 m under the sensor out to `reach` metres (a raw sweep's far returns), two walls
along the road (y = +-9 m), poles, and two boxes that move: a car ahead driving forward faster than
the sensor and one crossing from the right. The sensor drives forward `ego_m` and yaws `yaw_deg`
between the frames. Points are sampled on the surfaces (no ray casting), independently per frame,
so pc2 does not repeat pc1's points. flow = where a pc1 point is in frame 2's sensor coordinates.
"""

import dataclasses

import numpy as np

SENSOR_HEIGHT = 1.8


def yaw(degrees: float) -> np.ndarray:
  """The right-handed rotation about +z (x forward turns towards y left for degrees > 0)."""
  a = np.radians(degrees)
  return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _box(rng, centre, size, n):
  """n points on the four sides and the top of a box standing on the ground."""
  c, s = np.asarray(centre, float), np.asarray(size, float)
  u = rng.uniform(-0.5, 0.5, (n, 3)) * s
  face = rng.integers(0, 5, n)
  u[face == 0, 0], u[face == 1, 0] = -s[0] / 2, s[0] / 2
  u[face == 2, 1], u[face == 3, 1] = -s[1] / 2, s[1] / 2
  u[face == 4, 2] = s[2] / 2
  return c + u


@dataclasses.dataclass
class Scene:
  pc1: np.ndarray
  pc2: np.ndarray
  flow: np.ndarray  # true flow of pc1 (N x 3)
  ego_flow: np.ndarray  # the sensor's motion seen at each pc1 point (N x 3)
  ego_rotation: np.ndarray  # frame-1 -> frame-2 coordinates of static points: R p + t
  ego_translation: np.ndarray
  ground1: np.ndarray  # bool N: pc1 point on the ground
  moving1: np.ndarray  # bool N: pc1 point on a moving box


def _frame(rng, boxes, n_ground, reach):
  """Points of one frame in world coordinates (frame-1 sensor) and their part: 0 ground, 1 static,
  2 + i moving box i."""
  r = reach * np.sqrt(rng.uniform(0, 1, n_ground))  # uniform over the disc
  a = rng.uniform(0, 2 * np.pi, n_ground)
  ground = np.c_[r * np.cos(a), r * np.sin(a), np.full(n_ground, -SENSOR_HEIGHT)]
  walls = []
  for side in (-9.0, 9.0):
    m = 1500
    walls.append(np.c_[rng.uniform(-30, 40, m), np.full(m, side), rng.uniform(-1.8, 2.5, m)])
  poles = [_box(rng, (x, y, -0.3), (0.3, 0.3, 3.0), 120) for x, y in ((12, 6), (25, -6), (-8, 5))]
  static = np.concatenate(walls + poles)
  parts = [np.zeros(len(ground), int), np.ones(len(static), int)]
  points = [ground, static]
  for i, (centre, size) in enumerate(boxes):
    b = _box(rng, centre, size, 900)
    points.append(b)
    parts.append(np.full(len(b), 2 + i))
  return np.concatenate(points), np.concatenate(parts)


def sweep_pair(seed: int = 0, ego_m: float = 1.0, yaw_deg: float = 2.0, n_ground: int = 6000,
               reach: float = 100.0, car_m: float = 1.6, crossing_m: float = 0.8) -> Scene:
  """Two sweeps (see the module docstring); the boxes' frame-1 -> frame-2 moves are world
  translations: the car +car_m along x, the crossing box +crossing_m along y."""
  rng = np.random.default_rng(seed)
  boxes1 = [((10.0, 0.0, -1.05), (4.2, 1.8, 1.5)), ((16.0, -5.0, -1.05), (1.8, 4.2, 1.5))]
  moves = [np.array([car_m, 0.0, 0.0]), np.array([0.0, crossing_m, 0.0])]
  boxes2 = [(np.add(c, m), s) for (c, s), m in zip(boxes1, moves)]
  # The sensor's frame-2 pose in frame-1 coordinates: x -> R_s x + t_s; static p: R_s^T (p - t_s).
  r_s, t_s = yaw(yaw_deg), np.array([ego_m, 0.0, 0.0])
  rot, trans = r_s.T, -r_s.T @ t_s
  world1, part1 = _frame(rng, boxes1, n_ground, reach)
  world2, _ = _frame(rng, boxes2, n_ground, reach)
  moved = world1.copy()
  for i, m in enumerate(moves):
    moved[part1 == 2 + i] += m
  pc1 = world1
  pc2 = world2 @ rot.T + trans
  flow = moved @ rot.T + trans - pc1
  ego_flow = pc1 @ rot.T + trans - pc1
  f32 = lambda a: a.astype(np.float32)
  return Scene(f32(pc1), f32(pc2), f32(flow), f32(ego_flow), rot, trans, part1 == 0, part1 >= 2)
