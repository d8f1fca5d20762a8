"""Moving objects of a raw sweep pair: what the ego-motion does not explain, one rigid motion each.

    flow_Nx3, found = object_flow(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion, surface)

With the sensor's motion known (jaxflow.lidar.ego), pc2 is brought into pc1's frame: the static
world then overlaps itself and every moving thing does not. The non-ground points below `object_top`
above the ground are grouped into objects by connectivity seen from above (cells of `cell`); each
object with enough unexplained points (a share of its points, or a count) gets motions from
several starts (standing still, the caller's flow, e.g. the network's, fitted rigidly, and the best
translation of a search over +-`search_per_s` / `frame_rate_hz` m), each refined by a bird's-eye
ICP (yaw and translation, point-to-line: jaxflow.geometry.registration; its height follows the
ground), and keeps the motion that fits pc2 best, standing still unless another fits clearly
better (jaxflow.geometry.groups.beats); a kept motion is refitted on all the object's points.
A walking person moves less a frame than `unexplained`: a group shaped as a person (narrow,
upright, a person's height) first gets the shift of the centroid of pc2's points around it,
kept when it beats standing still by the same rule. An object moved farther than its own width
must land where pc1 saw nothing. A group kept still may join a mover to what stands beside it (a
car passing parked cars): the connected cells of its unexplained points are fitted in turn, each
kept only where it leaves a place pc2 shows empty for one pc1 showed empty. What pc2 saw is
judged from its sensor's place (`sensor2`). Points no object claims keep the ego-motion.
All in z-up coordinates, frame 1. The names are the fields of `settings`,
jaxflow.lidar.settings.Objects (default: its values).
"""

import dataclasses

import numpy as np

from jaxflow.geometry import groups, neighbours, registration, rigid, visibility as views
from jaxflow.lidar import ego
from jaxflow.lidar.settings import DEFAULTS


@dataclasses.dataclass(frozen=True)
class Found:
  """What object_flow did: objects considered, moved, and each moved one's world motion."""
  objects: int
  candidates: int
  moved: list  # (points, translation 3, yaw deg, start name) of each moved object


def _per_point(target: ego.Target, moved_Kx3) -> np.ndarray:
  """Bird's-eye distance (point-to-line, or to a pole) of each point to pc2; inf: no match."""
  rows = target.bev_rows(moved_Kx3)
  out = np.full(len(moved_Kx3), -np.inf)
  np.maximum.at(out, rows.index, np.abs(rows.residual))
  out[out < 0] = np.inf
  return out


def _bev_icp(target: ego.Target, points_Kx3, start: rigid.Motion, settings) -> rigid.Motion:
  """Yaw and horizontal translation of `start` refined seen from above (robust, the scale
  shrinking every 4 rounds: `icp_scales`), `rounds` rounds at most, turning about the object's
  centre."""

  def rows_of(moved_Kx3, scale):
    rows = target.bev_rows(moved_Kx3)
    gate = settings.icp_gate * scale + settings.icp_gate_margin
    return dataclasses.replace(rows, gate=np.abs(rows.residual) < gate)

  last = len(settings.icp_scales) - 1
  scales = [settings.icp_scales[min(i // 4, last)] for i in range(settings.rounds)]
  return registration.robust_fit(points_Kx3, start, rows_of, scales, dof="yaw_xy",
                                 about_centroid=True, damping=1e-3, converged=1e-5)


def _costs(tree, points_Kx3, visibility, to2, truncate) -> np.ndarray:
  """Truncated 3-D distance of each point to ego-compensated pc2, NaN where pc2 could not see it
  (a box slid along its own side still matches seen from above, not in 3-D), in units of
  `truncate` (far objects are sampled sparsely: their distances are larger whatever the motion)."""
  d, _ = tree.nearest(points_Kx3, truncate)
  d = np.minimum(d, truncate) / truncate
  d[visibility.hidden(to2.apply(points_Kx3))] = np.nan
  return d


def _mean(costs, min_seen: float) -> float:
  """A motion's cost: the mean over the visible points (1, the truncation, when fewer than
  `min_seen` of them are)."""
  seen = np.isfinite(costs)
  return float(costs[seen].mean()) if seen.mean() >= min_seen else 1.0


def _rule(settings) -> groups.Rule:
  """The objects block's judgement: a motion beats standing still by `margin`, by
  `relative_margin` of still's cost and by `significance` standard errors."""
  return groups.Rule(settings.margin, settings.relative_margin, settings.significance,
                     settings.min_seen, settings.min_points // 2)


def _clearly_better(base, other, settings) -> bool:
  """groups.beats under the objects block's rule; where pc2 cannot see the base placement (a car
  come nearer along the line of sight hides its old place), the other must fit within
  `hidden_fit` on its own."""
  verdict = groups.beats(base, other, _rule(settings))
  return _mean(other, settings.min_seen) <= settings.hidden_fit if verdict is None else verdict


def _search(tree, points_Kx3, search: float, settings) -> rigid.Motion:
  """The best horizontal translation within +-`search` m (3-D cost; coarse, then fine)."""
  best = np.zeros(3)
  truncate = settings.truncate
  coarse = settings.search_coarse_step
  for half, step in ((search, coarse), (coarse, settings.search_step / 2)):
    steps = np.arange(-half, half + 1e-9, step)
    dx, dy = np.meshgrid(steps, steps, indexing="ij")
    shifts = best + np.c_[dx.ravel(), dy.ravel(), np.zeros(dx.size)]
    d, _ = tree.nearest((points_Kx3[None] + shifts[:, None]).reshape(-1, 3), truncate)
    cost = np.minimum(d, truncate).reshape(len(shifts), -1).mean(1)
    cost += 1e-4 * np.linalg.norm(shifts, axis=1)  # ties: the smaller move
    best = shifts[int(np.argmin(cost))]
  return rigid.Motion(np.eye(3), best)


def _moving_parts(scene, points_Kx3, motion, truncate) -> np.ndarray:
  """Bool K: the points of an object that move with `motion`. A group seen from above can join a
  moving car to the parked car beside it (a gap under two cells): split it by connectivity at
  `part_cell`, without bridging, and keep still every part of `min_points` that standing still
  explains clearly better than the motion (the test the motion passed against it)."""
  s = scene.settings
  parts = groups.cell_components(points_Kx3, np.ones(len(points_Kx3), bool), s.part_cell,
                                 bridge=False)
  keep = np.ones(len(points_Kx3), bool)
  if parts.count < 2:
    return keep
  still = scene.costs(points_Kx3, truncate)
  moving = scene.costs(motion.apply(points_Kx3), truncate)
  for _, mine in parts.members():
    if len(mine) >= s.min_points and _clearly_better(moving[mine], still[mine], s):
      keep[mine] = False
  return keep


def object_groups(points_Nx3, height_N, cell: float | None = None, bridge: bool = True,
                  settings=None) -> groups.Groups:
  """The objects of a sweep: 8-connected occupied cells (default the settings' cell) seen from
  above, from the points between 0 and `object_top` above the ground (gaps of a cell bridged
  unless `bridge` is False); higher points join the object below."""
  settings = DEFAULTS.objects if settings is None else settings
  low = (height_N > 0) & (height_N < settings.object_top)
  return groups.cell_components(points_Nx3, low, settings.cell if cell is None else cell, bridge)


@dataclasses.dataclass(frozen=True)
class _Scene:
  """What every object of a pair is fitted and judged against: pc2 brought into frame 1."""
  target: ego.Target  # pc2 seen from above (the ICP's point-to-line rows)
  tree: neighbours.Tree  # pc2's points above the ground (3-D costs)
  new: np.ndarray  # bool, each of those points: pc1 does not explain it (from above)
  visibility: views.View  # what pc2's sensor saw (a placement it could not see: no evidence)
  ego_motion: rigid.Motion
  search: float  # m: an object's translation search, +- this (a frame's worth of search_per_s)
  max_yaw_deg: float  # degrees an object may turn in a frame
  settings: object  # the objects block

  def costs(self, points_Kx3, truncate: float) -> np.ndarray:
    return _costs(self.tree, points_Kx3, self.visibility, self.ego_motion, truncate)

  def plausible(self, motion: rigid.Motion, points_Kx3) -> bool:
    """No car turns or jumps farther than the limits in a frame."""
    yaw = abs(np.degrees(np.arctan2(motion.rotation[1, 0], motion.rotation[0, 0])))
    centre = points_Kx3.mean(0)
    shift = np.linalg.norm(motion.apply(centre[None])[0] - centre)
    return yaw <= self.max_yaw_deg and shift <= self.search + self.settings.search_slack


def _is_person(idx, pc1_Nx3, height_N, s) -> bool:
  """Whether a group is shaped as a person: narrow from above, upright, a person's height."""
  pts = pc1_Nx3[idx]
  return bool(len(idx) >= s.min_points
              and np.ptp(pts[:, :2], axis=0).max() <= s.person_size
              and s.person_top[0] <= height_N[idx].max() <= s.person_top[1]
              and np.ptp(height_N[idx]) >= s.person_upright)


def _person_shift(scene, pts_Kx3):
  """A person's horizontal motion: the centroid of pc2's points (above the ground, from above
  within `person_radius` of the moved centre and at its height) minus the group's, iterated; None
  when too few points of pc2 are there or the shift is under `person_min_shift`."""
  s = scene.settings
  centre, shift = pts_Kx3.mean(0), np.zeros(3)
  above2 = scene.tree.points
  for _ in range(s.person_rounds):
    d = np.linalg.norm(above2[:, :2] - (centre[:2] + shift[:2]), axis=1)
    near = (d < s.person_radius) & (np.abs(above2[:, 2] - centre[2]) < s.person_top[1] / 2)
    if near.sum() < max(s.person_least_matches, len(pts_Kx3) * s.person_matched_share):
      return None
    shift[:2] = above2[near, :2].mean(0) - centre[:2]
  if np.linalg.norm(shift) < s.person_min_shift:
    return None
  return rigid.Motion(np.eye(3), shift)


def _is_candidate(idx, unexplained_N, height_N, pc1_Nx3, s) -> bool:
  """Whether a group is worth fitting: enough points, enough of them the ego-motion leaves
  unexplained, and not structure (a facade, a tree, one column of a far wall's returns)."""
  if len(idx) < s.min_points or (unexplained_N[idx].mean() < s.min_unexplained
                                 and unexplained_N[idx].sum() < s.many_unexplained):
    return False
  return not (np.ptp(pc1_Nx3[idx, :2], axis=0).max() > s.max_size
              or (height_N[idx] > s.object_top).mean() > s.max_high)


def _novelty(scene, pts_Kx3, motion, truncate) -> float:
  """Share of pc2's points that an object moved by `motion` lands on (within `truncate`) which
  pc1 does not explain where they are: a mover lands where it was not; a piece of still structure
  slid onto more of that structure lands on what pc1 saw there too."""
  d, j = scene.tree.nearest(motion.apply(pts_Kx3), truncate)
  j = np.unique(j[np.isfinite(d)])
  if not len(j):
    return 0.0
  return float(scene.new[j].mean())


def _new_place(scene, pts_Kx3, fit) -> bool:
  """Whether a part's motion takes it from a place pc2 shows empty (mean cost at least `vacated`)
  to one pc1 showed empty (`_novelty`), and the part is object-sized (`part_size` wide)."""
  s = scene.settings
  _, motion, truncate = fit
  return bool(_mean(scene.costs(pts_Kx3, truncate), s.min_seen) >= s.vacated
              and np.ptp(pts_Kx3[:, :2], axis=0).max() >= s.part_size
              and _novelty(scene, pts_Kx3, motion, truncate) >= s.novelty)


def _onto_what_stood(scene, pts_Kx3, fit) -> bool:
  """Whether a motion takes an object farther than its own width onto what pc1 saw there too
  (under `novelty` of the pc2 points it lands on new): a thing slid onto its neighbours. A mover
  that far has left its own place, so where it lands pc1 saw nothing."""
  _, motion, truncate = fit
  centre = pts_Kx3.mean(0)
  shift = np.linalg.norm(motion.apply(centre[None])[0, :2] - centre[:2])
  if shift <= np.ptp(pts_Kx3[:, :2], axis=0).max():
    return False
  return _novelty(scene, pts_Kx3, motion, truncate) < scene.settings.novelty


def _unexplained_parts(idx, unexplained_N, pc1_Nx3, s):
  """Indices of each group of a group's unexplained points (connected cells, no bridging, with
  every point of the group in their cells) of `min_points` or more, but at most `part_share` of
  the group (a larger one is the group again)."""
  seeds = unexplained_N[idx]
  if seeds.sum() < s.min_points:
    return []
  parts = groups.cell_components(pc1_Nx3[idx], seeds, s.cell, bridge=False)
  return [idx[mine] for _, mine in parts.members()
          if s.min_points <= len(mine) <= s.part_share * len(idx)]


def _truncation(pts_Kx3, queries_Qx3, s) -> float:
  """An object's cost truncation (m): `spacings` of its median point spacing (each query's
  nearest other point of the object), within truncate .. max_truncate."""
  spacing = np.median(neighbours.Tree(pts_Kx3).knn(queries_Qx3, 2, distances=True)[0][:, 1])
  return float(np.clip(s.spacings * spacing, s.truncate, s.max_truncate))


def _fit_object(scene: _Scene, pts_Kx3, given_Kx3, rng):
  """(start name, motion, truncation) of an object's best motion, or None when standing still
  is not clearly beaten. `given_Kx3`: where a caller's flow takes the points (frame 1), or None.
  Motions are searched on half the points and judged on the other half: the best of many motions
  fits its own points better than standing still by chance alone."""
  s = scene.settings
  shuffled = pts_Kx3[rng.permutation(len(pts_Kx3))]
  sample, judge = shuffled[0::2][:s.search_points], shuffled[1::2]
  starts = {"search": _search(scene.tree, sample, scene.search, s)}
  if given_Kx3 is not None:
    starts["network"] = rigid.kabsch(pts_Kx3, given_Kx3)
  truncate = _truncation(pts_Kx3, judge, s)
  still_costs = scene.costs(judge, truncate)
  best_name, best, best_costs = "still", rigid.Motion(np.eye(3), np.zeros(3)), still_costs
  for name, start in starts.items():
    for m in (start, _bev_icp(scene.target, sample, start, s)):
      if not scene.plausible(m, judge):
        continue
      c = scene.costs(m.apply(judge), truncate)
      if _mean(c, s.min_seen) < _mean(best_costs, s.min_seen):
        best_name, best, best_costs = name, m, c
  if best_name == "still" or not _clearly_better(still_costs, best_costs, s):
    return None
  refit = _bev_icp(scene.target, pts_Kx3, best, s)  # chosen on halves: now fitted on all points
  if _mean(scene.costs(refit.apply(pts_Kx3), truncate), s.min_seen) <= _mean(
      scene.costs(best.apply(pts_Kx3), truncate), s.min_seen):
    best = refit
  return best_name, best, truncate


def _fit_person(scene, pts_Kx3):
  """("person", shift, truncation) of a person's centroid shift (_person_shift) when it beats
  standing still on the group's points, else None."""
  shift = _person_shift(scene, pts_Kx3)
  if shift is None:
    return None
  s = scene.settings
  truncate = _truncation(pts_Kx3, pts_Kx3, s)
  still = scene.costs(pts_Kx3, truncate)
  if not _clearly_better(still, scene.costs(shift.apply(pts_Kx3), truncate), s):
    return None
  return "person", shift, truncate


def _on_the_ground(motion: rigid.Motion, pts_Kx3, surface) -> rigid.Motion:
  """`motion` with its height following the ground under the object's new place."""
  centre = pts_Kx3.mean(0)
  new_centre = motion.apply(centre[None])[0]
  below = np.r_[new_centre[:2], centre[2]][None]
  rise = surface.height(centre[None])[0] - surface.height(below)[0]
  return rigid.Motion(motion.rotation, motion.translation + [0, 0, rise])


def _low_ground_under(pts_Kx3, pc1_Nx3, ground1_N, height_N, s) -> np.ndarray:
  """Indices of the ground points (higher than `low_ground`) in an object's cells: its own lowest
  points, which fell under the ground's margin."""
  cells = set(map(tuple, np.floor(pts_Kx3[:, :2] / s.cell).astype(np.int64)))
  low = np.flatnonzero(ground1_N & (height_N > s.low_ground))
  if not len(low):
    return low
  keys = np.floor(pc1_Nx3[low, :2] / s.cell).astype(np.int64)
  return low[np.array([tuple(c) in cells for c in keys])]


def object_flow(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion: rigid.Motion, surface=None,
                start_flow_Nx3=None, seed: int = 0, settings=None, ego_settings=None,
                frame_rate_hz: float | None = None, sensor2=None):
  """(flow N x 3 of every pc1 point, Found): the ego-motion flow, and the rigid motion of each
  object the ego-motion does not explain (module docstring). `surface`: the ground in frame 1
  (jaxflow.lidar.ground.Surface; heights and an object's vertical motion); `start_flow_Nx3`: a flow
  to start each object from (e.g. the network's). `settings`: the objects block; `ego_settings`:
  the ego block (pc2's bird's-eye ego.Target); `frame_rate_hz` divides the per-second limits
  (default: the config's); `sensor2`: where pc2's sensor is in its frame (jaxflow.lidar.sensor;
  default the origin), whence what pc2 saw and hid is judged."""
  s = DEFAULTS.objects if settings is None else settings
  rate = DEFAULTS.frame_rate_hz if frame_rate_hz is None else frame_rate_hz
  pc1 = np.asarray(pc1_Nx3, np.float64)
  ground1 = np.asarray(ground1_N, bool)
  flow = ego_motion.flow(pc1).astype(np.float64)
  back = ego_motion.inverse()
  pc2_in1 = back.apply(pc2_Mx3)
  target = ego.Target(pc2_in1, ground2_M, ego_settings)
  above2 = pc2_in1[~np.asarray(ground2_M, bool)]
  if target.tree is None or len(above2) < 3:
    return flow.astype(np.float32), Found(0, 0, [])
  height = surface.height(pc1) if surface is not None else pc1[:, 2] - pc1[ground1, 2].mean() if (
    ground1.any()) else pc1[:, 2] - pc1[:, 2].min()
  found = object_groups(pc1, np.where(ground1, -1.0, height), settings=s).without(ground1)
  unexplained = _per_point(target, pc1) > s.unexplained
  new = _per_point(ego.Target(pc1, ground1, ego_settings), above2) > s.unexplained
  scene = _Scene(target, neighbours.Tree(above2), new,
                 views.View(pc2_Mx3, "z", s.azimuth_bins, s.elevation_bins, s.hidden, sensor2),
                 ego_motion, s.search_per_s / rate, s.max_yaw_deg_per_s / rate, s)
  given = None if start_flow_Nx3 is None else back.apply(
    pc1 + np.asarray(start_flow_Nx3, np.float64))
  rng = np.random.default_rng(seed)
  moved, candidates, still = [], 0, []

  def fit_group(idx, pts):
    fit = _fit_person(scene, pts) if _is_person(idx, pc1, height, s) else None
    if fit is None:
      if not _is_candidate(idx, unexplained, height, pc1, s):
        return None, False
      usable = given is not None and np.isfinite(given[idx]).all()
      fit = _fit_object(scene, pts, given[idx] if usable else None, rng)
    return fit, True

  def apply(idx, pts, fit):
    name, best, truncate = fit
    if surface is not None:
      best = _on_the_ground(best, pts, surface)
    parts = _moving_parts(scene, pts, best, truncate)
    idx, pts = idx[parts], pts[parts]
    flow[idx] = best.then(ego_motion).flow(pts)
    yaw = float(np.degrees(np.arctan2(best.rotation[1, 0], best.rotation[0, 0])))
    moved.append((len(idx), best.translation, yaw, name))
    if surface is not None:
      low = _low_ground_under(pts, pc1, ground1, height, s)
      flow[low] = best.then(ego_motion).flow(pc1[low])

  for _, idx in found.members():
    fit, tried = fit_group(idx, pc1[idx])
    candidates += tried
    if fit is not None and _onto_what_stood(scene, pc1[idx], fit):
      fit = None
    if fit is None:
      still.append(idx)
    else:
      apply(idx, pc1[idx], fit)
  # A group kept still may join a mover to what stands beside it (a car passing parked cars): its
  # unexplained points' own groups are fitted in turn.
  for idx in still:
    for part in _unexplained_parts(idx, unexplained, pc1, s):
      fit, tried = fit_group(part, pc1[part])
      candidates += tried
      if fit is not None and _new_place(scene, pc1[part], fit):
        apply(part, pc1[part], fit)
  return flow.astype(np.float32), Found(found.count, candidates, moved)
