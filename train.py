r"""Trains a jaxflow model and evaluates it.

    python train.py --config configs/default.py --workdir runs/default [--config.FIELD=VALUE ...]

Rerunning the same command resumes from WORKDIR/checkpoints. SIGTERM/SIGINT save a checkpoint at
the current step and exit with 128 + the signal number.
"""

import sys

from absl import flags
from ml_collections import config_flags

from jaxflow import cli, distributed, training

distributed.define_flags()
_WORKDIR = flags.DEFINE_string("workdir", None, "Folder for checkpoints, metrics and results.")
_CONFIG = config_flags.DEFINE_config_file("config", None, "Training config file.", lock_config=True)
flags.mark_flags_as_required(["config", "workdir"])


def main(argv):
  if len(argv) > 1:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  distributed.initialize_from_flags()
  try:
    training.train_and_evaluate(_CONFIG.value, _WORKDIR.value)
  except training.Interrupted as e:
    print(e, file=sys.stderr)
    return 128 + e.signum


if __name__ == "__main__":
  cli.run(main)
