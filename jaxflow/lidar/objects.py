"""Moving objects of a raw sweep pair: what the ego-motion does not explain, one rigid motion each.

    flow_Nx3, found = object_flow(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion, surface)

With the sensor's motion known (jaxflow.lidar.ego), pc2 is brought into pc1's frame: the static
world then overlaps itself and every moving thing does not. The non-ground points below `object_top`
above the ground are grouped into objects by connectivity seen from above (cells of `cell`); every
object but structure, at any speed, gets motions from several starts (standing still, the
caller's flow, e.g. the network's, fitted rigidly, and the best translation of a search over
+-`search.per_s` / `frame_rate_hz` m: jaxflow.lidar.grid_search), each refined by a bird's-eye
ICP (yaw and translation, point-to-line: jaxflow.geometry.registration; its height follows the
ground), and keeps the motion that fits pc2 best, standing still unless another fits clearly
better (jaxflow.lidar.judge); a kept motion is refitted on all the object's points. A walking
person moves less a frame than `unexplained`: a group shaped as a person (narrow, upright, a
person's height) first gets the shift of the centroid of pc2's points around it, kept when it
beats standing still by the same rule (jaxflow.lidar.person). A long object sliding along its
flat side (a car passing beside the sensor) leaves few points unexplained and a cost flat along
its length: its ends vote for its shift along its axis (jaxflow.lidar.along), a candidate's start
unless the costs clearly refute it, kept along a flat side (an end face seen refines it). An
object moved farther than its own width must leave a place pc2 shows empty and land where pc1 saw
nothing (each start and each of the search's best shifts is held to it). A group kept still may
join a mover to what stands beside it (a car passing parked cars): the connected cells of its
unexplained points are fitted in turn, each kept only where it leaves a place pc2 shows empty for
one pc1 showed empty. A slow mover, which leaves no empty place, may be kept by the pair's own
evidence instead (jaxflow.lidar.slow, when `judge.evidence` is set). What pc2
saw is judged from its sensor's place (`sensor2`). Points no
object claims keep the ego-motion. All z up, frame 1. The names: fields of `settings`,
jaxflow.lidar.settings.Objects.
"""

import dataclasses

import numpy as np

from jaxflow.geometry import groups, neighbours, registration, rigid, visibility as views
from jaxflow.lidar import along, ego, grid_search, judge, parts, person, slow
from jaxflow.lidar.settings import DEFAULTS


@dataclasses.dataclass(frozen=True)
class Found:
  """What object_flow did: objects considered, moved, and each moved one's world motion."""
  objects: int
  candidates: int
  moved: list  # (points, translation 3, yaw deg, start name) of each moved object
  # (pc1 indices, motion in frame 1 before the ego-motion) of each moved object, as `moved`
  motions: tuple = ()


def _per_point(target: ego.Target, moved_Kx3) -> np.ndarray:
  """Bird's-eye distance (point-to-line, or to a pole) of each point to pc2; inf: no match."""
  rows = target.bev_rows(moved_Kx3)
  out = np.full(len(moved_Kx3), -np.inf)
  np.maximum.at(out, rows.index, np.abs(rows.residual))
  out[out < 0] = np.inf
  return out


def _bev_icp(target: ego.Target, points_Kx3, start: rigid.Motion, settings) -> rigid.Motion:
  """Yaw and horizontal translation of `start` refined seen from above (robust, the scale
  shrinking every 4 rounds: `icp.scales`), `icp.rounds` rounds at most, turning about the object's
  centre."""

  def rows_of(moved_Kx3, scale):
    rows = target.bev_rows(moved_Kx3)
    gate = settings.icp.gate * scale + settings.icp.gate_margin
    return dataclasses.replace(rows, gate=np.abs(rows.residual) < gate)

  last = len(settings.icp.scales) - 1
  scales = [settings.icp.scales[min(i // 4, last)] for i in range(settings.icp.rounds)]
  return registration.robust_fit(points_Kx3, start, rows_of, scales, dof="yaw_xy",
                                 about_centroid=True, damping=1e-3, converged=1e-5)


def _moving_parts(scene, points_Kx3, motion, truncate) -> np.ndarray:
  """Bool K: the points of an object that move with `motion`. A group seen from above can join a
  moving car to the parked car beside it (a gap under two cells): split it by connectivity at
  `part.cell`, without bridging, and keep still every part of `min_points` that standing still
  explains clearly better than the motion (the test the motion passed against it)."""
  s = scene.settings
  pieces = groups.cell_components(points_Kx3, np.ones(len(points_Kx3), bool), s.part.cell,
                                  bridge=False)
  keep = np.ones(len(points_Kx3), bool)
  if pieces.count < 2:
    return keep
  still = scene.costs(points_Kx3, truncate)
  moving = scene.costs(motion.apply(points_Kx3), truncate)
  for _, mine in pieces.members():
    if len(mine) >= s.min_points and judge.clearly_better(moving[mine], still[mine], s):
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
  before: object  # what pc1 shows a long object's vote (jaxflow.lidar.along.Before)
  visibility: views.View  # what pc2's sensor saw (a placement it could not see: no evidence)
  ego_motion: rigid.Motion
  search: float  # m: an object's translation search, +- this (a frame's worth of search.per_s)
  max_yaw_deg: float  # degrees an object may turn in a frame
  settings: object  # the objects block
  evidence: object = None  # pc2's planes and the pair's noise (judge.Evidence; None: margins only)

  def costs(self, points_Kx3, truncate: float) -> np.ndarray:
    return judge.costs(self.tree, points_Kx3, self.visibility, self.ego_motion, truncate)

  def plausible(self, motion: rigid.Motion, points_Kx3) -> bool:
    """No car turns or jumps farther than the limits in a frame."""
    yaw = abs(motion.yaw_deg)
    centre = points_Kx3.mean(0)
    shift = np.linalg.norm(motion.apply(centre[None])[0] - centre)
    return yaw <= self.max_yaw_deg and shift <= self.search + self.settings.search.slack


def _is_structure(idx, height_N, pc1_Nx3, s) -> bool:
  """Whether a group is too few points or structure (a facade, a tree, one column of a far wall's
  returns): never fitted."""
  return (len(idx) < s.min_points or np.ptp(pc1_Nx3[idx, :2], axis=0).max() > s.max_size
          or (height_N[idx] > s.object_top).mean() > s.max_high)


def _fit_object(scene: _Scene, pts_Kx3, given_Kx3, rng, vote=None):
  """(start name, motion, truncation) of an object's best motion, or None when standing still
  is not clearly beaten. `given_Kx3`: where a caller's flow takes the points (frame 1), or None;
  `vote`: what a long object's ends say (jaxflow.lidar.along), or None.
  Motions are searched on half the points and judged on the other half: the best of many motions
  fits its own points better than standing still by chance alone."""
  s = scene.settings
  shuffled = pts_Kx3[rng.permutation(len(pts_Kx3))]
  sample, judged = shuffled[0::2][:s.search.points], shuffled[1::2]
  truncate = judge.truncation(pts_Kx3, judged, s)
  allowed = lambda m: scene.plausible(m, judged) and not parts.onto_what_stood(
    scene, judged, (None, m, truncate))
  shifts = grid_search.best_shifts(scene.tree, sample, scene.search, s)
  starts = {"search": next((m for m in shifts if allowed(m)), shifts[0])}  # the best allowed
  if given_Kx3 is not None:
    starts["network"] = rigid.kabsch(pts_Kx3, given_Kx3)
  still_costs = scene.costs(judged, truncate)
  best = "still", rigid.Motion(np.eye(3), np.zeros(3)), still_costs
  for name, start in starts.items():
    for m in (start, _bev_icp(scene.target, sample, start, s)):
      if not allowed(m):
        continue
      c = scene.costs(m.apply(judged), truncate)
      if judge.mean(c, s.judge.min_seen) < judge.mean(best[2], s.judge.min_seen):
        best = name, m, c
  if vote is not None:  # a long object: its ends say where it is along its flat side
    best = along.adopt(scene, judged, truncate, vote, (best, still_costs),
                       lambda m: _bev_icp(scene.target, sample, m, s))
  best_name, best, best_costs = best
  if best_name == "still":
    return None
  if not judge.clearly_better(still_costs, best_costs, s):
    if not slow.evident(scene, judged, best, truncate):
      return None
    best_name += slow.EVIDENCE  # what the margins alone leave still: refined on its faces below
  if best_name == "search" and not grid_search.halves_agree(scene.tree, judged, best,
                                                               scene.search, s):
    return None
  refit = _bev_icp(scene.target, pts_Kx3, best, s)  # chosen on halves: now fitted on all points
  if best_name.endswith(slow.EVIDENCE):  # a slow mover: its faces say where
    plane_fit = scene.evidence.refine(pts_Kx3, refit, truncate, s)
    kept = slow.settled(scene, pts_Kx3, (plane_fit, refit, best), truncate)
    return None if kept is None else (best_name, kept, truncate)
  if best_name.endswith("along"):  # a flat side: the refit slides along it, the ends say where
    refit = along.settle(scene.target, pts_Kx3, refit, vote, s)
  if scene.plausible(refit, pts_Kx3) and judge.mean(
      scene.costs(refit.apply(pts_Kx3), truncate), s.judge.min_seen) <= judge.mean(
      scene.costs(best.apply(pts_Kx3), truncate), s.judge.min_seen):
    best = refit  # (a refit that ran off as far as no object goes in a frame is not)
  return best_name, best, truncate


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


def _scene(pc1, pc2_Mx3, ground1, ground2_M, ego_motion, s, ego_settings, rate, sensor2):
  """The pair's _Scene (pc2 brought into frame 1); None: pc2 has too few points above the ground."""
  pc2_in1 = ego_motion.inverse().apply(pc2_Mx3)
  target = ego.Target(pc2_in1, ground2_M, ego_settings)
  above2 = pc2_in1[~np.asarray(ground2_M, bool)]
  if target.tree is None or len(above2) < 3:
    return None
  before = ego.Target(pc1, ground1, ego_settings)  # pc1 seen from above
  visibility = views.View(pc2_Mx3, "z", s.judge.azimuth_bins, s.judge.elevation_bins,
                          s.judge.hidden, sensor2)
  tree = neighbours.Tree(above2)
  return _Scene(target, tree, _per_point(before, above2) > s.unexplained,
                along.before(pc1, before, ~ground1, above2, s.unexplained), visibility,
                ego_motion, s.search.per_s / rate, s.max_yaw_deg_per_s / rate, s,
                judge.Evidence(tree, visibility, ego_motion, s) if s.judge.evidence else None)


@dataclasses.dataclass
class _Pass:
  """A pair's objects being fitted: what each fit reads, and the flow and motions it writes."""
  scene: _Scene
  pc1: np.ndarray
  ground1: np.ndarray  # bool N
  height: np.ndarray  # N: m above the ground
  unexplained: np.ndarray  # bool N: ego-compensated pc2 does not explain the point (from above)
  given: np.ndarray | None  # N x 3: where the caller's flow takes each point (frame 1)
  surface: object  # jaxflow.lidar.ground.Surface, or None
  seed: int  # each group's draws: its own stream (seed, its first point), whoever else is fitted
  flow: np.ndarray  # N x 3: the ego-motion's, each moved object's written over it
  moved: list = dataclasses.field(default_factory=list)  # Found.moved
  motions: list = dataclasses.field(default_factory=list)  # Found.motions
  candidates: int = 0
  groups: int = 0  # the sweep's object groups

  def fit(self, idx):
    """A group's fit (start name, motion, truncation), or None: a person's shift, or an object's
    motion, every group but structure a candidate (counted) at every speed: what moves is what
    pc2 shows moved (_fit_object's judgement), not what the ego-motion leaves unexplained, which a
    car creeping under 0.15 m a frame leaves nothing of."""
    scene, s, pc1 = self.scene, self.scene.settings, self.pc1
    fit = (person.fit_person(scene, pc1[idx]) if person.is_person(idx, pc1, self.height, s)
           else None)
    if fit is None:
      if _is_structure(idx, self.height, pc1, s):
        return None
      vote = along.group_vote(idx, pc1, scene.tree.points, scene.before, scene.search, s)
      usable = self.given is not None and np.isfinite(self.given[idx]).all()
      fit = _fit_object(scene, pc1[idx], self.given[idx] if usable else None,
                        np.random.default_rng([self.seed, int(idx.min())]), vote)
    self.candidates += 1
    return fit

  def found(self) -> Found:
    return Found(self.groups, self.candidates, self.moved, tuple(self.motions))

  def take_over(self, idx, fit):
    """apply, the points `idx` first taken from the movers that hold them (their entries in
    `moved` and `motions` keep the rest; one left with none is dropped)."""
    kept = []
    for (count, translation, yaw, name), (mine, motion) in zip(self.moved, self.motions):
      mine = mine[~np.isin(mine, idx)]
      if len(mine):
        kept.append(((len(mine), translation, yaw, name), (mine, motion)))
    self.moved, self.motions = [k[0] for k in kept], [k[1] for k in kept]
    self.apply(idx, fit)

  def apply(self, idx, fit):
    """The flow of a fitted group's points that move with it (_moving_parts), and of its own
    lowest points taken as ground."""
    name, best, truncate = fit
    pts = self.pc1[idx]
    if self.surface is not None:
      best = _on_the_ground(best, pts, self.surface)
    moving = _moving_parts(self.scene, pts, best, truncate)
    if name.endswith(slow.EVIDENCE):
      # What stands beside a slow mover (joined to it from above) stays still.
      moving &= ~self.scene.evidence.against(pts, best, truncate, self.scene.settings)
    idx, pts = idx[moving], pts[moving]
    if not len(idx):
      return
    world = best.then(self.scene.ego_motion)
    self.flow[idx] = world.flow(pts)
    self.moved.append((len(idx), best.translation, best.yaw_deg, name))
    self.motions.append((idx, best))
    if self.surface is not None:
      low = _low_ground_under(pts, self.pc1, self.ground1, self.height, self.scene.settings)
      self.flow[low] = world.flow(self.pc1[low])


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
  run = object_pass(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion, surface, start_flow_Nx3,
                    seed, settings, ego_settings, frame_rate_hz, sensor2)
  return run.flow.astype(np.float32), run.found()


def object_pass(pc1_Nx3, pc2_Mx3, ground1_N, ground2_M, ego_motion: rigid.Motion, surface=None,
                start_flow_Nx3=None, seed: int = 0, settings=None, ego_settings=None,
                frame_rate_hz: float | None = None, sensor2=None) -> _Pass:
  """object_flow's work (its arguments), as the _Pass that did it: its flow (float64), what it
  found, and the scene it judged against (None: pc2 has too few points above the ground)."""
  s = DEFAULTS.objects if settings is None else settings
  rate = DEFAULTS.frame_rate_hz if frame_rate_hz is None else frame_rate_hz
  pc1 = np.asarray(pc1_Nx3, np.float64)
  ground1 = np.asarray(ground1_N, bool)
  flow = ego_motion.flow(pc1).astype(np.float64)
  scene = _scene(pc1, pc2_Mx3, ground1, ground2_M, ego_motion, s, ego_settings, rate, sensor2)
  height = surface.height(pc1) if surface is not None else pc1[:, 2] - pc1[ground1, 2].mean() if (
    ground1.any()) else pc1[:, 2] - pc1[:, 2].min()
  if scene is None:
    return _Pass(None, pc1, ground1, height, None, None, surface, seed, flow)
  found = object_groups(pc1, np.where(ground1, -1.0, height), settings=s).without(ground1)
  given = None if start_flow_Nx3 is None else ego_motion.inverse().apply(
    pc1 + np.asarray(start_flow_Nx3, np.float64))
  off = _per_point(scene.target, pc1)  # m from ego-compensated pc2, from above
  run = _Pass(scene, pc1, ground1, height, off > s.unexplained, given, surface, seed, flow,
              groups=found.count)
  if scene.evidence is not None:
    slow.measure_noise(scene, pc1[~ground1 & ~run.unexplained], s)
  still = []
  for _, idx in found.members():
    fit = run.fit(idx)
    if fit is not None and parts.onto_what_stood(scene, pc1[idx], fit):
      fit = None
    if fit is None:
      still.append(idx)
    else:
      run.apply(idx, fit)
  parts.fit_parts(run, still, off)
  return run
