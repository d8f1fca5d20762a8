"""A group kept still, in pieces: it may join a mover to what stands beside it (a car passing
parked cars, a slow car creeping beside a parked one), so its unexplained points' own groups (and,
with `part.split`, its pieces without bridging) are fitted in turn, each kept only where it leaves a
place pc2 shows empty for one pc1 showed empty, or, a slow mover, by the pair's own evidence
(jaxflow.lidar.slow). Also the rule that keeps any fit from sliding onto what stood
(`onto_what_stood`). `scene` and `run` are jaxflow.lidar.objects' _Scene and _Pass."""

import numpy as np

from jaxflow.geometry import groups
from jaxflow.lidar import judge, slow


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
  """Whether a part's motion takes it from a place pc2 shows empty (mean cost >= `part.vacated`)
  to one pc1 showed empty (`_novelty`), and the part is object-sized (`part.size` wide)."""
  s = scene.settings
  _, motion, truncate = fit
  return bool(judge.mean(scene.costs(pts_Kx3, truncate), s.judge.min_seen) >= s.part.vacated
              and np.ptp(pts_Kx3[:, :2], axis=0).max() >= s.part.size
              and _novelty(scene, pts_Kx3, motion, truncate) >= s.novelty)


def onto_what_stood(scene, pts_Kx3, fit) -> bool:
  """Whether a motion takes an object farther than its own width onto what pc1 saw there too
  (under `novelty` of the pc2 points it lands on new), or from a place pc2 still shows filled
  (standing still's mean cost under `part.vacated`): a thing slid onto its neighbours. A mover
  that far has left its own place, so pc2 sees it empty, and where it lands pc1 saw nothing."""
  _, motion, truncate = fit
  if judge.shift_from_above(pts_Kx3, motion) <= np.ptp(pts_Kx3[:, :2], axis=0).max():
    return False
  s = scene.settings
  return (judge.mean(scene.costs(pts_Kx3, truncate), s.judge.min_seen) < s.part.vacated
          or _novelty(scene, pts_Kx3, motion, truncate) < s.novelty)


def _unexplained_parts(idx, unexplained_N, pc1_Nx3, s):
  """Indices of each group of a group's unexplained points (connected cells, no bridging, with
  every point of the group in their cells) of `min_points` or more, but at most `part.share` of
  the group (a larger one is the group again)."""
  seeds = unexplained_N[idx]
  if seeds.sum() < s.min_points:
    return []
  parts = groups.cell_components(pc1_Nx3[idx], seeds, s.cell, bridge=False)
  return [idx[mine] for _, mine in parts.members()
          if s.min_points <= len(mine) <= s.part.share * len(idx)]


def fit_parts(run, still: list, off_N):
  """A group kept still may join a mover to what stands beside it (a car passing parked cars):
  its unexplained points' own groups are fitted in turn; split without bridging, it may join a
  slow mover, whose evidence is its faces, not an empty place (`off_N`: each point's distance from
  pc2 seen from above)."""
  scene, pc1, s = run.scene, run.pc1, run.scene.settings
  moved = np.zeros(len(pc1), bool)
  seeds = run.unexplained if scene.evidence is None else off_N > s.part.seeds
  for idx in still:
    pieces = slow.split_parts(idx, pc1, s) if s.part.split else []
    for part in pieces + _unexplained_parts(idx, seeds, pc1, s):
      part = part[~moved[part]]
      if len(part) < s.min_points:
        continue
      fit = run.fit(part)
      if fit is not None and not _new_place(scene, pc1[part], fit):
        fit = slow.evident_fit(scene, pc1[part], fit) if slow.stays(scene, pc1[part], fit) else None
      if fit is not None:
        run.apply(part, fit)
        moved[part] = True
