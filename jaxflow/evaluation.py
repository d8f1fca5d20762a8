"""Evaluation: the five metrics averaged over pairs, timed, printed as the paper's Tables 2-3.

    results = evaluate(model, params, dataset, num_points=8192, batch_size=1, num_iters=32)
    print(format_table([("KITTI", results)]))

Metrics are computed per pair on its valid points, then averaged over pairs; padding pairs
(`pair_valid` = 0) are excluded. `ms_per_pair` is the model's wall time (compilation excluded: the
function is compiled ahead of the timed calls) divided by the number of real pairs. Evaluation point
sampling is seeded, so the same call gives the same numbers. Batches are streamed (memory does not
grow with the number of pairs), with a progress bar in pairs/s on stderr. In a run over many
processes (jaxflow.distributed) each process evaluates every P-th batch and the sums are reduced.
"""

import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from tqdm import tqdm

from jaxflow import checkpointing, distributed, export, frames, methods, model_fields, tables
from jaxflow import test_time
from jaxflow.data import eval_batches, open_dataset
from jaxflow.errors import CheckpointError, ConfigError
from jaxflow.metrics import METRICS, ThreeWayAverage, format_three_way, per_pair_metrics
from jaxflow.model import build_model

# The shipped checkpoint, used by evaluate.py when --checkpoint is not given.
SHIPPED_CHECKPOINT = Path(__file__).absolute().parent / "checkpoints" / "jaxflow_synthetic"
# The settings evaluate.py and predict use when no --config is given (8192 points, 32 iterations).
EVAL_CONFIG = f"{Path(__file__).absolute().parent / 'configs' / 'default.py'}:eval"
# Model fields that change neither the parameters nor the training, taken from the user's config
# (memory, speed, arithmetic, test-time candidates): jaxflow.model_fields, the one table of them.
RUNTIME_MODEL_FIELDS = model_fields.RUNTIME_MODEL_FIELDS


def requested_model_fields(config_flag) -> list[str]:
  """The `config.model` fields a user asked for on a command line (`config_flag`: the absl flag of
  a config file): those given as `--config.model.FIELD=...` and, with an explicit config file, every
  field of its model except the runtime ones, which stay the checkpoint's unless given."""
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  given = {k.split(".", 1)[1] for k in config_flags.get_override_values(config_flag)
           if k.startswith("model.")}
  if config_flag.present:
    given |= {k for k in config_flag.value.model.keys() if k not in RUNTIME_MODEL_FIELDS}
  return sorted(given)


def model_predict_fn(model, num_iters: int, refine: bool,
                     optimise: test_time.Settings = test_time.Settings(),
                     method: str = "network", method_settings=None, with_info: bool = False):
  """jit (params, pc1, pc2) -> flow B x N x 3: the refined flow, or the last iteration's; then
  `optimise.steps` steps of test-time optimisation when > 0 (jaxflow.test_time); `method`
  (jaxflow.methods) turns it into the nsfp or optimise flow (model None for nsfp)."""

  def predict(params, pc1_BxNx3, pc2_BxMx3):
    out = model.apply({"params": params}, pc1_BxNx3, pc2_BxMx3, num_iters=num_iters, refine=refine)
    flow = out["refined"] if refine else out["flows"][:, -1]
    if optimise.steps:
      flow = test_time.optimise_flow(flow, pc1_BxNx3, pc2_BxMx3, optimise)[0]
    return flow

  return jax.jit(methods.flow_fn(method, predict, method_settings, with_info))


_metrics_fn = jax.jit(per_pair_metrics)


def _process_batches(dataset, batch_size: int, num_points: int | None, seed: int):
  """This process's share of `eval_batches` (every P-th batch) and its number of real pairs."""
  index, count = jax.process_index(), jax.process_count()
  batches = eval_batches(dataset, batch_size, num_points, seed=seed, shard=(index, count))
  starts = range(index * batch_size, len(dataset), count * batch_size)
  return batches, sum(min(batch_size, len(dataset) - s) for s in starts)


def _run(predict, args, batches, render_dir=None, compiled=None, total=None, save_dir=None,
         up="y") -> dict:
  """Averages the metrics of `predict(*args, pc1, pc2)` over the pairs of `batches` (this
  process's; the sums are added over processes). `compiled` caches the compiled `predict` by input
  shapes (compiled before timing) across calls; `total`: the pairs expected, for the progress bar.
  Batches with ego-motion flow and labels add "three_way" (metrics.ThreeWayAverage); save_dir:
  every pair's flow (jaxflow.export). A `predict` that returns (flow, info) (an optimising method's
  `with_info`) adds "convergence": the pairs it optimised, those whose flow went non-finite (the
  starting flow is kept), those whose early stopping fired, and the mean steps."""
  compiled = {} if compiled is None else compiled
  convergence = np.zeros(4)  # pairs with info, non-finite, early-stopped, steps
  three_way = ThreeWayAverage()
  saver = export.FlowSaver(save_dir) if save_dir is not None else None
  sums = dict.fromkeys(METRICS, 0.0)
  pairs, seconds = 0, 0.0
  bar = tqdm(total=total, desc="evaluating", unit="pair", file=sys.stderr, leave=False,
             dynamic_ncols=True, mininterval=1.0, disable=not distributed.is_primary())
  with bar:
    for batch in batches:
      pc1, pc2 = jnp.asarray(batch["pc1"]), jnp.asarray(batch["pc2"])
      key = (pc1.shape, pc2.shape)
      if key not in compiled:
        compiled[key] = predict.lower(*args, pc1, pc2).compile()
      start = time.perf_counter()
      pred = jax.block_until_ready(compiled[key](*args, pc1, pc2))
      seconds += time.perf_counter() - start
      valid = np.asarray(batch["pair_valid"], np.float64)
      if isinstance(pred, tuple):
        pred, info = pred[0], jax.device_get(pred[1])
        if info is not None:
          convergence += [valid.sum(), np.sum(valid * ~np.asarray(info["finite"])),
                          np.sum(valid * np.asarray(info["stopped"])),
                          np.sum(valid * np.asarray(info["steps"]))]
      per_pair = jax.device_get(_metrics_fn(pred, jnp.asarray(batch["flow"]),
                                           jnp.asarray(batch["mask"])))
      for k in METRICS:
        sums[k] += float(np.sum(np.asarray(per_pair[k], np.float64) * valid))
      pairs += int(valid.sum())
      three_way.add(pred, batch)
      if saver is not None:
        saver.add(batch, pred)
      bar.update(int(valid.sum()))
      if render_dir is not None:
        _render(render_dir, batch, np.asarray(pred), up)
  summed = distributed.sum_over_processes([*sums.values(), pairs, seconds, *convergence])
  totals, (pairs, seconds), convergence = summed[:len(METRICS)], summed[-6:-4], summed[-4:]
  sums, pairs = dict(zip(METRICS, totals)), int(pairs)
  three_way.reduce(distributed.sum_over_processes)
  if pairs == 0:
    raise ConfigError("the evaluation dataset holds no pairs")
  results = {k: sums[k] / pairs for k in METRICS}
  results.update(pairs=pairs, ms_per_pair=1000.0 * seconds / pairs, **three_way.results())
  if convergence[0]:
    results["convergence"] = {"pairs": int(convergence[0]), "non_finite": int(convergence[1]),
                              "early_stopped": int(convergence[2]),
                              "mean_steps": convergence[3] / convergence[0]}
  return results


def _output_name(refine: bool, optimise: test_time.Settings) -> str:
  return ("refined" if refine else "coarse") + (" + test-time" if optimise.steps else "")


def evaluate(model, params, dataset, *, num_points: int | None, batch_size: int, num_iters: int = 32,
             refine: bool = False, seed: int = 0, render_dir=None,
             optimise: test_time.Settings = test_time.Settings(), method: str = "network",
             method_settings=None, save_flows=None) -> dict:
  """Metrics of the model's flow on every pair of `dataset`, with pairs and ms_per_pair (the
  test-time optimisation included when `optimise.steps` > 0; `method`: jaxflow.methods);
  save_flows: a folder that receives the flow of every pair (jaxflow.export; the points evaluated:
  sampled unless num_points None)."""
  predict = model_predict_fn(model, num_iters, refine, optimise, method, method_settings,
                             with_info=method != "network")
  predict = frames.in_model_frame_jax(predict, frames.dataset_up(dataset))  # opensf's ego: z up
  batches, total = _process_batches(dataset, batch_size, num_points, seed)
  results = _run(predict, (distributed.local_copy(params),), batches, render_dir, total=total,
                 save_dir=save_flows, up=frames.dataset_up(dataset))
  results["output"] = _output_name(refine, optimise)
  results.update(methods.describe(method, method_settings or methods.settings(method)))
  if optimise.steps:
    results["test_time"] = dataclasses.asdict(optimise)
  return results


class Evaluator:
  """`evaluate` for repeated calls on the same pairs with new parameters (the held-out evaluation
  during training): the model is compiled once, every call re-samples the same pairs (seeded, so
  the same batches; nothing is kept between calls: memory does not grow with the pairs), and a call
  with the very same parameter arrays as the previous one (jax arrays are immutable) returns its
  results again (the end-of-run evaluation of a step just evaluated)."""

  def __init__(self, model, dataset, *, num_points: int | None, batch_size: int,
               num_iters: int = 32, refine: bool = False, seed: int = 0,
               optimise: test_time.Settings = test_time.Settings()):
    self.sampling = dict(dataset=dataset, batch_size=batch_size, num_points=num_points, seed=seed)
    eval_batches(**self.sampling)  # checks the arguments now (a generator would check them later)
    self.predict = model_predict_fn(model, num_iters, refine, optimise)
    self.output = _output_name(refine, optimise)
    self.compiled = {}
    self._last = ([], None)  # (parameter leaves, results) of the previous call

  def __call__(self, params) -> dict:
    leaves = jax.tree.leaves(params)
    last_leaves, last_results = self._last
    if len(leaves) == len(last_leaves) and all(a is b for a, b in zip(leaves, last_leaves)):
      return dict(last_results)
    batches, total = _process_batches(**self.sampling)
    results = _run(self.predict, (distributed.local_copy(params),), batches,
                   compiled=self.compiled, total=total)
    results["output"] = self.output
    self._last = (leaves, dict(results))
    return results

  def zero_flow(self) -> dict:
    """`evaluate_zero_flow` on the same pairs."""
    batches, total = _process_batches(**self.sampling)
    return _run(_zero_flow, (), batches, total=total)


_zero_flow = jax.jit(lambda pc1, pc2: jnp.zeros_like(pc1))


def evaluate_zero_flow(dataset, *, num_points: int | None, batch_size: int, seed: int = 0) -> dict:
  """The same metrics for a zero-flow prediction on the same pairs (the trivial baseline)."""
  batches, total = _process_batches(dataset, batch_size, num_points, seed)
  return _run(_zero_flow, (), batches, total=total)


def _render(render_dir, batch, pred_BxNx3, up="y"):
  try:
    from jaxflow import viz
  except ImportError as e:
    raise ConfigError(f"--render needs the jaxflow.viz module, which cannot be imported ({e})")
  viz.render_batch(render_dir, batch, pred_BxNx3, up)


def format_table(rows) -> str:
  """rows: (dataset name, results) -> the layout of the paper's Tables 2-3."""
  header = ("Dataset", "EPE(m)", "AccS(%)", "AccR(%)", "Outliers(%)", "θε(rad)", "pairs", "ms/pair")
  return tables.markdown_table(header, [(
    name, f"{r['epe']:.4f}", f"{r['acc_strict']:.2f}", f"{r['acc_relax']:.2f}",
    f"{r['outliers']:.2f}", f"{r['angle']:.4f}", str(r["pairs"]), f"{r['ms_per_pair']:.1f}",
  ) for name, r in rows])


def load_model(checkpoint=None, config: ml_collections.ConfigDict | None = None, model_fields=()):
  """(model, params, stored config, step, refine) of a checkpoint (None: the shipped one).

  The model comes from the checkpoint's stored config. `model_fields` names the fields of
  `config.model` the user asked for: one that contradicts the checkpoint is a CheckpointError,
  except RUNTIME_MODEL_FIELDS, which change no parameter and are taken from `config`.
  `refine` says whether the checkpoint's refinement was trained (stage 2).
  """
  if checkpoint is None:
    if not SHIPPED_CHECKPOINT.exists():
      raise CheckpointError(f"no checkpoint given and no shipped checkpoint at {SHIPPED_CHECKPOINT}")
    checkpoint = SHIPPED_CHECKPOINT
  state, saved, step = checkpointing.restore_checkpoint(checkpoint)
  if config is not None:
    runtime = [k for k in model_fields if k in RUNTIME_MODEL_FIELDS]
    checked = [k for k in model_fields if k not in RUNTIME_MODEL_FIELDS]
    diffs = checkpointing.model_differences(config, saved, fields=checked)
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


def evaluate_checkpoint(checkpoint, config: ml_collections.ConfigDict, dataset: str | None = None,
                        split: str | None = None, model_fields=(), json_path=None,
                        render_dir=None, save_flows=None, method: str = "network",
                        steps: int | None = None) -> dict:
  """Evaluates a checkpoint (workdir, checkpoints folder or step folder; None: the shipped one).

  The model comes from the checkpoint as `load_model` gives it; `config.eval` sets points (0: whole
  clouds), iterations, batch, seed, the test-time optimisation (`test_time`; steps 0: off) and,
  unless given, the dataset and split. `method` (jaxflow.methods; `steps` caps its optimiser):
  nsfp needs no checkpoint.
  """
  chosen = methods.settings(method, steps)
  dataset = dataset or config.eval.dataset
  split = split or config.eval.split
  if not dataset:
    raise ConfigError("no dataset to evaluate: give --dataset FORMAT:ROOT")
  model, params, step, refine = None, None, None, False
  if method in methods.NEEDS_NETWORK:
    model, params, _, step, refine = load_model(checkpoint, config, model_fields)
    checkpoint = checkpoint or SHIPPED_CHECKPOINT
  ds = open_dataset(dataset, split=split)
  results = evaluate(model, params, ds, num_points=config.eval.num_points or None,
                     batch_size=config.eval.batch_size, num_iters=config.eval.num_iters,
                     refine=refine, seed=config.eval.seed, render_dir=render_dir,
                     optimise=test_time.settings_from_config(config.eval), method=method,
                     method_settings=chosen, save_flows=save_flows)
  results.update(dataset=dataset, split=split, checkpoint=checkpoint and str(checkpoint), step=step,
                 num_points=config.eval.num_points, num_iters=config.eval.num_iters)
  if not distributed.is_primary():
    return results
  print(format_table([(f"{dataset} ({split})", results)]))
  if "three_way" in results:
    print(format_three_way([(f"{dataset} ({split})", results)]))
  note = methods.evaluation_note(method, results.get("convergence"))
  if note:
    print(f"note: {note}", file=sys.stderr)
  if json_path:
    Path(json_path).absolute().parent.mkdir(parents=True, exist_ok=True)
    Path(json_path).write_text(json.dumps(results, indent=2) + "\n")
  return results
