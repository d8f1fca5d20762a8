"""The sensor's own motion between two raw sweeps: GICP (small_gicp) from several starts, the
result chosen by how well it explains the static world.

    ego = estimate(pc1_Nx3, pc2_Mx3)                  # z up; ground kept or removed
    static_flow_Nx3 = ego.motion.flow(pc1_Nx3)

Registration is small_gicp's generalized ICP on all the points (ground included, when the sweep
has one), coarse to fine (`gicp.scales`: voxel size, neighbours for each point's covariance, largest
match). Covariances from 20-30 neighbours of a voxelled cloud matter on real sweeps: with 10
neighbours of 0.25 m voxels a neighbourhood is often one beam's ring, whose covariance pulls the
two sweeps' ring patterns together (0.17 m of false height on a real Argoverse 2 pair with its
ground removed; benchmarks/REAL_SWEEPS.md). Starts: zero, the caller's (e.g. the network's
dominant motion) and the best of a coarse yaw x translation grid seen from above (`search`).
Every start's result and zero motion itself are candidates, and the best of them refitted on the
points it explains (GICP has no robust loss: traffic beside the sensor pulls it), and (the
raw-sweep pipeline's) GICP refitted on the points the search's start explains (where that traffic
pulls GICP off from any start); the one with the least static residual (`Residual`: truncated
point-to-plane distance of pc1 to pc2's local planes) is returned, so a fit that explains the
world worse than standing still never is. The tuning is `settings`, jaxflow.lidar.settings.Ego
(default: its values); the search's per-second motions are divided by `frame_rate_hz` (default the
settings', 10 Hz).
"""

import dataclasses

import numpy as np
import small_gicp

from jaxflow.geometry import neighbours, registration, rigid
from jaxflow.lidar.settings import DEFAULTS

# small_gicp on one thread: its parallel sums differ by rounding from run to run (1 of 320k flow
# values by 1e-8 under load), and the same call must give the same flow (2.0 s a pair, 1.55 s on 2).
GICP_THREADS = 1


@dataclasses.dataclass(frozen=True)
class EgoMotion:
  """The sensor's motion (frame-1 -> frame-2 coordinates), how well it explains the sweeps, and
  every candidate's result (name -> (Motion, inlier fraction))."""
  motion: rigid.Motion
  inlier_fraction: float  # of pc1's voxels within `inlier` of pc2's local planes after the motion
  residual: float  # metres: mean truncated point-to-plane residual of those voxels
  start: str  # the chosen candidate ("zero", "search+gicp", "network+gicp", ...)
  starts: dict
  note: str | None = None  # set when the fit is implausible


def _rate(frame_rate_hz):
  """The frame rate given, or the config's (10 Hz)."""
  return DEFAULTS.frame_rate_hz if frame_rate_hz is None else frame_rate_hz


def search_grid(lowest_highest_step, frame_rate_hz: float) -> np.ndarray:
  """The values of a per-second (lowest, highest, step) a frame: both ends included."""
  lowest, highest, step = (v / frame_rate_hz for v in lowest_highest_step)
  return np.arange(lowest, highest + step / 2, step)


def yaw_motion(yaw_deg: float, x: float, y: float) -> rigid.Motion:
  c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
  return rigid.Motion.of([[c, -s, 0], [s, c, 0], [0, 0, 1]], [x, y, 0.0])


def _matrix(motion: rigid.Motion) -> np.ndarray:
  t = np.eye(4)
  t[:3, :3], t[:3, 3] = motion.rotation, motion.translation
  return t


class Registration:
  """pc1 and pc2 voxelled once per scale (small_gicp's clouds with covariances and pc2's k-d
  tree), for GICP from several starts and for the static residual."""

  def __init__(self, pc1_Nx3, pc2_Mx3, _targets=None, settings=None):
    self.pc1 = np.ascontiguousarray(pc1_Nx3, np.float64)
    self.pc2 = np.ascontiguousarray(pc2_Mx3, np.float64)
    self.settings = DEFAULTS.ego if settings is None else settings
    self._sources, self._targets = {}, {} if _targets is None else _targets

  def clouds(self, voxel: float, count: int):
    """(pc1's cloud, pc2's cloud, pc2's tree) at this voxel size, covariances of `count`
    neighbours."""
    key = voxel, count
    if key not in self._sources:
      self._sources[key] = small_gicp.preprocess_points(
        self.pc1, downsampling_resolution=voxel, num_neighbors=count,
        num_threads=GICP_THREADS)[0]
    if key not in self._targets:
      self._targets[key] = small_gicp.preprocess_points(
        self.pc2, downsampling_resolution=voxel, num_neighbors=count,
        num_threads=GICP_THREADS)
    return self._sources[key], *self._targets[key]

  def gicp(self, start: rigid.Motion, scales=None) -> rigid.Motion:
    """small_gicp's GICP of pc1 onto pc2 from `start`, one pass per scale (coarse to fine;
    default the settings' scales)."""
    transform = _matrix(start)
    for voxel, count, match in self.settings.gicp.scales if scales is None else scales:
      source, target, tree = self.clouds(voxel, count)
      if target.size() < count or source.size() < count:
        break
      result = small_gicp.align(target, source, tree, init_T_target_source=transform,
                                registration_type="GICP", max_correspondence_distance=match,
                                num_threads=GICP_THREADS,
                                max_iterations=self.settings.gicp.iterations)
      transform = result.T_target_source
    return rigid.Motion.of(transform[:3, :3], transform[:3, 3])

  def trimmed(self, motion: rigid.Motion, residual: "Residual") -> rigid.Motion:
    """GICP's finer passes again on the pc1 points within `inlier` of pc2's surfaces after
    `motion`, `gicp.trim_rounds` times: GICP has no robust loss, so a bus passing beside the
    sensor in a narrow street can pull it off (0.45 m on a generated city pair; 8 mm trimmed)."""
    scales, inlier = self.settings.gicp.scales, self.settings.inlier
    for _ in range(self.settings.gicp.trim_rounds):
      kept = residual.per_point(motion, self.pc1) < inlier
      if kept.sum() < min_points(self.settings):
        break
      motion = Registration(self.pc1[kept], self.pc2, self._targets, self.settings).gicp(
        motion, scales[1:])
    return motion

  def residual(self) -> "Residual":
    source, target, _ = self.clouds(self.settings.residual_voxel,
                                    self.settings.residual_neighbours)
    return Residual(source.points()[:, :3], target.points()[:, :3], target.normals()[:, :3],
                    self.settings)


class Residual:
  """The static residual of a motion: pc1's voxel centres moved, each one's distance to the
  local plane of its nearest pc2 voxel (small_gicp's normals), at most `truncate`, matched
  within 3 x `truncate` (Registration.residual)."""

  def __init__(self, source_Kx3, target_Lx3, normals_Lx3, settings=None):
    self.source = source_Kx3
    self.target = registration.PlaneTarget(target_Lx3, normals_Lx3)
    settings = DEFAULTS.ego if settings is None else settings
    self.truncate, self.inlier = settings.truncate, settings.inlier

  def per_point(self, motion: rigid.Motion, points_Kx3=None) -> np.ndarray:
    """Truncated point-to-plane distance of each of pc1's voxels, or of `points_Kx3` (`truncate`:
    no match)."""
    points = self.source if points_Kx3 is None else points_Kx3
    return self.target.plane_distance(motion.apply(points), self.truncate, 3 * self.truncate)

  def __call__(self, motion: rigid.Motion) -> tuple[float, float]:
    """(mean residual, fraction within `inlier`)."""
    r = self.per_point(motion)
    return (float(r.mean()), float((r < self.inlier).mean())) if len(r) else (self.truncate, 0.0)


class Target:
  """pc2 prepared once: a bird's-eye k-d tree of its non-ground points with each one's line
  direction (or none: a blob). jaxflow.lidar.objects's residuals and the coarse `search`."""

  def __init__(self, pc2_Mx3, ground2_M=None, settings=None):
    settings = DEFAULTS.ego if settings is None else settings
    k, self.max_match = settings.search.neighbours, settings.search.max_match
    above = np.asarray(pc2_Mx3, np.float64)
    if ground2_M is not None:
      above = above[~np.asarray(ground2_M, bool)]
    if len(above):  # seen from above, a wall's rings stack: one point a `bev_cell` cell (the mean)
      cells = np.floor(above[:, :2] / settings.search.bev_cell).astype(np.int64)
      _, inverse, count = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
      inverse = inverse.reshape(-1)
      above = np.stack([np.bincount(inverse, above[:, i]) / count for i in range(3)], 1)
    self.points = above
    self.tree = neighbours.Tree(above[:, :2]) if len(above) else None
    self.normal_Mx2 = np.zeros((len(above), 2))
    self.line_M = np.zeros(len(above), bool)
    self.usable_M = np.ones(len(above), bool)
    if len(above) > k:
      values, vectors = neighbours.local_spread(above[:, :2], k, self.tree)
      self.normal_Mx2 = vectors[:, :, 0]  # least spread: across the line
      self.line_M = values[:, 0] < settings.search.line ** 2 * np.maximum(values[:, 1], 1e-12)
      # Neither a line nor a small blob (a pole): an area seen from above (a tree's crown, a
      # roof), whose visible rim moves with the sensor: no residual there.
      self.usable_M = self.line_M | (values[:, 1] < settings.search.blob ** 2 * k)

  def bev_rows(self, moved_Kx3) -> registration.Rows:
    """Residual rows seen from above: one row a matched point with a line (across it), two rows
    for a blob (x and y); matches beyond `max_match` are left out."""
    if self.tree is None or not len(moved_Kx3):
      return registration.Rows(np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64))
    dist, j = self.tree.nearest(moved_Kx3[:, :2], self.max_match)
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
    return registration.Rows(np.concatenate(rows_r), np.concatenate(rows_n),
                             np.concatenate(rows_i))


def search(target: Target, above_Kx3, scale: float = 0.5, settings=None,
           frame_rate_hz: float | None = None) -> rigid.Motion:
  """The best yaw x forward x lateral motion of a coarse grid (the settings' search.*_per_s a
  frame): the least mean bird's-eye distance of the moved points to pc2's, each at most `scale`
  (one k-d tree query for the whole grid)."""
  settings, rate = DEFAULTS.ego if settings is None else settings, _rate(frame_rate_hz)
  yaw, x, y = np.meshgrid(np.radians(search_grid(settings.search.yaw_deg_per_s, rate)),
                          search_grid(settings.search.x_per_s, rate),
                          search_grid(settings.search.y_per_s, rate), indexing="ij")
  yaw, x, y = yaw.ravel(), x.ravel(), y.ravel()
  c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
  px, py = above_Kx3[None, :, 0], above_Kx3[None, :, 1]
  moved = np.stack([c * px - s * py + x[:, None], s * px + c * py + y[:, None]], -1)
  d, _ = target.tree.nearest(moved.reshape(-1, 2), scale)
  cost = np.minimum(d, scale).reshape(len(yaw), -1).mean(1)
  best = int(np.argmin(cost))  # the first of equal costs: the grid's order, as a loop would
  return yaw_motion(float(np.degrees(yaw[best])), float(x[best]), float(y[best]))


def min_points(settings) -> int:
  """The fewest points GICP fits (a lidar.settings.Ego): three times the neighbours a point takes
  in its finest pass."""
  return 3 * settings.gicp.scales[-1][1]


def estimate(pc1_Nx3, pc2_Mx3, ground1_N=None, ground2_M=None, starts=None, seed: int = 0,
             search_start: bool = True, settings=None, frame_rate_hz: float | None = None,
             refit_search: bool = False) -> EgoMotion:
  """The ego-motion of two z-up sweeps (module docstring). `starts`: extra named start motions
  (e.g. {"network": Motion}); `ground1_N`, `ground2_M` (optional): ground points, left out of the
  coarse search seen from above (GICP uses every point); `refit_search`: GICP refitted on the
  points the search's start explains is one more candidate (the raw-sweep pipeline's; not yet
  measured for optimise's world stage, which registers without it)."""
  settings = DEFAULTS.ego if settings is None else settings
  pc1 = np.asarray(pc1_Nx3, np.float64)
  pc2 = np.asarray(pc2_Mx3, np.float64)
  identity = rigid.Motion.of(np.eye(3), np.zeros(3))
  if min(len(pc1), len(pc2)) < min_points(settings):
    return EgoMotion(identity, 0.0, float("nan"), "zero", {}, note="ego-motion: too few points "
                     f"({len(pc1)} in pc1, {len(pc2)} in pc2) to fit; zero motion assumed")
  registration = Registration(pc1, pc2, settings=settings)
  residual = registration.residual()
  candidates = {"zero": identity}
  begin = {"zero": identity, **(starts or {})}
  if search_start:
    above1 = pc1 if ground1_N is None else pc1[~np.asarray(ground1_N, bool)]
    target = Target(pc2, ground2_M, settings)
    if len(above1) >= 3 and target.tree is not None:
      rng = np.random.default_rng(seed)
      sample = min(len(above1), settings.search.sample)
      coarse = above1[rng.choice(len(above1), sample, replace=False)]
      begin["search"] = search(target, coarse, settings=settings, frame_rate_hz=frame_rate_hz)
  for name, start in begin.items():
    candidates[f"{name}+gicp"] = registration.gicp(start)
  if refit_search and "search" in begin:  # GICP refitted on what the search's start explains:
    # cars passing beside the sensor (a sixth of a narrow street's points) pull GICP of every
    # point 0.64 m off the true motion, from any start (a generated city test pair).
    candidates["search+trimmed"] = registration.trimmed(begin["search"], residual)
  results = {name: (m, *residual(m)) for name, m in candidates.items()}
  best = min(results, key=lambda k: results[k][1])
  if best != "zero":  # the best fit refined on its inliers: one more candidate
    trimmed = registration.trimmed(results[best][0], residual)
    results[f"{best}+trimmed"] = (trimmed, *residual(trimmed))
    best = min(results, key=lambda k: results[k][1])
  motion, cost, fraction = results[best]
  note = None
  if fraction < settings.plausible_inliers:
    note = (f"ego-motion: the best rigid fit ({best}) explains only {100 * fraction:.0f}% "
            "of the points: are PC1 and PC2 consecutive sweeps of one sensor, in its own frame? "
            "The flows of the static world may be wrong")
  return EgoMotion(motion, fraction, cost, best, {k: (v[0], v[2]) for k, v in results.items()},
                   note)
