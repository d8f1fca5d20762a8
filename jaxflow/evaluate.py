r"""Evaluates a checkpoint on a dataset: the paper's table (EPE, AccS, AccR, outliers, angle).

    python -m jaxflow.evaluate --checkpoint runs/default --dataset synthetic_lidar:64 --split test
    python -m jaxflow.evaluate --config configs/kitti_eval.py --checkpoint runs/ft3d_stage2 \
        --dataset kitti:data/KITTI_processed_occ_final --json kitti.json

(`jaxflow-evaluate` and evaluate.py are the same command.) The model comes from the checkpoint
(workdir, checkpoints folder or step folder; default: the shipped
jaxflow/checkpoints/jaxflow_synthetic/). The config (default configs/default.py:eval: 8192 points, 32
iterations, one pair per batch) and --config.eval.FIELD=... set the evaluation; --dataset and --split
default to config.eval.dataset and config.eval.split. A dataset with av2 labels (opensf:DIR) also
gets the official Argoverse 2 numbers (jaxflow.av2_eval; docs/training.md) in the tables and the
JSON, and --submission DIR writes the challenge's files (jaxflow.submission);
--save-flows DIR writes the flow of every pair (one .npy per pair, named by the pair).
--method nsfp|optimise evaluates the per-pair optimisation methods instead of the network alone
(docs/methods.md).
"""

from jaxflow import cli, distributed, evaluation


def _define_flags():
  from absl import flags  # pylint: disable=import-outside-toplevel
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  distributed.define_flags()
  config_flags.DEFINE_config_file(
    "config", evaluation.EVAL_CONFIG, "Evaluation settings (config.eval).", lock_config=True)
  flags.DEFINE_string("checkpoint", None, "Workdir, checkpoints folder or step folder.")
  flags.DEFINE_string("dataset", None, "FORMAT:ROOT, e.g. kitti:data/KITTI_processed_occ_final "
                      "(default: config.eval.dataset).")
  flags.DEFINE_string("split", None, "Dataset split (default: config.eval.split).")
  flags.DEFINE_string("json", None, "Write the results here as JSON.")
  flags.DEFINE_string("render", None, "Render every pair into this folder (jaxflow.viz).")
  flags.DEFINE_string("save-flows", None, "Write the flow of every pair into this folder, one "
                      "NAME.npy per pair (jaxflow.export; the evaluated points: with "
                      "--config.eval.num_points=0 every point of pc1).")
  flags.DEFINE_string("submission", None, "Write the AV2 challenge's files into this folder "
                      "(jaxflow.submission: <log_id>/<timestamp_ns>.feather, annotations in "
                      "DIR_annotations; opensf datasets, --config.eval.num_points=0).")
  flags.DEFINE_enum("method", "network", ["network", "nsfp", "optimise"],
                    "network: the paper's protocol; nsfp: the NSFP baseline (no checkpoint); "
                    "optimise: the network's flow refined per pair (docs/methods.md).")
  flags.DEFINE_integer("steps", None, "Cap the optimisation steps of nsfp / optimise.")


def main(argv):
  from absl import flags  # pylint: disable=import-outside-toplevel

  FLAGS = flags.FLAGS
  if len(argv) > 1:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  distributed.initialize_from_flags()
  model_fields = evaluation.requested_model_fields(FLAGS["config"])
  evaluation.evaluate_checkpoint(FLAGS.checkpoint, FLAGS.config, FLAGS.dataset, FLAGS.split,
                                 model_fields, FLAGS.json, FLAGS.render,
                                 FLAGS["save-flows"].value, FLAGS.method, FLAGS.steps,
                                 submission_dir=FLAGS.submission)


def run():
  """The console script `jaxflow-evaluate`."""
  cli.run(main, _define_flags, {"config": evaluation.EVAL_CONFIG})


if __name__ == "__main__":
  run()
