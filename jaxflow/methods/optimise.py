"""The `optimise` method: the network's flow refined per pair by the fast optimiser (distance-grid
Chamfer + smoothness, then the piecewise-rigid steps of jaxflow.refine.rigid_clusters, an exact
polish, the scene's rigid bodies fitted to pc2 by jaxflow.refine.bodies, and the world's motion
registered by GICP, each stage adopted only where pc2 supports it): the recommended method for
pairs that are not raw LiDAR sweeps (those take the `lidar` method), and predict's default."""

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxflow.errors import ConfigError
from jaxflow.geometry import groups, neighbours, registration
from jaxflow.geometry.visibility import View
from jaxflow.lidar import ego
from jaxflow.refine import bodies, optimiser, progress, rigid_clusters
from jaxflow.methods.interface import Method


@dataclasses.dataclass(frozen=True)
class Guard:
  """When a group of points keeps the flow a stage was given rather than the stage's own
  (jaxflow.geometry.groups.given_kept): where pc2 sees under `min_seen` of the group moved by the
  stage's flow, or where the given flow places the group nearer pc2's surfaces by `margin` m on
  average and by `significance` standard errors, on the points pc2 sees both ways. Distances to
  pc2's local planes, truncated at `truncate` m; a point over `hidden` m behind pc2's nearest
  return in its direction (directions binned by `view_bin_deg` degrees), or outside pc2's view, is
  no evidence."""
  margin: float = 0.01
  significance: float = 2.0
  min_seen: float = 0.3
  truncate: float = 0.3
  hidden: float = 0.5
  view_bin_deg: float = 1.0

  def __post_init__(self):
    for name in ("margin", "significance"):
      if not getattr(self, name) >= 0:
        raise ValueError(f"optimise guard.{name} must be >= 0, got {getattr(self, name)!r}")
    if not 0 <= self.min_seen <= 1:
      raise ValueError(f"optimise guard.min_seen must be in [0, 1], got {self.min_seen!r}")
    for name in ("truncate", "hidden", "view_bin_deg"):
      if not getattr(self, name) > 0:
        raise ValueError(f"optimise guard.{name} must be > 0, got {getattr(self, name)!r}")

  def rule(self) -> groups.Rule:
    return groups.Rule(margin=self.margin, significance=self.significance, min_seen=self.min_seen)

  def evidence(self, pc2_Mx3) -> groups.Evidence:
    """What pc2 (in the model frame: y up, the sensor at the origin) shows. A cloud whose centre
    lies farther from the origin than any of its points from that centre was not seen from the
    origin (a map frame's coordinates): there every placement counts as seen."""
    centre = pc2_Mx3.mean(0)
    view = None
    if np.linalg.norm(centre) <= np.linalg.norm(pc2_Mx3 - centre, axis=1).max(initial=0.0):
      bins = round(360 / self.view_bin_deg), round(180 / self.view_bin_deg)
      view = View(pc2_Mx3, "y", *bins, self.hidden)
    return groups.Evidence(registration.PlaneTarget(pc2_Mx3), view, self.truncate)


@dataclasses.dataclass(frozen=True)
class World:
  """The scene's one rigid motion registered on the whole pair by GICP (jaxflow.lidar.ego.estimate),
  given to each point whose `neighbours` nearest points of pc1 it places as near pc2's local planes
  (distances truncated at `truncate` m) as the flow does, within `tie` m, and whose flow it moves
  by over `min_change` m: the descent's point-to-point Chamfer lets a static world seen as walls
  slide along them, a registration of surfaces does not; nearer than a registration's accuracy the
  free flow is the finer. A cluster of the flow that the world's motion fits worse by over `veto`
  m on average keeps its flow whole: a mover's roof or flank, parallel to its motion, cannot tell
  one motion from the other."""
  # tie, min_change and veto chosen on the generator's LiDAR val split (8 pairs, seeds 0-4), the
  # KITTI frame unchanged (benchmarks/STABILITY.md).
  neighbours: int = 16
  tie: float = 0.005
  min_change: float = 0.05
  veto: float = 0.03
  truncate: float = 0.3

  def __post_init__(self):
    if not isinstance(self.neighbours, int) or self.neighbours < 1:
      raise ValueError("optimise world.neighbours must be an integer >= 1, got "
                       f"{self.neighbours!r}")
    for name in ("tie", "min_change", "veto"):
      if not getattr(self, name) >= 0:
        raise ValueError(f"optimise world.{name} must be >= 0, got {getattr(self, name)!r}")
    if not self.truncate > 0:
      raise ValueError(f"optimise world.truncate must be > 0, got {self.truncate!r}")


@dataclasses.dataclass(frozen=True)
class Optimise:
  """The `optimise` method: from the network's flow after `start_iters` iterations, `descent` (the
  flow optimised as free vectors on the distance grid); then, for `rigid_steps` > 0, clusters of
  points that move together (jaxflow.refine.rigid_clusters) each get the rigid motion of their
  flow, optimised against pc2 for `rigid_steps` steps (6 numbers a cluster); then `polish`:
  free-vector steps from that flow on the exact two-way Chamfer (nearest points by k-d tree), which
  the one-way grid cannot give (steps 0: none); then `bodies` (None: none): the scene's rigid bodies
  found in that flow and fitted to pc2 (jaxflow.refine.bodies, on the host: one
  device-host round trip a batch). After each of the last three, `guard` (None: none): each group
  of points (the rigid clusters of the flow a stage was given, or the bodies' motions) keeps the
  flow it was given where pc2 does not support the stage's own (Guard). Last, `world` (None: none):
  the scene's GICP motion where it fits pc2 as well as the flow (World), also guarded."""
  # The network's iterations for the starting flow (None: the caller's, e.g. --iters) and its
  # correlation candidates (None: the model's, config.model.infer_truncate_k): 8 and 64 instead of
  # 32 and 512 take the network's start from ~10 to ~3 s a pair at 8192 points, and the method's
  # EPE on the 21 real FT3D pairs is no worse (benchmarks/SPEED.md).
  start_iters: int | None = 8
  start_candidates: int | None = 64
  descent: optimiser.Settings = optimiser.Settings(
    model="flow", objective="grid", steps=400, learning_rate=0.05, smoothness=1.0)
  clusters: rigid_clusters.Settings = rigid_clusters.Settings()
  rigid_steps: int = 150
  rigid_learning_rate: float = 0.01
  choose: bool = True  # per cluster, keep the rigid flow only where it fits pc2 better
  # Chosen on the synthetic val pairs (benchmarks/METHODS.md): 200 steps at lr 0.02.
  polish: optimiser.Settings = optimiser.Settings(
    model="flow", objective="exact", steps=200, learning_rate=0.02, smoothness=1.0, refresh=5)
  bodies: "bodies.Settings | None" = bodies.Settings()  # (a string: the field hides the module)
  # Each stage after the descent adopts its flow group by group only where pc2 supports it (None:
  # unguarded): a stage turned a few micrometres of change in its start into metres of error.
  guard: Guard | None = Guard()
  world: World | None = World()  # the last stage (None: none)

  def __post_init__(self):
    for name in ("start_iters", "start_candidates"):
      value = getattr(self, name)
      if value is not None and (not isinstance(value, int) or value < 1):
        raise ValueError(f"optimise {name} must be None or an integer >= 1, got {value!r}")
    if not isinstance(self.rigid_steps, int) or self.rigid_steps < 0:
      raise ValueError(f"optimise rigid_steps must be an integer >= 0, got {self.rigid_steps!r}")
    if not self.rigid_learning_rate > 0:
      raise ValueError("optimise rigid_learning_rate must be > 0, got "
                       f"{self.rigid_learning_rate!r}")


class _Clock:
  """Seconds of each stage into `seconds` (None: no clock, nothing waited for), and the flow after
  each of STAGES into `flows` (None: not kept; a stage's last call is its flow)."""

  def __init__(self, seconds: dict | None, flows: dict | None = None):
    self.seconds, self.flows, self.last = seconds, flows, time.perf_counter()

  def __call__(self, stage: str, *arrays):
    progress.stage(f"{stage} done")  # what a log's progress line says (jaxflow.refine.progress)
    if self.flows is not None and stage in STAGES:
      self.flows[stage] = arrays[0]
    if self.seconds is not None:
      jax.block_until_ready(arrays)
      now = time.perf_counter()
      self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self.last
      self.last = now


STAGES = ("descent", "rigid clusters", "polish", "rigid bodies", "world")


def optimise_flow(init_BxNx3, pc1_BxNx3, pc2_BxMx3, chosen: Optimise, seconds=None, flows=None,
                  resume=None):
  """The `optimise` method's flow from a starting flow (the network's), and the info of its first
  optimisation (jaxflow.refine.optimiser.optimise). Driven from Python: the searches (pc1's kNN
  graph, the distance grid, the polish's nearest points) run between compiled stages, so that no
  compiled program calls back to the host (JAX's persistent compilation cache keeps only such
  programs).
  `seconds`: a dict that gets each stage's seconds (each stage then waited for: a profile).
  `flows`: a dict that gets the flow after each stage run (STAGES). `resume`: (a stage, its flow)
  from an earlier call: that stage and those before it are not run again (info None); variants of
  the later stages then share the earlier ones (benchmarks/optimise_changes.py)."""
  after = -1 if resume is None else STAGES.index(resume[0])
  runs = lambda stage: STAGES.index(stage) > after
  clock = _Clock(seconds, flows)
  clock("start", init_BxNx3, pc1_BxNx3, pc2_BxMx3)
  guarded = Guarded(pc1_BxNx3, pc2_BxMx3, chosen.guard)
  search = chosen.descent.search
  grids = (optimiser.distance_grids(pc1_BxNx3, pc2_BxMx3, chosen.descent, now=True)
           if runs("rigid clusters") else None)
  k = max(chosen.descent.neighbours, chosen.polish.neighbours, chosen.clusters.neighbours)
  graph = neighbours.knn_now(pc1_BxNx3, pc1_BxNx3, k + 1, search)  # each point first
  nbr = lambda settings: graph[:, :, 1:settings.neighbours + 1]
  clock("grid and kNN graph", grids, graph)
  if runs("descent"):
    flow, info = optimiser.optimise(init_BxNx3, pc1_BxNx3, pc2_BxMx3, chosen.descent, grids=grids,
                                    nbr_BxNxK=nbr(chosen.descent))
    clock("descent", flow)
  else:
    flow, info = resume[1], None
  if chosen.rigid_steps and runs("rigid clusters"):
    labels, fitted = _rigid_stage(pc1_BxNx3, pc2_BxMx3, flow, grids,
                                  graph[:, :, :chosen.clusters.neighbours + 1], chosen)
    clock("rigid clusters", fitted)
    if chosen.choose:
      matches = [neighbours.nearest_now(pc1_BxNx3 + f, pc2_BxMx3, search) for f in (flow, fitted)]
      fitted = _choose(labels, flow, fitted, pc1_BxNx3, pc2_BxMx3, matches, chosen.descent.truncate)
    flow = guarded(labels, fitted, flow)
    clock("rigid clusters", flow)
  if chosen.polish.steps and runs("polish"):
    polished = optimiser.optimise_host_loop(flow, pc1_BxNx3, pc2_BxMx3, chosen.polish,
                                            nbr_BxNxK=nbr(chosen.polish))[0]
    if guarded.active:
      labels = _clusters(pc1_BxNx3, flow, graph[:, :, :chosen.clusters.neighbours + 1],
                         chosen.clusters)
      polished = guarded(labels, polished, flow)
    flow = polished
    clock("polish", flow)
  if chosen.bodies is not None and runs("rigid bodies"):
    fitted, motion_of = rigid_bodies_flow(pc1_BxNx3, pc2_BxMx3, flow, chosen.bodies)
    flow = guarded(motion_of, fitted, flow)
    clock("rigid bodies", flow)
  if chosen.world is not None:
    labels = _clusters(pc1_BxNx3, flow, graph[:, :, :chosen.clusters.neighbours + 1],
                       chosen.clusters)
    taken, flow_to = world_flow(pc1_BxNx3, pc2_BxMx3, flow, labels,
                                registered_world(pc1_BxNx3, pc2_BxMx3), chosen.world,
                                guarded.targets())
    flow = guarded(np.where(taken, 0, -1), flow_to, flow)
    clock("world", flow)
  return flow, info


# The model frame is y up; jaxflow.lidar.ego registers z-up sweeps: (x, y, z) -> (z, x, y).
_Z_UP = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def registered_world(pc1_BxNx3, pc2_BxMx3) -> np.ndarray:
  """Per pair, the flow of the scene's one rigid motion registered by GICP (B x N x 3)."""
  out = []
  for pc1, pc2 in zip(np.asarray(pc1_BxNx3, np.float64), np.asarray(pc2_BxMx3, np.float64)):
    found = ego.estimate(pc1 @ _Z_UP.T, pc2 @ _Z_UP.T).motion
    out.append(((pc1 @ _Z_UP.T) @ found.rotation.T + found.translation) @ _Z_UP - pc1)
  return np.stack(out)


def world_flow(pc1_BxNx3, pc2_BxMx3, flow_BxNx3, labels_BxN, by_world_BxNx3, world: World,
               targets=None):
  """Per pair, the points given the world's motion (B x N) and the flow with it (World).
  `labels_BxN`: the clusters of the flow (jaxflow.refine.rigid_clusters); `by_world_BxNx3`: the
  world's flow (registered_world); `targets`: each pair's registration.PlaneTarget of pc2 where
  one is built already (the guard's), None: built here."""
  taken, out = [], []
  pc2s = np.asarray(pc2_BxMx3, np.float64)
  targets = [registration.PlaneTarget(p) for p in pc2s] if targets is None else targets
  for pc1, flow, by_world, label, target in zip(
      *(np.asarray(a, np.float64) for a in (pc1_BxNx3, flow_BxNx3, by_world_BxNx3)),
      np.asarray(labels_BxN), targets):
    costs = [target.plane_distance(pc1 + f, world.truncate) for f in (by_world, flow)]
    near = neighbours.Tree(pc1).knn(pc1, world.neighbours)
    take = ((costs[0][near].mean(1) <= costs[1][near].mean(1) + world.tie)
            & (np.linalg.norm(by_world - flow, axis=1) > world.min_change))
    _, group = np.unique(label, return_inverse=True)
    worse = np.bincount(group, costs[0] - costs[1]) > world.veto * np.bincount(group)
    take &= ~worse[group]
    taken.append(take)
    out.append(np.where(take[:, None], by_world, flow))
  return np.stack(taken), np.stack(out).astype(np.float32)


class Guarded:
  """guarded(labels B x N, new, given) -> per pair, each group's new flow where pc2 supports it
  and its given flow elsewhere (Guard; None: the new flow everywhere)."""

  def __init__(self, pc1_BxNx3, pc2_BxMx3, guard: Guard | None):
    self.active = guard is not None
    if self.active:
      self.rule, self.pc1 = guard.rule(), np.asarray(pc1_BxNx3, np.float64)
      self.evidence = [guard.evidence(p) for p in np.asarray(pc2_BxMx3, np.float64)]

  def targets(self):
    """Each pair's PlaneTarget of pc2 (None when unguarded: none built)."""
    return [e.target for e in self.evidence] if self.active else None

  def __call__(self, labels_BxN, new_BxNx3, given_BxNx3):
    if not self.active:
      return new_BxNx3
    new, given = np.asarray(new_BxNx3), np.asarray(given_BxNx3)
    out = []
    for b, label_N in enumerate(np.asarray(labels_BxN)):
      found, label_N = np.unique(label_N, return_inverse=True)
      label_N = np.where(found[label_N] < 0, -1, label_N - (found < 0).sum())  # -1: no group
      costs = [self.evidence[b].costs(self.pc1[b] + f[b]) for f in (new, given)]
      keep = groups.given_kept(groups.Groups(label_N, len(found) - (found < 0).sum()), *costs,
                               self.rule)
      out.append(np.where(keep[:, None], given[b], new[b]))
    return jnp.asarray(np.stack(out))


@functools.partial(jax.jit, static_argnames="chosen")
def _rigid_stage(pc1_BxNx3, pc2_BxMx3, flow_BxNx3, grids, graph_BxNxK, chosen: Optimise):
  """The clusters of the flow and their rigid motions optimised against pc2 (labels, flow)."""
  labels = rigid_clusters.clusters(pc1_BxNx3, flow_BxNx3, chosen.clusters, graph_BxNxK)
  motions = rigid_clusters.fit(pc1_BxNx3, flow_BxNx3, labels, chosen.clusters.min_points,
                               chosen.descent.precision)
  stage = dataclasses.replace(chosen.descent, model="rigid", steps=chosen.rigid_steps,
                              learning_rate=chosen.rigid_learning_rate, smoothness=0.0)
  return labels, optimiser.optimise(flow_BxNx3, pc1_BxNx3, pc2_BxMx3, stage, (labels, *motions),
                                    grids)[0]


@functools.partial(jax.jit, static_argnames="truncate")
def _choose(labels, flow, fitted, pc1_BxNx3, pc2_BxMx3, matches, truncate: float):
  return rigid_clusters.choose(labels, (flow, fitted), pc1_BxNx3, pc2_BxMx3, truncate,
                               matches=matches)


@functools.partial(jax.jit, static_argnames="settings")
def _clusters(pc1_BxNx3, flow_BxNx3, graph_BxNxK, settings: rigid_clusters.Settings):
  return rigid_clusters.clusters(pc1_BxNx3, flow_BxNx3, settings, graph_BxNxK)


def rigid_bodies_flow(pc1_BxNx3, pc2_BxMx3, flow_BxNx3, chosen: bodies.Settings):
  """jaxflow.refine.bodies.rigid_bodies of each pair of a batch (NumPy on the host): the flow (a
  jax array) and each point's motion (B x N; -1: none, its flow unchanged)."""
  flows, motion_of = [], []
  for a, b, f in zip(*map(np.asarray, (pc1_BxNx3, pc2_BxMx3, flow_BxNx3))):
    flow, found = bodies.rigid_bodies(a, b, f, chosen)
    flows.append(flow)
    motion_of.append(np.full(len(a), -1) if found.motion_of is None else found.motion_of)
  return jnp.asarray(np.stack(flows)), np.stack(motion_of)


def _defaults(steps, iters, objective):
  """Optimise's defaults with --steps (capping every stage's steps but the rigid bodies') and
  --iters (its starting flow's iterations)."""
  del objective  # NSFP's
  chosen = Optimise()
  if iters is not None:
    if iters < 1:
      raise ConfigError(f"--iters must be >= 1, got {iters}")
    chosen = dataclasses.replace(chosen, start_iters=iters)
  if steps is not None:
    chosen = dataclasses.replace(chosen, descent=dataclasses.replace(chosen.descent, steps=steps),
                                 rigid_steps=min(chosen.rigid_steps, steps),
                                 polish=dataclasses.replace(
                                   chosen.polish, steps=min(chosen.polish.steps, steps)))
  return chosen


def _build(network_for, chosen: Optimise):
  start = jax.jit(network_for(chosen.start_iters, chosen.start_candidates))
  return lambda params, pc1, pc2: optimise_flow(start(params, pc1, pc2), pc1, pc2, chosen)


METHOD = Method("optimise", "the network's flow refined per pair against the whole clouds",
                up="y", needs_network=True, defaults=_defaults, build=_build)
