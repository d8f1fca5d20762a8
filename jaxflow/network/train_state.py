"""The train state and its optimiser: what a checkpoint holds and how it is shaped.

Below training and checkpointing (which restores into `abstract_train_state`): it imports no other
jaxflow module than errors; the model comes as an argument.
"""

import functools
import re
from typing import Any

import flax
import jax
import jax.numpy as jnp
import ml_collections
import optax
from flax import traverse_util

from jaxflow.errors import ConfigError

REFINE = "refine"  # top-level parameter name of the refinement module.


@flax.struct.dataclass
class TrainState:
  step: jax.Array  # int32 scalar: updates applied so far.
  params: Any
  opt_state: Any


def trainable_pattern(stage: int) -> str:
  """Regex over '/'-joined parameter paths selecting what a stage trains."""
  return rf"^(?!{REFINE}/)" if stage == 1 else rf"^{REFINE}/"


def split_params(params, pattern: str) -> tuple[dict, dict]:
  """(trainable, frozen): flat {path: leaf} dicts of the leaves whose path matches / does not."""
  flat = traverse_util.flatten_dict(params, sep="/")
  trainable = {k: v for k, v in flat.items() if re.search(pattern, k)}
  frozen = {k: v for k, v in flat.items() if k not in trainable}
  return trainable, frozen


def merge_params(*flat_dicts: dict):
  merged = {}
  for d in flat_dicts:
    merged.update(d)
  return traverse_util.unflatten_dict(merged, sep="/")


def param_labels(params, pattern: str):
  """'train' / 'frozen' for every leaf, by its path: the mask of `optax.multi_transform`."""
  trainable, frozen = split_params(params, pattern)
  return merge_params(
    {k: "train" for k in trainable}, {k: "frozen" for k in frozen}
  )


def learning_rate(config: ml_collections.ConfigDict, total_steps: int) -> optax.Schedule:
  if config.train.schedule == "constant":
    return optax.constant_schedule(config.train.lr)
  if config.train.schedule == "cosine":
    return optax.cosine_decay_schedule(config.train.lr, max(total_steps, 1))
  raise ConfigError(f"config.train.schedule must be 'constant' or 'cosine', got "
                    f"{config.train.schedule!r}")


def make_optimizer(config: ml_collections.ConfigDict, total_steps: int):
  """Adam on the stage's trainable parameters; the rest get zero updates and hold no state."""
  pattern = trainable_pattern(config.train.stage)
  return optax.multi_transform(
    {"train": optax.adam(learning_rate(config, total_steps)), "frozen": optax.set_to_zero()},
    functools.partial(param_labels, pattern=pattern),
  )


@functools.lru_cache(maxsize=8)
def _jitted_init(model):
  # One jitted init per model (modules compare by their fields): training's check by
  # jax.eval_shape and the real init then share one trace of the model.
  return jax.jit(functools.partial(model.init, num_iters=1))


def init_params(model, config: ml_collections.ConfigDict, rng):
  """Freshly initialised parameters (the shapes do not depend on the number of points)."""
  n = max(config.model.knn, 32)
  pc = jnp.zeros((1, n, 3), jnp.float32) + jnp.linspace(0.0, 1.0, n)[None, :, None]
  return _jitted_init(model)(rng, pc, pc)["params"]


def create_train_state(params, tx) -> TrainState:
  return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params))


def abstract_train_state(model, tx, config, sharding=None) -> TrainState:
  """Shapes, dtypes (and `sharding`) of the train state: orbax's restore target."""
  shapes = jax.eval_shape(
    lambda rng: create_train_state(init_params(model, config, rng), tx), jax.random.key(0)
  )
  sharding = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), shapes)
