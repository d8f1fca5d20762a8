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
better; a kept motion is refitted on all the object's points. Points no object claims keep the
ego-motion. All in z-up coordinates, frame 1. The names are the fields of `settings`, the
`objects` block of jaxflow/configs/sweep.py (default: its values).
"""

import dataclasses

import numpy as np
from scipy import ndimage

from jaxflow.configs import sweep as sweep_config
from jaxflow.geometry import neighbours, registration, rigid, visibility as views
from jaxflow.lidar import ego


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


def _better(still, moved, settings) -> bool:
  """Whether a motion's costs beat standing still's clearly: by `margin`, by `relative_margin` of
  still's cost, and by `significance` standard errors of the paired difference; where pc2 cannot
  see the object standing still (a car come nearer along the line of sight hides its old place),
  the motion alone must fit within `hidden_fit`."""
  min_seen = settings.min_seen
  if _mean(moved, min_seen) >= 1.0:
    return False
  if np.isfinite(still).mean() < min_seen:  # standing still, pc2 cannot see it: no evidence
    return _mean(moved, min_seen) <= settings.hidden_fit  # either way; it must fit on its own
  both = np.isfinite(still) & np.isfinite(moved)
  if both.sum() < settings.min_points // 2:
    return False
  diff = still[both] - moved[both]
  gain = diff.mean()
  error = diff.std() / np.sqrt(len(diff))
  return (gain >= max(settings.margin, settings.relative_margin * still[both].mean())
          and gain >= settings.significance * error)


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


def _moving_parts(tree, points_Kx3, motion, visibility, ego_motion, truncate,
                  settings) -> np.ndarray:
  """Bool K: the points of an object that move with `motion`. A group seen from above can join a
  moving car to the parked car beside it (a gap under two cells): split it by connectivity at
  `part_cell`, without bridging, and keep still every part of `min_points` that standing still
  explains clearly better than the motion (`_better`, the test a motion passed against it)."""
  part, count = cell_components(points_Kx3, np.ones(len(points_Kx3), bool), settings.part_cell,
                                bridge=False)
  keep = np.ones(len(points_Kx3), bool)
  if count < 2:
    return keep
  still = _costs(tree, points_Kx3, visibility, ego_motion, truncate)
  moving = _costs(tree, motion.apply(points_Kx3), visibility, ego_motion, truncate)
  for k in range(count):
    mine = part == k
    if mine.sum() >= settings.min_points and _better(moving[mine], still[mine], settings):
      keep[mine] = False
  return keep


def cell_components(points_Nx3, seeds_N, cell: float, bridge: bool):
  """(label N, count): the 8-connected components of the cells (of `cell` m, seen from above) that
  the `seeds_N` points occupy, gaps of one cell bridged when `bridge`; every point in a
  component's cells gets its label (0 .. count - 1), the others -1."""
  ij = np.floor(points_Nx3[:, :2] / cell).astype(np.int64)
  if not seeds_N.any():
    return np.full(len(points_Nx3), -1), 0
  ij = ij - ij[seeds_N].min(0)
  shape = ij[seeds_N].max(0) + 1
  inside = (ij >= 0).all(1) & (ij < shape).all(1)
  grid = np.zeros(shape, bool)
  grid[ij[seeds_N, 0], ij[seeds_N, 1]] = True
  if bridge:
    grid = ndimage.binary_dilation(grid, np.ones((3, 3)))
  labels, count = ndimage.label(grid, np.ones((3, 3)))
  out = np.full(len(points_Nx3), -1)
  out[inside] = labels[ij[inside, 0], ij[inside, 1]] - 1
  return out, count


def groups(points_Nx3, height_N, cell: float | None = None, bridge: bool = True, settings=None):
  """Object label of each point (-1: none) by 8-connected occupied cells (default the settings'
  cell) seen from above, from the points between 0 and `object_top` above the ground (gaps of a
  cell bridged unless `bridge` is False); higher points join the object below."""
  settings = sweep_config.block("objects", settings)
  low = (height_N > 0) & (height_N < settings.object_top)
  return cell_components(points_Nx3, low, settings.cell if cell is None else cell, bridge)


def object_flow(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion: rigid.Motion, surface=None,
                start_flow_Nx3=None, seed: int = 0, settings=None, ego_settings=None,
                frame_rate_hz: float | None = None):
  """(flow N x 3 of every pc1 point, Found): the ego-motion flow, and the rigid motion of each
  object the ego-motion does not explain (module docstring). `surface`: the ground in frame 1
  (jaxflow.lidar.ground.Surface; heights and an object's vertical motion); `start_flow_Nx3`: a flow
  to start each object from (e.g. the network's). `settings`: the objects block; `ego_settings`:
  the ego block (pc2's bird's-eye ego.Target); `frame_rate_hz` divides the per-second limits
  (default: the config's)."""
  s = sweep_config.block("objects", settings)
  rate = sweep_config.defaults().frame_rate_hz if frame_rate_hz is None else frame_rate_hz
  search, max_yaw_deg = s.search_per_s / rate, s.max_yaw_deg_per_s / rate
  min_seen = s.min_seen
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
  label, count = groups(pc1, np.where(ground1, -1.0, height), settings=s)
  label[ground1] = -1
  unexplained = _per_point(target, pc1) > s.unexplained
  tree = neighbours.Tree(above2)
  visibility = views.View(pc2_Mx3, "z", s.azimuth_bins, s.elevation_bins, s.hidden)
  rng = np.random.default_rng(seed)
  moved, candidates = [], 0
  order = np.argsort(label, kind="stable")
  bounds = np.searchsorted(label[order], np.arange(count + 1))
  for k in range(count):
    idx = order[bounds[k]:bounds[k + 1]]
    if len(idx) < s.min_points or (unexplained[idx].mean() < s.min_unexplained
                                   and unexplained[idx].sum() < s.many_unexplained):
      continue
    pts = pc1[idx]
    if (np.ptp(pts[:, :2], axis=0).max() > s.max_size
        or (height[idx] > s.object_top).mean() > s.max_high):
      continue  # structure: a facade, a tree, or one column of a far wall's returns
    candidates += 1
    # Motions are searched on half the points and judged on the other half: the best of many
    # motions fits its own points better than standing still by chance alone.
    shuffled = pts[rng.permutation(len(pts))]
    sample, judge = shuffled[0::2][:s.search_points], shuffled[1::2]
    still = rigid.Motion(np.eye(3), np.zeros(3))
    starts = {"search": _search(tree, sample, search, s)}
    if start_flow_Nx3 is not None and np.isfinite(start_flow_Nx3[idx]).all():
      given = back.apply(pts + np.asarray(start_flow_Nx3, np.float64)[idx])
      starts["network"] = rigid.kabsch(pts, given)
    spacing = np.median(neighbours.Tree(pts).knn(judge, 2, distances=True)[0][:, 1])
    truncate = float(np.clip(s.spacings * spacing, s.truncate, s.max_truncate))
    still_costs = _costs(tree, judge, visibility, ego_motion, truncate)
    best_name, best, best_costs = "still", still, still_costs
    for name, start in starts.items():
      for m in (start, _bev_icp(target, sample, start, s)):
        yaw = abs(np.degrees(np.arctan2(m.rotation[1, 0], m.rotation[0, 0])))
        shift = np.linalg.norm(m.apply(judge.mean(0)[None])[0] - judge.mean(0))
        if yaw > max_yaw_deg or shift > search + s.search_slack:  # no car turns or jumps so
          continue
        c = _costs(tree, m.apply(judge), visibility, ego_motion, truncate)
        if _mean(c, min_seen) < _mean(best_costs, min_seen):
          best_name, best, best_costs = name, m, c
    if best_name == "still" or not _better(still_costs, best_costs, s):
      continue
    refit = _bev_icp(target, pts, best, s)  # chosen on halves: now fitted on all points
    if _mean(_costs(tree, refit.apply(pts), visibility, ego_motion, truncate), min_seen) <= _mean(
        _costs(tree, best.apply(pts), visibility, ego_motion, truncate), min_seen):
      best = refit
    if surface is not None:  # on the ground: the height follows it
      centre = pts.mean(0)
      new_centre = best.apply(centre[None])[0]
      below = np.r_[new_centre[:2], centre[2]][None]  # the ground under the new place
      rise = surface.height(centre[None])[0] - surface.height(below)[0]
      best = rigid.Motion(best.rotation, best.translation + [0, 0, rise])
    parts = _moving_parts(tree, pts, best, visibility, ego_motion, truncate, s)
    idx, pts = idx[parts], pts[parts]
    flow[idx] = best.then(ego_motion).flow(pts)
    yaw = float(np.degrees(np.arctan2(best.rotation[1, 0], best.rotation[0, 0])))
    moved.append((len(idx), best.translation, yaw, best_name))
    if surface is not None:  # the object's own lowest points fell under the ground margin
      cells = set(map(tuple, np.floor(pts[:, :2] / s.cell).astype(np.int64)))
      low = np.flatnonzero(ground1 & (height > s.low_ground))
      if len(low):
        keys = np.floor(pc1[low, :2] / s.cell).astype(np.int64)
        mine = low[np.array([tuple(c) in cells for c in keys])]
        flow[mine] = best.then(ego_motion).flow(pc1[mine])
  return flow.astype(np.float32), Found(count, candidates, moved)
