"""Parameter count of each top-level module of a config's model.

    python -m jaxflow.summary --config configs/pvraft.py
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxflow.network.model import build_model


def parameter_counts(model_config) -> dict:
  """{top-level module: parameter count} of the model, from shapes alone (nothing computed)."""
  model = build_model(model_config)
  pc = jax.ShapeDtypeStruct((1, 64, 3), jnp.float32)
  shapes = jax.eval_shape(lambda a, b: model.init(jax.random.PRNGKey(0), a, b, num_iters=1), pc, pc)
  return {
    name: int(sum(np.prod(x.shape) for x in jax.tree_util.tree_leaves(tree)))
    for name, tree in shapes["params"].items()
  }


def main(argv):
  from absl import flags  # pylint: disable=import-outside-toplevel

  del argv
  counts = parameter_counts(flags.FLAGS.config.model)
  width = max(len(k) for k in counts)
  for name, count in counts.items():
    print(f"{name:<{width}}  {count:>10,}")
  if "refine" in counts:
    stage1 = sum(v for k, v in counts.items() if k != "refine")
    print(f"{'(stage 1: all but refine)':<{width}}  {stage1:>10,}")
  print(f"total parameters: {sum(counts.values())}")


def run():
  """`python -m jaxflow.summary --config FILE`: the flag is defined here, by the tool alone."""
  from jaxflow import cli  # pylint: disable=import-outside-toplevel
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  cli.run(main, lambda: config_flags.DEFINE_config_file(
    "config", None, "Config file whose model is counted (FILE.py[:ARG]).", lock_config=True),
          {"config": None})


if __name__ == "__main__":
  run()
