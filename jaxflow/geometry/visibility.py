"""What a sensor at the origin saw: its nearest return per direction (a coarse range image) and
the extent of its view, so that a point moved into its frame can be told SEEN (the sensor looked at
least that far there, an empty direction inside the view included), HIDDEN (behind a nearer
return: it neither supports nor refutes a motion) or OUTSIDE the view (a camera's edge, the range
cut). Used by jaxflow.lidar.objects (raw sweeps, z up) and jaxflow.refine.bodies (the model frame, y up)."""

import numpy as np

from jaxflow.geometry import frames

SEEN, HIDDEN, OUTSIDE = range(3)


def _axes(up: str) -> tuple[int, int, int]:
  """(azimuth's sine axis, its cosine axis, the up axis): (left, forward, up) of the frame."""
  forward, left, up_axis = frames.permutation(up, "z")
  return left, forward, up_axis


class View:
  """The returns `points_Mx3` of one sensor at `origin` (default the frame's), binned by azimuth x
  elevation about `up`."""

  def __init__(self, points_Mx3, up: str = "z", azimuth_bins: int = 360,
               elevation_bins: int = 180, hidden: float = 0.5, origin=None):
    self.axes, self.bins, self.hidden_by = _axes(up), (azimuth_bins, elevation_bins), hidden
    self.origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    points = np.asarray(points_Mx3, np.float64)
    key, r, azimuth, elevation = self._directions(points)
    self.nearest = np.full(azimuth_bins * elevation_bins, np.inf)
    np.minimum.at(self.nearest, key, r)
    self.extent = ((*np.quantile(azimuth, [0.001, 0.999]), *np.quantile(elevation, [0.001, 0.999]),
                    r.max()) if len(points) else (0.0, 0.0, 0.0, 0.0, 0.0))

  def _directions(self, points_Kx3):
    a, b, up = self.axes
    points_Kx3 = points_Kx3 - self.origin
    r = np.linalg.norm(points_Kx3, axis=1)
    azimuth = np.arctan2(points_Kx3[:, a], points_Kx3[:, b])
    elevation = np.arcsin(np.clip(points_Kx3[:, up] / np.maximum(r, 1e-9), -1, 1))
    columns, rows = self.bins
    i = np.clip(((azimuth + np.pi) / (2 * np.pi) * columns).astype(np.int64), 0, columns - 1)
    j = np.clip(((elevation + np.pi / 2) / np.pi * rows).astype(np.int64), 0, rows - 1)
    return i * rows + j, r, azimuth, elevation

  def hidden(self, points_Kx3) -> np.ndarray:
    """Behind the sensor's return in their direction by more than `hidden` metres."""
    key, r, _, _ = self._directions(np.asarray(points_Kx3, np.float64))
    return self.nearest[key] < r - self.hidden_by

  def state(self, points_Kx3) -> np.ndarray:
    """SEEN, HIDDEN or OUTSIDE for each point (in the sensor's coordinates)."""
    points = np.asarray(points_Kx3, np.float64)
    key, r, azimuth, elevation = self._directions(points)
    lo_az, hi_az, lo_el, hi_el, far = self.extent
    outside = (azimuth < lo_az) | (azimuth > hi_az) | (elevation < lo_el) | (elevation > hi_el) | (
      r > far)
    hidden = self.nearest[key] < r - self.hidden_by
    return np.where(outside, OUTSIDE, np.where(hidden, HIDDEN, SEEN))
