"""The three ways jaxflow estimates a flow, as used by evaluate.py and jaxflow.predict (`--method`).

- `network`: the trained network alone (the paper's protocol; evaluate.py's default).
- `nsfp`: Neural Scene Flow Prior (Li et al. 2021, the paper's Tables 4 and 7 baseline): NSFP's
  MLP optimised per pair from zero flow, no network, no checkpoint (`optimiser.NSFP`).
- `optimise`: the network's flow refined per pair by the fast optimiser (distance-grid Chamfer +
  smoothness, then the piecewise-rigid steps of jaxflow.methods.rigid_clusters, an exact polish, and
  the scene's rigid bodies fitted to pc2 by jaxflow.methods.bodies): the recommended method for
  pairs that are not raw LiDAR sweeps (those take `predict --lidar`, jaxflow.lidar.sweep), and
  predict's default.

    fn = flow_fn("optimise", network)   # network: (params, pc1, pc2) -> flow, B x N x 3
    flow_BxNx3 = fn(params, pc1_BxNx3, pc2_BxMx3)
"""

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxflow import configfile
from jaxflow.errors import ConfigError
from jaxflow.methods import bodies, objectives, optimiser, rigid_clusters

METHODS = ("network", "nsfp", "optimise")
NEEDS_NETWORK = ("network", "optimise")
# The nsfp method: NSFP's published settings, its exact two-way Chamfer (nearest points by k-d tree
# every step, ~60 ms a step at 8192 points on a 2-core CPU). The one-way distance grid is faster but
# far less accurate for NSFP on FT3D (benchmarks/METHODS.md).
NSFP = optimiser.NSFP


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


def settings(method: str, steps: int | None = None, iters: int | None = None,
             objective: str | None = None, fields: dict | None = None):
  """The settings of a method (None for `network`): its defaults; `steps` caps the optimiser's
  steps (optimise's rigid-bodies stage counts none: it runs whatever `steps`); `iters`: the
  network's iterations for optimise's starting flow; `objective`: NSFP's (exact or grid); then
  `fields`, {dotted field: value} at any depth (e.g. {"bodies.inlier": 0.1}; the command line's
  --method.optimise.bodies.inlier=0.1; configfile.replace_settings)."""
  if method not in METHODS:
    raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
  if objective is not None and method != "nsfp":
    raise ConfigError(f"--objective chooses NSFP's objective: it needs --method nsfp, not {method}")
  if method == "network":
    if fields:
      raise ConfigError(f"--method network has no settings to set ({', '.join(fields)}); the "
                        "network's are the config's (--config.model.FIELD)")
    return None
  chosen = _defaults(method, steps, iters, objective)
  return configfile.replace_settings(chosen, fields, f"method.{method}") if fields else chosen


def _defaults(method: str, steps: int | None, iters: int | None, objective: str | None):
  """The method's defaults with --steps, --iters and --objective applied."""
  if steps is not None and steps < 0:
    raise ConfigError(f"--steps must be >= 0, got {steps}")
  if method == "nsfp":
    if objective is not None and objective not in optimiser.OBJECTIVES:
      raise ConfigError(f"--objective must be one of {', '.join(optimiser.OBJECTIVES)}, "
                        f"got {objective!r}")
    return dataclasses.replace(NSFP, **({} if steps is None else {"steps": steps}),
                               **({} if objective is None else {"objective": objective}))
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


def start_network(model, num_iters: int, chosen: Optimise):
  """(model, iterations) of optimise's starting flow: `model` with at most
  `chosen.start_candidates` correlation candidates, and `chosen.start_iters` (else `num_iters`)
  iterations."""
  if chosen.start_candidates and model is not None:
    model = model.clone(truncate_k=min(chosen.start_candidates, model.truncate_k))
  return model, chosen.start_iters or num_iters


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


def flow_fn(method: str, network=None, chosen=None, with_info: bool = False):
  """(params, pc1 B x N x 3, pc2 B x M x 3) -> flow B x N x 3 of `method` (with `with_info`:
  (flow, info), info None for `network`). `network(params, pc1, pc2)` gives the network's flow;
  `chosen`: the method's settings (default `settings(method)`). For `network` a jitted function
  (`.lower` compiles it ahead); nsfp and optimise are driven from Python between compiled stages
  (optimiser.optimise_host_loop, optimise_flow): call them, do not jit them."""
  chosen = settings(method) if chosen is None else chosen
  if method in NEEDS_NETWORK and network is None:
    raise ConfigError(f"method {method!r} needs a network")
  if method == "network":
    run = jax.jit(lambda params, pc1, pc2: (network(params, pc1, pc2), None))
  elif method == "nsfp":
    run = lambda params, pc1, pc2: optimiser.optimise_host_loop(jnp.zeros_like(pc1), pc1, pc2,
                                                                chosen)
  else:
    start = jax.jit(network)
    run = lambda params, pc1, pc2: optimise_flow(start(params, pc1, pc2), pc1, pc2, chosen)
  if with_info:
    return run
  if method == "network":
    return jax.jit(lambda *args: run(*args)[0])
  return lambda *args: run(*args)[0]


def describe(method: str, chosen) -> dict:
  """The method and its settings, for results files."""
  if chosen is None:
    return {"method": method}
  return {"method": method, "method_settings": dataclasses.asdict(chosen)}


def convergence_note(method: str, info) -> str | None:
  """A line for the user when an optimisation did not converge (None when it did)."""
  if info is None:
    return None
  finite = np.asarray(info["finite"])
  if not finite.all():
    return f"{method}: the optimisation diverged (non-finite flow); the starting flow is returned"
  if method == "nsfp" and not np.asarray(info["stopped"]).all():
    return (f"{method}: early stopping did not fire within {int(np.max(info['steps']))} steps; "
            "the flow of the lowest loss is returned but may not have converged")
  return None


def evaluation_note(method: str, convergence: dict | None) -> str | None:
  """A line for evaluate.py's user when some pairs' optimisation did not converge."""
  if not convergence:
    return None
  notes = []
  if convergence["non_finite"]:
    notes.append(f"{convergence['non_finite']} of {convergence['pairs']} pairs diverged "
                 "(non-finite flow; their starting flow was kept)")
  if method == "nsfp" and convergence["early_stopped"] < convergence["pairs"]:
    running = convergence["pairs"] - convergence["early_stopped"]
    notes.append(f"early stopping did not fire on {running} of {convergence['pairs']} pairs "
                 "(their lowest-loss flow was used)")
  return f"{method}: " + "; ".join(notes) if notes else None


def network_fn(model, num_iters: int, refine: bool):
  """(params, pc1, pc2) -> the network's flow B x N x 3: the refined flow, or the last
  iteration's."""

  def network(params, pc1_BxNx3, pc2_BxMx3):
    out = model.apply({"params": params}, pc1_BxNx3, pc2_BxMx3, num_iters=num_iters, refine=refine)
    return out["refined"] if refine else out["flows"][:, -1]

  return network


def model_predict_fn(model, num_iters: int, refine: bool, method: str = "network",
                     method_settings=None, with_info: bool = False):
  """(params, pc1, pc2) -> flow B x N x 3 of `method` (flow_fn; model None for
  nsfp), with `with_info` (flow, info) (info None for `network`)."""
  if method == "optimise":  # its starting flow's iterations and candidates are its settings
    method_settings = settings(method) if method_settings is None else method_settings
    model, num_iters = start_network(model, num_iters, method_settings)
  network = None if model is None else network_fn(model, num_iters, refine)
  return flow_fn(method, network, method_settings, with_info)
