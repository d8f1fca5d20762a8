"""Raw LiDAR sweeps made to look like the training data: ground removal and a range cut.

    plane = fit_ground(points_Nx3, up="z")            # RANSAC plane under the lowest points
    keep_N = ~plane.ground(points_Nx3) & within_range(points_Nx3, "z", 35.0)
    flow_Nx3, info = raw_sweep_flow(flow_fn, pc1_Nx3, pc2_Mx3, up="z", max_range=35.0)

The benchmark layouts remove ground by height (KITTI's camera frame: y < -1.4) and keep 35 m
(DESIGN.md section 7); a raw sweep has neither. `raw_sweep_flow` runs a flow estimator on what
remains and gives every removed point (ground, or beyond the range) the ego-motion flow of a rigid
fit (`jaxflow.rigid`) to the static part of the estimated flow: ground and far points are static
world, so the sensor's motion is their flow.
"""

import dataclasses

import numpy as np

from jaxflow import rigid
from jaxflow.errors import ConfigError, DataError

UP_AXES = {"x": 0, "y": 1, "z": 2}
DEFAULT_MAX_RANGE = 35.0  # metres, horizontal distance from the sensor (the benchmarks' cut)
GROUND_MARGIN = 0.25  # metres above the plane still ground (KITTI: y < -1.4, road near -1.65)
CELL = 2.0  # metres: the ground is searched among the lowest points of each cell of this size
LOWEST = 0.3  # metres above a cell's lowest point that are ground candidates
INLIER = 0.1  # metres: RANSAC inlier distance
MAX_TILT_DEG = 20.0  # a ground plane's normal is within this of the up axis
ITERATIONS = 200


def axis(up: str) -> int:
  if up not in UP_AXES:
    raise ConfigError(f"up must be one of x, y, z, got {up!r}")
  return UP_AXES[up]


def horizontal_range(points_Nx3, up: str = "z") -> np.ndarray:
  """Distance of each point from the sensor in the plane orthogonal to `up` (N)."""
  other = [i for i in range(3) if i != axis(up)]
  return np.hypot(points_Nx3[:, other[0]], points_Nx3[:, other[1]])


def within_range(points_Nx3, up: str = "z", max_range: float | None = DEFAULT_MAX_RANGE):
  """Bool N: horizontal distance below max_range (all True for None or 0)."""
  if not max_range:
    return np.ones(len(points_Nx3), bool)
  return horizontal_range(points_Nx3, up) < max_range


@dataclasses.dataclass(frozen=True)
class Plane:
  """The plane normal . x + offset = 0, normal a unit vector pointing up."""
  normal: np.ndarray  # 3
  offset: float
  inliers: int = 0  # candidate points within INLIER of it

  def height(self, points_Nx3) -> np.ndarray:
    return np.asarray(points_Nx3, np.float64) @ self.normal + self.offset

  def ground(self, points_Nx3, margin: float = GROUND_MARGIN) -> np.ndarray:
    """Bool N: points below `margin` above the plane (points under it too: noise, kerbs)."""
    return self.height(points_Nx3) < margin

  @property
  def tilt_deg(self) -> float:
    return float(np.degrees(np.arccos(np.clip(np.abs(self.normal).max(), -1.0, 1.0))))


def _candidates(points_Nx3, up: int) -> np.ndarray:
  """Indices of the points within LOWEST of the lowest point of their horizontal CELL."""
  other = [i for i in range(3) if i != up]
  cells = np.floor(points_Nx3[:, other] / CELL).astype(np.int64)
  _, cell_N = np.unique(cells, axis=0, return_inverse=True)
  cell_N = cell_N.reshape(-1)
  lowest = np.full(cell_N.max() + 1, np.inf)
  np.minimum.at(lowest, cell_N, points_Nx3[:, up])
  return np.flatnonzero(points_Nx3[:, up] < lowest[cell_N] + LOWEST)


def _refit(points_Kx3, up_vector) -> tuple[np.ndarray, float]:
  """Least-squares plane through points: the direction of least spread, oriented up."""
  centre = points_Kx3.mean(0)
  normal = np.linalg.svd(points_Kx3 - centre, full_matrices=False)[2][-1]
  normal = normal if normal @ up_vector >= 0 else -normal
  return normal, float(-normal @ centre)


def fit_ground(points_Nx3, up: str = "z", max_range: float | None = DEFAULT_MAX_RANGE,
               seed: int = 0, name: str = "points") -> Plane:
  """The ground plane of a sweep: RANSAC over the lowest points of each horizontal cell.

  Candidates are the points within LOWEST (0.3 m) of the lowest point of their CELL x CELL (2 m)
  column, inside `max_range`. ITERATIONS random triples give planes; those tilted more than
  MAX_TILT_DEG from `up` are refused; the plane with most candidates within INLIER (0.1 m) wins and
  is refitted by least squares to them (twice). Seeded: the same sweep gives the same plane.
  Raises DataError(name) when no plane is found (fewer than 3 candidates, or none flat enough).
  """
  k = axis(up)
  points = np.asarray(points_Nx3, np.float64)
  inside = np.flatnonzero(within_range(points, up, max_range))
  cand = points[inside[_candidates(points[inside], k)]] if len(inside) else points[:0]
  if len(cand) < 3:
    raise DataError(name, f"no ground plane: only {len(cand)} points within {max_range} m")
  up_vector = np.eye(3)[k]
  rng = np.random.default_rng(seed)
  triples = cand[rng.integers(0, len(cand), (ITERATIONS, 3))]
  normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
  norms = np.linalg.norm(normals, axis=1)
  ok = norms > 1e-9
  normals[ok] /= norms[ok, None]
  normals *= np.where(normals @ up_vector < 0, -1.0, 1.0)[:, None]
  ok &= normals @ up_vector >= np.cos(np.radians(MAX_TILT_DEG))
  if not ok.any():
    raise DataError(name, f"no ground plane within {MAX_TILT_DEG} degrees of the {up} axis among "
                    "the lowest points: is the up axis right?")
  normals, offsets = normals[ok], -np.sum(normals[ok] * triples[ok, 0], axis=1)
  counts = [(np.abs(cand @ n + d) < INLIER).sum() for n, d in zip(normals, offsets)]
  best = int(np.argmax(counts))
  normal, offset = normals[best], float(offsets[best])
  for _ in range(2):
    near = np.abs(cand @ normal + offset) < INLIER
    if near.sum() < 3:
      break
    normal, offset = _refit(cand[near], up_vector)
  return Plane(normal, offset, int((np.abs(cand @ normal + offset) < INLIER).sum()))


@dataclasses.dataclass(frozen=True)
class SweepInfo:
  """What `raw_sweep_flow` did: the planes, the points kept and removed, the ego-motion fit."""
  planes: tuple  # (Plane of pc1, Plane of pc2)
  ground: tuple  # (pc1, pc2) ground points removed
  far: tuple  # (pc1, pc2) non-ground points beyond max_range
  kept: tuple  # (pc1, pc2) points the estimator saw
  motion: rigid.Motion  # ego-motion: the rigid fit to the static part of the estimated flow
  max_range: float | None

  def note(self) -> str:
    p = self.planes[0]
    return (f"--lidar: ground plane at height {-p.offset:.2f} m along the up axis (tilt "
            f"{p.tilt_deg:.1f} deg); removed {self.ground[0]} ground and {self.far[0]} points "
            f"beyond {self.max_range or 'no'} m of PC1 ({self.ground[1]} and {self.far[1]} of "
            f"PC2); flow estimated on {self.kept[0]} points; the {self.ground[0] + self.far[0]} "
            f"removed PC1 points get the ego-motion flow of a rigid fit to "
            f"{int(self.motion.inliers.sum())} static points ({self.motion.angle_deg:.2f} deg, "
            f"{np.linalg.norm(self.motion.translation):.2f} m)")


def lidar_keep(points_Nx3, up: str = "z", max_range: float | None = DEFAULT_MAX_RANGE,
               seed: int = 0, name: str = "points") -> tuple[np.ndarray, np.ndarray, Plane]:
  """(keep N, ground N, plane): the non-ground points within max_range."""
  plane = fit_ground(points_Nx3, up, max_range, seed, name)
  ground_N = plane.ground(points_Nx3)
  return ~ground_N & within_range(points_Nx3, up, max_range), ground_N, plane


def raw_sweep_flow(flow_fn, pc1_Nx3, pc2_Mx3, up: str = "z",
                   max_range: float | None = DEFAULT_MAX_RANGE,
                   names=("pc1", "pc2")) -> tuple[np.ndarray, SweepInfo]:
  """Flow N x 3 of EVERY point of pc1: `flow_fn(pc1_kept, pc2_kept)` on the non-ground points
  within max_range of both clouds; the removed pc1 points get the ego-motion flow (see the module
  docstring). Returns the flow and a SweepInfo."""
  pc1, pc2 = np.asarray(pc1_Nx3, np.float32), np.asarray(pc2_Mx3, np.float32)
  keep1, ground1, plane1 = lidar_keep(pc1, up, max_range, name=names[0])
  keep2, ground2, plane2 = lidar_keep(pc2, up, max_range, name=names[1])
  kept1 = pc1[keep1]
  flow_kept = np.asarray(flow_fn(kept1, pc2[keep2]), np.float32)
  motion = rigid.fit_static_motion(kept1, flow_kept)
  flow = np.empty_like(pc1)
  flow[keep1] = flow_kept
  flow[~keep1] = motion.flow(pc1[~keep1])
  info = SweepInfo(planes=(plane1, plane2), ground=(int(ground1.sum()), int(ground2.sum())),
                   far=(int((~keep1 & ~ground1).sum()), int((~keep2 & ~ground2).sum())),
                   kept=(int(keep1.sum()), int(keep2.sum())), motion=motion, max_range=max_range)
  return flow, info
