r"""Evaluates a method on a dataset (jaxflow-evaluate, evaluate.py): the paper's table (EPE, AccS,
AccR, outliers, angle), pairs and ms a pair.

    python -m jaxflow.evaluate --checkpoint runs/default --dataset synthetic_lidar:64 --split test
    python -m jaxflow.evaluate --config configs/kitti_eval.py --checkpoint runs/ft3d_stage2 \
        --dataset kitti:data/KITTI_processed_occ_final --json kitti.json
    python -m jaxflow.evaluate --dataset synthetic_lidar:8 --method optimise --steps 100

The model comes from the checkpoint (workdir, checkpoints folder or step folder; default: the
shipped jaxflow/checkpoints/jaxflow_synthetic/). --checkpoint RUN without --config evaluates as the
run did its held-out figure: its stored config.eval (dataset, split, points, iterations, batch,
seed; jaxflow.evaluation.run_config), so the first example above gives the EPE train.py printed and
wrote to RUN/eval.json; a note says which settings came from the run and which from the command
line, and another when the points or iterations are more than 2x the training's. Otherwise the
config (default configs/default.py:eval: 8192 points, 32 iterations, one pair per batch) and
--config.eval.FIELD=... set the evaluation (an explicit --config FILE: all of it); the flags
shared with predict say the same in both tools (--iters, --max_points, --full, --corr_chunk, --seed:
config.eval.num_iters / num_points / seed, config.model.corr_chunk). --dataset and --split default
to config.eval.dataset and config.eval.split. --method (jaxflow.methods.registry) is `network` (the
paper's protocol) by default; optimise and nsfp are the per-pair optimisation methods
(docs/methods.md; predict's default is optimise). A dataset with ego-motion flow and labels
(opensf:DIR) also gets the official Argoverse 2 numbers (jaxflow.evaluation.av2_eval;
docs/training.md) in the tables and the JSON, and --submission DIR writes the challenge's files
(jaxflow.evaluation.submission). --save_flows DIR writes the flow of every pair (one .npy per pair,
named by the pair), --render_dir DIR the Fig. 2 view of every pair (predict's --render FILE: one
pair). Many processes: --coordinator, --num_processes, --process_id (jaxflow.runtime.distributed).
"""

import functools
import sys

from jaxflow import cli, data
from jaxflow.data import registry as data_registry
from jaxflow.runtime import distributed
from jaxflow.evaluation import evaluator, export, movers, reporting, run_config
from jaxflow.methods import registry


def _dataset_help() -> str:
  """--dataset's help: every registered format with its spec (jaxflow.data.registry.usage)."""
  data.formats()  # every reader registers its formats
  return ("FORMAT:SPEC (default: config.eval.dataset), e.g. kitti:data/KITTI_processed_occ_final. "
          "The formats: " + data_registry.usage() + ".")


def _define_flags():
  from absl import flags  # pylint: disable=import-outside-toplevel
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  cli.define_process_flags()
  config_flags.DEFINE_config_file(
    "config", cli.EVAL_CONFIG, "Evaluation settings (config.eval).", lock_config=True)
  flags.DEFINE_string("checkpoint", None, "Workdir, checkpoints folder or step folder (default: the "
                      "shipped jaxflow/checkpoints/jaxflow_synthetic/).")
  flags.DEFINE_string("dataset", None, _dataset_help())
  flags.DEFINE_string("split", None, "Dataset split (default: config.eval.split).")
  flags.DEFINE_string("json", None, "Write the results here as JSON.")
  flags.DEFINE_string("render_dir", None, "Render every pair into this folder as NAME.png "
                      "(jaxflow.viz.figures).")
  flags.DEFINE_string("submission", None, "Write the AV2 challenge's files into this folder "
                      "(jaxflow.evaluation.submission: <log_id>/<timestamp_ns>.feather, annotations in "
                      "DIR_annotations; opensf datasets, --max_points 0).")
  cli.define_run_flags("network")


def _say(notes):
  """The notes on stderr (process 0 of many)."""
  for note in notes if distributed.is_primary() else ():
    print(f"note: {note}", file=sys.stderr)


def _check_outputs(FLAGS):
  """Every output path checked before any work: one line (exit 2) when one cannot be written; a
  missing folder is made, with a note (docs/users.md)."""
  notes = export.check_outputs([
    (f"--{flag}", FLAGS[flag].value, suffixes, folder)
    for flag, suffixes, folder in (("json", (".json",), False), ("save_flows", (), True),
                                   ("render_dir", (), True), ("submission", (), True))])
  for note in notes:
    print(f"note: {note}", file=sys.stderr)


def _run_settings(FLAGS, config, method: str):
  """(config with a run's own evaluation settings (--checkpoint RUN without --config: its stored
  config.eval, jaxflow.evaluation.run_config) under the command line's, the notes: which came from
  where, and whether points or iterations are more than 2x from the training's)."""
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  if not FLAGS.checkpoint or not registry.get(method).needs_network:
    return config, []
  run = run_config.saved_config(FLAGS.checkpoint)
  notes = []
  if not FLAGS["config"].present:
    given = {k.split(".", 1)[1] for k in config_flags.get_override_values(FLAGS["config"])
             if k.startswith("eval.")}
    given |= {field for field, flag in (("dataset", FLAGS.dataset), ("split", FLAGS.split),
                                        ("num_iters", FLAGS.iters), ("seed", FLAGS.seed),
                                        ("num_points", FLAGS.max_points)) if flag is not None}
    given |= {"num_points"} if FLAGS.full else set()
    with config.unlocked():  # the flags' dataset and split, as the line below names them
      config.eval.dataset = FLAGS.dataset or config.eval.dataset
      config.eval.split = FLAGS.split or config.eval.split
    config, notes = run_config.apply(FLAGS.checkpoint, config, given, run)
  gap = run_config.training_gap(FLAGS.checkpoint, config, iterations=method == "network", run=run)
  return config, notes + ([gap] if gap else [])


def main(argv):
  from absl import flags  # pylint: disable=import-outside-toplevel

  FLAGS = flags.FLAGS
  if len(argv) > 1:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  _check_outputs(FLAGS)
  distributed.initialize_from_flags()
  config, model_fields = cli.run_settings(FLAGS.config)
  ((method, chosen),) = cli.run_methods()  # jaxflow.methods.registry's, as predict's
  config, notes = _run_settings(FLAGS, config, method)
  on_batch = []
  if FLAGS.save_flows:
    on_batch.append(export.FlowSaver(FLAGS.save_flows).add)
  if FLAGS.render_dir:
    on_batch.append(functools.partial(reporting.render_batch, FLAGS.render_dir))
  named = movers.for_spec(FLAGS.dataset or config.eval.dataset, FLAGS.split or config.eval.split,
                          config.eval.num_points)  # a log with instance ids: its movers by name
  on_batch += [named.add] if named else []
  results = evaluator.evaluate_checkpoint(FLAGS.checkpoint, config, FLAGS.dataset, FLAGS.split,
                                           model_fields, method, chosen, on_batch,
                                           submission_dir=FLAGS.submission,
                                           on_start=functools.partial(_say, notes))
  if named:
    results["movers"] = named.results()
  if distributed.is_primary():
    reporting.report(results, FLAGS.json)
    if named:
      print(named.table())


def run():
  """The console script `jaxflow-evaluate`."""
  cli.run(main, _define_flags, {"config": cli.EVAL_CONFIG},
          {"render": "render_dir"})


if __name__ == "__main__":
  run()
