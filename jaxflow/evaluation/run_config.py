"""A training run's own evaluation settings, for evaluate.py --checkpoint RUN.

    config, lines = run_config.apply(checkpoint, config, given={"dataset", "split"})

A run stores its config beside its checkpoints (jaxflow.network.checkpointing): its `config.eval`
is how its held-out figure was made (dataset, split, points, iterations, batch, seed). evaluate.py
starts from those settings when it is given --checkpoint without an explicit --config file, so that
`evaluate.py --checkpoint RUN` reproduces the figure the training printed and wrote (eval.json);
what the command line gives (`given`: a flag, a --config.eval.FIELD) overrides the run's; points
given there keep the command's batch size too (the run's batch was sized for its points, and whole
clouds are evaluated one at a time). Either
way, `training_gap` says when the evaluation is more than 2x away from the training in points or
iterations (a model trained on 384 points read at 8192 can do worse than zero flow).
"""

import ml_collections

from jaxflow.network import checkpointing

# config.eval's fields that make a held-out figure (what evaluate.py takes from a run).
FIELDS = ("dataset", "split", "num_points", "num_iters", "batch_size", "seed")
FAR = 2.0  # a ratio beyond which the evaluation is said to differ from the training


def saved_config(checkpoint) -> ml_collections.ConfigDict:
  """The config stored with a checkpoint (workdir, checkpoints folder or step folder)."""
  ckpts, _, config = checkpointing.open_checkpoint(checkpoint)
  ckpts.close()
  return config


def _value(config, field):
  return config.eval.get(field) if "eval" in config else None


def apply(checkpoint, config: ml_collections.ConfigDict, given=(),
          run: ml_collections.ConfigDict | None = None) -> tuple[ml_collections.ConfigDict, list[str]]:
  """(config with config.eval's FIELDS taken from the run's stored config (`run`, default read from
  `checkpoint`), except those in `given`; one line saying which setting came from where)."""
  run = run or saved_config(checkpoint)
  config = config.copy_and_resolve_references()
  taken, kept = [], []
  given = set(given) | ({"batch_size"} if "num_points" in given else set())
  with config.unlocked():
    for field in FIELDS:
      value = _value(run, field)
      if field in given or value is None:
        kept.append(f"{field} {config.eval.get(field)!r}")
        continue
      config.eval[field] = value
      taken.append(f"{field} {value!r}")
  line = (f"settings from the run's config ({checkpoint}): {', '.join(taken) or 'none'}"
          + (f"; from the command line: {', '.join(kept)}" if kept else ""))
  return config, [line]


def training_gap(checkpoint, config: ml_collections.ConfigDict, iterations: bool = True,
                 run: ml_collections.ConfigDict | None = None) -> str | None:
  """A note when config.eval's points (or, with `iterations`, its iterations) are more than FAR
  times the run's training's (config.data.num_points, config.train.num_iters); None otherwise."""
  run = run or saved_config(checkpoint)
  far = []
  trained = run.get("data", {}).get("num_points")
  points = config.eval.num_points
  if trained and (not points or max(points, trained) > FAR * min(points, trained)):
    far.append(f"{'whole clouds' if not points else f'{points} points'} (trained on {trained})")
  trained = run.get("train", {}).get("num_iters")
  iters = config.eval.num_iters
  if iterations and trained and iters and max(iters, trained) > FAR * min(iters, trained):
    far.append(f"{iters} iterations (trained with {trained})")
  if not far:
    return None
  return (f"evaluating at {' and '.join(far)}: more than {FAR:g}x from the training, so the "
          "figures may be far from the run's own (its config.eval: "
          f"{_value(run, 'num_points')} points, {_value(run, 'num_iters')} iterations)")
