"""What a flow method is to the rest of jaxflow: a name, the frame it works in, its settings and a
function from a batch of pairs to their flow. Each method is one module holding a `METHOD`;
jaxflow.methods.registry lists them by name, and every caller (predict, evaluate.py, the API)
reaches a method through it, by its properties, never by its name.

    run = METHOD.build(network_for, settings)       # network_for(iters, candidates) -> network
    flow_BxNx3, info = run(params, pc1_BxNx3, pc2_BxMx3)

The clouds reach `run` in the method's frame (`up`; jaxflow.geometry.frames): callers rotate them
once, outside every method. `info` is None or the optimiser's per-pair dict (finite, stopped,
steps; jaxflow.refine.optimiser).
"""

import dataclasses
from typing import Callable


@dataclasses.dataclass(frozen=True)
class Method:
  """One flow method (module docstring)."""
  name: str
  summary: str  # one line for --help
  up: str  # the up axis of its frame: "y" the models' (x left, y up, z forward), "z" a LiDAR's
  needs_network: bool  # loads a checkpoint
  # (steps, iters, objective) -> its default settings (None: it has none): --steps caps an
  # optimiser's steps, --iters the network's iterations, --objective is NSFP's.
  defaults: Callable
  # (network_for, settings) -> run(params, pc1, pc2) -> (flow, info); network_for(iters=None,
  # candidates=None) is the network's (params, pc1, pc2) -> flow with those iterations and
  # correlation candidates (None: the caller's), or None when no network is loaded.
  build: Callable
  jitted: bool = False  # run is one jitted program (`.lower` compiles it ahead)
  compiles: bool = True  # its first call on new shapes compiles (evaluation warms it up untimed)
  objectives: tuple = ()  # the objectives --objective may choose (none: it takes no --objective)
  stops_early: bool = False  # its optimiser stops early: a run that did not is noted
  # It refines the network's flow at every point: on sampled clouds the network sees the samples,
  # its flow spread to every point is the method's start (jaxflow.inference).
  refines_start: bool = False
  # It reads whole raw sweeps on the host (jaxflow.lidar.sweep): never sampled, and predict's
  # Prediction carries what the pipeline found (a SweepInfo).
  raw_sweeps: bool = False
