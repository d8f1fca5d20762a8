"""The flow methods of jaxflow by name, as evaluate.py, jaxflow.predict, the API and the benchmarks
use them (`--method`). Each is one module with a `METHOD` (jaxflow.methods.interface.Method):

- `network`: the trained network alone (the paper's protocol; evaluate.py's default);
- `nsfp`: the NSFP baseline, an MLP optimised per pair, no checkpoint (jaxflow.methods.nsfp);
- `optimise`: the network's flow refined per pair (jaxflow.methods.optimise; predict's default);
- `lidar`: raw LiDAR sweeps, ground, ego-motion and moving objects, a method's flow of their points
  only where its settings ask (jaxflow.methods.lidar; predict --lidar).

    fn = model_predict_fn(model, num_iters=32, refine=False, method="optimise")
    flow_BxNx3 = fn(params, pc1_BxNx3, pc2_BxMx3)      # in the method's frame (METHODS[...].up)

A new method is a module with a METHOD, passed to `register` (docs/contributing.md); callers ask
its properties (interface.Method), never its name.
"""

import dataclasses
import functools

import jax
import numpy as np

from jaxflow.runtime import configfile
from jaxflow.errors import ConfigError
from jaxflow.methods import lidar, network, nsfp, optimise
from jaxflow.methods.interface import Method

REGISTRY: dict[str, Method] = {}
METHODS: tuple = ()


def register(method: Method):
  """Adds a method under its name (a new one, or a name's replacement: a test's toy method)."""
  global METHODS  # pylint: disable=global-statement  (the names --method offers, in order)
  REGISTRY[method.name] = method
  METHODS = tuple(REGISTRY)


def nested(method: str) -> Method:
  """The method a raw-sweep method runs on the sweeps' points (method.lidar.method)."""
  chosen = get(method)
  if chosen.raw_sweeps:
    raise ConfigError(f"method.lidar.method: {method!r} reads raw sweeps itself, not their points")
  return chosen


def _nested_run(method: str, network_for):
  return build(method, network_for), nested(method).up


for _method in (network.METHOD, nsfp.METHOD,
                # optimise refines the network's flow at every point (its module's owner may say
                # so in its METHOD; until then it is said here).
                dataclasses.replace(optimise.METHOD, refines_start=True),
                # the lidar method runs the others through the registry (no import back up)
                dataclasses.replace(lidar.METHOD, build=lidar.builder(_nested_run))):
  register(_method)


def get(method: str) -> Method:
  """The Method of a name; a ConfigError naming the methods for any other."""
  if method not in REGISTRY:
    raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
  return REGISTRY[method]


def settings(method: str, steps: int | None = None, iters: int | None = None,
             objective: str | None = None, fields: dict | None = None):
  """The settings of a method (None for `network`), a frozen dataclass: its defaults with `steps`
  (the optimiser's cap), `iters` (optimise's starting flow's network iterations), `objective`
  (NSFP's) applied, then `fields`, {dotted field: value} at any depth (e.g. {"bodies.inlier":
  0.1}; the command line's --method.optimise.bodies.inlier=0.1; configfile.replace_settings)."""
  chosen_method = get(method)
  if objective is not None and not chosen_method.objectives:
    takes = [name for name, m in REGISTRY.items() if m.objectives]
    raise ConfigError(f"--objective chooses the objective of {' or '.join(takes)}: it needs "
                      f"--method {takes[0]}, not {method}")
  if steps is not None and steps < 0:
    raise ConfigError(f"--steps must be >= 0, got {steps}")
  chosen = chosen_method.defaults(steps, iters, objective)
  if fields and chosen is None:
    raise ConfigError(f"--method {method} has no --method.{method}.* settings "
                      f"({', '.join(fields)}); its settings are the config's "
                      "(--config.model.FIELD)")
  return configfile.replace_settings(chosen, fields, f"method.{method}") if fields else chosen


def network_fn(model, num_iters: int, refine: bool):
  """(params, pc1, pc2) -> the network's flow B x N x 3: the refined flow, or the last
  iteration's."""

  def network(params, pc1_BxNx3, pc2_BxMx3):
    out = model.apply({"params": params}, pc1_BxNx3, pc2_BxMx3, num_iters=num_iters, refine=refine)
    return out["refined"] if refine else out["flows"][:, -1]

  return network


def network_for(model, num_iters: int, refine: bool):
  """network_for(iters=None, candidates=None) -> network_fn of `model` with those iterations (None:
  `num_iters`) and at most that many correlation candidates (None: the model's); None without a
  model."""

  def make(iters: int | None = None, candidates: int | None = None):
    if model is None:
      return None
    chosen = model if not candidates else model.clone(truncate_k=min(candidates, model.truncate_k))
    return network_fn(chosen, iters or num_iters, refine)

  return make


def flow_fn(method: str, network=None, chosen=None, with_info: bool = False):
  """(params, pc1 B x N x 3, pc2 B x M x 3) -> flow B x N x 3 of `method` (with `with_info`:
  (flow, info), info None unless an optimiser ran), in the method's frame. `network(params, pc1,
  pc2)` gives the network's flow (whatever iterations the method asks for; model_predict_fn builds
  them); `chosen`: the method's settings (default `settings(method)`). A jitted method's function
  is jitted (`.lower` compiles it ahead); the others are driven from Python between compiled
  stages: call them, do not jit them."""
  return build(method, lambda iters=None, candidates=None: network, chosen, with_info)


def build(method: str, network_for, chosen=None, with_info: bool = False):
  """flow_fn's function from `network_for(iters=None, candidates=None)` (network_for's), which may
  give None where no network is loaded."""
  chosen_method = get(method)
  chosen = settings(method) if chosen is None else chosen
  if chosen_method.needs_network and network_for() is None:
    raise ConfigError(f"method {method!r} needs a network")
  run = chosen_method.build(network_for, chosen)
  if with_info:
    return run
  if chosen_method.jitted:
    return jax.jit(lambda *args: run(*args)[0])
  return lambda *args: run(*args)[0]


def model_predict_fn(model, num_iters: int, refine: bool, method: str = "network",
                     method_settings=None, with_info: bool = False):
  """(params, pc1, pc2) -> flow B x N x 3 of `method` (flow_fn; model None for the methods without
  a network), with `with_info` (flow, info). The same arguments give the same function, so a
  second evaluation or prediction of a model in one process reuses its traced and compiled
  programs (a model and settings are frozen dataclasses, equal when their fields are)."""
  return _model_predict_fn(model, num_iters, refine, method, get(method), method_settings,
                           with_info)


@functools.lru_cache(maxsize=16)
def _model_predict_fn(model, num_iters, refine, method, registered, method_settings, with_info):
  del registered  # (in the key: a method registered again under its name is built again)
  return build(method, network_for(model, num_iters, refine), method_settings, with_info)


def network_asked(method: str, chosen) -> tuple | None:
  """(iters, candidates) of the network `method` asks network_for for with its settings `chosen`
  (None: the caller's), or None when it asks for none: what it starts from."""
  asked = []

  def network_for(iters=None, candidates=None):
    asked.append((iters, candidates))
    return lambda params, pc1, pc2: pc1  # never called: the method is built, not run

  get(method).build(network_for, chosen)
  return asked[0] if asked else None


def describe_settings(method: str, chosen) -> str:
  """--print_config's lines of a method's settings (configfile.describe_settings). Settings that
  extend another block (lidar's: the pipeline's Sweep) list its fields with its comments."""
  prefix = f"method.{method}"
  lines = configfile.describe_settings(chosen, prefix).splitlines()
  base = type(chosen).__mro__[1]
  if dataclasses.is_dataclass(base):  # configfile reads the comments of a class's own source
    inherited = configfile.describe_settings(base(**{
      f.name: getattr(chosen, f.name) for f in dataclasses.fields(base)}), prefix).splitlines()
    known = {line.split(" = ")[0] for line in inherited}
    lines = inherited + [line for line in lines if line.split(" = ")[0] not in known]
  return "\n".join(lines)


def settings_dict(chosen) -> dict | None:
  """A method's settings as plain data (its dataclass's fields)."""
  return None if chosen is None else dataclasses.asdict(chosen)


def describe(method: str, chosen) -> dict:
  """The method and its settings, for results files."""
  if chosen is None:
    return {"method": method}
  return {"method": method, "method_settings": settings_dict(chosen)}


def convergence_note(method: str, info) -> str | None:
  """A line for the user when an optimisation did not converge (None when it did)."""
  if info is None:
    return None
  finite = np.asarray(info["finite"])
  if not finite.all():
    return f"{method}: the optimisation diverged (non-finite flow); the starting flow is returned"
  if get(method).stops_early and not np.asarray(info["stopped"]).all():
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
  if get(method).stops_early and convergence["early_stopped"] < convergence["pairs"]:
    running = convergence["pairs"] - convergence["early_stopped"]
    notes.append(f"early stopping did not fire on {running} of {convergence['pairs']} pairs "
                 "(their lowest-loss flow was used)")
  return f"{method}: " + "; ".join(notes) if notes else None
