"""Checkpoints: an orbax `CheckpointManager` holding the train state and the config that made it.

Layout of a workdir:

    WORKDIR/config.json                  the config of the newest checkpoint (as stored in it)
    WORKDIR/checkpoints/<step>/state     the train state (`StandardSave`)
    WORKDIR/checkpoints/<step>/config    the config as JSON (`JsonSave`)

orbax writes a step into `<step>.orbax-checkpoint-tmp-*` and renames it when complete, so a
half-written step is never listed. A numbered step folder that lacks orbax's metadata or one of the
two items (copied by hand, truncated) is refused with a `CheckpointError` naming it.

A run resumed with another recipe (`train.resume_with_new_recipe`) records it in the stored config:
its `recipe_changes` lists, per resume, the step it resumed from and the fields that changed there
(the steps up to it ran with the earlier values).
"""

import contextlib
import json
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import orbax.checkpoint as ocp
from flax import traverse_util

from jaxflow.errors import CheckpointError
from jaxflow.network import train_state
from jaxflow.network.model import build_model
# Model fields added after checkpoints were written without them, and the value they had then.
from jaxflow.network.model_fields import ADDED_MODEL_FIELDS, RUNTIME_MODEL_FIELDS

ITEMS = ("state", "config")
# The shipped checkpoint (found from the package, not the working directory): the default of
# evaluate.py and predict.
SHIPPED_CHECKPOINT = Path(__file__).absolute().parent.parent / "checkpoints" / "jaxflow_synthetic"
_STEP_METADATA = "_CHECKPOINT_METADATA"  # written by orbax into every finalised step folder


def config_to_dict(config: ml_collections.ConfigDict, recipe_changes=None) -> dict:
  """The config as plain JSON types (tuples become lists), with `recipe_changes` when given."""
  d = json.loads(config.to_json_best_effort())
  if recipe_changes:
    d["recipe_changes"] = list(recipe_changes)
  return d


def config_from_dict(d: dict) -> ml_collections.ConfigDict:
  return ml_collections.ConfigDict(d)


def model_differences(a: ml_collections.ConfigDict, b: ml_collections.ConfigDict,
                      fields=None, ignore=()) -> list[str]:
  """`field: a != b` for each model field (or each of `fields`, less `ignore`) where the two
  configs differ."""
  da, db = ({**ADDED_MODEL_FIELDS, **config_to_dict(c.model)} for c in (a, b))
  names = sorted(set(da) | set(db)) if fields is None else fields
  return [f"{k}: {da.get(k)!r} != {db.get(k)!r}" for k in names
          if k not in ignore and da.get(k) != db.get(k)]


def incomplete_reason(step_dir: Path) -> str | None:
  """Why a step folder is not a complete checkpoint, or None when it is."""
  if not step_dir.is_dir():
    return "no such folder"
  if not (step_dir / _STEP_METADATA).exists():
    return f"missing {_STEP_METADATA} (half-written or copied incompletely)"
  for item in ITEMS:
    if not (step_dir / item).is_dir():
      return f"missing the '{item}' item"
  return None


class Checkpoints:
  """The checkpoints of one run: `WORKDIR/checkpoints`, keeping the last `max_to_keep` steps."""

  def __init__(self, directory, max_to_keep: int | None = 3, create: bool = True):
    self.directory = Path(directory).absolute()
    if not create and not self.directory.is_dir():
      raise CheckpointError(f"{self.directory}: no such checkpoint folder")
    options = ocp.CheckpointManagerOptions(
      max_to_keep=max_to_keep,
      create=create,
      # Synchronous: when save() returns the step is committed (what the signal handler relies on).
      enable_async_checkpointing=False,
    )
    self.manager = ocp.CheckpointManager(self.directory, item_names=ITEMS, options=options)

  def steps(self) -> list[int]:
    return sorted(self.manager.all_steps())

  def latest_step(self) -> int | None:
    """The newest step; a CheckpointError when that step folder is incomplete."""
    steps = self.steps()
    if not steps:
      return None
    self._check(steps[-1])
    return steps[-1]

  def step_dir(self, step: int) -> Path:
    return self.directory / str(step)

  def _check(self, step: int):
    reason = incomplete_reason(self.step_dir(step))
    if reason:
      raise CheckpointError(
        f"{self.step_dir(step)}: incomplete checkpoint ({reason}); delete it to use an earlier step"
      )

  def save(self, step: int, state: Any, config: ml_collections.ConfigDict,
           recipe_changes=None) -> bool:
    """Saves `state` and its config at `step` (every process calls it; orbax writes collectively);
    False when the step was already saved (e.g. a periodic save at the step a signal arrived)."""
    if step in self.manager.all_steps():
      return False
    self.manager.save(
      step,
      args=ocp.args.Composite(
        state=ocp.args.StandardSave(state),
        config=ocp.args.JsonSave(config_to_dict(config, recipe_changes)),
      ),
      force=True,
    )
    self.manager.wait_until_finished()
    return True

  def restore_config(self, step: int) -> ml_collections.ConfigDict:
    self._check(step)
    try:
      out = self.manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
    except Exception as e:  # orbax/tensorstore raise many types; the user needs the path.
      raise CheckpointError(f"{self.step_dir(step)}: unreadable config ({_short(e)})") from e
    return config_from_dict(out["config"])

  def restore_state(self, step: int, abstract_state: Any) -> Any:
    """The state at `step`, shaped (and sharded) like `abstract_state` (from `jax.eval_shape`)."""
    self._check(step)
    try:
      out = self.manager.restore(
        step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract_state))
      )
    except Exception as e:
      raise CheckpointError(
        f"{self.step_dir(step)}: cannot restore the train state ({_short(e)})"
      ) from e
    return out["state"]

  def close(self):
    self.manager.close()


def _short(e: Exception, limit: int = 300) -> str:
  text = " ".join(str(e).split()) or type(e).__name__
  return text if len(text) <= limit else text[:limit] + " ..."


def locate(path) -> tuple[Path, int]:
  """(checkpoints folder, step) for a workdir, a checkpoints folder or one step folder.

  A workdir or checkpoints folder gives its newest complete step.
  """
  path = Path(path).absolute()
  if not path.exists():
    raise CheckpointError(f"{path}: no such checkpoint, workdir or step folder")
  if path.name.isdigit() and any((path / item).exists() for item in ITEMS):
    reason = incomplete_reason(path)
    if reason:
      raise CheckpointError(f"{path}: incomplete checkpoint ({reason})")
    return path.parent, int(path.name)
  directory = path / "checkpoints" if (path / "checkpoints").is_dir() else path
  steps = sorted(
    int(p.name) for p in directory.iterdir() if p.name.isdigit() and p.is_dir()
  ) if directory.is_dir() else []
  if not steps:
    raise CheckpointError(f"{path}: no checkpoint found (expected <step>/ folders in {directory})")
  reason = incomplete_reason(directory / str(steps[-1]))
  if reason:
    raise CheckpointError(
      f"{directory / str(steps[-1])}: incomplete checkpoint ({reason}); delete it or name an "
      "earlier step folder"
    )
  return directory, steps[-1]


def open_checkpoint(path) -> tuple[Checkpoints, int, ml_collections.ConfigDict]:
  """(read-only Checkpoints, step, config) of a workdir, checkpoints folder or step folder."""
  directory, step = locate(path)
  ckpts = Checkpoints(directory, max_to_keep=None, create=False)
  try:
    return ckpts, step, ckpts.restore_config(step)
  except CheckpointError:
    ckpts.close()
    raise


def write_config(config: ml_collections.ConfigDict, workdir, recipe_changes=None) -> Path:
  """WORKDIR/config.json: call it only with the config of a checkpoint just saved beside it."""
  path = Path(workdir) / "config.json"
  tmp = path.with_suffix(".json.tmp")
  tmp.write_text(json.dumps(config_to_dict(config, recipe_changes), indent=2) + "\n")
  os.replace(tmp, path)
  return path


def restore_checkpoint(path, step: int | None = None):
  """(TrainState, config, step) of a workdir, checkpoints folder or step folder; the model and
  optimiser are rebuilt from the config stored in the checkpoint."""
  ckpts, latest, config = open_checkpoint(path)
  step = latest if step is None else step
  with contextlib.closing(ckpts):  # on errors too: a notebook goes on after a CheckpointError
    try:
      model = build_model(config.model)
    except (ValueError, TypeError) as e:
      raise CheckpointError(f"{ckpts.step_dir(step)}: its config does not build a model ({e})")
    tx = train_state.make_optimizer(config, 1)
    target = train_state.abstract_train_state(model, tx, config)
    return ckpts.restore_state(step, target), config, step


# What may change when a workdir is resumed: how often the run logs, saves and evaluates, how long
# it runs (with a constant learning rate), and how data is read; every other train, data and seed
# field changes what is trained (the model's fields are compared by `model_differences`).
RESUMABLE_FIELDS = ("train.num_steps", "train.num_epochs", "train.log_every",
                    "train.checkpoint_every", "train.max_to_keep", "train.resume_with_new_recipe",
                    "data.prefetch", "data.workers", "data.skip_broken")


def recipe_differences(saved: ml_collections.ConfigDict,
                       config: ml_collections.ConfigDict) -> list[str]:
  """`field: saved != config` for the seed, data and train fields (less RESUMABLE_FIELDS; with a
  decaying learning rate the run length is part of the recipe) where the checkpoint's config and
  `config` differ. Fields the checkpoint's config does not know (added since) are not compared."""
  free = set(RESUMABLE_FIELDS)
  if config.train.schedule != "constant":
    free -= {"train.num_steps", "train.num_epochs"}
  flat = lambda c: traverse_util.flatten_dict(
    {k: v for k, v in config_to_dict(c).items() if k in ("seed", "data", "train")}, sep=".")
  old, new = flat(saved), flat(config)
  return [f"{k}: {old[k]!r} != {new[k]!r}" for k in sorted(new)
          if k in old and k not in free and old[k] != new[k]]


def save_params(workdir, params, config: ml_collections.ConfigDict, note: str = "") -> Path:
  """Writes parameters made elsewhere (e.g. imported weights) as step 0 of a new workdir, which
  evaluate.py, jaxflow.predict and train.py (resume, or stage 2's init_from) load like a trained
  run; the optimiser state is freshly initialised. `note` is written to WORKDIR/NOTE.txt."""
  workdir = Path(workdir).absolute()
  tx = train_state.make_optimizer(config, 1)
  expected = train_state.abstract_train_state(build_model(config.model), tx, config).params
  shape = lambda t: jax.tree.map(lambda x: (tuple(x.shape), str(x.dtype)), t)
  if shape(params) != shape(expected):
    raise CheckpointError(f"{workdir}: the parameters do not match config.model")
  ckpts = Checkpoints(workdir / "checkpoints", max_to_keep=None)
  if ckpts.steps():
    raise CheckpointError(f"{workdir}: already holds checkpoints; write to a new folder")
  ckpts.save(0, train_state.create_train_state(jax.tree.map(jnp.asarray, params), tx), config)
  ckpts.close()
  write_config(config, workdir)
  if note:
    (workdir / "NOTE.txt").write_text(note + "\n")
  return workdir


def load_for_inference(checkpoint=None, config: ml_collections.ConfigDict | None = None,
                       model_fields=()):
  """(model, params, stored config, step, refine) of a checkpoint (None: the shipped one), the
  model built for inference from the checkpoint's stored config.

  `model_fields` names the fields of `config.model` the user asked for: one that contradicts the
  checkpoint is a CheckpointError, except RUNTIME_MODEL_FIELDS (jaxflow.network.model_fields), which
  change no parameter and are taken from `config`. `refine`: the checkpoint's refinement was trained
  (stage 2), so the refined flow is the output.
  """
  if checkpoint is None:
    if not SHIPPED_CHECKPOINT.exists():
      raise CheckpointError(f"no checkpoint given and no shipped checkpoint at {SHIPPED_CHECKPOINT}")
    checkpoint = SHIPPED_CHECKPOINT
  state, saved, step = restore_checkpoint(checkpoint)
  if config is not None:
    runtime = [k for k in model_fields if k in RUNTIME_MODEL_FIELDS]
    checked = [k for k in model_fields if k not in RUNTIME_MODEL_FIELDS]
    diffs = model_differences(config, saved, fields=checked)
    if diffs:
      raise CheckpointError(
        f"{checkpoint}: the config's model contradicts the checkpoint's ({'; '.join(diffs)}, "
        "config != checkpoint); the model comes from the checkpoint: drop those model fields"
      )
    with saved.unlocked():
      for k in runtime:
        saved.model[k] = config.model[k]
  refine = saved.train.stage == 2 and saved.model.refine != "none"
  return build_model(saved.model, inference=True), state.params, saved, step, refine
