"""The `nsfp` method: Neural Scene Flow Prior (Li et al. 2021, the paper's Tables 4 and 7
baseline): NSFP's MLP optimised per pair from zero flow, no network, no checkpoint. Its published
settings (optimiser.NSFP): the exact two-way Chamfer, nearest points by k-d tree every step (~170 ms
a step at 8192 points on a 2-core CPU); the one-way distance grid (--objective grid) is faster but
far less accurate for NSFP on FT3D (benchmarks/METHODS.md). Its progress goes to stderr
(optimiser.optimise_host_loop: a bar on a terminal, plain lines with the expected time in a log)."""

import dataclasses

import jax.numpy as jnp

from jaxflow.errors import ConfigError
from jaxflow.refine import optimiser
from jaxflow.methods.interface import Method


def _defaults(steps, iters, objective):
  del iters  # no network
  if objective is not None and objective not in optimiser.OBJECTIVES:
    raise ConfigError(f"--objective must be one of {', '.join(optimiser.OBJECTIVES)}, "
                      f"got {objective!r}")
  return dataclasses.replace(optimiser.NSFP, **({} if steps is None else {"steps": steps}),
                             **({} if objective is None else {"objective": objective}))


def _build(network_for, settings):
  del network_for
  return lambda params, pc1, pc2: optimiser.optimise_host_loop(jnp.zeros_like(pc1), pc1, pc2,
                                                               settings)


METHOD = Method("nsfp", "the NSFP baseline: an MLP optimised per pair, no checkpoint", up="y",
                needs_network=False, defaults=_defaults, build=_build,
                objectives=optimiser.OBJECTIVES, stops_early=True)
