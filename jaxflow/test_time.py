"""Test-time optimisation of a predicted flow (opt-in; not part of the paper's network or protocol).

Starting from the network's flow, Adam minimises, per pair and with no ground truth:
  truncated Chamfer distance between pc1 + flow and pc2 (both directions, each nearest-point term
  clipped at `truncate` m so that occluded points and points leaving the view do not pull)
  + `smoothness` x the mean L1 difference of the flow over pc1's `neighbours`-nearest graph.
These are the self-supervised losses of NSFP and SCOOP's test-time refinement. The nearest points are
searched again every few steps and are constants of the gradient (as in a Chamfer loss). The loop
is jaxflow.optimiser's (free flow vectors, exact Chamfer; the flow of the lowest loss is returned),
the terms jaxflow.objectives'.
"""

import dataclasses
import functools

import jax

from jaxflow import objectives, optimiser
from jaxflow.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class Settings:
  steps: int = 0  # 0: off
  learning_rate: float = 0.01
  smoothness: float = 3.0  # chosen with steps=2000 on synthetic validation pairs (MODEL_CARD.md)
  neighbours: int = 8
  truncate: float = 2.0  # metres
  refresh: int = 10  # steps between two searches of the nearest points (the search is the cost)
  chunk: int = 2048  # unused since the k-d tree search; accepted so older configs still load

  def __post_init__(self):
    # neighbours >= 1: the smoothness term averages over them (none would make it NaN).
    for name, least in (("steps", 0), ("neighbours", 1), ("refresh", 1), ("chunk", 0)):
      if not isinstance(getattr(self, name), int) or getattr(self, name) < least:
        raise ValueError(f"test-time {name} must be an integer >= {least}, "
                         f"got {getattr(self, name)!r}")
    for name in ("learning_rate", "smoothness", "truncate"):
      if not getattr(self, name) >= 0:
        raise ValueError(f"test-time {name} must be >= 0, got {getattr(self, name)!r}")


def settings_from_config(config_eval) -> Settings:
  """`Settings` from config.eval.test_time (absent in older configs: off)."""
  if "test_time" not in config_eval:
    return Settings()
  fields = config_eval.test_time.to_dict()
  unknown = sorted(set(fields) - {f.name for f in dataclasses.fields(Settings)})
  if unknown:
    raise ConfigError(f"config.eval.test_time: unknown field(s) {', '.join(unknown)}")
  try:
    return Settings(**fields)
  except ValueError as e:
    raise ConfigError(f"config.eval.test_time: {e}") from None


def correspondences(flow_BxNx3, pc1_BxNx3, pc2_BxMx3):
  """Indices of the nearest pc2 point of each warped pc1 point (B x N x 1) and of the nearest warped
  point of each pc2 point (B x M x 1), for the flow given."""
  warped = pc1_BxNx3 + flow_BxNx3
  return objectives.nearest(warped, pc2_BxMx3), objectives.nearest(pc2_BxMx3, warped)


def objective(flow_BxNx3, pc1_BxNx3, pc2_BxMx3, nbr_BxNxK, match, settings: Settings):
  """The minimised loss, one value per pair (B), with the nearest points `match` (from
  `correspondences`) held fixed: they carry no gradient, their distances do."""
  chamfer = objectives.chamfer_terms(pc1_BxNx3 + flow_BxNx3, pc2_BxMx3, match, settings.truncate)
  return chamfer + settings.smoothness * objectives.smoothness(flow_BxNx3, nbr_BxNxK)


def optimiser_settings(settings: Settings) -> optimiser.Settings:
  """The same optimisation in jaxflow.optimiser's terms (free flow vectors, exact Chamfer)."""
  return optimiser.Settings(
    model="flow", objective="exact", steps=settings.steps, learning_rate=settings.learning_rate,
    smoothness=settings.smoothness, neighbours=settings.neighbours, truncate=settings.truncate,
    refresh=settings.refresh)


@functools.partial(jax.jit, static_argnames="settings")
def optimise_flow(flow_BxNx3, pc1_BxNx3, pc2_BxMx3, settings: Settings):
  """The flow of the lowest objective within `settings.steps` Adam steps (jaxflow.optimiser, each
  pair on its own; the nearest points searched again every `settings.refresh` steps); returns
  (flow B x N x 3, objective before and after, B each, with the nearest points of the flow)."""
  flow, _ = optimiser.optimise(flow_BxNx3, pc1_BxNx3, pc2_BxMx3, optimiser_settings(settings))
  nbr = objectives.neighbours(pc1_BxNx3, settings.neighbours)
  search = functools.partial(correspondences, pc1_BxNx3=pc1_BxNx3, pc2_BxMx3=pc2_BxMx3)
  before = objective(flow_BxNx3, pc1_BxNx3, pc2_BxMx3, nbr, search(flow_BxNx3), settings)
  after = objective(flow, pc1_BxNx3, pc2_BxMx3, nbr, search(flow), settings)
  return flow, before, after
