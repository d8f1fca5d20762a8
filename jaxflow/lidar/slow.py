"""Slow movers (a car creeping 0.1-0.3 m a frame, a walker): they leave pc2 no empty place and
their margins are small, so a motion is kept where the pair's own noise makes it overwhelming
evidence (jaxflow.lidar.judge.Evidence), then refined on the object's faces. Used by
jaxflow.lidar.objects when `judge.evidence` is set; `scene` is its _Scene."""

import numpy as np

from jaxflow.geometry import groups
from jaxflow.lidar import judge

EVIDENCE = " (evidence)"  # a fit's name ends so where the evidence, not the margins, kept it


def evident(scene, pts_Kx3, motion, reach) -> bool:
  """Whether the pair's own noise makes `motion` beat standing still on `pts_Kx3`
  (judge.Evidence.beats_still; False without the evidence)."""
  return scene.evidence is not None and scene.evidence.beats_still(pts_Kx3, motion, reach,
                                                                   scene.settings)


def _slow_shift(pts_Kx3, motion, s) -> bool:
  """Whether `motion` moves an object's centre at most `judge.slow` m and within its own width
  seen from above (it leaves pc2 no empty place)."""
  return judge.shift_from_above(pts_Kx3, motion) <= min(s.judge.slow,
                                                        np.ptp(pts_Kx3[:, :2], axis=0).max())


def stays(scene, pts_Kx3, fit) -> bool:
  """Whether a part's motion keeps it within its own width (a slow mover, which leaves pc2 no
  empty place: _new_place cannot hold it) and the pair's noise makes it clearly better than
  standing still on all its points."""
  _, motion, truncate = fit
  return _slow_shift(pts_Kx3, motion, scene.settings) and evident(scene, pts_Kx3, motion, truncate)


def settled(scene, pts_Kx3, motions, truncate):
  """The first of `motions` (the most refined first) that is plausible and that the evidence of
  all of `pts_Kx3` keeps, or None: a refinement is judged again, as a new motion (it may have
  run off past standing still, or beyond `judge.slow`)."""
  return next((m for m in motions if scene.plausible(m, pts_Kx3)
               and evident(scene, pts_Kx3, m, truncate)), None)


def evident_fit(scene, pts_Kx3, found):
  """A part's fit kept by the evidence (`stays`): named so, its motion refined on its faces where
  the refined motion is kept by the evidence too."""
  name, motion, truncate = found
  if not name.endswith(EVIDENCE):
    refined = scene.evidence.refine(pts_Kx3, motion, truncate, scene.settings)
    motion = settled(scene, pts_Kx3, (refined,), truncate) or motion
  return name if name.endswith(EVIDENCE) else name + EVIDENCE, motion, truncate


def split_parts(idx, pc1_Nx3, s):
  """Indices of each piece of a group kept still, connected at the objects' cell without
  bridging, of `min_points` or more, but at most `part.share` of the group: a car creeping beside
  a parked one is one group across the bridged gap."""
  parts = groups.cell_components(pc1_Nx3[idx], np.ones(len(idx), bool), s.cell, bridge=False)
  return [idx[mine] for _, mine in parts.members()
          if s.min_points <= len(mine) <= s.part.share * len(idx)]


def measure_noise(scene, static_Kx3, s):
  """The pair's noise, measured on an even sample of `judge.noise_points` of its static world."""
  step = max(1, len(static_Kx3) // max(1, s.judge.noise_points))
  scene.evidence.measure_noise(static_Kx3[::step], s)
