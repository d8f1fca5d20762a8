"""Synthetic scene-flow pairs made in-process from a seed, so the project runs with no download.

A scene is a set of rigid objects built from primitives (boxes, ellipsoids incl. bumpy "rocks",
capped cylinders, bent plates = cylindrical shell patches, tori, planes); each object has its own
rigid motion and the sensor moves too. Each frame is ray-cast from the sensor at the origin, so a
cloud holds exactly the surface points the sensor sees (the nearest hit of every ray, occlusion
exact up to the bumps of rocks). The two frames use independent ray jitter, so pc2 samples the
frame-2 surfaces at other points than pc1 (no correspondence); the flow of a pc1 point is where
that surface point moves in frame 2, in frame 2's sensor coordinates (sensor motion included).

- synthetic_things: FlyingThings3D-like, in the FT3D reader's convention (after its x, z flip): a
  pinhole camera of FT3D's field of view (960 x 540 px, f = 1050 px: the real samples fill |x/z| <=
  0.457, |y/z| <= 0.257), z forward (depth), x left, y vertical (the objects float, as in FT3D, so
  the sign of y carries no gravity; the scenes are mirror-symmetric in x, and x left makes the frame
  right-handed like the readers': jaxflow.geometry.frames). 5-15 objects (primitives and composites:
  chairs, tables, dumbbells, snowmen, mushrooms, arches) centred at 9-32 m before a tilted
  background wall at 28-60 m, often cut by the 35 m limit as FT3D's far backgrounds are; the FT3D
  reader's cut applied. Like the real samples (a random subset of a depth camera's valid pixels) the
  clouds have ~11k points whatever part of the view the objects fill: a coarse 48 x 27 cast measures
  that part, then a jittered grid of 1-4 x 160 x 90 rays is cast. Motion ranges (`THINGS`) are tuned
  to the real samples' flow, depth, extent and density statistics (benchmarks/RESULTS.md).
- synthetic_lidar: KITTI-like driving pairs in the KITTI reader's convention (y up, z forward,
  ground near y = -1.6): ground, buildings, poles, trees, parked and moving cars (body + cabin),
  pedestrians and ego-motion (0.3-1.5 m forward, +-2 deg yaw per frame); 64 beams over the
  camera's vertical field of view (-16 to +3 deg) x 640 azimuths over its horizontal one (+-42 deg),
  then the KITTI reader's ground removal and 35 m cut (`kitti_keep`, the same function).

A pc2 point is cut by the same rule as pc1 points, applied to it and its own position in frame 1.
Pair i is fully determined by (kind, split, i): its rng is np.random.default_rng((kind, split, i)),
so splits never share a seed. Masks are all True.
"""

import dataclasses
import math

import numpy as np

from jaxflow.data.readers import DEPTH_LIMIT, ft3d_keep, kitti_keep
from jaxflow.data.registry import Dataset, Pair, register
from jaxflow.errors import DataError

KINDS = ("synthetic_things", "synthetic_lidar", "synthetic_mix")
SPLITS = ("train", "val", "test")
DEFAULT_COUNT = {"train": 4910, "val": 200, "test": 200}  # train as the FT3D quarter

BOX, ELLIPSOID, CYLINDER, SHELL, TORUS, PLANE = range(6)
_EPS = 1e-6

# FT3D camera: 960 x 540 px, focal 1050 px -> |x/z| <= 0.457, |y/z| <= 0.257.
THINGS_U, THINGS_V, THINGS_W, THINGS_H = 480 / 1050, 270 / 1050, 160, 90
THINGS_POINTS = 11000  # points wanted within 35 m: the grid is 1-4 x 160 x 90 to reach it
LIDAR_BEAMS, LIDAR_COLUMNS = 64, 640
LIDAR_ELEVATION_DEG, LIDAR_AZIMUTH_DEG = (-16.0, 3.0), 42.0


@dataclasses.dataclass
class Scene:
  """Primitives in frame-1 sensor coordinates and each object's frame-1 -> frame-2 map x -> A x + b."""
  kind_P: np.ndarray  # int primitive kinds
  obj_P: np.ndarray  # object of each primitive
  rot_Px3x3: np.ndarray  # local -> sensor rotation
  pos_Px3: np.ndarray  # local origin in sensor coordinates
  size_Px3: np.ndarray  # kind-specific sizes (see the kernels)
  box_Px2x3: np.ndarray  # local axis-aligned bounding box (centre, half extents)
  bumps: dict  # primitive -> (amplitude, waves 3x3, phases 3) of a bumpy ellipsoid
  a_Kx3x3: np.ndarray
  b_Kx3: np.ndarray

  def frame_pose(self, frame: int):
    if frame == 0:
      return self.rot_Px3x3, self.pos_Px3
    a = self.a_Kx3x3[self.obj_P]
    return a @ self.rot_Px3x3, np.einsum("pij,pj->pi", a, self.pos_Px3) + self.b_Kx3[self.obj_P]


@dataclasses.dataclass
class Grid:
  """Ray directions 3 x H x W from the origin and each row's / column's coordinate bounds.

  Rows and columns are indexed by increasing coordinate: for a pinhole grid the coordinates are
  y/z and x/z, for a spherical one elevation and azimuth (radians).
  """
  dirs_3xHxW: np.ndarray
  row_lo: np.ndarray
  row_hi: np.ndarray
  col_lo: np.ndarray
  col_hi: np.ndarray
  pinhole: bool


def things_grid(rng: np.random.Generator, scale: float = 1) -> Grid:
  """FT3D's field of view on a (scale x) 160 x 90 grid, one ray per cell at a random point in it."""
  w, h = round(THINGS_W * scale), round(THINGS_H * scale)
  cols = np.linspace(-THINGS_U, THINGS_U, w + 1)
  rows = np.linspace(-THINGS_V, THINGS_V, h + 1)
  dirs = np.empty((3, h, w))
  for i, edges in ((0, cols), (1, rows)):  # u = x/z and v = y/z, each at a random point of its cell
    rng.random(out=dirs[i])
    dirs[i] *= edges[1] - edges[0]
  dirs[0] += cols[:-1]
  dirs[1] += rows[:-1, None]
  dirs[2] = 1.0
  return Grid(dirs, rows[:-1], rows[1:], cols[:-1], cols[1:], pinhole=True)


def lidar_grid(rng: np.random.Generator, scale: int = 1) -> Grid:
  """64 beams (scale x) over elevation x azimuth columns with a random phase per frame."""
  el = np.deg2rad(np.linspace(*LIDAR_ELEVATION_DEG, LIDAR_BEAMS * scale))
  half = np.deg2rad(LIDAR_AZIMUTH_DEG)
  step = 2 * half / (LIDAR_COLUMNS * scale)
  az = -half + (np.arange(LIDAR_COLUMNS * scale) + rng.random()) * step
  ce, se, ca, sa = np.cos(el)[:, None], np.sin(el)[:, None], np.cos(az), np.sin(az)
  dirs = np.stack([ce * sa, np.broadcast_to(se, (len(el), len(az))), ce * ca])
  return Grid(dirs, el, el, az - step / 2, az + step / 2, pinhole=False)


# Ray-primitive intersections in the primitive's local frame: rays o + t d (o: 3, d: 3 x K) -> t
# (K), inf where missed; t is in units of |d|. Rows of d are kept separate: numpy is fastest on 1-D
# arrays.

def _box(o, d, size):
  t_near, t_far = None, None
  with np.errstate(divide="ignore", invalid="ignore"):
    for i in range(3):
      inv = 1.0 / d[i]
      t1, t2 = (-size[i] - o[i]) * inv, (size[i] - o[i]) * inv
      lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
      t_near = lo if t_near is None else np.maximum(t_near, lo)
      t_far = hi if t_far is None else np.minimum(t_far, hi)
  return np.where((t_far >= t_near) & (t_near > _EPS), t_near, np.inf)


def _ellipsoid(o, d, size):
  o, d = o / size, d / size[:, None]
  a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
  b = o @ d
  disc = b * b - a * (o @ o - 1.0)
  with np.errstate(invalid="ignore"):
    t = (-b - np.sqrt(disc)) / a
  return np.where((disc >= 0) & (t > _EPS), t, np.inf)


def _cylinder(o, d, size):
  """Capped cylinder about the y axis: radius size[0], half height size[1]."""
  r, hh = size[0], size[1]
  dx, dy, dz = d
  a = dx * dx + dz * dz
  b = o[0] * dx + o[2] * dz
  disc = b * b - a * (o[0] ** 2 + o[2] ** 2 - r * r)
  with np.errstate(invalid="ignore", divide="ignore"):
    t_side = (-b - np.sqrt(disc)) / a
    side = (disc >= 0) & (t_side > _EPS) & (np.abs(o[1] + t_side * dy) <= hh)
    t = np.where(side, t_side, np.inf)
    if abs(o[1]) > hh:  # outside the slab: the ray may enter through the cap facing the origin
      t_cap = (math.copysign(hh, o[1]) - o[1]) / dy
      x, z = o[0] + t_cap * dx, o[2] + t_cap * dz
      cap = (t_cap > _EPS) & (x * x + z * z <= r * r)
      t = np.where(cap & (t_cap < t), t_cap, t)
  return t


def _shell(o, d, size):
  """Bent plate: the patch |angle| <= size[1], |y| <= size[2] of a cylinder of radius size[0]
  about the axis x = 0, z = -size[0] (so the patch passes through the origin, facing +z)."""
  rb, half_angle, hh = size
  o = o + np.array([0.0, 0.0, rb])
  dx, dy, dz = d
  a = dx * dx + dz * dz
  b = o[0] * dx + o[2] * dz
  disc = b * b - a * (o[0] ** 2 + o[2] ** 2 - rb * rb)
  best = np.full(len(dx), np.inf)
  with np.errstate(invalid="ignore", divide="ignore"):
    s = np.sqrt(disc)
    for t in ((-b + s) / a, (-b - s) / a):  # far root first, so the near one wins
      ok = (t > _EPS) & (np.abs(o[1] + t * dy) <= hh) & (o[2] + t * dz >= rb * math.cos(half_angle))
      best = np.where(ok, t, best)
  return best


def _torus(o, d, size, traces: int = 20, samples: int = 48, halvings: int = 6):
  """Torus about the y axis (major radius size[0], minor size[1]).

  Sphere tracing its exact SDF from the bounding sphere never passes the first hit and settles most
  rays in a few steps; the rest (grazing rays converge slowly) take the first sign change among
  `samples` points of the remaining chord, then bisection and secant steps. A ray whose path
  through the tube is shorter than the sample step counts as a miss.
  """
  big, small = size[0], size[1]
  a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
  b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
  disc = b * b - a * (o @ o - (big + small) ** 2)
  t = np.full(len(a), np.inf)
  idx = np.flatnonzero(disc > 0)
  if not len(idx):
    return t
  d, a, b, s = d.take(idx, axis=1), a[idx], b[idx], np.sqrt(disc[idx])
  t_in, t_out = np.maximum((-b - s) / a, 0.0), (-b + s) / a

  def sdf(tt, d):  # tt: K, or K x samples with d[i][:, None]
    x, y, z = o[0] + tt * d[0], o[1] + tt * d[1], o[2] + tt * d[2]
    q = np.sqrt(x * x + z * z) - big
    return np.sqrt(q * q + y * y) - small

  inv_norm = 1.0 / np.sqrt(a)
  tt = t_in
  for _ in range(traces):
    tt = tt + sdf(tt, d) * inv_norm
  settled = (sdf(tt, d) < 1e-7) & (tt < t_out)
  t[idx[settled]] = tt[settled]
  rest = np.flatnonzero(~settled & (tt < t_out))
  if not len(rest):
    return t
  d, start, end = d.take(rest, axis=1), tt[rest], t_out[rest]
  ts = start[:, None] + (end - start)[:, None] * np.linspace(0, 1, samples)
  inside = sdf(ts, d[:, :, None]) < 0
  hit = inside.any(axis=1)
  first = inside.argmax(axis=1)[hit]
  rows = np.flatnonzero(hit)
  lo, hi = ts[rows, np.maximum(first - 1, 0)], ts[rows, first]
  d = d.take(rows, axis=1)
  for _ in range(halvings):
    mid = 0.5 * (lo + hi)
    out = sdf(mid, d) > 0
    lo, hi = np.where(out, mid, lo), np.where(out, hi, mid)
  f_lo, f_hi = sdf(lo, d), sdf(hi, d)
  for _ in range(2):  # the SDF is nearly linear across the small bracket: secant steps from its ends
    root = lo + (hi - lo) * f_lo / np.maximum(f_lo - f_hi, 1e-300)
    f_root = sdf(root, d)
    out = f_root > 0
    lo, f_lo = np.where(out, root, lo), np.where(out, f_root, f_lo)
    hi, f_hi = np.where(out, hi, root), np.where(out, f_hi, f_root)
  t[idx[rest[rows]]] = np.where(root > _EPS, root, np.inf)
  return t


def _plane(o, d, size):
  """Rectangle y = 0, |x| <= size[0], |z| <= size[2] (two-sided)."""
  with np.errstate(divide="ignore", invalid="ignore"):
    t = -o[1] / d[1]
  x, z = o[0] + t * d[0], o[2] + t * d[2]
  return np.where((t > _EPS) & (np.abs(x) <= size[0]) & (np.abs(z) <= size[2]), t, np.inf)


_KERNELS = {BOX: _box, ELLIPSOID: _ellipsoid, CYLINDER: _cylinder, SHELL: _shell, TORUS: _torus,
            PLANE: _plane}


def _blocks(grid: Grid, center_Px3, axes_Px3x3) -> np.ndarray:
  """Row and column ranges (P x 4: i0, i1, j0, j1) whose rays can reach each oriented box
  (centre, half-extent axes as columns)."""
  corners_8xPx3 = center_Px3 + np.einsum("cj,pij->cpi", _CORNERS, axes_Px3x3)
  x, y, z = corners_8xPx3.transpose(2, 0, 1)
  if grid.pinhole:  # the grid is regular in x/z, y/z: a box in front projects inside its corners' hull
    ahead = (z > 1e-3).all(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
      u, v = x / z, y / z
    h_lo, h_hi = np.where(ahead, u.min(0), -np.inf), np.where(ahead, u.max(0), np.inf)
    v_lo, v_hi = np.where(ahead, v.min(0), -np.inf), np.where(ahead, v.max(0), np.inf)
  else:  # azimuth of a box not holding the vertical axis spans its corners'; elevation is bounded
    (x0, y0, z0), (x1, y1, z1) = (x.min(0), y.min(0), z.min(0)), (x.max(0), y.max(0), z.max(0))
    every = (z0 <= 0) & (x0 <= 0) & (x1 >= 0)
    azimuth = np.arctan2(x, z)
    h_lo, h_hi = np.where(every, -np.inf, azimuth.min(0)), np.where(every, np.inf, azimuth.max(0))
    zero = np.zeros_like(x0)  # by the nearest and farthest horizontal distance of the box
    near = np.hypot(np.maximum(np.maximum(x0, -x1), zero), np.maximum(np.maximum(z0, -z1), zero))
    far = np.hypot(np.maximum(abs(x0), abs(x1)), np.maximum(abs(z0), abs(z1)))
    v_lo = np.arctan2(y0, np.where(y0 < 0, near, far))
    v_hi = np.arctan2(y1, np.where(y1 > 0, near, far))
  return np.stack([np.searchsorted(grid.row_hi, v_lo, "left"),
                   np.searchsorted(grid.row_lo, v_hi, "right"),
                   np.searchsorted(grid.col_hi, h_lo, "left"),
                   np.searchsorted(grid.col_lo, h_hi, "right")], axis=1)


_CHUNK = 8192  # rays per kernel call: temporaries above ~128 KB are mmap-ed, page-faulted and freed
_CORNERS = np.array([(i, j, k) for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)


def _primitive_boxes(scene: Scene, frame: int):
  """Centres (P x 3) and half-extent axes (P x 3 x 3, columns) of the primitives' oriented boxes."""
  rot, pos = scene.frame_pose(frame)
  return pos + np.einsum("pij,pj->pi", rot, scene.box_Px2x3[:, 0]), rot * scene.box_Px2x3[:, 1, None, :]


def coverage(scene: Scene, frame: int, grid: Grid, max_depth: float = math.inf) -> float:
  """Fraction of the grid's rays that hit a surface nearer than max_depth (z); tori count as the
  flat ellipsoids around them (close enough here, and much cheaper to cast)."""
  torus = scene.kind_P == TORUS
  if torus.any():
    size = scene.size_Px3.copy()
    outer = size[torus, 0] + size[torus, 1]
    size[torus] = np.stack([outer, size[torus, 1], outer], 1)
    scene = dataclasses.replace(scene, kind_P=np.where(torus, ELLIPSOID, scene.kind_P), size_Px3=size)
  points, _ = render(scene, frame, grid, max_depth)
  return float((points[2] < max_depth).sum()) / grid.dirs_3xHxW[0].size


def render(scene: Scene, frame: int, grid: Grid, max_depth: float = math.inf):
  """Ray-casts one frame: (points 3 x N float64 in that frame's sensor coordinates, primitive N).

  Primitives lying wholly at z >= max_depth are skipped: what they hit or hide is cut anyway.
  They are cast nearest first, so one whose rays all hit something nearer is skipped too (t >= z
  on both grids). Points are kept 3 x N here: numpy is much faster on rows than on N x 3 broadcasts.
  """
  rot, pos = scene.frame_pose(frame)
  _, h, w = grid.dirs_3xHxW.shape
  depth_HxW = np.full((h, w), np.inf)
  prim_HxW = np.full((h, w), -1, np.int32)
  center_Px3, axes_Px3x3 = _primitive_boxes(scene, frame)
  blocks = _blocks(grid, center_Px3, axes_Px3x3).tolist()
  z_near = (center_Px3[:, 2] - np.abs(axes_Px3x3[:, 2]).sum(1)).tolist()
  kinds = scene.kind_P.tolist()
  for p in np.argsort(z_near, kind="stable").tolist():
    i0, i1, j0, j1 = blocks[p]
    if i0 >= i1 or j0 >= j1 or z_near[p] >= max_depth or depth_HxW[i0:i1, j0:j1].max() < z_near[p]:
      continue
    kind, r, o = kinds[p], rot[p], -(pos[p] @ rot[p])
    step = max(1, _CHUNK // (j1 - j0))
    for i in range(i0, i1, step):  # chunks: large temporaries cost page faults on every allocation
      block = slice(i, min(i + step, i1)), slice(j0, j1)
      dirs_3xK = grid.dirs_3xHxW[:, block[0], block[1]]
      shape = dirs_3xK.shape[1:]
      t = _KERNELS[kind](o, r.T @ dirs_3xK.reshape(3, -1), scene.size_Px3[p]).reshape(shape)
      current = depth_HxW[block]
      closer = t < current
      np.copyto(current, t, where=closer)  # copyto: 2-D boolean indexing is far slower
      np.copyto(prim_HxW[block], p, where=closer)
  hit = np.flatnonzero(prim_HxW >= 0)
  prim_N = prim_HxW.reshape(-1)[hit]
  points_3xN = depth_HxW.reshape(-1)[hit] * grid.dirs_3xHxW.reshape(3, -1).take(hit, axis=1)
  for p, (amplitude, waves, phases) in scene.bumps.items():
    sel = np.flatnonzero(prim_N == p)
    if len(sel):  # rock: the base-ellipsoid hit displaced radially by a smooth bump field
      local = rot[p].T @ (points_3xN.take(sel, axis=1) - pos[p][:, None])
      unit = local / np.sqrt((local * local).sum(0))
      bump = amplitude * np.sin(waves @ unit + phases[:, None]).mean(axis=0)
      points_3xN[:, sel] = rot[p] @ (local * (1 + bump)) + pos[p][:, None]
  return points_3xN, prim_N


def warp(scene: Scene, points_3xN, prim_N, inverse: bool = False):
  """Frame-1 points (3 x N) of primitives prim_N -> their frame-2 positions (2 -> 1 with inverse)."""
  a_Kx3x3, b_Kx3 = scene.a_Kx3x3, scene.b_Kx3
  if inverse:  # x = A^T (y - b) = A^T y - A^T b
    a_Kx3x3 = a_Kx3x3.transpose(0, 2, 1)
    b_Kx3 = -np.einsum("kij,kj->ki", a_Kx3x3, b_Kx3)
  obj_N = scene.obj_P[prim_N]
  a_9xN = np.ascontiguousarray(a_Kx3x3.reshape(-1, 9).T).take(obj_N, axis=1)
  b_3xN = np.ascontiguousarray(b_Kx3.T).take(obj_N, axis=1)
  x, y, z = points_3xN
  for i in range(3):
    b_3xN[i] += a_9xN[3 * i] * x + a_9xN[3 * i + 1] * y + a_9xN[3 * i + 2] * z
  return b_3xN


def _nx3(points_3xN) -> np.ndarray:
  return np.ascontiguousarray(points_3xN.T, dtype=np.float32)


# Scene building.

def rotation(axis, angle: float) -> np.ndarray:
  """Rotation by `angle` radians about `axis` (Rodrigues, in plain floats: scenes build many).
  Not jaxflow.geometry.rigid.rotations_from_vectors: every generated scene depends on this one's
  rounding, bit for bit."""
  x, y, z = (float(v) for v in axis)
  n = math.sqrt(x * x + y * y + z * z)
  x, y, z = x / n, y / n, z / n
  c, s = math.cos(angle), math.sin(angle)
  t = 1 - c
  return np.array([[c + x * x * t, x * y * t - z * s, x * z * t + y * s],
                   [y * x * t + z * s, c + y * y * t, y * z * t - x * s],
                   [z * x * t - y * s, z * y * t + x * s, c + z * z * t]])


def random_rotation(rng) -> np.ndarray:
  q = rng.normal(size=4)
  w, x, y, z = q / np.linalg.norm(q)
  return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                   [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                   [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _unit(rng):
  v = rng.normal(size=3)
  return v / math.sqrt(float(v @ v))


def _local_box(kind, size, bump) -> np.ndarray:
  """(centre, half extents) of a primitive's axis-aligned bounding box in its own frame."""
  if kind == ELLIPSOID:
    return np.array([ZERO, size * (1 + bump)])
  if kind == CYLINDER:
    return np.array([ZERO, (size[0], size[1], size[0])])
  if kind == SHELL:
    rb, half_angle, hh = size
    depth = rb * (1 - math.cos(half_angle))
    return np.array([(0, 0, -depth / 2), (rb * math.sin(min(half_angle, math.pi / 2)), hh, depth / 2)])
  if kind == TORUS:
    return np.array([ZERO, (size[0] + size[1], size[1], size[0] + size[1])])
  if kind == PLANE:
    return np.array([ZERO, (size[0], 0, size[2])])
  return np.array([ZERO, size])  # BOX


class Builder:
  """Collects objects (a rigid set of primitives with one motion) into a Scene; object 0 is the
  static world, which moves only with the sensor."""

  def __init__(self, sensor_rot, sensor_pos):
    self.prims, self.bumps = [], {}
    self.sensor_t = sensor_rot.T  # frame-2 sensor pose (rotation, position) in frame-1 coordinates
    self.sensor_pos = np.asarray(sensor_pos, float)
    self.motions = [(self.sensor_t, -self.sensor_t @ self.sensor_pos)]

  def add(self, parts, rot, pos, motion_rot=None, motion_pos=None):
    """parts: [(kind, local rot, local pos, size, bump)] in the object's frame; object pose (rot, pos);
    motion: frame-1 -> frame-2 x -> motion_rot (x - pos) + pos + motion_pos in frame-1 coordinates,
    none for a static object."""
    pos = np.asarray(pos, float)
    k = 0
    if motion_rot is not None or motion_pos is not None:
      k = len(self.motions)
      m = np.eye(3) if motion_rot is None else motion_rot
      shift = np.zeros(3) if motion_pos is None else np.asarray(motion_pos, float)
      b = self.sensor_t @ (pos - m @ pos + shift - self.sensor_pos)
      self.motions.append((self.sensor_t @ m, b))
    for kind, lrot, lpos, size, bump in parts:
      size = np.asarray(size, float)
      if bump:
        self.bumps[len(self.prims)] = bump
      amplitude = bump[0] if bump else 0.0
      self.prims.append((kind, k, rot @ lrot, rot @ np.asarray(lpos, float) + pos, size,
                         _local_box(kind, size, amplitude)))

  def scene(self) -> Scene:
    kind, obj, rot, pos, size, box = zip(*self.prims)
    return Scene(np.array(kind), np.array(obj), np.array(rot), np.array(pos), np.array(size),
                 np.array(box), self.bumps, np.array([m[0] for m in self.motions]),
                 np.array([m[1] for m in self.motions]))


IDENTITY = np.eye(3)
ZERO = (0.0, 0.0, 0.0)
_ROT_X90 = rotation((1, 0, 0), math.pi / 2)  # local y -> z
_ROT_XM90 = rotation((1, 0, 0), -math.pi / 2)  # local z -> y
_ROT_Z90 = rotation((0, 0, 1), math.pi / 2)  # local y -> -x


def random_bump(rng, amplitude):
  return (amplitude, rng.normal(size=(3, 3)) * rng.uniform(2, 5), rng.uniform(0, 2 * np.pi, 3))


def _thing_parts(rng, s: float):
  """One random FlyingThings-like object of size ~s (metres, half extent)."""
  u = lambda lo, hi: rng.uniform(lo, hi)
  choice = rng.integers(13)
  if choice == 0:
    return [(BOX, IDENTITY, ZERO, s * rng.uniform(0.3, 1.0, 3), None)]
  if choice == 1:
    return [(ELLIPSOID, IDENTITY, ZERO, s * rng.uniform(0.4, 1.0, 3), None)]
  if choice == 2:
    return [(CYLINDER, IDENTITY, ZERO, (s * u(0.2, 0.6), s * u(0.4, 1.0), 0), None)]
  if choice == 3:
    return [(TORUS, IDENTITY, ZERO, (s * u(0.55, 0.8), s * u(0.12, 0.3), 0), None)]
  if choice == 4:  # thin plate
    return [(BOX, IDENTITY, ZERO, (s * u(0.6, 1.0), s * u(0.4, 1.0), s * u(0.01, 0.04)), None)]
  if choice == 5:  # bent plate
    return [(SHELL, IDENTITY, ZERO, (s * u(0.5, 1.5), u(0.5, 1.4), s * u(0.3, 0.9)), None)]
  if choice == 6:  # rock
    return [(ELLIPSOID, IDENTITY, ZERO, s * rng.uniform(0.5, 0.9, 3), random_bump(rng, u(0.05, 0.15)))]
  if choice == 7:  # chair: seat, back, four legs
    w, leg = s * 0.5, s * 0.5
    parts = [(BOX, IDENTITY, (0, 0, 0), (w, 0.06 * s, w), None),
             (BOX, IDENTITY, (0, 0.5 * s, -w), (w, 0.5 * s, 0.05 * s), None)]
    parts += [(CYLINDER, IDENTITY, (x * w * 0.85, -leg, z * w * 0.85), (0.05 * s, leg, 0), None)
              for x in (-1, 1) for z in (-1, 1)]
    return parts
  if choice == 8:  # table: top and four legs
    w, d, leg = s, s * u(0.5, 0.9), s * 0.45
    parts = [(BOX, IDENTITY, (0, leg, 0), (w, 0.05 * s, d), None)]
    parts += [(BOX, IDENTITY, (x * w * 0.85, 0, z * d * 0.8), (0.06 * s, leg, 0.06 * s), None)
              for x in (-1, 1) for z in (-1, 1)]
    return parts
  if choice == 9:  # dumbbell
    r = s * u(0.25, 0.4)
    return [(ELLIPSOID, IDENTITY, (-s + r, 0, 0), (r, r, r), None),
            (ELLIPSOID, IDENTITY, (s - r, 0, 0), (r, r, r), None),
            (CYLINDER, _ROT_Z90, ZERO, (r * 0.3, s - r, 0), None)]
  if choice == 10:  # snowman
    r = s * 0.45
    return [(ELLIPSOID, IDENTITY, (0, -r, 0), (r, r, r), None),
            (ELLIPSOID, IDENTITY, (0, 0.45 * r, 0), (0.7 * r,) * 3, None),
            (ELLIPSOID, IDENTITY, (0, 1.4 * r, 0), (0.45 * r,) * 3, None)]
  if choice == 11:  # mushroom: stem and flat cap
    return [(CYLINDER, IDENTITY, (0, -0.3 * s, 0), (0.2 * s, 0.5 * s, 0), None),
            (ELLIPSOID, IDENTITY, (0, 0.25 * s, 0), (0.8 * s, 0.3 * s, 0.8 * s), None)]
  # arch: two pillars and a bent roof
  return [(BOX, IDENTITY, (-0.7 * s, -0.2 * s, 0), (0.2 * s, 0.6 * s, 0.25 * s), None),
          (BOX, IDENTITY, (0.7 * s, -0.2 * s, 0), (0.2 * s, 0.6 * s, 0.25 * s), None),
          (SHELL, _ROT_XM90, (0, 0.4 * s, 0), (0.9 * s, 1.2, 0.25 * s), None)]


# Ranges tuned so flow magnitudes, depths and extents match the real FT3D samples (RESULTS.md).
THINGS = {
    "activity": (0.35, 1.3),  # per scene, scales every motion range below (real pairs differ a lot)
    "camera_deg": 4.5,  # camera rotation per frame, uniform in [0, this] about a random axis
    "camera_m": 0.9,  # camera translation per frame
    "object_deg": 20.0,  # object rotation per frame
    "object_m": 2.4,  # object translation per frame
    "wall_m": (28.0, 60.0),  # background wall depth (beyond 35 m it is cut, as FT3D's far backgrounds)
    "wall_tilt": 0.4,  # radians, about x and about y
    "depth_m": (9.0, 32.0),  # depth of the object centres
}


def things_scene(rng) -> Scene:
  """FlyingThings-like scene: 5-15 objects before a wall, each and the camera moving (see THINGS)."""
  activity = rng.uniform(*THINGS["activity"])
  cam_rot = rotation(_unit(rng), np.deg2rad(rng.uniform(0, THINGS["camera_deg"] * activity)))
  cam_pos = _unit(rng) * rng.uniform(0, THINGS["camera_m"] * activity)
  builder = Builder(cam_rot, cam_pos)
  depth = rng.uniform(*THINGS["wall_m"])
  tilt = THINGS["wall_tilt"]
  wall_rot = (rotation((1, 0, 0), rng.uniform(-tilt, tilt))
              @ rotation((0, 1, 0), rng.uniform(-tilt, tilt)))
  builder.add([(PLANE, _ROT_X90, ZERO, (80, 0, 50), None)], wall_rot, (0, 0, depth))
  for _ in range(rng.integers(5, 16)):
    z = rng.uniform(*THINGS["depth_m"])
    center = (rng.uniform(-1, 1) * THINGS_U * z, rng.uniform(-1, 1) * THINGS_V * z, z)
    scale = rng.uniform(0.5, 2.5) * math.sqrt(z / 20)
    motion = rotation(_unit(rng), np.deg2rad(rng.uniform(0, THINGS["object_deg"] * activity)))
    builder.add(_thing_parts(rng, scale), random_rotation(rng), center, motion,
                _unit(rng) * rng.uniform(0, THINGS["object_m"] * activity))
  return builder.scene()


def car_parts(rng):
  """A car in its own frame (origin on the ground below its centre, heading +z): body and cabin.

  No wheels: below the body they would lie in the band (y < -1.4) that ground removal deletes.
  """
  w, length, h = rng.uniform(0.8, 0.95), rng.uniform(1.8, 2.4), rng.uniform(0.3, 0.4)
  body_y = 0.25 + h
  return [(BOX, IDENTITY, (0, body_y, 0), (w, h, length), None),
          (BOX, IDENTITY, (0, body_y + h + 0.3, -0.15 * length), (w - 0.08, 0.3, 0.5 * length), None)]


def lidar_scene(rng) -> Scene:
  """KITTI-like street: ground, buildings, poles, trees, cars and pedestrians; the ego car moves."""
  yaw = np.deg2rad(rng.uniform(-2, 2))
  forward = rng.uniform(0.3, 1.5)
  builder = Builder(rotation((0, 1, 0), yaw), (rng.uniform(-0.05, 0.05), 0, forward))
  g = -rng.uniform(1.55, 1.75)  # ground height below the sensor
  builder.add([(PLANE, IDENTITY, ZERO, (80, 0, 80), None)], IDENTITY, (0, g, 30))
  road = rng.uniform(5, 8)  # half width of the road
  for side in (-1, 1):  # building facades along both sides, with gaps
    z = rng.uniform(-10, 0)
    while z < 60:
      length = rng.uniform(6, 25)
      if rng.random() < 0.8:
        x = side * (road + rng.uniform(2, 7))
        height = rng.uniform(3, 15)
        builder.add([(BOX, IDENTITY, ZERO, (4, height / 2, length / 2), None)],
                    rotation((0, 1, 0), rng.uniform(-0.08, 0.08)),
                    (x + side * 4, g + height / 2, z + length / 2))
      z += length + rng.uniform(0, 6)
    for _ in range(rng.integers(1, 5)):  # poles and trees on the sidewalk
      x, z, h = side * (road + rng.uniform(0.3, 1.8)), rng.uniform(3, 45), rng.uniform(3, 7)
      parts = [(CYLINDER, IDENTITY, (0, h / 2, 0), (rng.uniform(0.08, 0.25), h / 2, 0), None)]
      if rng.random() < 0.5:
        crown = rng.uniform(1.0, 2.2)
        crown_size = (crown, crown * 0.8, crown)
        parts.append((ELLIPSOID, IDENTITY, (0, h + crown * 0.6, 0), crown_size, random_bump(rng, 0.12)))
      builder.add(parts, IDENTITY, (x, g, z))
    for _ in range(rng.integers(0, 4)):  # parked cars
      x, z = side * (road - 1.1), rng.uniform(4, 45)
      heading = rng.uniform(-0.1, 0.1) + (side < 0) * math.pi
      builder.add(car_parts(rng), rotation((0, 1, 0), heading), (x, g, z))
    for _ in range(rng.integers(0, 3)):  # pedestrians walking on the sidewalk
      x, z = side * (road + rng.uniform(0.5, 2)), rng.uniform(3, 35)
      parts = [(CYLINDER, IDENTITY, (0, 0.8, 0), (0.22, 0.8, 0), None),
               (ELLIPSOID, IDENTITY, (0, 1.8, 0), (0.13,) * 3, None)]
      builder.add(parts, IDENTITY, (x, g, z), rotation((0, 1, 0), rng.uniform(-0.1, 0.1)),
                  (rng.uniform(-0.05, 0.05), 0, rng.uniform(-0.15, 0.15)))
  lanes = [x for x in (-3.5, 0.0, 3.5) if abs(x) + 1.2 < road - 1.1]
  for lane in lanes:  # traffic: cars ahead in the ego lane move the same way, others either way
    z = rng.uniform(6, 12)
    heading = 0.0 if lane >= 0 or rng.random() < 0.3 else math.pi
    while z < 45:
      if rng.random() < 0.6:
        speed = rng.uniform(0, 1.5)
        turn = np.deg2rad(rng.uniform(-3, 3))
        direction = np.array([math.sin(heading + turn / 2), 0, math.cos(heading + turn / 2)])
        builder.add(car_parts(rng), rotation((0, 1, 0), heading + rng.uniform(-0.05, 0.05)),
                    (lane + rng.uniform(-0.3, 0.3), g, z), rotation((0, 1, 0), turn), speed * direction)
      z += rng.uniform(8, 20)
  return builder.scene()


_COARSE = things_grid(np.random.default_rng(0), 0.3)  # 48 x 27 rays, to measure `coverage`
_KIND_ID = {"synthetic_things": 1, "synthetic_lidar": 2}
_SPLIT_ID = {"train": 0, "val": 1, "test": 2}


def scene_rng(kind: str, split: str, index: int) -> np.random.Generator:
  """The rng of pair `index`: seeded by (kind, split, index), so splits never share seeds."""
  return np.random.default_rng((_KIND_ID[kind], _SPLIT_ID[split], index))


def make_scene(kind: str, split: str, index: int) -> tuple[Scene, np.random.Generator]:
  rng = scene_rng(kind, split, index)
  return (things_scene(rng) if kind == "synthetic_things" else lidar_scene(rng)), rng


def synthetic_pair(kind: str, split: str, index: int) -> Pair:
  """Pair `index` of kind "synthetic_things" or "synthetic_lidar" in `split`."""
  scene, rng = make_scene(kind, split, index)
  things = kind == "synthetic_things"
  keep_fn = ft3d_keep if things else kitti_keep
  clouds = []
  for frame in (0, 1):
    if things:  # like a random subset of a depth camera's pixels: a resolution for ~THINGS_POINTS
      covered = coverage(scene, frame, _COARSE, DEPTH_LIMIT)
      scale = math.sqrt(THINGS_POINTS / max(covered * THINGS_W * THINGS_H, 1.0))
      grid = things_grid(rng, min(max(scale, 1.0), 4.0))
    else:
      grid = lidar_grid(rng)
    points, prim = render(scene, frame, grid, max_depth=DEPTH_LIMIT)
    near = np.flatnonzero(points[2] < DEPTH_LIMIT)  # both cuts drop the rest: skip warping it
    points, prim = points.take(near, axis=1), prim[near]
    other = warp(scene, points, prim, inverse=frame == 1)  # the same surface point in the other frame
    keep = np.flatnonzero(keep_fn(points.T, other.T) if frame == 0 else keep_fn(other.T, points.T))
    clouds.append((points.take(keep, axis=1), other.take(keep, axis=1)))
  (pc1, pc1_in2), (pc2, _) = clouds
  return Pair(pc1=_nx3(pc1), pc2=_nx3(pc2), flow=_nx3(pc1_in2 - pc1),
              mask=np.ones(pc1.shape[1], bool), name=f"{kind}/{split}/{index}")


class Synthetic(Dataset):
  """`count` synthetic pairs of one kind and split, generated on demand (nothing cached)."""
  up = "y"  # generated in the models' frame: x left, y up, z forward

  def __init__(self, kind: str, split: str, count: int):
    self.kind, self.split, self.count = kind, split, count
    self.name = f"{kind}:{count}"

  def __len__(self):
    return self.count

  def load(self, i):
    if self.kind == "synthetic_mix":  # alternating things / lidar
      return synthetic_pair(("synthetic_things", "synthetic_lidar")[i % 2], self.split, i // 2)
    return synthetic_pair(self.kind, self.split, i)

  def describe(self):
    return (f"{self.name} split={self.split}: {self.count} pairs generated on demand, "
            "each seeded by (kind, split, index)")


def open_synthetic(kind: str, count: str, split: str | None) -> Synthetic:
  """`open_dataset` for "synthetic_things[:COUNT]", "synthetic_lidar[:COUNT]" and
  "synthetic_mix[:COUNT]"."""
  spec = f"{kind}:{count}" if count else kind
  if kind not in KINDS:
    raise DataError(spec, f"unknown synthetic kind {kind!r}; expected one of {KINDS}")
  split = split or "train"
  if split not in SPLITS:
    raise DataError(spec, f"unknown split {split!r}; synthetic splits are {SPLITS}")
  if not count:
    return Synthetic(kind, split, DEFAULT_COUNT[split])
  if not count.isdigit() or int(count) < 1:
    raise DataError(spec, f"COUNT must be a positive integer, got {count!r}")
  return Synthetic(kind, split, int(count))


for _kind in KINDS:
  register(_kind, lambda count, split, kind=_kind: open_synthetic(kind, count, split))
