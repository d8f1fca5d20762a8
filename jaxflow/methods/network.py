"""The `network` method: the trained network's flow alone (the paper's protocol, evaluate.py's
default)."""

import jax

from jaxflow.methods.interface import Method


def _build(network_for, settings):
  del settings  # the network's settings are the config's (--config.model.FIELD)
  network = network_for()
  return jax.jit(lambda params, pc1, pc2: (network(params, pc1, pc2), None))


METHOD = Method("network", "the network alone (the paper's protocol)", up="y",
                needs_network=True, defaults=lambda steps, iters, objective: None, build=_build,
                jitted=True)
