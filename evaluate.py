r"""Evaluates a checkpoint on a dataset and prints the paper's table (EPE, AccS, AccR, outliers, angle).

    python evaluate.py --checkpoint runs/default --dataset synthetic_lidar:64 --split test
    python evaluate.py --config configs/kitti_eval.py --checkpoint runs/ft3d_stage2 \
        --dataset kitti:data/KITTI_processed_occ_final --json kitti.json

The model comes from the checkpoint (workdir, checkpoints folder or step folder; default: the shipped
jaxflow/checkpoints/jaxflow_synthetic/). The config (default configs/default.py:eval: 8192 points,
32 iterations, one pair per batch) and --config.eval.FIELD=... set the evaluation; --dataset and
--split default to config.eval.dataset and config.eval.split. --method nsfp|optimise evaluates the
per-pair optimisation methods instead of the network alone (docs/methods.md).
"""

from absl import flags
from ml_collections import config_flags

from jaxflow import cli, evaluation

_CONFIG = config_flags.DEFINE_config_file(
  "config", evaluation.EVAL_CONFIG, "Evaluation settings (config.eval).", lock_config=True
)
_CHECKPOINT = flags.DEFINE_string("checkpoint", None, "Workdir, checkpoints folder or step folder.")
_DATASET = flags.DEFINE_string(
  "dataset", None, "FORMAT:ROOT, e.g. kitti:data/KITTI_processed_occ_final (default: config.eval.dataset)."
)
_SPLIT = flags.DEFINE_string("split", None, "Dataset split (default: config.eval.split).")
_JSON = flags.DEFINE_string("json", None, "Write the results here as JSON.")
_RENDER = flags.DEFINE_string("render", None, "Render every pair into this folder (jaxflow.viz).")
_METHOD = flags.DEFINE_enum("method", "network", ["network", "nsfp", "optimise"],
                            "network: the paper's protocol; nsfp: the NSFP baseline (no checkpoint); "
                            "optimise: the network's flow refined per pair (docs/methods.md).")
_STEPS = flags.DEFINE_integer("steps", None, "Cap the optimisation steps of nsfp / optimise.")


def main(argv):
  if len(argv) > 1:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  model_fields = evaluation.requested_model_fields(flags.FLAGS["config"])
  evaluation.evaluate_checkpoint(_CHECKPOINT.value, _CONFIG.value, _DATASET.value, _SPLIT.value,
                                 model_fields, _JSON.value, _RENDER.value, _METHOD.value,
                                 _STEPS.value)


if __name__ == "__main__":
  cli.run(main)
