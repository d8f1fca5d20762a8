"""Training: the train state, the pure train step and the loop, `train_and_evaluate(config, workdir)`.

Steps are counted in updates: step s is the s-th update (it consumed batch s - 1 of the loader), and
checkpoint s holds the state after it. Rerunning the same command resumes from the newest checkpoint;
`BatchLoader.batch(step)` is deterministic, so the resumed run replays the same data order.

Two stages (paper 4.1). Stage 1 trains everything but the refinement with the sequence loss (from
scratch, or warm-started from another run's parameters with `config.train.init_from`). Stage 2
loads stage 1 (`config.train.init_from`) and trains only the refinement with the refinement loss: the
gradient is taken only w.r.t. the trainable parameters (the others are closed over), the optimiser
is an `optax.multi_transform` whose frozen group is `set_to_zero` (no optimiser state), and the model
runs with `freeze_backbone=True`.
"""

import contextlib
import functools
import json
import math
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import flax
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from flax import traverse_util
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
from tqdm import tqdm

from jaxflow import checkpointing, curves, evaluation, test_time
from jaxflow.data import BatchLoader, open_dataset
from jaxflow.errors import CheckpointError, ConfigError, NonFiniteError
from jaxflow.losses import refinement_loss, sequence_loss
from jaxflow.metrics import METRICS
from jaxflow.model import PARAMETER_FREE_FIELDS, build_model
from jaxflow.model_fields import REFINE_FIELDS

BATCH_KEYS = ("pc1", "pc2", "flow", "mask")
REFINE = "refine"  # top-level parameter name of the refinement module.


@flax.struct.dataclass
class TrainState:
  step: jax.Array  # int32 scalar: updates applied so far.
  params: Any
  opt_state: Any


class Interrupted(Exception):
  """Training stopped on SIGTERM/SIGINT after saving a checkpoint at `step`."""

  def __init__(self, signum: int, step: int, path):
    self.signum, self.step = signum, step
    name = signal.Signals(signum).name
    super().__init__(
      f"stopped by {name} at step {step}; checkpoint saved in {path}; "
      "rerun the same command to resume"
    )


# Parameters and the optimiser.


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


def init_params(model, config: ml_collections.ConfigDict, rng):
  """Freshly initialised parameters (the shapes do not depend on the number of points)."""
  n = max(config.model.knn, 32)
  pc = jnp.zeros((1, n, 3), jnp.float32) + jnp.linspace(0.0, 1.0, n)[None, :, None]
  return jax.jit(functools.partial(model.init, num_iters=1))(rng, pc, pc)["params"]


def create_train_state(params, tx) -> TrainState:
  return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params))


def abstract_train_state(model, tx, config, sharding=None) -> TrainState:
  """Shapes, dtypes (and `sharding`) of the train state: orbax's restore target."""
  shapes = jax.eval_shape(
    lambda rng: create_train_state(init_params(model, config, rng), tx), jax.random.key(0)
  )
  sharding = sharding or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), shapes)


def augmentation(config) -> dict | None:
  """config.data.augment without its identity entries (None when nothing is augmented)."""
  identity = {"rotation_deg": 0.0, "scale": (1.0, 1.0), "jitter": 0.0}
  aug = {k: tuple(v) if isinstance(v, (list, tuple)) else v
         for k, v in config.data.augment.items()}
  aug = {k: v for k, v in aug.items() if v != identity.get(k)}
  return aug or None


# The train step.


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
        return refinement_loss(out["refined"], batch["flow"], batch["mask"])
      return sequence_loss(out["flows"], batch["flow"], batch["mask"], gamma=gamma)

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
  """A 1-D mesh over the local devices: batches are split over 'data', parameters replicated."""
  return Mesh(np.asarray(devices if devices is not None else jax.local_devices()), ("data",))


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
  """The arrays of a loader batch, split on their leading (pair) axis over the mesh."""
  return jax.device_put({k: batch[k] for k in BATCH_KEYS}, NamedSharding(mesh, P("data")))


# Checkpoints.


def restore_checkpoint(path, step: int | None = None):
  """(TrainState, config, step) of a workdir, checkpoints folder or step folder; the model and
  optimiser are rebuilt from the config stored in the checkpoint."""
  ckpts, latest, config = checkpointing.open_checkpoint(path)
  step = latest if step is None else step
  with contextlib.closing(ckpts):  # on errors too: a notebook goes on after a CheckpointError
    try:
      model = build_model(config.model)
    except (ValueError, TypeError) as e:
      raise CheckpointError(f"{ckpts.step_dir(step)}: its config does not build a model ({e})")
    target = abstract_train_state(model, make_optimizer(config, 1), config)
    return ckpts.restore_state(step, target), config, step


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
  loaded_state, loaded_config, step = restore_checkpoint(config.train.init_from)
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


# Host-side bookkeeping: metrics.jsonl, the progress bar, signals.


class MetricsLog:
  """Appends one JSON object per logged step to WORKDIR/metrics.jsonl."""

  def __init__(self, path: Path, resume_step: int):
    self.path = path
    if path.exists():  # drop lines logged after the checkpoint we resume from (replayed now)
      keep = [l for l in path.read_text().splitlines() if l and json.loads(l)["step"] <= resume_step]
      path.write_text("".join(l + "\n" for l in keep))

  def write(self, record: dict):
    with self.path.open("a") as f:
      f.write(json.dumps(record) + "\n")


class StopSignals:
  """Turns SIGTERM/SIGINT into a flag the loop polls; a second signal interrupts at once."""

  def __init__(self):
    self.signum = None
    self._previous = {}

  def _handle(self, signum, frame):
    if self.signum is not None:
      raise KeyboardInterrupt
    self.signum = signum

  def __enter__(self):
    if threading.current_thread() is threading.main_thread():
      for s in (signal.SIGTERM, signal.SIGINT):
        self._previous[s] = signal.signal(s, self._handle)
    return self

  def __exit__(self, *exc):
    for s, h in self._previous.items():
      signal.signal(s, h)


def _finite(x) -> bool:
  return x is not None and math.isfinite(x)


# The loop.


def _check_config(config, n_devices: int):
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


def train_and_evaluate(config: ml_collections.ConfigDict, workdir) -> TrainState:
  """Trains (resuming from WORKDIR/checkpoints when it holds one), then evaluates on
  `config.eval.dataset` and writes WORKDIR/eval.json (the model and zero flow on the same pairs)."""
  workdir = Path(workdir).absolute()
  mesh = make_mesh()
  _check_config(config, mesh.size)

  dataset = open_dataset(config.data.dataset, split=config.data.split)
  loader = BatchLoader(
    dataset, config.train.batch_size, config.data.num_points, seed=config.seed, shuffle=True,
    augment=augmentation(config), skip_broken=config.data.skip_broken,
    prefetch=config.data.prefetch, crop_from=config.data.crop_from,
    crop_mask_outside=config.data.crop_mask_outside,
  )
  total_steps = config.train.num_steps or config.train.num_epochs * loader.steps_per_epoch
  tx = make_optimizer(config, total_steps)
  schedule = learning_rate(config, total_steps)
  replicated = NamedSharding(mesh, P())
  try:  # the model's own checks (fields, widths) fail here, before anything is written
    model = build_model(config.model)
    target = abstract_train_state(model, tx, config, replicated)
  except (ValueError, TypeError) as e:
    raise ConfigError(f"config.model does not make a model: {e}") from e
  workdir.mkdir(parents=True, exist_ok=True)
  ckpts = checkpointing.Checkpoints(workdir / "checkpoints", max_to_keep=config.train.max_to_keep)

  start = ckpts.latest_step()
  if start is not None:
    saved = ckpts.restore_config(start)
    diffs = checkpointing.model_differences(saved, config, ignore=evaluation.RUNTIME_MODEL_FIELDS)
    if saved.train.stage != config.train.stage:
      diffs.append(f"train.stage: {saved.train.stage} != {config.train.stage}")
    if diffs:
      raise ConfigError(
        f"{workdir} holds a run with a different model or stage ({'; '.join(diffs)}); "
        "use another --workdir"
      )
    state = ckpts.restore_state(start, target)
    print(f"resuming from {ckpts.step_dir(start)}", file=sys.stderr)
  else:
    start = 0
    params = init_params(model, config, jax.random.key(config.seed))
    params = _load_init_params(params, config)
    state = jax.device_put(create_train_state(params, tx), replicated)
  checkpointing.write_config(config, workdir)

  train_step = jit_train_step(model, tx, config, mesh)
  log = MetricsLog(workdir / "metrics.jsonl", start)
  heldout, eval_log = None, None
  if config.eval.every:
    heldout = heldout_evaluator(config)
    eval_log = MetricsLog(workdir / "eval_metrics.jsonl", start)
  pairs_per_step = config.train.batch_size
  pending = []  # (step, metrics on device) since the last fetch
  window_start = time.perf_counter()

  def fetch_and_log(step: int):
    """Reads the pending metrics (one host sync), logs them, stops on a non-finite value."""
    nonlocal pending, window_start
    if not pending:
      return
    fetched = jax.device_get([m for _, m in pending])
    steps = [s for s, _ in pending]
    elapsed = time.perf_counter() - window_start
    pending, window_start = [], time.perf_counter()
    record = {
      "step": step,
      "loss": float(np.mean([m["loss"] for m in fetched])),
      "grad_norm": float(np.mean([m["grad_norm"] for m in fetched])),
      "param_norm": float(fetched[-1]["param_norm"]),
      "pairs_per_s": len(steps) * pairs_per_step / max(elapsed, 1e-9),
      "lr": float(schedule(step - 1)),
      "stage": config.train.stage,
      "time": time.time(),
    }
    log.write({k: (v if not isinstance(v, float) or _finite(v) else None)
               for k, v in record.items()})
    bar.set_postfix(loss=f"{record['loss']:.4f}", pairs_s=f"{record['pairs_per_s']:.1f}")
    for s, m in zip(steps, fetched):
      if not (_finite(float(m["loss"])) and _finite(float(m["grad_norm"]))):
        last = ckpts.steps()
        raise NonFiniteError(
          f"non-finite loss or gradient at step {s} (loss={float(m['loss'])}, "
          f"grad_norm={float(m['grad_norm'])}); that state was not saved; last good checkpoint: "
          + (str(ckpts.step_dir(last[-1])) if last else "none")
        )

  def save(step: int):
    fetch_and_log(step)  # never save a state whose step produced a non-finite value
    ckpts.save(step, state, config)

  bar = tqdm(total=total_steps, initial=start, desc=f"stage {config.train.stage}", unit="step",
             dynamic_ncols=True, mininterval=1.0, file=sys.stderr)
  try:
    with StopSignals() as stop:
      step = start
      if step < total_steps:
        for batch_index, batch in loader.iterate(start):
          state, metrics = train_step(state, device_batch(batch, mesh))
          step = batch_index + 1
          pending.append((step, metrics))
          if len(pending) > 2:
            # Waits for the step before last (no transfer; the device keeps the next one queued):
            # keeps the progress bar and a stop signal within two steps of the device.
            jax.block_until_ready(pending[-3][1]["loss"])
          bar.update(1)
          if step % config.train.log_every == 0:
            fetch_and_log(step)
          if step % config.train.checkpoint_every == 0 or step == total_steps:
            save(step)
          if heldout is not None and step % config.eval.every == 0:
            started = time.perf_counter()
            results = heldout(state.params)
            eval_log.write({"step": step, "stage": config.train.stage, "time": time.time(),
                            **{k: results[k] for k in (*METRICS, "pairs")}})
            bar.write(f"step {step}: held-out EPE {results['epe']:.4f} m "
                      f"({config.eval.dataset}, {results['pairs']} pairs)", file=sys.stderr)
            window_start += time.perf_counter() - started  # pairs_per_s counts training alone
          if stop.signum is not None:
            save(step)
            curves.plot_learning_curve(workdir)
            raise Interrupted(stop.signum, step, ckpts.step_dir(step))
          if step >= total_steps:
            break
      fetch_and_log(step)
      ckpts.save(step, state, config)
  finally:
    bar.close()
    ckpts.close()

  if loader.broken:
    print(f"skipped {len(loader.broken)} unreadable sample(s) in training: "
          + ", ".join(map(str, loader.broken)), file=sys.stderr)
  if config.eval.dataset:
    results = evaluate_run(state.params, config, heldout)
    (workdir / "eval.json").write_text(json.dumps(results, indent=2) + "\n")
    print(evaluation.format_table(
      [(f"{config.eval.dataset} ({config.eval.split})", results["model"]),
       ("zero flow", results["zero_flow"])]
    ))
  curves.plot_learning_curve(workdir)
  return state


def heldout_evaluator(config) -> evaluation.Evaluator:
  """The model's metrics on `config.eval`'s held-out pairs, as the run's stage outputs them (the
  model as it evaluates: `model.infer_truncate_k`)."""
  ds = open_dataset(config.eval.dataset, split=config.eval.split)
  return evaluation.Evaluator(
    build_model(config.model, inference=True), ds, num_points=config.eval.num_points or None,
    batch_size=config.eval.batch_size, num_iters=config.eval.num_iters,
    refine=config.train.stage == 2, seed=config.eval.seed,
    optimise=test_time.settings_from_config(config.eval),
  )


def evaluate_run(params, config, evaluator=None) -> dict:
  """{"model": metrics, "zero_flow": metrics} on `config.eval`'s held-out pairs (`evaluator`: the
  run's `heldout_evaluator`, already compiled)."""
  evaluator = evaluator or heldout_evaluator(config)
  return {"model": evaluator(params), "zero_flow": evaluator.zero_flow()}
