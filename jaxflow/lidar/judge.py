"""How a placement of an object is judged against pc2: per-point costs, and the rule another
placement must pass to replace one (jaxflow.lidar.objects, jaxflow.lidar.along).

    c = costs(tree, points_Kx3, view, ego_motion, truncation(points_Kx3, points_Kx3, settings))
    clearly_better(still_costs, moved_costs, settings)   # moved replaces standing still

`settings` is the objects block (jaxflow.lidar.settings.Objects); the names are fields of its
`judge` block (Judge), but `min_points`. Evidence: the same question asked of point-to-plane
residuals in units of the pair's own noise, whose sum grows with the points (a slow mover's).
"""

import numpy as np

from jaxflow.geometry import groups, neighbours, rigid


def costs(tree, points_Kx3, visibility, to2, truncate) -> np.ndarray:
  """Truncated 3-D distance of each point to ego-compensated pc2, NaN where pc2 could not see it
  (a box slid along its own side still matches seen from above, not in 3-D), in units of
  `truncate` (far objects are sampled sparsely: their distances are larger whatever the motion)."""
  d, _ = tree.nearest(points_Kx3, truncate)
  d = np.minimum(d, truncate) / truncate
  d[visibility.hidden(to2.apply(points_Kx3))] = np.nan
  return d


def mean(costs, min_seen: float) -> float:
  """A motion's cost: the mean over the visible points (1, the truncation, when fewer than
  `min_seen` of them are)."""
  seen = np.isfinite(costs)
  return float(costs[seen].mean()) if seen.mean() >= min_seen else 1.0


def rule(settings) -> groups.Rule:
  """The objects block's judgement: a motion beats standing still by `margin`, by
  `relative_margin` of still's cost and by `significance` standard errors."""
  judging = settings.judge
  return groups.Rule(judging.margin, judging.relative_margin, judging.significance,
                     judging.min_seen, settings.min_points // 2)


def clearly_better(base, other, settings) -> bool:
  """groups.beats under the objects block's rule; where pc2 cannot see the base placement (a car
  come nearer along the line of sight hides its old place), the other must fit within
  `hidden_fit` on its own."""
  verdict = groups.beats(base, other, rule(settings))
  judging = settings.judge
  return mean(other, judging.min_seen) <= judging.hidden_fit if verdict is None else verdict


def truncation(pts_Kx3, queries_Qx3, s) -> float:
  """An object's cost truncation (m): `spacings` of its median point spacing (each query's
  nearest other point of the object), within truncate .. max_truncate."""
  spacing = np.median(neighbours.Tree(pts_Kx3).knn(queries_Qx3, 2, distances=True)[0][:, 1])
  judging = s.judge
  return float(np.clip(judging.spacings * spacing, judging.truncate, judging.max_truncate))


def shift_from_above(points_Kx3, motion) -> float:
  """How far `motion` moves the points' centre, seen from above (m)."""
  centre = points_Kx3.mean(0)
  return float(np.linalg.norm(motion.apply(centre[None])[0, :2] - centre[:2]))


class Evidence:
  """pc2's local planes (frame 1; each from its `judge.plane_points` nearest, computed where first
  asked) and the pair's noise: how far its static world's points lie from them. A placement's
  evidence is its point-to-plane residuals in units of that noise, so that it grows with the
  points: a slow mover's leading and trailing faces, hundreds of points a few noises off when
  standing still, outweigh anything that chance gives a handful of points. Where pc2's
  neighbours of a point lie along one line (a ring across a near car's flank: its rings are far
  apart, its points along a ring close), there is no plane, and that point says nothing."""

  def __init__(self, tree, visibility, to2, settings):
    self.tree, self.visibility, self.to2 = tree, visibility, to2
    self.neighbours, self.surface = settings.judge.plane_points, settings.judge.surface
    self.normals = np.full((len(tree.points), 3), np.nan)
    self.planar = np.zeros(len(tree.points), bool)
    self.noise = np.nan

  def distance(self, points_Kx3, reach: float) -> np.ndarray:
    """Per point: the distance to the plane of its nearest pc2 point (inf: none within `reach`;
    NaN: that point's neighbours lie along a line, no plane)."""
    d, j = self.tree.nearest(points_Kx3, reach)
    near = np.isfinite(d)
    j = np.where(near, j, 0)
    todo = np.unique(j[near])
    todo = todo[np.isnan(self.normals[todo, 0])]
    if len(todo):
      nb = self.tree.points[self.tree.knn(self.tree.points[todo], self.neighbours)]
      centred = nb - nb.mean(1, keepdims=True)
      spread, axes = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
      self.normals[todo] = axes[:, :, 0]
      self.planar[todo] = spread[:, 1] >= self.surface * spread[:, 2]
    gap = np.abs(np.sum((points_Kx3 - self.tree.points[j]) * self.normals[j], 1))
    return np.where(near, np.where(self.planar[j], gap, np.nan), np.inf)

  def measure_noise(self, static_Kx3, s) -> float:
    """The pair's noise (m): 1.4826 x the median point-to-plane residual of points the ego-motion
    explains (a Gaussian's sigma from its median absolute value), at least `noise_floor`."""
    r = self.distance(static_Kx3, s.judge.truncate)
    r = r[np.isfinite(r)]
    self.noise = float(max(s.judge.noise_floor, 1.4826 * np.median(r) if len(r) else np.inf))
    return self.noise

  def gains(self, points_Kx3, moved_Kx3, reach: float, s):
    """(bool K: the points seen in both placements whose nearest pc2 point within `reach`, in
    both, has a plane (or there is none: capped), and per such point standing still's squared
    residual minus the moved one's, each capped at `noise_cap` noises, in squared noises)."""
    cap = s.judge.noise_cap
    seen = ~self.visibility.hidden(self.to2.apply(points_Kx3)) & ~self.visibility.hidden(
      self.to2.apply(moved_Kx3))
    still = np.full(len(points_Kx3), np.nan)
    moved = still.copy()
    still[seen] = np.minimum(self.distance(points_Kx3[seen], reach) / self.noise, cap) ** 2
    moved[seen] = np.minimum(self.distance(moved_Kx3[seen], reach) / self.noise, cap) ** 2
    seen &= ~np.isnan(still) & ~np.isnan(moved)
    return seen, still[seen] - moved[seen]

  def against(self, points_Kx3, motion, reach: float, s) -> np.ndarray:
    """Bool K: the points of a slow mover whose neighbourhood (within the objects' `cell`, among
    `points_Kx3`) fits standing still better than `motion` by a noise squared a point or more on
    average: static things beside a walker or a creeping car, which a group from above joins
    to it (the mover's own faces gain, its sides gain nothing either way)."""
    seen, gain_seen = self.gains(points_Kx3, motion.apply(points_Kx3), reach, s)
    gain = np.full(len(points_Kx3), np.nan)
    gain[seen] = gain_seen
    if not seen.any():
      return np.zeros(len(points_Kx3), bool)
    near = neighbours.Tree(points_Kx3[seen]).kd.query_ball_point(points_Kx3, s.cell)
    total = np.array([gain[seen][n].sum() if len(n) else 0.0 for n in near])
    count = np.array([len(n) for n in near])
    return (count > 0) & (total <= -np.maximum(count, 1))

  def beats_still(self, points_Kx3, motion, reach: float, s) -> bool:
    """Whether `motion` beats standing still by the evidence of `points_Kx3` (Judge.evidence):
    it moves their centre at most `slow` m, and the gains add up to `evidence` at `significance`
    standard errors, on `min_seen` of the points seen in both placements."""
    if not s.judge.evidence or not np.isfinite(self.noise):
      return False
    if shift_from_above(points_Kx3, motion) > s.judge.slow:
      return False
    gain = self.gains(points_Kx3, motion.apply(points_Kx3), reach, s)[1]
    if len(gain) < max(s.min_points // 2, s.judge.min_seen * len(points_Kx3)):
      return False
    error = gain.std() / np.sqrt(len(gain))
    return bool(gain.sum() >= s.judge.evidence and gain.mean() >= s.judge.significance * error)

  def cost(self, points_Kx3, reach: float, s) -> float:
    """The capped squared point-to-plane residuals of `points_Kx3`, summed, in squared noises (a
    point on no plane costs the cap: a placement onto pc2's ring lines earns nothing)."""
    r = np.nan_to_num(self.distance(points_Kx3, reach) / self.noise, nan=np.inf)
    return float(np.sum(np.minimum(r, s.judge.noise_cap) ** 2))

  def refine(self, points_Kx3, motion, reach: float, s, rounds: int = 8):
    """`motion` with its horizontal translation refined point-to-plane against pc2's planes
    (Gauss-Newton, residuals gated from `reach` down to `noise_cap` noises): the search's grid
    and a bird's-eye ICP stop a slow mover a grid step short, and only its faces, a few noises
    off, say where it is. Kept only where its capped cost is lower."""
    best, best_cost = motion, self.cost(motion.apply(points_Kx3), reach, s)
    shift = np.array(motion.translation, np.float64)
    floor = s.judge.noise_cap * self.noise
    for k in range(rounds):
      gate = max(floor, reach * 0.5 ** k)
      moved = points_Kx3 @ motion.rotation.T + shift
      d, j = self.tree.nearest(moved, gate)
      near = np.isfinite(d)
      if near.sum() < 3:
        break
      self.distance(moved[near], gate)  # the normals where first asked
      n = self.normals[j[near]]
      r = np.sum((moved[near] - self.tree.points[j[near]]) * n, 1)
      use = (np.abs(r) < gate) & self.planar[j[near]]
      a = n[use, :2]
      if len(a) < 3:
        break
      step = np.linalg.lstsq(a.T @ a + 1e-6 * np.eye(2), -a.T @ r[use], rcond=None)[0]
      shift[:2] += step
    candidate = rigid.Motion(motion.rotation, shift)
    if self.cost(candidate.apply(points_Kx3), reach, s) < best_cost:
      best = candidate
    return best
