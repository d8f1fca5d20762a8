"""The ground of raw LiDAR sweeps: one RANSAC plane, or local planes per cell; a range cut.

    plane = fit_ground(points_Nx3, up="z")            # RANSAC plane under the lowest points
    surface = fit_surface(points_Nx3, up="z")         # a plane per 2 m cell: slopes, crowned roads
    ground_N = surface.ground(points_Nx3)             # less than 0.25 m above the ground under it
    surface, ground_N = find_ground(points_Nx3, up="z")   # both: what raw_sweep_flow does
    keep_N = ~ground_N & within_range(points_Nx3, "z", 35.0)

The benchmark layouts remove ground by height (KITTI's camera frame: y < -1.4) and keep 35 m
(the KITTI loader's convention); a raw sweep has neither. `check_up_axis` refuses an up axis
under which the sweep's largest plane, most likely its ground, stands upright; `check_ground`
notes a ground that looks wrong. jaxflow.lidar.sweep uses all of it for the flow of raw sweep
pairs. The tuning is `settings`, jaxflow.lidar.settings.Ground (default: its values).
"""

import dataclasses

import numpy as np

from jaxflow.errors import DataError
from jaxflow.geometry import frames
from jaxflow.lidar.settings import DEFAULTS


def horizontal_range(points_Nx3, up: str = "z") -> np.ndarray:
  """Distance of each point from the sensor in the plane orthogonal to `up` (N)."""
  other = [i for i in range(3) if i != frames.up_index(up)]
  return np.hypot(points_Nx3[:, other[0]], points_Nx3[:, other[1]])


def within_range(points_Nx3, up: str = "z",
                 max_range: float | None = DEFAULTS.max_range):
  """Bool N: horizontal distance below max_range (all True for None or 0)."""
  if not max_range:
    return np.ones(len(points_Nx3), bool)
  return horizontal_range(points_Nx3, up) < max_range


@dataclasses.dataclass(frozen=True)
class Plane:
  """The plane normal . x + offset = 0, normal a unit vector pointing up."""
  normal: np.ndarray  # 3
  offset: float
  inliers: int  # candidate points within the settings' inlier distance of it
  margin: float  # metres above the plane still ground (the settings' margin when fitted)

  def height(self, points_Nx3) -> np.ndarray:
    return np.asarray(points_Nx3, np.float64) @ self.normal + self.offset

  def ground(self, points_Nx3, margin: float | None = None) -> np.ndarray:
    """Bool N: points below `margin` (default the plane's: its settings' margin) above the plane
    (points under it too: noise, kerbs)."""
    return self.height(points_Nx3) < (self.margin if margin is None else margin)

  @property
  def tilt_deg(self) -> float:
    return float(np.degrees(np.arccos(np.clip(np.abs(self.normal).max(), -1.0, 1.0))))


def _candidates(points_Nx3, up: int, settings) -> np.ndarray:
  """Indices of the points within settings.lowest of the lowest point of their horizontal cell."""
  other = [i for i in range(3) if i != up]
  cells = np.floor(points_Nx3[:, other] / settings.cell).astype(np.int64)
  _, cell_N = np.unique(cells, axis=0, return_inverse=True)
  cell_N = cell_N.reshape(-1)
  lowest = np.full(cell_N.max() + 1, np.inf)
  np.minimum.at(lowest, cell_N, points_Nx3[:, up])
  return np.flatnonzero(points_Nx3[:, up] < lowest[cell_N] + settings.lowest)


def _refit(points_Kx3, up_vector) -> tuple[np.ndarray, float]:
  """Least-squares plane through points: the direction of least spread, oriented up."""
  centre = points_Kx3.mean(0)
  normal = np.linalg.svd(points_Kx3 - centre, full_matrices=False)[2][-1]
  normal = normal if normal @ up_vector >= 0 else -normal
  return normal, float(-normal @ centre)


def fit_ground(points_Nx3, up: str = "z",
               max_range: float | None = DEFAULTS.max_range, seed: int = 0,
               name: str = "points", settings=None) -> Plane:
  """The ground plane of a sweep: RANSAC over the lowest points of each horizontal cell.

  Candidates are the points within `lowest` (0.3 m) of the lowest point of their `cell` x `cell`
  (2 m) column, inside `max_range`. `iterations` random triples give planes; those tilted more
  than `max_tilt_deg` from `up` are refused; the plane with most candidates within `inlier`
  (0.1 m) wins and is refitted by least squares to them (twice); the names are the fields of
  `settings`. Seeded: the same sweep gives the same plane. Raises DataError(name) when no plane
  is found (fewer than 3 candidates, or none flat enough).
  """
  settings = DEFAULTS.ground if settings is None else settings
  inlier, max_tilt_deg = settings.inlier, settings.max_tilt_deg
  k = frames.up_index(up)
  points = np.asarray(points_Nx3, np.float64)
  inside = np.flatnonzero(within_range(points, up, max_range))
  cand = points[inside[_candidates(points[inside], k, settings)]] if len(inside) else points[:0]
  if len(cand) < 3:
    raise DataError(name, f"no ground plane: only {len(cand)} points within {max_range} m")
  up_vector = np.eye(3)[k]
  rng = np.random.default_rng(seed)
  triples = cand[rng.integers(0, len(cand), (settings.iterations, 3))]
  normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
  norms = np.linalg.norm(normals, axis=1)
  ok = norms > 1e-9
  normals[ok] /= norms[ok, None]
  normals *= np.where(normals @ up_vector < 0, -1.0, 1.0)[:, None]
  ok &= normals @ up_vector >= np.cos(np.radians(max_tilt_deg))
  if not ok.any():
    raise DataError(name, f"no ground plane within {max_tilt_deg} degrees of the {up} axis among "
                    "the lowest points: is the up axis right?")
  normals, offsets = normals[ok], -np.sum(normals[ok] * triples[ok, 0], axis=1)
  counts = [(np.abs(cand @ n + d) < inlier).sum() for n, d in zip(normals, offsets)]
  best = int(np.argmax(counts))
  normal, offset = normals[best], float(offsets[best])
  for _ in range(2):
    near = np.abs(cand @ normal + offset) < inlier
    if near.sum() < 3:
      break
    normal, offset = _refit(cand[near], up_vector)
  return Plane(normal, offset, int((np.abs(cand @ normal + offset) < inlier).sum()),
               settings.margin)


@dataclasses.dataclass(frozen=True)
class Surface:
  """The ground as a plane per `cell` x `cell` column: height h = a u + b v + c along `up`, (u, v)
  the two other axes in order. `supported`: the cells whose plane rests on ground points nearby."""
  up: int
  cell: float
  origin: np.ndarray  # 2: (u, v) of the corner of cell (0, 0)
  coef_HxWx3: np.ndarray
  supported_HxW: np.ndarray
  margin: float  # metres above the ground still ground (the settings' margin when fitted)

  def _split(self, points_Nx3):
    p = np.asarray(points_Nx3, np.float64)
    other = [i for i in range(3) if i != self.up]
    return p[:, other], p[:, self.up]

  def _cells(self, uv_Nx2):
    ij = np.floor((uv_Nx2 - self.origin) / self.cell).astype(np.int64)
    return np.clip(ij, 0, np.array(self.coef_HxWx3.shape[:2]) - 1)

  def height(self, points_Nx3) -> np.ndarray:
    """Height of each point above the ground under it (N, metres)."""
    uv, h = self._split(points_Nx3)
    ij = self._cells(uv)
    a, b, c = np.moveaxis(self.coef_HxWx3[ij[:, 0], ij[:, 1]], -1, 0)
    return h - (a * uv[:, 0] + b * uv[:, 1] + c)

  def ground(self, points_Nx3, margin: float | None = None) -> np.ndarray:
    """Bool N: points below `margin` (default the surface's: its settings' margin) above the
    ground."""
    return self.height(points_Nx3) < (self.margin if margin is None else margin)

  @property
  def sensor_height(self) -> float:
    """Height of the sensor (the origin) above the ground under it."""
    return float(self.height(np.zeros((1, 3)))[0])

  @property
  def support(self) -> float:
    """Fraction of the height map's occupied cells resting on ground."""
    return float(self.supported_HxW.mean())


def _lowest_per_cell(uv_Nx2, h_N, origin, cell, shape):
  """(flat cell index, u, v, h) of the second-lowest point of every occupied cell (the lowest of
  a single-point cell): one stray point below the ground does not set a cell's height."""
  ij = np.clip(np.floor((uv_Nx2 - origin) / cell).astype(np.int64), 0, np.array(shape) - 1)
  flat = ij[:, 0] * shape[1] + ij[:, 1]
  order = np.lexsort((h_N, flat))
  flat_sorted = flat[order]
  first = np.flatnonzero(np.r_[True, flat_sorted[1:] != flat_sorted[:-1]])
  count = np.diff(np.r_[first, len(order)])
  pick = order[first + (count > 1)]
  return flat[pick], uv_Nx2[pick, 0], uv_Nx2[pick, 1], h_N[pick]


def _window_planes(w_HxW, u_HxW, v_HxW, h_HxW, window: int, max_tilt_deg: float):
  """Weighted least-squares plane of each cell's window: (coef HxWx3, weight sum HxW, ok HxW)."""
  from scipy import ndimage  # pylint: disable=import-outside-toplevel
  terms = [w_HxW, w_HxW * u_HxW, w_HxW * v_HxW, w_HxW * u_HxW * u_HxW, w_HxW * u_HxW * v_HxW,
           w_HxW * v_HxW * v_HxW, w_HxW * h_HxW, w_HxW * u_HxW * h_HxW, w_HxW * v_HxW * h_HxW]
  s, su, sv, suu, suv, svv, sh, suh, svh = (
    ndimage.uniform_filter(t, window, mode="constant") * window * window for t in terms)
  a_HxWx3x3 = np.stack([np.stack([suu, suv, su], -1), np.stack([suv, svv, sv], -1),
                        np.stack([su, sv, s], -1)], -2)
  rhs = np.stack([suh, svh, sh], -1)
  det = np.linalg.det(a_HxWx3x3)
  ok = (s >= 4) & (np.abs(det) > 1e-6 * np.maximum(s, 1) ** 3)
  a_HxWx3x3[~ok] = np.eye(3)
  coef = np.linalg.solve(a_HxWx3x3, rhs[..., None])[..., 0]
  tilt_ok = np.hypot(coef[..., 0], coef[..., 1]) < np.tan(np.radians(max_tilt_deg))
  return coef, s, ok & tilt_ok


def _fit_windows(coef_HxWx3, w_HxW, u_HxW, v_HxW, h_HxW, windows, max_tilt_deg: float):
  """(coef HxWx3, done HxW): each cell's plane from the smallest of `windows` whose fit holds
  (_window_planes), `coef_HxWx3`'s where none does."""
  new, done = coef_HxWx3.copy(), np.zeros(w_HxW.shape, bool)
  for window in windows:
    fitted, _, ok = _window_planes(w_HxW, u_HxW, v_HxW, h_HxW, window, max_tilt_deg)
    take = ok & ~done
    new[take] = fitted[take]
    done |= take
  return new, done


def _lowest_grids(uv_Nx2, h_N, origin, cell: float, n: int):
  """(occupied, u, v, h), each n x n: the cells holding points, and the (u, v, h) of each one's
  lowest point (_lowest_per_cell; 0 in an empty cell)."""
  flat, lu, lv, lh = _lowest_per_cell(uv_Nx2, h_N, origin, cell, (n, n))
  occupied = np.zeros(n * n, bool)
  occupied[flat] = True
  grids = []
  for values in (lu, lv, lh):
    g = np.zeros(n * n)
    g[flat] = values
    grids.append(g.reshape(n, n))
  return (occupied.reshape(n, n), *grids)


def _grow(coef_HxWx3, occupied_HxW, u_HxW, v_HxW, h_HxW, settings):
  """(coef, supported) of the lowest points' surface grown from `coef_HxWx3` round by round: each
  round refits every window to the cells not more than `surface.above` above the current
  surface, until no cell gains support."""
  supported = np.zeros(occupied_HxW.shape, bool)
  for _ in range(settings.surface.rounds):
    residual = h_HxW - (coef_HxWx3[..., 0] * u_HxW + coef_HxWx3[..., 1] * v_HxW
                        + coef_HxWx3[..., 2])
    weight = (occupied_HxW & (residual < settings.surface.above)).astype(np.float64)
    new, done = _fit_windows(coef_HxWx3, weight, u_HxW, v_HxW, h_HxW,
                             tuple(settings.surface.windows), settings.max_tilt_deg)
    grown = (done & ~supported).sum()
    coef_HxWx3, supported = new, done
    if not grown:
      break
  return coef_HxWx3, supported


def _refit_near(surface: Surface, points_Nx3, uv_Nx2, h_N, settings) -> Surface:
  """The surface refitted to the mean of every point near it (|height| < surface.near) in each
  cell, weighted by their count: the lowest points lie low by the noise."""
  n = surface.coef_HxWx3.shape[0]
  near = np.abs(surface.height(points_Nx3)) < settings.surface.near
  ij = surface._cells(uv_Nx2[near])
  flat_near = ij[:, 0] * n + ij[:, 1]
  count = np.bincount(flat_near, minlength=n * n).reshape(n, n).astype(np.float64)
  means = [np.bincount(flat_near, x, minlength=n * n).reshape(n, n) / np.maximum(count, 1)
           for x in (uv_Nx2[near, 0], uv_Nx2[near, 1], h_N[near])]
  # means are reliable: a 3-cell window where it holds
  new, _ = _fit_windows(surface.coef_HxWx3, np.sqrt(count), *means,
                        (3, *settings.surface.windows), settings.max_tilt_deg)
  return Surface(surface.up, surface.cell, surface.origin, new, surface.supported_HxW,
                 settings.margin)


def fit_surface(points_Nx3, up: str = "z", plane: Plane | None = None, name: str = "points",
                extent: float | None = None, cell: float | None = None,
                settings=None) -> Surface:
  """The local ground of a sweep (or of two sweeps put in one frame): per cell, a plane fitted to
  the lowest points of the cells around it, the cells whose lowest point is more than
  `surface.above` above the current surface left out (objects), grown round by round from
  `plane` (default: fit_ground's RANSAC plane within `plane_range` of the sensor) so that slopes
  and crowned roads are followed. A cell too far from any ground keeps the plane of the nearest
  window that has one. `extent`, `cell`: default the settings' surface.extent, surface.cell.
  """
  settings = DEFAULTS.ground if settings is None else settings
  extent = settings.surface.extent if extent is None else extent
  cell = settings.surface.cell if cell is None else cell
  k = frames.up_index(up)
  points = np.asarray(points_Nx3, np.float64)
  plane = plane or fit_ground(points, up, settings.plane_range, name=name, settings=settings)
  other = [i for i in range(3) if i != k]
  uv, h = points[:, other], points[:, k]
  n = int(np.ceil(2 * extent / cell))
  origin = np.full(2, -extent)
  normal = plane.normal
  ref = np.array([-normal[other[0]] / normal[k], -normal[other[1]] / normal[k],
                  -plane.offset / normal[k]])
  coef, supported = _grow(np.broadcast_to(ref, (n, n, 3)).copy(),
                          *_lowest_grids(uv, h, origin, cell, n), settings)
  surface = Surface(k, cell, origin, coef, supported, settings.margin)
  for _ in range(2):
    surface = _refit_near(surface, points, uv, h, settings)
  return surface


def find_ground(points_Nx3, up: str = "z", name: str = "points",
                settings=None) -> tuple[Surface, np.ndarray]:
  """(Surface, ground N bool) of a sweep: fit_ground's plane within `plane_range` (20 m), then
  fit_surface from it (what raw_sweep_flow does to each sweep). Raises fit_ground's DataError
  when the sweep has no ground plane."""
  settings = DEFAULTS.ground if settings is None else settings
  plane = fit_ground(points_Nx3, up, settings.plane_range, name=name, settings=settings)
  surface = fit_surface(points_Nx3, up, plane, name, settings=settings)
  return surface, surface.ground(points_Nx3)


def check_ground(surface: Surface, ground_N, name: str, up: str, points_Nx3=None,
                 settings=None) -> str | None:
  """A ground that looks wrong: more than `max_sensor_height` below the origin or more than
  -`min_sensor_height` above it, or holding more than `max_ground_fraction` of the sweep. Under a
  wrong up axis (a wall taken for the ground) `check_up_axis` on `points_Nx3` raises the error
  that names the right axis; otherwise the problem is returned as a note (None: no problem): a
  frame whose origin lies below the road, or a sweep of an empty car park, is data, not an error."""
  settings = DEFAULTS.ground if settings is None else settings
  lowest, highest = settings.min_sensor_height, settings.max_sensor_height
  height, fraction = surface.sensor_height, float(np.mean(ground_N))
  problem = None
  if not lowest <= height <= highest:
    problem = (f"the ground found along --up {up} lies {height:.1f} m below the origin (a "
               f"sensor's or vehicle's frame puts it {lowest:g} to {highest:g} m below)")
  elif fraction > settings.max_ground_fraction:
    problem = (f"the ground found along --up {up} holds {100 * fraction:.0f}% of the points "
               f"(more than {100 * settings.max_ground_fraction:.0f}%)")
  if problem is None:
    return None
  if points_Nx3 is not None:
    check_up_axis(points_Nx3, up, name, 0.0, settings=settings)
  return f"{name}: {problem}; taken as the ground all the same (a wrong --up?)"


def check_up_axis(points_Nx3, up: str, name: str, ground_fraction: float,
                  seed: int = 0, settings=None) -> str | None:
  """Refuses an up axis perpendicular to the sweep's largest plane when that plane holds a third
  of the points (`up_check.share`) and more than what was taken as ground (`ground_fraction`,
  times `up_check.over_ground`), and lies where a ground would (within `max_sensor_height` of the
  origin): the ground is a sweep's largest plane, a wall rarely is. A perpendicular plane farther
  away (a facade beside a sweep whose ground was removed upstream) gives a note (returned)
  instead: `up` may well be right."""
  settings = DEFAULTS.ground if settings is None else settings
  k = frames.up_index(up)
  p = np.asarray(points_Nx3, np.float64)
  p = p[np.isfinite(p).all(1)]
  if len(p) < 3:
    return None
  rng = np.random.default_rng(seed)
  sample = p[rng.choice(len(p), min(len(p), settings.up_check.points), replace=False)]
  triples = sample[rng.integers(0, len(sample), (settings.up_check.planes, 3))]
  normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
  norms = np.linalg.norm(normals, axis=1)
  ok = norms > 1e-6
  if not ok.any():
    return None
  normals, triples = normals[ok] / norms[ok, None], triples[ok]
  counts = (np.abs((sample[None] - triples[:, None, 0]) @ normals[..., None])[..., 0]
            < settings.inlier).sum(1)
  best = int(np.argmax(counts))
  share = counts[best] / len(sample)
  across = abs(normals[best, k]) < np.cos(np.radians(settings.up_check.tilt_deg))
  if not (share > settings.up_check.share
          and share > settings.up_check.over_ground * ground_fraction and across):
    return None
  along = "xyz"[int(np.argmax(np.abs(normals[best])))]
  distance = abs(float(normals[best] @ triples[best, 0]))  # of the origin from the plane
  if distance <= settings.max_sensor_height:
    raise DataError(name, f"no ground plane across the {up} axis: the sweep's largest plane "
                    f"({100 * share:.0f}% of the points, {distance:.1f} m from the origin) is "
                    f"perpendicular to it, and is most likely the ground: use --up {along} (or "
                    f"--noground_limits, ground_limits=False in Python, if {up} is right)")
  return (f"{name}: its largest plane ({100 * share:.0f}% of the points) is perpendicular to "
          f"--up {up}, {distance:.1f} m from the origin: a wall, if {up} is up (else use --up "
          f"{along})")

