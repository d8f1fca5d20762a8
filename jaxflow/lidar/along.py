"""A long object's motion along its own length, from its ends: where its flat side cannot tell.

    seen = before(pc1_Nx3, target1, above1_N, pc2_Mx3, reach)     # once a pair: what pc1 shows
    found = group_vote(idx, pc1_Nx3, pc2_Mx3, seen, reach, settings)   # a Vote, or None
    chosen = adopt(scene, points_Kx3, truncate, found, (chosen, still_costs), refine)

A car passing beside the sensor shows it mostly its long flat side, which matches itself slid
along its length: a distance cost is flat along it but near its ends (few returns), and only its
ends are unexplained (too few points to make it a candidate). What fixes the car along its length
is its extent: where its side (and each height band of it: body, cabin) begins and ends. Seen
along the object's long axis, the cells (`along.bin` m along it, `along.band` m high) its points
occupy in pc1 and those pc2's points near it occupy (each band's returns joined into the stretch
they sample) are compared at every shift within +-`reach` m: each pair of occupied cells votes for
their difference, once a cell whatever its count of returns (their spacing is the sensor's, not
the car's). The translation most cells agree on is the shift. The projection of a rigid
translation on any axis is the shift of the projected shape, so the vote holds for any axis whose
profile has ends; it is asked only of a group `along.min_length` m long or more whose own lines
(seen from above) barely face along its axis (`along.faces`): a flat side. An end face seen fixes
an object along its axis without it, and a profile seen from another angle changes. pc2's points
that pc1's other points explain (what stands beside the object) do not vote. The vote makes the
group a candidate, and starts its motion's fit (adopt), kept only where the costs do not clearly
refute it and it beats standing still clearly (jaxflow.lidar.judge). The names are fields of
jaxflow.lidar.settings.Objects (`along.*`: its Along block).
"""

import dataclasses

import numpy as np

from jaxflow.geometry import neighbours, rigid
from jaxflow.lidar import judge


@dataclasses.dataclass(frozen=True)
class Vote:
  """What a long object's ends say: its move along its axis."""
  axis: np.ndarray  # unit 3-vector, horizontal: the group's long axis seen from above
  shift: float  # m along `axis`
  support: float  # share of the group's occupied cells that pc2's match at that shift


def long_axis(points_Kx3) -> tuple[np.ndarray, float]:
  """(unit 2-vector, length m) of a group seen from above: its principal horizontal axis and its
  extent along it."""
  xy = points_Kx3[:, :2] - points_Kx3[:, :2].mean(0)
  _, vectors = np.linalg.eigh(xy.T @ xy)
  axis = vectors[:, -1]
  return axis, float(np.ptp(xy @ axis))


def _cells(along_K, height_K, lo: float, size: int, s) -> np.ndarray:
  """Bool (height bands x `size`): the cells along the axis (from `lo`) that points occupy, and
  those between two of a band's at most `along.gap` m apart: a ring's returns become the stretch
  they sample, whatever their spacing."""
  i = np.floor((along_K - lo) / s.along.bin).astype(np.int64)
  k = np.floor(height_K / s.along.band).astype(np.int64)
  keep = (i >= 0) & (i < size)
  out = np.zeros((int(k.max() - k.min()) + 1 if len(k) else 1, size), bool)
  out[k[keep] - k.min(), i[keep]] = True
  band, at = np.nonzero(out)  # by band, then along
  joined = (band[1:] == band[:-1]) & (at[1:] - at[:-1] <= s.along.gap / s.along.bin)
  runs = np.zeros((len(out), size + 1), np.int64)
  np.add.at(runs, (band[:-1][joined], at[:-1][joined]), 1)
  np.add.at(runs, (band[1:][joined], at[1:][joined]), -1)
  return out | (np.cumsum(runs, axis=1)[:, :-1] > 0)


def vote(points_Kx3, others_Mx3, axis_2, reach: float, settings):
  """(shift m along `axis_2`, support) of a group (`points_Kx3`, frame 1) against pc2's points
  near it (`others_Mx3`, frame 1; only those within `along.cross` m across the axis of the group's
  band and within its heights count): the shift within +-`reach` whose occupied cells match most of
  pc2's, and the share of the group's occupied cells it matches; None when no cell matches."""
  s = settings
  axis = np.array([axis_2[0], axis_2[1], 0.0])
  across = np.array([-axis_2[1], axis_2[0], 0.0])
  a1, c1, z1 = points_Kx3 @ axis, points_Kx3 @ across, points_Kx3[:, 2]
  a2, c2, z2 = others_Mx3 @ axis, others_Mx3 @ across, others_Mx3[:, 2]
  near = ((c2 > c1.min() - s.along.cross) & (c2 < c1.max() + s.along.cross)
          & (z2 > z1.min() - s.along.band) & (z2 < z1.max() + s.along.band)
          & (a2 > a1.min() - reach - s.along.bin) & (a2 < a1.max() + reach + s.along.bin))
  if not near.any():
    return None
  lo = a1.min() - reach - s.along.bin
  size = int(np.ceil((a1.max() - lo + reach) / s.along.bin)) + 2
  z0 = min(z1.min(), z2[near].min())
  mine = _cells(a1, z1 - z0, lo, size, s)
  theirs = _cells(a2[near], z2[near] - z0, lo, size, s)
  bands = max(len(mine), len(theirs))
  mine = np.pad(mine, ((0, bands - len(mine)), (0, 0)))
  theirs = np.pad(theirs, ((0, bands - len(theirs)), (0, 0)))
  steps = int(round(reach / s.along.bin))
  shifts = np.arange(-steps, steps + 1)
  score = np.array([np.logical_and(np.roll(mine, j, axis=1), theirs).sum() for j in shifts])
  if score.max() == 0:
    return None
  best = shifts[score == score.max()]
  return float(best.mean() * s.along.bin), float(score.max() / mine.sum())


@dataclasses.dataclass(frozen=True)
class Before:
  """What pc1 shows the vote: its lines from above (the group's own faces), and which pc1 point
  explains each of pc2's points (its nearest above the ground within `reach` m, or -1)."""
  target: object  # jaxflow.lidar.ego.Target of pc1
  owner: np.ndarray  # M


def before(pc1_Nx3, target1, above1_N, points_Mx3, reach: float) -> Before:
  """The Before of a pair: pc1's `target1` and the owner of each of `points_Mx3` (frame 1)."""
  above = np.flatnonzero(above1_N)
  if not len(above):
    return Before(target1, np.full(len(points_Mx3), -1))
  d, j = neighbours.Tree(pc1_Nx3[above]).nearest(points_Mx3, reach)
  return Before(target1, np.where(np.isfinite(d), above[np.minimum(j, len(above) - 1)], -1))


def group_vote(idx, pc1_Nx3, points_Mx3, seen: Before, reach: float, settings) -> Vote | None:
  """The vote of pc1's group `idx` against pc2's points (`points_Mx3`, frame 1) that no other pc1
  point explains; None for a group under `along.min_length` m long, one whose own lines face
  along its axis (`along.faces`: an end face fixes it), or a vote under `along.support`."""
  pts = pc1_Nx3[idx]
  axis, length = long_axis(pts)
  axis = np.array([axis[0], axis[1], 0.0])
  if length < settings.along.min_length or facing(seen.target, pts, axis) >= settings.along.faces:
    return None
  owner = seen.owner
  free = owner < 0
  free[owner >= 0] = np.isin(owner[owner >= 0], idx)
  found = vote(pts, points_Mx3[free], axis[:2], reach, settings)
  if found is None or found[1] < settings.along.support:
    return None
  return Vote(axis, *found)


def shift_of(motion: rigid.Motion, points_Kx3, found: Vote) -> float:
  """How far `motion` moves the points' centre along the vote's axis (m)."""
  centre = points_Kx3.mean(0)
  return float((motion.apply(centre[None])[0] - centre) @ found.axis)


def with_shift(motion: rigid.Motion, points_Kx3, found: Vote) -> rigid.Motion:
  """`motion` with its move of the points' centre along the vote's axis the vote's shift (across
  the axis and its turn unchanged)."""
  change = (found.shift - shift_of(motion, points_Kx3, found)) * found.axis
  return rigid.Motion(motion.rotation, motion.translation + change)


def adopt(scene, points_Kx3, truncate: float, found: Vote, chosen, refine):
  """The chosen motion of a long object (`chosen`: ((start name, motion, costs of `points_Kx3`
  moved), standing still's costs)), or that motion moved along the object's axis as its ends say
  (`found`) and refined from there (`refine`: motion -> motion; an end face seen fixes it, along a
  flat side the ends' shift is kept: settle), named so. Adopted where the ends differ by more
  than half a cell of the vote, the costs (`scene.costs`: jaxflow.lidar.objects) do not clearly
  refute it (along a flat side they cannot tell) and it beats standing still clearly, as the
  chosen motion must too."""
  (name, motion, costs), still = chosen
  s = scene.settings
  if abs(shift_of(motion, points_Kx3, found) - found.shift) <= s.along.bin / 2:
    return chosen[0]
  moved = settle(scene.target, points_Kx3, refine(with_shift(motion, points_Kx3, found)), found, s)
  if not scene.plausible(moved, points_Kx3):
    return chosen[0]
  moved_costs = scene.costs(moved.apply(points_Kx3), truncate)
  if judge.clearly_better(moved_costs, costs, s) or not judge.clearly_better(still, moved_costs, s):
    return chosen[0]
  return ("along" if name == "still" else name + "+along"), moved, moved_costs


def facing(target, points_Kx3, axis) -> float:
  """How much the lines seen from above (`target`: jaxflow.lidar.ego.Target) that `points_Kx3`
  (placed) match face along `axis` (unit, horizontal): the mean squared along-axis part of their
  normals. An end face seen fixes an object along its axis, a flat side along it does not."""
  dist, j = target.tree.nearest(points_Kx3[:, :2], target.max_match)
  j = j[np.isfinite(dist)]
  j = j[target.usable_M[j] & target.line_M[j]]
  if not len(j):
    return 0.0
  return float(np.mean((target.normal_Mx2[j] @ axis[:2]) ** 2))


def settle(target, points_Kx3, motion: rigid.Motion, found: Vote, settings) -> rigid.Motion:
  """`motion` (of a long object's points), its move along the axis the vote's where the lines it
  lands on face along the axis under `along.faces` (facing): a flat side, along which a fit
  slides (the pull of its few point-to-point matches); else `motion` as the shape fixes it."""
  if facing(target, motion.apply(points_Kx3), found.axis) < settings.along.faces:
    return with_shift(motion, points_Kx3, found)
  return motion
