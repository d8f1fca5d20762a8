"""Training: the pure train step and the loop, `train_and_evaluate(config, workdir)`.

Step s is the s-th update (it consumed the loader's batch s - 1); checkpoint s holds the state
after it. The same command resumes from the newest checkpoint with the same data order
(`BatchLoader.batch(step)` is deterministic); another recipe is refused
(`checkpointing.recipe_differences`) unless `config.train.resume_with_new_recipe` records it.

Two stages (paper 4.1). Stage 1 trains everything but the refinement with the sequence loss (from
scratch, or warm-started from another run's parameters with `config.train.init_from`). Stage 2 loads
stage 1 (`config.train.init_from`) and trains only the refinement with the refinement loss: the
gradient is taken only w.r.t. the trainable parameters (the others are closed over), the optimiser
is an `optax.multi_transform` whose frozen group is `set_to_zero` (no optimiser state), and the
model runs with `freeze_backbone=True`.

Many processes (jaxflow.runtime.distributed): one mesh over every process's devices, each process loads its
rows of every global batch, all of them save checkpoints together; process 0 writes the files.
"""

import dataclasses
import json
import signal
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
from tqdm import tqdm

from jaxflow.runtime import distributed
from jaxflow.data import BatchLoader, open_dataset
from jaxflow.errors import CheckpointError, ConfigError
from jaxflow.evaluation import evaluator, reporting
from jaxflow.evaluation.metrics import METRICS
from jaxflow.network import checkpointing
from jaxflow.network.model import build_model
from jaxflow.network.model_fields import PARAMETER_FREE_FIELDS, REFINE_FIELDS, RUNTIME_MODEL_FIELDS
from jaxflow.network.train_state import (
  REFINE, TrainState, abstract_train_state, create_train_state, init_params, learning_rate,
  make_optimizer, merge_params, split_params, trainable_pattern)
from jaxflow.training import events, losses
from jaxflow.training.run_log import Interrupted, MetricsLog, PendingMetrics, StopSignals
from jaxflow.viz import curves

BATCH_KEYS = ("pc1", "pc2", "flow", "mask")


def augmentation(config) -> dict | None:
  """config.data.augment without its identity entries (None when nothing is augmented)."""
  identity = {"rotation_deg": 0.0, "scale": (1.0, 1.0), "jitter": 0.0}
  aug = {k: tuple(v) if isinstance(v, (list, tuple)) else v
         for k, v in config.data.augment.items()}
  aug = {k: v for k, v in aug.items() if v != identity.get(k)}
  return aug or None



def make_train_step(model, tx, config: ml_collections.ConfigDict):
  """The pure step `(state, batch) -> (state, metrics)` of `config.train.stage`."""
  stage2 = config.train.stage == 2
  pattern = trainable_pattern(config.train.stage)
  num_iters, gamma = config.train.num_iters, config.train.gamma

  def train_step(state: TrainState, batch: dict):
    trainable, frozen = split_params(state.params, pattern)

    def loss_fn(trainable):
      out = model.apply(
        {"params": merge_params(trainable, frozen)}, batch["pc1"], batch["pc2"],
        num_iters=num_iters, refine=stage2, freeze_backbone=stage2,
      )
      if stage2:
        return losses.refinement_loss(out["refined"], batch["flow"], batch["mask"])
      return losses.sequence_loss(out["flows"], batch["flow"], batch["mask"], gamma=gamma)

    # No gradient is computed for the frozen leaves; the optimiser sees zeros there and its
    # set_to_zero group ignores them.
    loss, grads = jax.value_and_grad(loss_fn)(trainable)
    zeros = {k: jnp.zeros_like(v) for k, v in frozen.items()}
    updates, opt_state = tx.update(merge_params(grads, zeros), state.opt_state, state.params)
    new_trainable, _ = split_params(optax.apply_updates(state.params, updates), pattern)
    # The frozen leaves are passed through as they were: bitwise unchanged.
    params = merge_params(new_trainable, frozen)
    metrics = {"loss": loss, "grad_norm": global_norm(grads),
               "param_norm": global_norm(new_trainable)}
    return state.replace(step=state.step + 1, params=params, opt_state=opt_state), metrics

  return train_step




def global_norm(tree) -> jax.Array:
  """sqrt of the sum of squares of every leaf (optax.global_norm, without its deprecation)."""
  return jnp.sqrt(sum(jnp.sum(jnp.square(x)) for x in jax.tree.leaves(tree)))


def make_mesh(devices=None) -> Mesh:
  """A 1-D mesh over the devices of every process (or `devices`): batches are split over 'data',
  parameters replicated."""
  return distributed.global_mesh() if devices is None else Mesh(np.asarray(devices), ("data",))


def jit_train_step(model, tx, config, mesh: Mesh):
  replicated = NamedSharding(mesh, P())
  data = NamedSharding(mesh, P("data"))
  return jax.jit(
    make_train_step(model, tx, config),
    in_shardings=(replicated, data),
    out_shardings=(replicated, replicated),
    donate_argnums=0,
  )


def device_batch(batch: dict, mesh: Mesh) -> dict:
  """The global batch, split on its leading (pair) axis over the mesh, from this process's rows
  of it (`batch`: a loader batch of those rows, `distributed.local_rows`)."""
  sharding = NamedSharding(mesh, P("data"))
  local = {k: batch[k] for k in BATCH_KEYS}
  rows = len(local["pc1"]) * mesh.size // len(mesh.local_devices)
  return distributed.global_batch(local, sharding, rows)


# Starting: a fresh state or the workdir's newest checkpoint.


def _load_init_params(params, config):
  """`params` with subtrees taken from the run `config.train.init_from`: in stage 2 every subtree but
  the refinement (the stage-1 backbone), in stage 1 every subtree (a warm start: a new round with
  another recipe continues from the previous round's parameters; the optimiser starts afresh).

  The refinement's own fields (model_fields.REFINE_FIELDS) may differ from the loaded run's: stage 2
  starts from any stage-1 run of the same backbone, with or without a refinement (PV-RAFT's stage 1
  has refine='none'), and initialises the refinement afresh; so does a stage-1 warm start whose
  refinement differs (stage 1 does not train it)."""
  stage = config.train.stage
  if not config.train.init_from:
    if stage == 2:
      raise ConfigError("stage 2 needs config.train.init_from (the stage-1 workdir or step folder)")
    return params
  loaded_state, loaded_config, step = checkpointing.restore_checkpoint(config.train.init_from)
  diffs = checkpointing.model_differences(loaded_config, config,
                                          ignore=PARAMETER_FREE_FIELDS + REFINE_FIELDS)
  if diffs:
    raise CheckpointError(
      f"{config.train.init_from}: its model differs from this config's ({'; '.join(diffs)})"
    )
  refine_changed = checkpointing.model_differences(loaded_config, config, fields=REFINE_FIELDS)
  keep_refine = stage == 1 and not refine_changed
  loaded = {k: v for k, v in loaded_state.params.items() if keep_refine or k != REFINE}
  what = "backbone" if stage == 2 else "parameters"
  print(f"stage {stage}: {what} loaded from {config.train.init_from} (step {step})", file=sys.stderr)
  if REFINE in params and REFINE not in loaded:
    print(f"  refinement '{config.model.refine}' freshly initialised"
          + (f" (init_from: {'; '.join(refine_changed)} != config)" if refine_changed else ""),
          file=sys.stderr)
  changed = checkpointing.model_differences(loaded_config, config, fields=PARAMETER_FREE_FIELDS)
  if changed:  # e.g. more candidates for larger windows: the same parameters, run differently
    print(f"  parameter-free fields changed (init_from != config): {'; '.join(changed)}",
          file=sys.stderr)
  return {**params, **loaded}


def _check_config(config, n_devices: int):
  evaluator.check_no_test_time(config.eval)
  t = config.train
  if t.stage not in (1, 2):
    raise ConfigError(f"config.train.stage must be 1 or 2, got {t.stage}")
  if t.stage == 2 and config.model.refine == "none":
    raise ConfigError(
      "stage 2 trains the refinement, but config.model.refine is 'none': give the refinement to "
      "add to the stage-1 run (--config.model.refine=setconv for PV-RAFT's, =graph for the "
      "paper's; configs/pvraft.py:stage2 and configs/paper.py:stage2 set it)")
  if t.batch_size % n_devices:
    raise ConfigError(
      f"config.train.batch_size={t.batch_size} must be a multiple of the {n_devices} devices"
    )
  for name in ("log_every", "checkpoint_every", "batch_size", "num_iters"):
    if t[name] < 1:
      raise ConfigError(f"config.train.{name} must be >= 1, got {t[name]}")
  if t.num_steps < 1 and t.num_epochs < 1:
    raise ConfigError("config.train.num_steps or config.train.num_epochs must be >= 1")
  if config.eval.every < 0 or (config.eval.every and not config.eval.dataset):
    raise ConfigError(f"config.eval.every={config.eval.every} needs to be 0, or > 0 with a "
                      f"config.eval.dataset (got {config.eval.dataset!r})")


@dataclasses.dataclass
class Run:
  """What the loop needs of a run, made once by `prepare`."""
  config: ml_collections.ConfigDict
  workdir: Path
  mesh: Mesh
  model: object
  tx: object
  loader: BatchLoader
  total_steps: int
  ckpts: checkpointing.Checkpoints
  recipe_changes: list  # [{"step": s, "changed": [...]}]: resumes with another recipe
  heldout: evaluator.Evaluator | None = None  # with eval.every: compiled once, reused at the end
  tensorboard: events.EventWriter | None = None  # TensorBoard events beside metrics.jsonl


def prepare(config: ml_collections.ConfigDict, workdir) -> Run:
  """Checks the config, opens the training data (this process's rows of each batch) and the
  workdir's checkpoints; nothing is written before the model is known to build."""
  workdir = Path(workdir).absolute()
  mesh = make_mesh()
  _check_config(config, mesh.size)
  dataset = open_dataset(config.data.dataset, split=config.data.split)
  rows = distributed.local_rows(NamedSharding(mesh, P("data")), config.train.batch_size)
  loader = BatchLoader(
    dataset, config.train.batch_size, config.data.num_points, seed=config.seed, shuffle=True,
    augment=augmentation(config), skip_broken=config.data.skip_broken,
    prefetch=config.data.prefetch, crop_from=config.data.crop_from,
    crop_mask_outside=config.data.crop_mask_outside, rows=rows,
  )
  total_steps = config.train.num_steps or config.train.num_epochs * loader.steps_per_epoch
  tx = make_optimizer(config, total_steps)
  try:  # the model's own checks (fields, widths) fail here, before anything is written
    model = build_model(config.model)
    jax.eval_shape(lambda rng: init_params(model, config, rng), jax.random.key(0))
  except (ValueError, TypeError) as e:
    raise ConfigError(f"config.model does not make a model: {e}") from e
  workdir.mkdir(parents=True, exist_ok=True)
  ckpts = checkpointing.Checkpoints(workdir / "checkpoints", max_to_keep=config.train.max_to_keep)
  return Run(config, workdir, mesh, model, tx, loader, total_steps, ckpts, [],
             tensorboard=events.EventWriter(workdir, enabled=distributed.is_primary()))


def start_state(run: Run) -> tuple[TrainState, int]:
  """(state, step): the newest checkpoint's when the workdir holds one and was trained with this
  model, stage and recipe; otherwise a fresh (or `train.init_from`) state at step 0."""
  config, ckpts = run.config, run.ckpts
  replicated = NamedSharding(run.mesh, P())
  start = ckpts.latest_step()
  if start is None:
    params = init_params(run.model, config, jax.random.key(config.seed))
    params = _load_init_params(params, config)
    host = jax.device_get(create_train_state(params, run.tx))
    return jax.device_put(host, replicated), 0
  saved = ckpts.restore_config(start)
  diffs = checkpointing.model_differences(saved, config, ignore=RUNTIME_MODEL_FIELDS)
  if saved.train.stage != config.train.stage:
    diffs.append(f"train.stage: {saved.train.stage} != {config.train.stage}")
  if diffs:
    raise ConfigError(
      f"{run.workdir} holds a run with a different model or stage ({'; '.join(diffs)}); "
      "use another --workdir"
    )
  run.recipe_changes = list(checkpointing.config_to_dict(saved).get("recipe_changes", []))
  recipe = checkpointing.recipe_differences(saved, config)
  if recipe and not config.train.get("resume_with_new_recipe", False):
    raise ConfigError(
      f"{ckpts.step_dir(start)} was trained with another recipe ({'; '.join(recipe)}; checkpoint "
      "!= config): rerun with its recipe, use another --workdir, or continue with this one: "
      "--config.train.resume_with_new_recipe=True"
    )
  if recipe:
    run.recipe_changes.append({"step": start, "changed": recipe})
    print(f"continuing with a new recipe from step {start}: {'; '.join(recipe)}", file=sys.stderr)
  target = abstract_train_state(run.model, run.tx, config, replicated)
  state = ckpts.restore_state(start, target)
  print(f"resuming from {ckpts.step_dir(start)}", file=sys.stderr)
  return state, start


# The loop.


def save(run: Run, step: int, state: TrainState):
  """A checkpoint at `step` (every process), then config.json beside it (process 0)."""
  if run.ckpts.save(step, state, run.config, run.recipe_changes) and distributed.is_primary():
    checkpointing.write_config(run.config, run.workdir, run.recipe_changes)


def train(run: Run, state: TrainState, start: int) -> TrainState:
  """Steps `start` .. total_steps: logs, saves, evaluates on held-out pairs every eval.every
  steps, and on SIGTERM/SIGINT saves and raises `Interrupted`."""
  config, primary = run.config, distributed.is_primary()
  train_step = jit_train_step(run.model, run.tx, config, run.mesh)
  heldout, eval_log = None, None
  if config.eval.every:
    heldout = run.heldout = heldout_evaluator(config)
    eval_log = MetricsLog(run.workdir / "eval_metrics.jsonl", start, enabled=primary,
                          events=run.tensorboard, prefix="eval")
  last_good = lambda: run.ckpts.steps() and run.ckpts.step_dir(run.ckpts.steps()[-1])
  bar = tqdm(total=run.total_steps, initial=start, desc=f"stage {config.train.stage}",
             unit="step", dynamic_ncols=True, mininterval=1.0, file=sys.stderr,
             disable=not primary)
  pending = PendingMetrics(MetricsLog(run.workdir / "metrics.jsonl", start, enabled=primary,
                                      events=run.tensorboard, prefix="train"),
                           learning_rate(config, run.total_steps), config.train.batch_size,
                           config.train.stage, bar, last_good)
  step = start
  with bar, StopSignals() as stop:
    if step < run.total_steps:
      for batch_index, batch in run.loader.iterate(start):
        state, metrics = train_step(state, device_batch(batch, run.mesh))
        step = batch_index + 1
        pending.append(step, metrics)
        bar.update(1)
        if step % config.train.log_every == 0:
          pending.flush(step)
        if step % config.train.checkpoint_every == 0 or step == run.total_steps:
          pending.flush(step)  # never save a state whose step produced a non-finite value
          save(run, step, state)
        if heldout is not None and step % config.eval.every == 0:
          started = time.perf_counter()
          results = heldout(state.params)
          eval_log.write({"step": step, "stage": config.train.stage, "time": time.time(),
                          **{k: results[k] for k in (*METRICS, "pairs")}})
          run.tensorboard.pictures(step, heldout.samples)
          bar.write(f"step {step}: held-out EPE {results['epe']:.4f} m "
                    f"({config.eval.dataset}, {results['pairs']} pairs)", file=sys.stderr)
          pending.pause(time.perf_counter() - started)  # pairs_per_s counts training alone
        if _stop_requested(stop, step, config.train.log_every):
          pending.flush(step)
          save(run, step, state)
          if primary:
            curves.plot_learning_curve(run.workdir)
          raise Interrupted(stop.signum or signal.SIGTERM, step, run.ckpts.step_dir(step))
        if step >= run.total_steps:
          break
    pending.flush(step)
    save(run, step, state)
  return state


def _stop_requested(stop: StopSignals, step: int, every: int) -> bool:
  """Whether a signal asked to stop: at once in one process; in many, every `every` steps, when
  all of them agree (a signal to any one stops them all at the same step)."""
  if jax.process_count() == 1:
    return stop.signum is not None
  if step % every:
    return False
  return bool(distributed.sum_over_processes([stop.signum is not None])[0])


def finish(run: Run, state: TrainState):
  """The end-of-run evaluation (eval.json and the table) and the learning curve (process 0)."""
  config = run.config
  if run.loader.broken:
    print(f"skipped {len(run.loader.broken)} unreadable sample(s) in training: "
          + ", ".join(map(str, run.loader.broken)), file=sys.stderr)
  if config.eval.dataset:
    evaluator = run.heldout or heldout_evaluator(config)
    results = evaluate_run(state.params, config, evaluator)
    step = int(jax.device_get(state.step))
    run.tensorboard.scalars(step, results["model"], "eval")
    run.tensorboard.scalars(step, results["zero_flow"], "eval_zero_flow")
    run.tensorboard.pictures(step, evaluator.samples)
    if distributed.is_primary():
      (run.workdir / "eval.json").write_text(json.dumps(results, indent=2) + "\n")
      print(reporting.format_table(
        [(f"{config.eval.dataset} ({config.eval.split})", results["model"]),
         ("zero flow", results["zero_flow"])]
      ))
  if distributed.is_primary():
    curves.plot_learning_curve(run.workdir)


def train_and_evaluate(config: ml_collections.ConfigDict, workdir) -> TrainState:
  """Trains (resuming from WORKDIR/checkpoints when it holds one), then evaluates on
  `config.eval.dataset` and writes WORKDIR/eval.json (the model and zero flow on the same pairs)."""
  run = prepare(config, workdir)
  try:
    state, start = start_state(run)
    state = train(run, state, start)
  finally:
    run.ckpts.close()
    run.tensorboard.flush()
  try:
    finish(run, state)
  finally:
    run.tensorboard.close()
  return state


def heldout_evaluator(config) -> evaluator.Evaluator:
  """The model's metrics on `config.eval`'s held-out pairs, as the run's stage outputs them (the
  model as it evaluates: `model.infer_truncate_k`)."""
  ds = open_dataset(config.eval.dataset, split=config.eval.split)
  return evaluator.Evaluator(
    build_model(config.model, inference=True), ds, num_points=config.eval.num_points or None,
    batch_size=config.eval.batch_size, num_iters=config.eval.num_iters,
    refine=config.train.stage == 2, seed=config.eval.seed, keep=events.PICTURES,
  )


def evaluate_run(params, config, evaluator=None) -> dict:
  """{"model": metrics, "zero_flow": metrics} on `config.eval`'s held-out pairs (`evaluator`: the
  run's `heldout_evaluator`, already compiled)."""
  evaluator = evaluator or heldout_evaluator(config)
  return {"model": evaluator(params), "zero_flow": evaluator.zero_flow()}
