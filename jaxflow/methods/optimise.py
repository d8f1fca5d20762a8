"""The `optimise` method: the network's flow refined per pair by the fast optimiser (distance-grid
Chamfer + smoothness, then the piecewise-rigid steps of jaxflow.methods.rigid_clusters, an exact
polish, and the scene's rigid bodies fitted to pc2 by jaxflow.methods.bodies): the recommended
method for pairs that are not raw LiDAR sweeps (those take the `lidar` method), and predict's
default."""

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxflow.errors import ConfigError
from jaxflow.methods import bodies, objectives, optimiser, rigid_clusters
from jaxflow.methods.interface import Method


@dataclasses.dataclass(frozen=True)
class Optimise:
  """The `optimise` method: from the network's flow after `start_iters` iterations, `descent` (the
  flow optimised as free vectors on the distance grid); then, for `rigid_steps` > 0, clusters of
  points that move together (jaxflow.methods.rigid_clusters) each get the rigid motion of their
  flow, optimised against pc2 for `rigid_steps` steps (6 numbers a cluster); then `polish`:
  free-vector steps from that flow on the exact two-way Chamfer (nearest points by k-d tree), which
  the one-way grid cannot give (steps 0: none); then `bodies` (None: none): the scene's rigid bodies
  found in that flow and fitted to pc2 (jaxflow.methods.bodies, on the host: one
  device-host round trip a batch)."""
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
  """Seconds of each stage into `seconds` (None: no clock, nothing waited for)."""

  def __init__(self, seconds: dict | None):
    self.seconds, self.last = seconds, time.perf_counter()

  def __call__(self, stage: str, *arrays):
    if self.seconds is not None:
      jax.block_until_ready(arrays)
      now = time.perf_counter()
      self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self.last
      self.last = now


def optimise_flow(init_BxNx3, pc1_BxNx3, pc2_BxMx3, chosen: Optimise, seconds=None):
  """The `optimise` method's flow from a starting flow (the network's), and the info of its first
  optimisation (jaxflow.methods.optimiser.optimise). Driven from Python: the searches (pc1's kNN
  graph, the distance grid, the polish's nearest points) run between compiled stages, so that no
  compiled program calls back to the host (JAX's persistent compilation cache keeps only such
  programs).
  `seconds`: a dict that gets each stage's seconds (each stage then waited for: a profile)."""
  clock = _Clock(seconds)
  clock("start", init_BxNx3, pc1_BxNx3, pc2_BxMx3)
  search = chosen.descent.search
  grids = optimiser.distance_grids(pc1_BxNx3, pc2_BxMx3, chosen.descent, now=True)
  k = max(chosen.descent.neighbours, chosen.polish.neighbours, chosen.clusters.neighbours)
  graph = objectives.knn_now(pc1_BxNx3, pc1_BxNx3, k + 1, search)  # each point first
  nbr = lambda settings: graph[:, :, 1:settings.neighbours + 1]
  clock("grid and kNN graph", grids, graph)
  flow, info = optimiser.optimise(init_BxNx3, pc1_BxNx3, pc2_BxMx3, chosen.descent, grids=grids,
                                  nbr_BxNxK=nbr(chosen.descent))
  clock("descent", flow)
  if chosen.rigid_steps:
    labels, fitted = _rigid_stage(pc1_BxNx3, pc2_BxMx3, flow, grids,
                                  graph[:, :, :chosen.clusters.neighbours + 1], chosen)
    clock("rigid clusters", fitted)
    if chosen.choose:
      matches = [objectives.nearest_now(pc1_BxNx3 + f, pc2_BxMx3, search) for f in (flow, fitted)]
      fitted = _choose(labels, flow, fitted, pc1_BxNx3, pc2_BxMx3, matches, chosen.descent.truncate)
      clock("rigid clusters", fitted)
    flow = fitted
  if chosen.polish.steps:
    flow = optimiser.optimise_host_loop(flow, pc1_BxNx3, pc2_BxMx3, chosen.polish,
                                        nbr_BxNxK=nbr(chosen.polish))[0]
    clock("polish", flow)
  if chosen.bodies is not None:
    flow = rigid_bodies_flow(pc1_BxNx3, pc2_BxMx3, flow, chosen.bodies)
    clock("rigid bodies", flow)
  return flow, info


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


def rigid_bodies_flow(pc1_BxNx3, pc2_BxMx3, flow_BxNx3, chosen: bodies.Settings):
  """jaxflow.methods.bodies.rigid_bodies of each pair of a batch (NumPy on the host), as a jax array."""
  return jnp.asarray(np.stack([bodies.rigid_bodies(a, b, f, chosen)[0] for a, b, f in
                               zip(*map(np.asarray, (pc1_BxNx3, pc2_BxMx3, flow_BxNx3)))]))


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
