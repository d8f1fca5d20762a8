r"""Trains a jaxflow model and evaluates it (python -m jaxflow.train, jaxflow-train, train.py).

    python -m jaxflow.train --config configs/default.py --workdir runs/default [--config.FIELD=V]
    python -m jaxflow.train --config configs/default.py --print_config    # the fields, commented

The run writes its checkpoints, metrics.jsonl and TensorBoard event files (jaxflow.training.events:
`tensorboard --logdir WORKDIR`) into WORKDIR. Rerunning the same command resumes from
WORKDIR/checkpoints. SIGTERM/SIGINT save a checkpoint at
the current step and exit with 128 + the signal number. `configs/NAME.py` is the package's config
of that name when the working directory has none.
"""

import sys
from pathlib import Path

from jaxflow import cli
from jaxflow.runtime import host_memory


def _define_flags():
  from absl import flags  # pylint: disable=import-outside-toplevel
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  cli.define_process_flags()
  flags.DEFINE_string("workdir", None, "Folder for checkpoints, metrics and results.")
  config_flags.DEFINE_config_file("config", None, "Training config file (FILE.py[:ARG]; "
                                  "--print_config lists its fields).", lock_config=True)
  flags.mark_flags_as_required(["config"])  # --workdir too, but not with --print_config


def written(workdir) -> str:
  """What a run left in its workdir, one `  PATH  (what)` line each, for the end of train.py."""
  what = {"checkpoints": "checkpoints (rerun the command to resume)", "config.json": "the config",
          "metrics.jsonl": "training metrics",
          "eval_metrics.jsonl": "held-out metrics during training",
          "eval.json": "held-out evaluation (model and zero flow)",
          "learning_curve.png": "learning curve"}
  workdir = Path(workdir).absolute()
  lines = [f"  {workdir / name}  ({text})" for name, text in what.items()
           if (workdir / name).exists()]
  if any(workdir.glob("events.out.tfevents.*")):
    lines.append(f"  {workdir}/events.out.tfevents.*  (TensorBoard: tensorboard --logdir "
                 f"{workdir})")
  return "\n".join(lines)


def main(argv):
  from absl import flags  # pylint: disable=import-outside-toplevel
  # Here, not at the top: --print_config and --help answer without loading jax.
  from jaxflow.runtime import distributed  # pylint: disable=import-outside-toplevel
  from jaxflow.training import run_log, trainer

  if len(argv) > 1:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  distributed.initialize_from_flags()
  workdir = flags.FLAGS.workdir
  if not workdir:
    cli.fail("--workdir is required: the folder for the run's checkpoints, metrics and results")
  try:
    trainer.train_and_evaluate(flags.FLAGS.config, workdir)
  except run_log.Interrupted as e:
    print(e, file=sys.stderr)
    return 128 + e.signum
  print(f"outputs in {Path(workdir).absolute()}:\n{written(workdir)}", file=sys.stderr)
  return 0


def run():
  """The console script `jaxflow-train`."""
  # The training step's temporaries are reused, not faulted in afresh (jaxflow.runtime.host_memory).
  cli.run(main, _define_flags, {"config": None}, host_memory_default=host_memory.KEEP)


if __name__ == "__main__":
  run()
