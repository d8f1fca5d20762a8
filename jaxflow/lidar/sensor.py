"""Where a sweep's sensor is in its frame, from the sweep alone.

    position_3, gain = sensor_position(non_ground_Nx3, settings)   # lidar.settings.Sensor

A spinning lidar fires its beams at fixed elevations, so seen from the sensor its points lie on a
few sharp elevation rings; seen from elsewhere (a vehicle frame's origin on the rear axle, near
the road: Argoverse 2's, Waymo's) each ring smears over a band of elevations. The position kept is
the one from which the elevations are least smeared: the entropy of their histogram in fine bins
less that in bins `coarse` times wider (a sharp ring adds nothing to the fine bins' entropy, a
smear adds log `coarse`; the difference does not favour a position seen from which the sweep
spans fewer degrees). Searched on a grid (forward x height, then sideways), then refined axis by
axis (z up). The ground is left out: seen from the road's own height, the whole road lies at one
elevation.
"""

import numpy as np


def _entropy(elevation_deg, bin_deg: float) -> float:
  """The histogram's entropy (nats), with Miller and Madow's correction for the sample's size
  (fine bins hold a few points each: the plain estimate falls with the bins occupied)."""
  counts = np.bincount(np.floor((elevation_deg + 90.0) / bin_deg).astype(np.int64))
  counts = counts[counts > 0]
  share = counts / len(elevation_deg)
  return float(-(share * np.log(share)).sum() + (len(counts) - 1) / (2 * len(elevation_deg)))


def smear(points_Kx3, position_3, settings) -> float:
  """How smeared the points' elevations are seen from `position_3` (0: sharp rings)."""
  offset = points_Kx3 - position_3
  elevation = np.degrees(np.arctan2(offset[:, 2], np.linalg.norm(offset[:, :2], axis=1)))
  return (_entropy(elevation, settings.fine_bin_deg)
          - _entropy(elevation, settings.fine_bin_deg * settings.coarse))


def sensor_position(points_Nx3, settings, seed: int = 0) -> tuple[np.ndarray, float]:
  """(the sensor's position 3, the smear it saves over the frame's origin); the origin when the
  best position saves less than `min_gain` (no rings: not a spinning lidar's sweep) or `find` is
  off."""
  points = np.asarray(points_Nx3, np.float64)
  if not settings.find:
    return np.zeros(3), 0.0
  points = points[np.linalg.norm(points[:, :2], axis=1) > settings.min_range]
  origin = np.zeros(3)
  if len(points) < settings.least_points:
    return origin, 0.0
  if len(points) > settings.sample:
    points = points[np.random.default_rng(seed).choice(len(points), settings.sample, False)]
  at_origin = smear(points, origin, settings)
  (x0, x1, dx), (z0, z1, dz) = settings.search_x, settings.search_z
  grid = [np.array([x, 0.0, z]) for x in np.arange(x0, x1 + 1e-9, dx)
          for z in np.arange(z0, z1 + 1e-9, dz)]
  costs = [smear(points, p, settings) for p in grid]
  best, cost = grid[int(np.argmin(costs))], min(costs)
  y0, y1, dy = settings.search_y  # sensors sit near the centreline: a line, not a third axis
  for y in np.arange(y0, y1 + 1e-9, dy):
    c = smear(points, np.array([best[0], y, best[2]]), settings)
    if c < cost:
      best, cost = np.array([best[0], y, best[2]]), c
  for step in settings.refine_steps:
    improved = True
    while improved:  # axis by axis until no step along any axis lowers the smear
      improved = False
      for axis in range(3):
        for sign in (-1, 1):
          trial = best.copy()
          trial[axis] += sign * step
          c = smear(points, trial, settings)
          if c < cost:
            best, cost, improved = trial, c, True
  gain = at_origin - cost
  return (best, gain) if gain >= settings.min_gain else (origin, gain)
