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
disagree, pc2 decides, as it decides every fit of pc1's points: the backward motion replaces the
forward answer, standing still or another motion, only where pc1's points fit pc2 clearly better
with it by the objects' own judge, and it passes its other rules. (pc2's points do not judge it
too: the backward motion was fitted to them, and a slow car in a queue, its own place hidden in
pc1, fits the place of the car behind it as well: benchmarks/REAL_SWEEPS.md.) A pair taken
backwards weighs the same two sets of movers. `objects.both_ways=False`: the forward pass alone.
"""

from concurrent import futures

import numpy as np

from jaxflow.geometry import neighbours, rigid
from jaxflow.lidar import judge, objects, parts, slow
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
  `forward` gives them that motion where they fit pc2 clearly better with it than with the flow
  it gave them."""
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
  truncate = judge.truncation(pts, pts, s)
  fit = ("both ways", motion, truncate)
  if not forward.scene.plausible(motion, pts) or parts.onto_what_stood(forward.scene, pts, fit):
    return
  now = back.apply(pts + forward.flow[idx])  # the forward answer, frame 1
  # Where the forward answer is standing still, the evidence of the pair's noise may decide too
  # (a slow mover: judge.Evidence).
  still = np.allclose(now, pts, atol=1e-6)
  evidence = forward.scene.evidence
  if judge.clearly_better(forward.scene.costs(now, truncate),
                          forward.scene.costs(motion.apply(pts), truncate), s):
    forward.take_over(idx, fit)
  elif still and evidence is not None and evidence.beats_still(pts, motion, truncate, s):
    forward.take_over(idx, ("both ways" + slow.EVIDENCE, motion, truncate))
