"""The `lidar` method: raw LiDAR sweeps by jaxflow.lidar.sweep (the ground, the sensor's
ego-motion, one rigid motion per moving object; NumPy on the host, no network), each pair of a
batch in turn. `predict --lidar` is this method on one pair (there a camera's view also runs a
network method); its settings are jaxflow.lidar.settings.Sweep (--method.lidar.FIELD=V)."""

import jax.numpy as jnp
import numpy as np

from jaxflow.lidar import sweep
from jaxflow.lidar.settings import DEFAULTS
from jaxflow.methods.interface import Method


def _build(network_for, settings):
  del network_for  # a 360-degree sweep needs none (predict --lidar --method X: X's flow a start)

  def run(params, pc1_BxNx3, pc2_BxMx3):
    del params
    flows = [sweep.raw_sweep_flow(None, a, b, up="z", settings=settings)[0]
             for a, b in zip(np.asarray(pc1_BxNx3), np.asarray(pc2_BxMx3))]
    return jnp.asarray(np.stack(flows)), None

  return run


METHOD = Method("lidar", "raw LiDAR sweeps: ground, ego-motion and moving objects, no network",
                up="z", needs_network=False,
                defaults=lambda steps, iters, objective: DEFAULTS, build=_build, compiles=False)
