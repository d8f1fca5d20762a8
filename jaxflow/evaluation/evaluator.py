"""Evaluation: the five metrics averaged over pairs, timed (the library; what evaluate.py prints and
writes is jaxflow.evaluation.reporting).

    results = evaluate(model, params, dataset, num_points=8192, batch_size=1, num_iters=32)
    print(reporting.format_table([("KITTI", results)]))

Metrics are computed per pair on its valid points, then averaged over pairs; padding pairs
(`pair_valid` = 0) are excluded. Two wall times: `first_pair_s`, the first batch's seconds a pair
with its compilation (what a user waits for the first flow; the first pair at batch 1), and
`ms_per_pair`, the steady state: the other pairs' (a new shape among them compiled before its
clock starts; with one batch only, that batch run again once compiled). Evaluation point sampling
is seeded, so the same call gives the same numbers. Batches are streamed (memory does not
grow with the number of pairs), with a bar in pairs/s on a terminal (stderr) and, in a log, a
line every 10 s (jaxflow.refine.progress.Working). In a run over many
processes (jaxflow.runtime.distributed) each process evaluates every P-th batch and the sums are reduced.
`on_batch` callbacks (batch, predicted flow) see every batch: evaluate.py's --render_dir and
--save_flows.
"""

import sys
import time

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from tqdm import tqdm

from jaxflow.runtime import distributed
from jaxflow.data import eval_batches, open_dataset
from jaxflow.errors import ConfigError
from jaxflow.evaluation import av2_eval, submission
from jaxflow.evaluation.metrics import METRICS, ThreeWayAverage, per_pair_metrics
from jaxflow.geometry import frames
from jaxflow.methods import registry
from jaxflow.network import checkpointing
from jaxflow.refine import progress

# The convergence counts of an optimising method, summed over pairs (names of `_Totals`).
CONVERGENCE = ("optimised", "non_finite", "early_stopped", "steps")


def check_no_test_time(config_eval):
  """config.eval.test_time (an older config's per-pair refinement) is refused, naming what replaced
  it: the per-pair methods of jaxflow.methods.registry."""
  if "test_time" in config_eval:
    raise ConfigError("config.eval.test_time was removed: per-pair refinement of the network's "
                      "flow is --method optimise (with --steps N to cap its steps); drop "
                      "config.eval.test_time from the config")


_metrics_fn = jax.jit(per_pair_metrics)


def _process_batches(dataset, batch_size: int, num_points: int | None, seed: int):
  """This process's share of `eval_batches` (every P-th batch) and its number of real pairs."""
  index, count = jax.process_index(), jax.process_count()
  batches = eval_batches(dataset, batch_size, num_points, seed=seed, shard=(index, count))
  starts = range(index * batch_size, len(dataset), count * batch_size)
  return batches, sum(min(batch_size, len(dataset) - s) for s in starts)


class _Totals(dict):
  """Named sums over pairs (valid pairs only), added over processes by `reduced`."""

  def __init__(self):
    super().__init__(dict.fromkeys([*METRICS, "pairs", *_Timer.TOTALS, *CONVERGENCE], 0.0))

  def reduced(self) -> dict:
    return dict(zip(self, distributed.sum_over_processes(list(self.values()))))


def _timed(fn, *args):
  start = time.perf_counter()
  out = jax.block_until_ready(fn(*args))
  return out, time.perf_counter() - start


class _Timer:
  """`predict(*args, pc1, pc2)` of each batch, timed into `totals`: the first batch with its
  compilation, the others after it (the module docstring). `compiled`: the compiled `predict` by
  input shapes; `warm_up`: after the first batch, a Python-driven `predict` is called once untimed
  on new shapes (its compilation; a method that compiles nothing, the lidar pipeline, is not)."""
  TOTALS = ("first_seconds", "first_pairs", "seconds", "timed_pairs")

  def __init__(self, predict, args, compiled, warm_up, totals):
    self.predict, self.args, self.compiled, self.warm_up = predict, args, compiled, warm_up
    self.totals = totals
    self.again = None  # the first batch (pc1, pc2, pairs); () once another batch came

  def _compiled(self, pc1, pc2, warm: bool):
    key = (pc1.shape, pc2.shape)
    if key not in self.compiled:
      if hasattr(self.predict, "lower"):
        self.compiled[key] = self.predict.lower(*self.args, pc1, pc2).compile()
      else:  # driven from Python (registry.flow_fn): its stages compile at a first call
        if warm and self.warm_up:
          jax.block_until_ready(self.predict(*self.args, pc1, pc2))
        self.compiled[key] = self.predict
    return self.compiled[key]

  def __call__(self, pc1, pc2, pairs):
    if self.again is None:  # the first batch: its compilation is part of its time
      self.again = (pc1, pc2, pairs)
      pred, seconds = _timed(lambda: self._compiled(pc1, pc2, warm=False)(*self.args, pc1, pc2))
      self.totals["first_seconds"] += seconds
      self.totals["first_pairs"] += pairs
      return pred
    self.again = ()  # the steady state comes from the other batches (the first's clouds freed)
    pred, seconds = _timed(self._compiled(pc1, pc2, warm=True), *self.args, pc1, pc2)
    self.totals["seconds"] += seconds
    self.totals["timed_pairs"] += pairs
    return pred

  def finish(self) -> bool:
    """The steady state of a run of one batch: that batch again, compiled (True when so)."""
    if self.again:
      pc1, pc2, pairs = self.again
      _, seconds = _timed(self._compiled(pc1, pc2, warm=False), *self.args, pc1, pc2)
      self.totals["seconds"] += seconds
      self.totals["timed_pairs"] += pairs
    return bool(self.again)


def _shown(total):
  """(bar, working, done): the pairs' bar on a terminal, in a log a line every progress.EVERY_S
  seconds (progress.Working), by process 0; `done[0]`: the pairs so far (a disabled bar counts
  none)."""
  primary, done = distributed.is_primary(), [0]
  bar = tqdm(total=total, desc="evaluating", unit="pair", file=sys.stderr, leave=False,
             dynamic_ncols=True, mininterval=1.0, disable=None if primary else True)
  working = progress.Working("evaluating", lambda: f"{done[0]}/{total} pairs",
                             progress=False if not primary or not bar.disable else None)
  return bar, working, done


def _run(predict, args, batches, compiled=None, total=None, on_batch=(), on_pair=None,
         warm_up: bool = True) -> dict:
  """Averages the metrics of `predict(*args, pc1, pc2)` over the pairs of `batches` (this
  process's; the sums are added over processes), timed as the module docstring says (`_Timer`:
  `compiled` caches the compiled `predict` by input shapes across calls, `warm_up`); `total`: the
  pairs expected, for the progress bar.
  Batches with ego-motion flow and labels add "three_way_local" (OpenSceneFlow's local reading,
  metrics.ThreeWayAverage) and, with av2 labels, "av2" and "bucketed" (the official readings,
  av2_eval.Official; `on_pair(name, labels)` gets each pair's: SubmissionWriter.add). A `predict`
  that returns (flow, info) (an optimising method's `with_info`) adds "convergence": the pairs it
  optimised, those whose flow went non-finite (the starting flow is kept), those whose early
  stopping fired, and the mean steps. `on_batch`: callables (batch, flow B x N x 3, numpy)."""
  totals = _Totals()
  timer = _Timer(predict, args, {} if compiled is None else compiled, warm_up, totals)
  three_way = ThreeWayAverage()
  official = av2_eval.Official(on_pair)
  bar, working, done = _shown(total)
  with bar, working:
    for batch in batches:
      valid = np.asarray(batch["pair_valid"], np.float64)
      pred = timer(jnp.asarray(batch["pc1"]), jnp.asarray(batch["pc2"]), valid.sum())
      if isinstance(pred, tuple):
        pred, info = pred[0], jax.device_get(pred[1])
        if info is not None:
          totals["optimised"] += valid.sum()
          totals["non_finite"] += np.sum(valid * ~np.asarray(info["finite"]))
          totals["early_stopped"] += np.sum(valid * np.asarray(info["stopped"]))
          totals["steps"] += np.sum(valid * np.asarray(info["steps"]))
      per_pair = jax.device_get(_metrics_fn(pred, jnp.asarray(batch["flow"]),
                                           jnp.asarray(batch["mask"])))
      for k in METRICS:
        totals[k] += float(np.sum(np.asarray(per_pair[k], np.float64) * valid))
      totals["pairs"] += valid.sum()
      three_way.add(pred, batch)
      official.add(pred, batch)
      for callback in on_batch:
        callback(batch, np.asarray(pred))
      bar.update(int(valid.sum()))
      done[0] += int(valid.sum())
  rerun = timer.finish()
  totals = totals.reduced()
  three_way.reduce(distributed.sum_over_processes)
  official.reduce(distributed.sum_over_processes)
  pairs = int(totals["pairs"])
  if pairs == 0:
    raise ConfigError("the evaluation dataset holds no pairs")
  results = {k: totals[k] / pairs for k in METRICS}
  results.update(pairs=pairs, first_pair_s=totals["first_seconds"] / totals["first_pairs"],
                 ms_per_pair=1000.0 * totals["seconds"] / totals["timed_pairs"],
                 steady="rerun" if rerun else "others",  # ms_per_pair: one batch run again
                 **three_way.results(), **official.results())
  if totals["optimised"]:
    optimised = totals["optimised"]
    results["convergence"] = {"pairs": int(optimised), "non_finite": int(totals["non_finite"]),
                              "early_stopped": int(totals["early_stopped"]),
                              "mean_steps": totals["steps"] / optimised}
  return results


def evaluate(model, params, dataset, *, num_points: int | None, batch_size: int, num_iters: int = 32,
             refine: bool = False, seed: int = 0, method: str = "network", method_settings=None,
             on_batch=(), on_pair=None) -> dict:
  """Metrics of `method`'s flow (jaxflow.methods.registry: the network alone by default) on every pair of
  `dataset`, with pairs, first_pair_s and ms_per_pair; `on_batch`: callables (batch, flow) of every
  batch (the points evaluated: sampled unless num_points None); `on_pair`: see `_run`."""
  chosen = registry.get(method)
  predict = registry.model_predict_fn(model, num_iters, refine, method, method_settings,
                                      with_info=not chosen.jitted)
  # The clouds rotated into the method's frame and the flow back (the reader says its up axis).
  up = dataset.up
  predict = frames.in_frame(predict, up, chosen.up, jitted=chosen.jitted)
  batches, total = _process_batches(dataset, batch_size, num_points, seed)
  batches = ({**batch, "up": up} for batch in batches)  # the clouds' frame, for the pictures
  results = _run(predict, (distributed.local_copy(params),), batches, total=total,
                 on_batch=on_batch, on_pair=on_pair, warm_up=chosen.compiles)
  results["output"] = "refined" if refine else "coarse"
  results.update(registry.describe(method, method_settings or registry.settings(method)))
  return results


class FirstPairs:
  """An evaluation's on_batch callback that keeps its first `count` real pairs with their flow
  (name, pc1, pc2, flow, gt, mask): the pictures of a training run's events
  (training.events.EventWriter.pictures)."""

  def __init__(self, count: int):
    self.count, self.pairs = count, []

  def __call__(self, batch, pred_BxNx3):
    for i, name in enumerate(batch["names"]):
      if len(self.pairs) < self.count and batch["pair_valid"][i]:
        self.pairs.append((str(name), *(np.asarray(batch[k][i]) for k in ("pc1", "pc2")),
                           np.asarray(pred_BxNx3[i]), np.asarray(batch["flow"][i]),
                           np.asarray(batch["mask"][i])))


class Evaluator:
  """`evaluate` of the network for repeated calls on the same pairs with new parameters (the
  held-out evaluation during training): the model is compiled once, every call re-samples the same
  pairs (seeded, so the same batches; nothing is kept between calls: memory does not grow with the
  pairs), and a call with the very same parameter arrays as the previous one (jax arrays are
  immutable) returns its results again (the end-of-run evaluation of a step just evaluated).
  `keep` > 0: `samples` holds the first `keep` pairs of the last call with their flow
  (FirstPairs: the pictures of the run's TensorBoard events)."""

  def __init__(self, model, dataset, *, num_points: int | None, batch_size: int,
               num_iters: int = 32, refine: bool = False, seed: int = 0, keep: int = 0):
    self.sampling = dict(dataset=dataset, batch_size=batch_size, num_points=num_points, seed=seed)
    eval_batches(**self.sampling)  # checks the arguments now (a generator would check them later)
    self.predict = registry.model_predict_fn(model, num_iters, refine)
    self.output = "refined" if refine else "coarse"
    self.compiled = {}
    self._last = ([], None)  # (parameter leaves, results) of the previous call
    self.keep, self.samples = keep, []

  def __call__(self, params) -> dict:
    leaves = jax.tree.leaves(params)
    last_leaves, last_results = self._last
    if len(leaves) == len(last_leaves) and all(a is b for a, b in zip(leaves, last_leaves)):
      return dict(last_results)
    batches, total = _process_batches(**self.sampling)
    first = FirstPairs(self.keep)
    results = _run(self.predict, (distributed.local_copy(params),), batches,
                   compiled=self.compiled, total=total, on_batch=[first] if self.keep else ())
    self.samples = first.pairs
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


def evaluate_checkpoint(checkpoint, config: ml_collections.ConfigDict, dataset: str | None = None,
                        split: str | None = None, model_fields=(), method: str = "network",
                        method_settings=None, on_batch=(), submission_dir=None,
                        on_start=None) -> dict:
  """Evaluates a checkpoint (workdir, checkpoints folder or step folder; None: the shipped one).

  The model comes from the checkpoint (checkpointing.load_for_inference); `config.eval` sets points
  (0: whole clouds), iterations, batch, seed and, unless given, the dataset and split. `method`
  (jaxflow.methods.registry; `method_settings` default registry.settings(method)): nsfp needs no
  checkpoint. The results also name the dataset, split, checkpoint and step. `submission_dir`: the
  AV2 challenge's files of every pair (jaxflow.evaluation.submission), summarised under
  "submission". `on_start()`: called once the model and the dataset are open, before the first pair
  (evaluate.py's notes: none before a checkpoint's one-line error).
  """
  check_no_test_time(config.eval)
  chosen = method_settings if method_settings is not None else registry.settings(method)
  dataset = dataset or config.eval.dataset
  split = split or config.eval.split
  if not dataset:
    raise ConfigError("no dataset to evaluate: give --dataset FORMAT:ROOT")
  model, params, step, refine = None, None, None, False
  if registry.get(method).needs_network:
    model, params, _, step, refine = checkpointing.load_for_inference(checkpoint, config,
                                                                      model_fields)
    checkpoint = checkpoint or checkpointing.SHIPPED_CHECKPOINT
  ds = open_dataset(dataset, split=split)
  writer = submission_dir and submission.SubmissionWriter(submission_dir, config.eval.num_points, ds)
  if on_start is not None:
    on_start()
  results = evaluate(model, params, ds, num_points=config.eval.num_points or None,
                     batch_size=config.eval.batch_size, num_iters=config.eval.num_iters,
                     refine=refine, seed=config.eval.seed, method=method,
                     method_settings=chosen, on_batch=on_batch, on_pair=writer and writer.add)
  results.update(dataset=dataset, split=split, checkpoint=checkpoint and str(checkpoint), step=step,
                 num_points=config.eval.num_points, num_iters=config.eval.num_iters)
  if "av2" in results:  # on the challenge's points, or the reader's (a note in the table)
    results["av2"]["challenge_points"] = av2_eval.challenge_points(ds)
  if writer:
    results["submission"] = {"summary": writer.summary(), "note": writer.note}
  return results
