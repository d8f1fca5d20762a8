"""A walking person: a group shaped as one (narrow from above, upright, a person's height) moves
5-17 cm a frame, under what the ego-motion leaves unexplained, so it first gets the shift of the
centroid of pc2's points around it (jaxflow.lidar.objects), kept when it beats standing still
clearly: by the margins, or by the evidence of the pair's own noise (judge.Evidence).

    if is_person(idx, pc1_Nx3, height_N, settings):
      fit = fit_person(scene, pc1_Nx3[idx])   # ("person", shift, truncation) or None

`settings` is the objects block (jaxflow.lidar.settings.Objects): its `person` block.
"""

import numpy as np

from jaxflow.geometry import rigid
from jaxflow.lidar import judge


def is_person(idx, pc1_Nx3, height_N, s) -> bool:
  """Whether a group is shaped as a person: narrow from above, upright, a person's height."""
  pts = pc1_Nx3[idx]
  return bool(len(idx) >= s.min_points
              and np.ptp(pts[:, :2], axis=0).max() <= s.person.size
              and s.person.top[0] <= height_N[idx].max() <= s.person.top[1]
              and np.ptp(height_N[idx]) >= s.person.upright)


def _person_shift(scene, pts_Kx3):
  """A person's horizontal motion: the centroid of pc2's points (above the ground, from above
  within `person.radius` of the moved centre and at its height) minus the group's, iterated; None
  when too few points of pc2 are there or the shift is under `person.min_shift`."""
  s = scene.settings
  centre, shift = pts_Kx3.mean(0), np.zeros(3)
  above2 = scene.tree.points
  for _ in range(s.person.rounds):
    d = np.linalg.norm(above2[:, :2] - (centre[:2] + shift[:2]), axis=1)
    near = (d < s.person.radius) & (np.abs(above2[:, 2] - centre[2]) < s.person.top[1] / 2)
    if near.sum() < max(s.person.least_matches, len(pts_Kx3) * s.person.matched_share):
      return None
    shift[:2] = above2[near, :2].mean(0) - centre[:2]
  if np.linalg.norm(shift) < s.person.min_shift:
    return None
  return rigid.Motion(np.eye(3), shift)


def fit_person(scene, pts_Kx3):
  """("person", shift, truncation) of a person's centroid shift (_person_shift) when it beats
  standing still on the group's points, else None."""
  shift = _person_shift(scene, pts_Kx3)
  if shift is None:
    return None
  s = scene.settings
  truncate = judge.truncation(pts_Kx3, pts_Kx3, s)
  still = scene.costs(pts_Kx3, truncate)
  if judge.clearly_better(still, scene.costs(shift.apply(pts_Kx3), truncate), s):
    return "person", shift, truncate
  if scene.evidence is not None and scene.evidence.beats_still(pts_Kx3, shift, truncate, s):
    return "person (evidence)", shift, truncate
  return None
