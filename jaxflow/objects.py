"""Moving objects of a raw sweep pair: what the ego-motion does not explain, one rigid motion each.

    flow_Nx3, found = object_flow(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion, surface)

With the sensor's motion known (jaxflow.ego), pc2 is brought into pc1's frame: the static world
then overlaps itself and every moving thing does not. The non-ground points below OBJECT_TOP
above the ground are grouped into objects by connectivity seen from above (cells of CELL); each
object with enough unexplained points (a share of its points, or a count) gets motions from
several starts (standing still, the caller's flow, e.g. the network's, fitted rigidly, and the best
translation of a search over +-SEARCH m), each refined by a bird's-eye ICP (yaw and translation;
its height follows the ground), and keeps the motion that fits pc2 best, standing still unless
another fits clearly better; a kept motion is refitted on all the object's points. Points no
object claims keep the ego-motion. All in z-up coordinates, frame 1.
"""

import dataclasses

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from jaxflow import ego, rigid, visibility as views

CELL = 0.3  # metres: objects are connected cells seen from above (gaps of a cell bridged)
PART_CELL = 0.15  # metres: a moved object's parts, connected cells seen from above (no bridging)
OBJECT_TOP = 2.6  # metres above the ground: higher points (crowns, facades' tops) join no object
MIN_POINTS = 12
MAX_HIGH = 0.25  # an object with more of its points above OBJECT_TOP is structure, not a vehicle
MAX_SIZE = 14.0  # metres: a larger group is structure (a facade), never moved
UNEXPLAINED = 0.15  # metres: a point this far from ego-compensated pc2 (seen from above)
MIN_UNEXPLAINED = 0.15  # an object with fewer unexplained points than this share stands still
MANY_UNEXPLAINED = 100  # ... unless it has this many (a car beside the sensor, sliding along its
# own side, is explained but at its ends)
SEARCH, SEARCH_STEP = 3.5, 0.25  # metres: the translation search of an object (3 m a frame)
TRUNCATE = 0.3  # metres: a point's cost is its 3-D distance to pc2, at most this
SPACINGS, MAX_TRUNCATE = 3.0, 1.5  # ... or this many of the object's point spacings (m, at most)
MARGIN = 0.05  # a motion replaces standing still when its mean cost (of the truncation) is lower
# by this
RELATIVE_MARGIN = 0.1  # ... and lower by this share of standing still's cost
SIGNIFICANCE = 3.0  # ... and by this many standard errors of the per-point difference
MAX_YAW_DEG = 10.0  # a frame
LOW_GROUND = 0.05  # metres: "ground" points this high inside a moving object's cells move with it
ROUNDS = 15
AZIMUTH_BINS, ELEVATION_BINS = 1200, 360  # the visibility image: 0.3 x 0.5 degrees
HIDDEN = 0.5  # metres: a point this far behind pc2's return in its direction is hidden
HIDDEN_FIT = 0.45  # ... and a motion of an object hidden when still must fit this well
MIN_SEEN = 0.3  # a motion that leaves fewer of an object's points visible in pc2 is refused


@dataclasses.dataclass(frozen=True)
class Found:
  """What object_flow did: objects considered, moved, and each moved one's world motion."""
  objects: int
  candidates: int
  moved: list  # (points, translation 3, yaw deg, start name) of each moved object


def _world(motion: rigid.Motion, ego_motion: rigid.Motion) -> rigid.Motion:
  """ego o motion: a frame-1 world motion followed by the sensor's."""
  return rigid.Motion(ego_motion.rotation @ motion.rotation,
                      ego_motion.rotation @ motion.translation + ego_motion.translation)


def _inverse(m: rigid.Motion) -> rigid.Motion:
  return rigid.Motion(m.rotation.T, -m.rotation.T @ m.translation)


def _per_point(target: ego.Target, moved_Kx3) -> np.ndarray:
  """Bird's-eye distance (point-to-line, or to a pole) of each point to pc2; inf: no match."""
  r, _, idx = target.bev_residuals(moved_Kx3)
  out = np.full(len(moved_Kx3), -np.inf)
  np.maximum.at(out, idx, np.abs(r))
  out[out < 0] = np.inf
  return out


def _bev_icp(target: ego.Target, points_Kx3, start: rigid.Motion) -> rigid.Motion:
  """Yaw and horizontal translation of `start` refined (robust, shrinking scale)."""
  rotation, translation = start.rotation.copy(), start.translation.copy()
  for i in range(ROUNDS):
    scale = (0.3, 0.15, 0.08, 0.05)[min(i // 4, 3)]
    moved = points_Kx3 @ rotation.T + translation
    centre = moved.mean(0)  # rotate about the object's centre (well conditioned)
    r, n, idx = target.bev_residuals(moved)
    if len(r) < 3:
      break
    q = moved[idx] - centre
    w = 1.0 / (1.0 + (r / scale) ** 2) ** 2 * (np.abs(r) < 3 * scale + 0.2)
    jac = np.c_[q[:, 0] * n[:, 1] - q[:, 1] * n[:, 0], n[:, 0], n[:, 1]]
    h = jac.T @ (jac * w[:, None]) + 1e-3 * np.eye(3)
    step = -np.linalg.solve(h, jac.T @ (w * r))
    c, s = np.cos(step[0]), np.sin(step[0])
    d_rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    rotation = d_rot @ rotation
    translation = d_rot @ (translation - centre) + centre + np.r_[step[1:], 0.0]
    if np.abs(step).max() < 1e-5:
      break
  return rigid.Motion(rotation, translation)


def _costs(tree, points_Kx3, visibility, to2, truncate) -> np.ndarray:
  """Truncated 3-D distance of each point to ego-compensated pc2, NaN where pc2 could not see it
  (a box slid along its own side still matches seen from above, not in 3-D), in units of
  `truncate` (far objects are sampled sparsely: their distances are larger whatever the motion)."""
  d, _ = tree.query(points_Kx3, distance_upper_bound=truncate)
  d = np.minimum(d, truncate) / truncate
  d[visibility.hidden(to2.apply(points_Kx3))] = np.nan
  return d


def _mean(costs) -> float:
  """A motion's cost: the mean over the visible points (TRUNCATE when too few are)."""
  seen = np.isfinite(costs)
  return float(costs[seen].mean()) if seen.mean() >= MIN_SEEN else 1.0


def _better(still, moved) -> bool:
  """Whether a motion's costs beat standing still's clearly: by MARGIN, by RELATIVE_MARGIN of
  still's cost, and by SIGNIFICANCE standard errors of the paired difference; where pc2 cannot see
  the object standing still (a car come nearer along the line of sight hides its old place), the
  motion alone must fit within HIDDEN_FIT."""
  if _mean(moved) >= 1.0:
    return False
  if np.isfinite(still).mean() < MIN_SEEN:  # standing still, pc2 cannot see it: no evidence
    return _mean(moved) <= HIDDEN_FIT  # either way; the motion must fit on its own
  both = np.isfinite(still) & np.isfinite(moved)
  if both.sum() < MIN_POINTS // 2:
    return False
  diff = still[both] - moved[both]
  gain = diff.mean()
  error = diff.std() / np.sqrt(len(diff))
  return gain >= max(MARGIN, RELATIVE_MARGIN * still[both].mean()) and gain >= SIGNIFICANCE * error


def _search(tree, points_Kx3) -> rigid.Motion:
  """The best horizontal translation within +-SEARCH (3-D cost; coarse, then fine)."""
  best = np.zeros(3)
  for half, step in ((SEARCH, 0.5), (0.5, SEARCH_STEP / 2)):
    steps = np.arange(-half, half + 1e-9, step)
    dx, dy = np.meshgrid(steps, steps, indexing="ij")
    shifts = best + np.c_[dx.ravel(), dy.ravel(), np.zeros(dx.size)]
    d, _ = tree.query((points_Kx3[None] + shifts[:, None]).reshape(-1, 3),
                      distance_upper_bound=TRUNCATE)
    cost = np.minimum(d, TRUNCATE).reshape(len(shifts), -1).mean(1)
    cost += 1e-4 * np.linalg.norm(shifts, axis=1)  # ties: the smaller move
    best = shifts[int(np.argmin(cost))]
  return rigid.Motion(np.eye(3), best)


def _moving_parts(tree, points_Kx3, motion, visibility, ego_motion, truncate) -> np.ndarray:
  """Bool K: the points of an object that move with `motion`. A group seen from above can join a
  moving car to the parked car beside it (a gap under two cells): split it by connectivity at
  PART_CELL, without bridging, and keep still every part of MIN_POINTS that standing still
  explains clearly better than the motion (`_better`, the test a motion passed against it)."""
  ij = np.floor(points_Kx3[:, :2] / PART_CELL).astype(np.int64)
  ij -= ij.min(0)
  grid = np.zeros(ij.max(0) + 1, bool)
  grid[ij[:, 0], ij[:, 1]] = True
  labels, count = ndimage.label(grid, np.ones((3, 3)))
  part = labels[ij[:, 0], ij[:, 1]]
  keep = np.ones(len(points_Kx3), bool)
  if count < 2:
    return keep
  still = _costs(tree, points_Kx3, visibility, ego_motion, truncate)
  moving = _costs(tree, motion.apply(points_Kx3), visibility, ego_motion, truncate)
  for k in range(1, count + 1):
    mine = part == k
    if mine.sum() >= MIN_POINTS and _better(moving[mine], still[mine]):
      keep[mine] = False
  return keep


def groups(points_Nx3, height_N, cell: float = CELL, bridge: bool = True):
  """Object label of each point (-1: none) by 8-connected occupied cells seen from above, from
  the points between 0 and OBJECT_TOP above the ground (gaps of a cell bridged unless `bridge`
  is False); higher points join the object below."""
  low = (height_N > 0) & (height_N < OBJECT_TOP)
  ij = np.floor(points_Nx3[:, :2] / cell).astype(np.int64)
  if not low.any():
    return np.full(len(points_Nx3), -1), 0
  lo = ij[low].min(0)
  ij = ij - lo
  shape = ij[low].max(0) + 1
  inside = (ij >= 0).all(1) & (ij < shape).all(1)
  grid = np.zeros(shape, bool)
  grid[ij[low, 0], ij[low, 1]] = True
  if bridge:
    grid = ndimage.binary_dilation(grid, np.ones((3, 3)))
  labels, count = ndimage.label(grid, np.ones((3, 3)))
  out = np.full(len(points_Nx3), -1)
  out[inside] = labels[ij[inside, 0], ij[inside, 1]] - 1
  return out, count


def object_flow(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion: rigid.Motion, surface=None,
                start_flow_Nx3=None, seed: int = 0):
  """(flow N x 3 of every pc1 point, Found): the ego-motion flow, and the rigid motion of each
  object the ego-motion does not explain (module docstring). `surface`: the ground in frame 1
  (jaxflow.ground.Surface; heights and an object's vertical motion); `start_flow_Nx3`: a flow to
  start each object from (e.g. the network's)."""
  pc1 = np.asarray(pc1_Nx3, np.float64)
  ground1 = np.asarray(ground1_N, bool)
  flow = ego_motion.flow(pc1).astype(np.float64)
  back = _inverse(ego_motion)
  pc2_in1 = back.apply(pc2_Mx3)
  target = ego.Target(pc2_in1, ground2_M)
  above2 = pc2_in1[~np.asarray(ground2_M, bool)]
  if target.tree is None or len(above2) < 3:
    return flow.astype(np.float32), Found(0, 0, [])
  height = surface.height(pc1) if surface is not None else pc1[:, 2] - pc1[ground1, 2].mean() if (
    ground1.any()) else pc1[:, 2] - pc1[:, 2].min()
  label, count = groups(pc1, np.where(ground1, -1.0, height))
  label[ground1] = -1
  unexplained = _per_point(target, pc1) > UNEXPLAINED
  tree = cKDTree(above2)
  visibility = views.View(pc2_Mx3, "z", AZIMUTH_BINS, ELEVATION_BINS, HIDDEN)
  rng = np.random.default_rng(seed)
  moved, candidates = [], 0
  order = np.argsort(label, kind="stable")
  bounds = np.searchsorted(label[order], np.arange(count + 1))
  for k in range(count):
    idx = order[bounds[k]:bounds[k + 1]]
    if len(idx) < MIN_POINTS or (unexplained[idx].mean() < MIN_UNEXPLAINED
                                 and unexplained[idx].sum() < MANY_UNEXPLAINED):
      continue
    pts = pc1[idx]
    if np.ptp(pts[:, :2], axis=0).max() > MAX_SIZE or (height[idx] > OBJECT_TOP).mean() > MAX_HIGH:
      continue  # structure: a facade, a tree, or one column of a far wall's returns
    candidates += 1
    # Motions are searched on half the points and judged on the other half: the best of many
    # motions fits its own points better than standing still by chance alone.
    shuffled = pts[rng.permutation(len(pts))]
    sample, judge = shuffled[0::2][:150], shuffled[1::2]
    still = rigid.Motion(np.eye(3), np.zeros(3))
    starts = {"search": _search(tree, sample)}
    if start_flow_Nx3 is not None and np.isfinite(start_flow_Nx3[idx]).all():
      given = back.apply(pts + np.asarray(start_flow_Nx3, np.float64)[idx])
      starts["network"] = rigid.kabsch(pts, given)
    spacing = np.median(cKDTree(pts).query(judge, 2)[0][:, 1])
    truncate = float(np.clip(SPACINGS * spacing, TRUNCATE, MAX_TRUNCATE))
    still_costs = _costs(tree, judge, visibility, ego_motion, truncate)
    best_name, best, best_costs = "still", still, still_costs
    for name, start in starts.items():
      for m in (start, _bev_icp(target, sample, start)):
        yaw = abs(np.degrees(np.arctan2(m.rotation[1, 0], m.rotation[0, 0])))
        shift = np.linalg.norm(m.apply(judge.mean(0)[None])[0] - judge.mean(0))
        if yaw > MAX_YAW_DEG or shift > SEARCH + 0.5:  # no car turns or jumps like that
          continue
        c = _costs(tree, m.apply(judge), visibility, ego_motion, truncate)
        if _mean(c) < _mean(best_costs):
          best_name, best, best_costs = name, m, c
    if best_name == "still" or not _better(still_costs, best_costs):
      continue
    refit = _bev_icp(target, pts, best)  # chosen and judged on halves: now fitted on all points
    if _mean(_costs(tree, refit.apply(pts), visibility, ego_motion, truncate)) <= _mean(
        _costs(tree, best.apply(pts), visibility, ego_motion, truncate)):
      best = refit
    if surface is not None:  # on the ground: the height follows it
      centre = pts.mean(0)
      new_centre = best.apply(centre[None])[0]
      below = np.r_[new_centre[:2], centre[2]][None]  # the ground under the new place
      rise = surface.height(centre[None])[0] - surface.height(below)[0]
      best = rigid.Motion(best.rotation, best.translation + [0, 0, rise])
    parts = _moving_parts(tree, pts, best, visibility, ego_motion, truncate)
    idx, pts = idx[parts], pts[parts]
    flow[idx] = _world(best, ego_motion).flow(pts)
    yaw = float(np.degrees(np.arctan2(best.rotation[1, 0], best.rotation[0, 0])))
    moved.append((len(idx), best.translation, yaw, best_name))
    if surface is not None:  # the object's own lowest points fell under the ground margin
      cells = set(map(tuple, np.floor(pts[:, :2] / CELL).astype(np.int64)))
      low = np.flatnonzero(ground1 & (height > LOW_GROUND))
      if len(low):
        keys = np.floor(pc1[low, :2] / CELL).astype(np.int64)
        mine = low[np.array([tuple(c) in cells for c in keys])]
        flow[mine] = _world(best, ego_motion).flow(pc1[mine])
  return flow.astype(np.float32), Found(count, candidates, moved)
