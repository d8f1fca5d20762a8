"""The `lidar` method: raw LiDAR sweeps by jaxflow.lidar.sweep (the ground, the sensor's ego-motion,
one rigid motion per moving object; NumPy on the host), each pair of a batch in turn. Its settings
(`Lidar`, --method.lidar.FIELD=V) are the pipeline's (jaxflow.lidar.settings.Sweep) and the method
it may run on the sweeps' non-ground points within max_range: on a camera's view that method's flow
is kept there; on a 360-degree sweep it is one more start of the fits only with `start`. Its
network, if any, is loaded only when that method runs (jaxflow.inference). `predict --lidar
[--method X]` is this method with method X (default optimise), `start` when X is given."""

import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxflow.geometry import frames
from jaxflow.lidar import sweep
from jaxflow.lidar.settings import Sweep
from jaxflow.methods.interface import Method


@dataclasses.dataclass(frozen=True)
class Lidar(Sweep):
  """The `lidar` method's settings: the pipeline's (Sweep) and the method it may run."""
  # A method of jaxflow.methods.registry run on the non-ground points within max_range: a camera's
  # view (under min_azimuth of the azimuth) keeps its flow there; None: no method, no checkpoint.
  method: str | None = None
  # On a 360-degree sweep, `method`'s flow is one more start of the fits (slow;
  # benchmarks/REAL_SWEEPS.md); without it no method runs on a sweep.
  start: bool = False

  def __post_init__(self):
    self.pipeline()  # the pipeline's own checks (jaxflow.lidar.settings)

  def pipeline(self) -> Sweep:
    """The pipeline's settings alone."""
    return Sweep(**{f.name: getattr(self, f.name) for f in dataclasses.fields(Sweep)})


def settings_of(settings) -> Lidar:
  """`settings` as the lidar method's: a Sweep (the pipeline's alone) runs no method."""
  if isinstance(settings, Lidar):
    return settings
  pipeline = sweep.settings_of(settings)  # None: the defaults; a ConfigError for anything else
  return Lidar(**{f.name: getattr(pipeline, f.name) for f in dataclasses.fields(Sweep)})


def pair_flow(flow_fn, pc1_Nx3, pc2_Mx3, settings: Lidar, up: str = "z", names=("pc1", "pc2"),
              ground_limits: bool = True, seed: int = 0):
  """(flow N x 3, SweepInfo) of one pair by jaxflow.lidar.sweep.raw_sweep_flow; `flow_fn(kept1,
  kept2)` (in the clouds' frame) is `settings.method`'s flow, None without one; `seed`: the
  pipeline's draws (its ego-motion's starts, its groups' random halves)."""
  return sweep.raw_sweep_flow(flow_fn, pc1_Nx3, pc2_Mx3, up=up, names=names,
                              use_network=settings.start, ground_limits=ground_limits,
                              seed=seed, settings=settings)


def in_frame(flow_fn, up: str, method_up: str):
  """flow_fn(pc1 N x 3, pc2 M x 3) of clouds with up axis `up`, from one that works with up axis
  `method_up` (a method's frame): the clouds are rotated into it and the flow back."""
  forward = frames.permutation(up, method_up)
  back = np.argsort(forward)
  turn = lambda points_Nx3: np.ascontiguousarray(points_Nx3[:, forward])
  return lambda pc1_Nx3, pc2_Mx3: np.ascontiguousarray(
    np.asarray(flow_fn(turn(pc1_Nx3), turn(pc2_Mx3)))[:, back])


def builder(nested):
  """The lidar method's build; `nested(name, network_for)` -> (run of that method, flow only; its
  up axis): jaxflow.methods.registry's, which knows the other methods."""

  def build(network_for, settings):
    settings = settings_of(settings)
    method = None

    def run(params, pc1_BxNx3, pc2_BxMx3):
      nonlocal method
      flow_fn = None
      if settings.method is not None:  # its network (evaluate.py: only one it loaded) built once
        method = method or nested(settings.method, network_for)
        flow_fn = in_frame(lambda a, b: method[0](params, a[None], b[None])[0], "z", method[1])
      flows = [pair_flow(flow_fn, a, b, settings)[0]
               for a, b in zip(np.asarray(pc1_BxNx3), np.asarray(pc2_BxMx3))]
      return jnp.asarray(np.stack(flows)), None

    return run

  return build


# Its build runs no other method: jaxflow.methods.registry registers it with builder(its lookup).
METHOD = Method("lidar", "raw LiDAR sweeps: ground, ego-motion and moving objects, no network",
                up="z", needs_network=False, defaults=lambda steps, iters, objective: Lidar(),
                build=builder(None), compiles=False, raw_sweeps=True)
