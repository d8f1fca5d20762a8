"""Moving objects sought from both sweeps: a mover seen in either is found in either direction.

    flow_Nx3, found = object_flow(pc1, pc2, ground1, ground2, ego_motion, surface, seed=0,
                                  sensors=(sensor1, sensor2))

jaxflow.lidar.objects segments pc1 and fits each of its groups against pc2, so what pc1 shows of a
mover decides whether it is found: a car joined to what stands beside it in pc1 and apart in pc2,
seen end-on in one sweep and side-on in the other, or sampled by too few rings in one of them. So
the step runs both ways: forward on pc1's groups against pc2, and backward on pc2's groups against
pc1 (the ego-motion inverted, heights from the same ground, judged from pc1's sensor), the two
passes in two threads. They are associated through the backward motions: each backward mover,
its motion inverted, stood at pc1's time where it lands on pc1, and pc1's points there (above the
ground, within a cell seen from above) are offered that motion. Where the two directions
disagree, what both sweeps show decides (pc1's points moved onto pc2, and pc2's moved back onto
pc1: along a flat side pc2's extent is what pc1's points lack). Where the forward pass left the
points standing (or moved them under `dynamic`), the backward motion must beat that clearly, by
the objects' own judge, and pass its other rules; where it moved them otherwise, both are movers
and only which motion is asked: the backward one must fit better by the judge's significance
alone (jaxflow.lidar.judge.better: between two motions sliding along a flat side the gain is
small, but consistent). A pair taken backwards weighs the same two sets of movers,
so predicting it finds what the forward run finds. `objects.both_ways=False`: the forward pass
alone.
"""

from concurrent import futures

import numpy as np

from jaxflow.geometry import neighbours, rigid
from jaxflow.lidar import judge, objects
from jaxflow.lidar.settings import DEFAULTS


class _Moved:
  """A ground surface of frame 1 read from another frame: heights of points mapped into frame 1."""

  def __init__(self, surface, to1: rigid.Motion):
    self.surface, self.to1 = surface, to1

  def height(self, points_Nx3) -> np.ndarray:
    return self.surface.height(self.to1.apply(points_Nx3))


def object_flow(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion: rigid.Motion, surface=None,
                start_flow_Nx3=None, seed: int = 0, settings=None, ego_settings=None,
                frame_rate_hz: float | None = None, sensors=(None, None)):
  """(flow N x 3 of every pc1 point, objects.Found) as jaxflow.lidar.objects.object_flow (its
  arguments; `sensors`: where pc1's and pc2's sensors are, each in its own frame), with pc2's
  movers associated (module docstring); Found counts both passes' groups and candidates."""
  s = DEFAULTS.objects if settings is None else settings
  forward_args = (pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion, surface, start_flow_Nx3,
                  seed, s, ego_settings, frame_rate_hz, sensors[1])
  if not s.both_ways:
    forward = objects.object_pass(*forward_args)
    return forward.flow.astype(np.float32), forward.found()
  back = ego_motion.inverse()
  backward_args = (pc2_Mx3, pc1_Nx3, ground2_M, ground1_N, back,
                   None if surface is None else _Moved(surface, back), None, seed, s,
                   ego_settings, frame_rate_hz, sensors[0])
  # The two passes are independent: one thread each (the k-d searches release the GIL).
  with futures.ThreadPoolExecutor(2) as pool:
    forward, backward = pool.map(lambda args: objects.object_pass(*args),
                                 (forward_args, backward_args))
  if forward.scene is None:
    return forward.flow.astype(np.float32), forward.found()
  above1 = np.flatnonzero(~forward.ground1)
  for idx2, motion2 in backward.motions:
    _offer(forward, backward, idx2, motion2, above1, s)
  found = forward.found()
  return forward.flow.astype(np.float32), objects.Found(
    found.objects + backward.groups, found.candidates + backward.candidates, found.moved,
    found.motions)


def _offer(forward, backward, idx2, motion2: rigid.Motion, above1, s):
  """Offers a backward mover (pc2's points `idx2`, their motion to pc1's time `motion2`, frame 2)
  to pc1's points above the ground (`above1`) near where it stood at pc1's time (from above):
  `forward` gives them that motion where it fits both sweeps clearly better than the one it gave
  them (_two_sided)."""
  to2 = forward.scene.ego_motion
  back = to2.inverse()
  stood = back.apply(motion2.apply(backward.pc1[idx2]))  # frame 1
  # Frame 1 -> frame 2 -> pc2's time to pc1's undone -> frame 1.
  motion = to2.then(motion2.inverse()).then(back)
  # Within a cell from above, as objects are grouped (the two sweeps' rings cross an object at
  # other heights).
  reach = s.cell
  candidates = above1[((forward.pc1[above1] >= stood.min(0) - reach)
                       & (forward.pc1[above1] <= stood.max(0) + reach)).all(1)]
  d, _ = neighbours.Tree(stood[:, :2]).nearest(forward.pc1[candidates, :2], reach)
  idx = candidates[np.isfinite(d)]
  pts = forward.pc1[idx]
  if len(idx) < s.min_points:
    return  # pc1 did not see it there (hidden, or out of its rings)
  fit = ("both ways", motion, judge.truncation(pts, pts, s))
  if not forward.scene.plausible(motion, pts) or objects.onto_what_stood(forward.scene, pts, fit):
    return
  now = _motion_of(forward, idx)
  moving = np.linalg.norm(now.apply(pts) - pts, axis=1).mean() >= s.dynamic
  if judge.better(_two_sided(forward, idx, backward, idx2, now, s),
                  _two_sided(forward, idx, backward, idx2, motion, s), s, moving):
    forward.take_over(idx, fit)


def _motion_of(run, idx) -> rigid.Motion:
  """The motion (frame 1) `run` gave most of the points `idx`: standing still where no mover
  holds half of them."""
  best, most = rigid.Motion(np.eye(3), np.zeros(3)), len(idx) / 2
  for mine, motion in run.motions:
    held = np.isin(idx, mine).sum()
    if held > most:
      best, most = motion, held
  return best


def _two_sided(forward, idx, backward, idx2, motion: rigid.Motion, s) -> np.ndarray:
  """Per-point costs of `motion` (frame 1) seen from both sweeps: pc1's points `idx` moved onto
  pc2, and pc2's points `idx2` moved back onto pc1 (along a flat side pc2's extent is the
  evidence pc1's points lack), each in its own truncation."""
  to2 = forward.scene.ego_motion
  in2 = to2.inverse().then(motion.inverse()).then(to2)  # frame 2, pc2's time to pc1's
  pts1, pts2 = forward.pc1[idx], backward.pc1[idx2]
  return np.concatenate([
    forward.scene.costs(motion.apply(pts1), judge.truncation(pts1, pts1, s)),
    backward.scene.costs(in2.apply(pts2), judge.truncation(pts2, pts2, s))])
