"""The sensor's own motion between two raw sweeps: a robust ICP of what stays still (issue 26).

    ego = estimate(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, surface2)   # z up
    static_flow_Nx3 = ego.motion.flow(pc1_Nx3)

Independently sampled sweeps have no point-to-point counterparts: a beam's ring on the road lies
at another place in the other sweep, so plain ICP pulls the two ring patterns together (towards
zero motion). Two kinds of residual avoid that, each along a direction the sampling does not bias:
- the ground: the height of each moved pc1 ground point above pc2's local ground surface
  (jaxflow.ground.Surface): fixes height, pitch and roll;
- everything else seen from above (bird's eye view, where the rings of a wall or a pole stack into
  one dense line or blob): the distance from each moved pc1 point to pc2's line through its
  nearest points (walls, facades, cars: point-to-line), or to the point itself (poles, trunks):
  fixes the horizontal translation and the yaw.
Moving objects are outliers: Geman-McClure weights with a scale that shrinks over the rounds.
Started from several motions (zero, the caller's, e.g. the network's dominant one, and the best of
a coarse yaw x translation search); the fit that explains most points wins.
"""

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from jaxflow import rigid

ROUNDS = 30
SCALES = (0.5, 0.25, 0.12, 0.06, 0.04)  # metres: the robust loss's scale, shrinking
MAX_MATCH = 1.5  # metres: a bird's-eye match farther than this is no match
INLIER = 0.1  # metres: a point within this of its match (after the fit) is explained
PLAUSIBLE_INLIERS = 0.5  # a fit explaining fewer of the static-looking points is warned about
SAMPLE = (6000, 3000)  # non-ground and ground points used (seeded sample)
NEIGHBOURS = 8  # bird's-eye neighbours of a pc2 cell for its line
BEV_CELL = 0.1  # metres: pc2's points above the ground merged per cell seen from above
LINE = 0.15  # a pc2 neighbourhood with minor / major spread below this is a line
BLOB = 0.15  # metres: a neighbourhood spread less than this in every direction is a pole
SEARCH_YAW_DEG = np.arange(-6.0, 6.01, 1.0)
SEARCH_X = np.arange(-4.0, 4.01, 0.5)  # forward, metres a frame
SEARCH_Y = np.arange(-1.5, 1.51, 0.5)


@dataclasses.dataclass(frozen=True)
class EgoMotion:
  """The sensor's motion (frame-1 -> frame-2 coordinates), how well it explains the sweeps, and
  every start's result (name -> (Motion, inlier fraction))."""
  motion: rigid.Motion
  inlier_fraction: float  # of the sampled non-ground points within INLIER of pc2 after the fit
  residual: float  # metres: RMS bird's-eye residual of those inliers
  start: str
  starts: dict
  note: str | None = None  # set when the fit is implausible


def motion_from(rotation, translation) -> rigid.Motion:
  return rigid.Motion(np.asarray(rotation, np.float64), np.asarray(translation, np.float64))


def yaw_motion(yaw_deg: float, x: float, y: float) -> rigid.Motion:
  c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
  return motion_from([[c, -s, 0], [s, c, 0], [0, 0, 1]], [x, y, 0.0])


def rotation_from_vector(omega_3) -> np.ndarray:
  """Rotation matrix of the rotation vector omega (Rodrigues), NumPy float64."""
  angle = float(np.linalg.norm(omega_3))
  if angle < 1e-12:
    return np.eye(3)
  k = omega_3 / angle
  kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
  return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


class Target:
  """pc2 prepared once: a bird's-eye k-d tree of its non-ground points with each one's line
  direction (or none: a blob), and its ground surface."""

  def __init__(self, pc2_Mx3, ground2_M, surface2):
    above = np.asarray(pc2_Mx3, np.float64)[~np.asarray(ground2_M, bool)]
    if len(above):  # seen from above, a wall's rings stack: one point a BEV_CELL cell (the mean)
      cells = np.floor(above[:, :2] / BEV_CELL).astype(np.int64)
      _, inverse, count = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
      inverse = inverse.reshape(-1)
      above = np.stack([np.bincount(inverse, above[:, i]) / count for i in range(3)], 1)
    self.points = above
    self.surface = surface2
    self.tree = cKDTree(above[:, :2]) if len(above) else None
    self.normal_Mx2 = np.zeros((len(above), 2))
    self.line_M = np.zeros(len(above), bool)
    self.usable_M = np.ones(len(above), bool)
    if len(above) > NEIGHBOURS:
      _, idx = self.tree.query(above[:, :2], NEIGHBOURS)
      nb = above[idx][..., :2]
      centred = nb - nb.mean(1, keepdims=True)
      cov = np.einsum("mki,mkj->mij", centred, centred)
      values, vectors = np.linalg.eigh(cov)
      self.normal_Mx2 = vectors[:, :, 0]  # least spread: across the line
      self.line_M = values[:, 0] < LINE ** 2 * np.maximum(values[:, 1], 1e-12)
      # Neither a line nor a small blob (a pole): an area seen from above (a tree's crown, a
      # roof), whose visible rim moves with the sensor: no residual there.
      self.usable_M = self.line_M | (values[:, 1] < BLOB ** 2 * NEIGHBOURS)

  def bev_residuals(self, moved_Kx3):
    """(residual R, normal R x 3, point index K of each row): one row a matched point with a line
    (across it), two rows for a blob (x and y); matches beyond MAX_MATCH are left out."""
    if self.tree is None or not len(moved_Kx3):
      return np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64)
    dist, j = self.tree.query(moved_Kx3[:, :2], distance_upper_bound=MAX_MATCH)
    ok = np.flatnonzero(np.isfinite(dist))
    ok = ok[self.usable_M[j[ok]]]
    j = j[ok]
    diff = moved_Kx3[ok, :2] - self.points[j, :2]
    line = self.line_M[j]
    n_line = self.normal_Mx2[j[line]]
    rows_n = [np.c_[n_line, np.zeros(len(n_line))], np.tile([1.0, 0, 0], ((~line).sum(), 1)),
              np.tile([0, 1.0, 0], ((~line).sum(), 1))]
    rows_r = [np.sum(diff[line] * n_line, 1), diff[~line, 0], diff[~line, 1]]
    rows_i = [ok[line], ok[~line], ok[~line]]
    return np.concatenate(rows_r), np.concatenate(rows_n), np.concatenate(rows_i)

  def ground_residuals(self, moved_Gx3):
    """(height above pc2's ground, its normal G x 3)."""
    if self.surface is None or not len(moved_Gx3):
      return np.zeros(0), np.zeros((0, 3))
    ij = self.surface._cells(moved_Gx3[:, :2])  # pylint: disable=protected-access
    a, b, _ = np.moveaxis(self.surface.coef_HxWx3[ij[:, 0], ij[:, 1]], -1, 0)
    n = np.stack([-a, -b, np.ones_like(a)], 1)
    norm = np.linalg.norm(n, axis=1)
    return self.surface.height(moved_Gx3) / norm, n / norm[:, None]


def _cost(target: Target, motion: rigid.Motion, above_Kx3, scale: float) -> float:
  """Mean truncated bird's-eye distance of the moved points to pc2's points (coarse search)."""
  d, _ = target.tree.query(motion.apply(above_Kx3)[:, :2], distance_upper_bound=scale)
  return float(np.minimum(d, scale).mean())


def search(target: Target, above_Kx3) -> rigid.Motion:
  """The best yaw x forward x lateral motion of a coarse grid (bird's-eye cost)."""
  best, best_cost = None, np.inf
  for yaw in SEARCH_YAW_DEG:
    for x in SEARCH_X:
      for y in SEARCH_Y:
        m = yaw_motion(yaw, x, y)
        c = _cost(target, m, above_Kx3, 0.5)
        if c < best_cost:
          best, best_cost = m, c
  return best


def icp(target: Target, above_Kx3, ground_Gx3, start: rigid.Motion, rounds: int = ROUNDS):
  """Gauss-Newton rounds of the robust two-term residual from `start` -> (Motion, inlier
  fraction, residual)."""
  rotation, translation = start.rotation.copy(), start.translation.copy()
  for i in range(rounds):
    scale = SCALES[min(i * len(SCALES) // max(rounds - 4, 1), len(SCALES) - 1)]
    moved_a = above_Kx3 @ rotation.T + translation
    moved_g = ground_Gx3 @ rotation.T + translation
    r_a, n_a, idx = target.bev_residuals(moved_a)
    r_g, n_g = target.ground_residuals(moved_g)
    q = np.concatenate([moved_a[idx], moved_g[:len(r_g)]])
    n = np.concatenate([n_a, n_g])
    r = np.concatenate([r_a, r_g])
    if len(r) < 6:
      break
    w = 1.0 / (1.0 + (r / scale) ** 2) ** 2
    w[len(r_a):] *= max(len(r_a), 1) / max(len(r_g), 1) * 0.5  # the two terms weigh alike
    jac = np.c_[np.cross(q, n), n]
    h = jac.T @ (jac * w[:, None]) + 1e-6 * np.eye(6)
    step = -np.linalg.solve(h, jac.T @ (w * r))
    d_rot = rotation_from_vector(step[:3])
    rotation, translation = d_rot @ rotation, d_rot @ translation + step[3:]
    if np.abs(step).max() < 1e-6 and scale == SCALES[-1]:
      break
  motion = motion_from(rotation, translation)
  fraction, residual = explained(target, motion, above_Kx3)
  return motion, fraction, residual


def explained(target: Target, motion: rigid.Motion, above_Kx3):
  """(fraction of the points within INLIER of pc2 seen from above after `motion`, RMS of theirs)."""
  if target.tree is None or not len(above_Kx3):
    return 0.0, float("nan")
  r, _, idx = target.bev_residuals(motion.apply(above_Kx3))
  per_point = np.full(len(above_Kx3), -np.inf)
  np.maximum.at(per_point, idx, np.abs(r))  # a blob's two rows: the larger decides
  per_point[per_point < 0] = np.inf  # no match
  inlier = per_point < INLIER
  residual = float(np.sqrt(np.mean(per_point[inlier] ** 2))) if inlier.any() else float("nan")
  return float(inlier.mean()), residual


def estimate(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, surface2=None, starts=None, seed: int = 0,
             search_start: bool = True) -> EgoMotion:
  """The ego-motion of two z-up sweeps (module docstring). `starts`: extra named start motions
  (e.g. {"network": Motion}); `surface2`: pc2's ground (None: the ground term is left out)."""
  pc1 = np.asarray(pc1_Nx3, np.float64)
  ground1 = np.asarray(ground1_N, bool)
  rng = np.random.default_rng(seed)
  above, on_ground = pc1[~ground1], pc1[ground1]
  above = above[np.sort(rng.choice(len(above), min(len(above), SAMPLE[0]), replace=False))]
  on_ground = on_ground[np.sort(rng.choice(len(on_ground), min(len(on_ground), SAMPLE[1]),
                                           replace=False))]
  target = Target(pc2_Mx3, ground2_M, surface2 if len(on_ground) else None)
  identity = motion_from(np.eye(3), np.zeros(3))
  if target.tree is None or len(above) < 3:
    return EgoMotion(identity, 0.0, float("nan"), "zero", {}, note="ego-motion: too few points "
                     f"above the ground ({len(above)} of pc1, {len(target.points)} of pc2) to fit; "
                     "zero motion assumed")
  candidates = {"zero": identity, **(starts or {})}
  if search_start:
    coarse = above[rng.choice(len(above), min(len(above), 600), replace=False)]
    candidates["search"] = search(target, coarse)
  results = {name: icp(target, above, on_ground, m) for name, m in candidates.items()}
  best = max(results, key=lambda k: (round(results[k][1], 3), -results[k][2]))
  motion, fraction, residual = results[best]
  note = None
  if fraction < PLAUSIBLE_INLIERS:
    note = (f"ego-motion: the best rigid fit ({best} start) explains only {100 * fraction:.0f}% "
            "of the points above the ground: are PC1 and PC2 consecutive sweeps of one sensor, "
            "in its own frame? The flows of the static world may be wrong")
  return EgoMotion(motion, fraction, residual, best,
                   {k: (v[0], v[1]) for k, v in results.items()}, note)
