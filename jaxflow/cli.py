"""Shared command-line wrapper: a user's mistake is one line on stderr and exit code 2.

    from jaxflow import cli
    cli.run(main)              # absl: checks the config flags, parses, then main(argv)
    cli.guard(main, args)      # any other parser: calls main(args) with the same error handling

`jaxflow.errors.JaxflowError` (bad file, argument, checkpoint, non-finite training), absl flag
errors, a config file that does not load and a `--config.FIELD` that names no field print
`error: <message>` and exit with 2, without a traceback; anything else is a bug and keeps its
traceback. `--print_config` prints the config (overrides applied) with its fields' comments.
"""

import sys
import warnings
from typing import Any, Callable

from absl import app, flags, logging
from ml_collections import config_flags

from jaxflow import configfile, determinism
from jaxflow.errors import ConfigError, JaxflowError

EXIT_USER_ERROR = 2


def fail(message: str):
  """Prints `error: message` as one line on stderr and exits with code 2."""
  print("error: " + " ".join(str(message).split()), file=sys.stderr)
  sys.exit(EXIT_USER_ERROR)


def _drop_closed_loop_reports():
  """Drops the "Event loop is closed" errors that orbax's abandoned reads report.

  When one array of a checkpoint cannot be read, orbax raises (a CheckpointError here) and closes
  its event loop while tensorstore's reads of the other arrays are still running; each of them then
  reports a RuntimeError into the closed loop as an unraisable exception, a traceback after the
  one-line error, and the coroutines it abandons warn at exit that they were never awaited. The
  failure itself has been raised; these reports add nothing.
  """
  warnings.filterwarnings("ignore", message=r"coroutine '.*' was never awaited",
                          category=RuntimeWarning)
  previous = sys.unraisablehook
  if getattr(previous, "drops_closed_loop_reports", False):
    return  # installed by an earlier call

  def hook(unraisable):
    e = unraisable.exc_value
    if not (isinstance(e, RuntimeError) and str(e) == "Event loop is closed"):
      previous(unraisable)

  hook.drops_closed_loop_reports = True
  sys.unraisablehook = hook


def guard(main: Callable[..., Any], *args, **kwargs):
  """main(*args, **kwargs), with a JaxflowError turned into one line and exit code 2."""
  _drop_closed_loop_reports()
  try:
    return main(*args, **kwargs)
  except JaxflowError as e:
    fail(str(e))


def _parse_flags(argv: list[str], config_names=()) -> list[str]:
  try:
    argv = flags.FLAGS(argv)
  except flags.Error as e:
    fail(str(e))
  if flags.FLAGS.deterministic:  # before anything starts jax's backend (jaxflow.determinism)
    try:
      determinism.enable()
    except ConfigError as e:
      fail(str(e))
  if not flags.FLAGS["verbosity"].present:  # orbax and jax log every step of a save at INFO
    logging.set_verbosity(logging.WARNING)
  if flags.FLAGS.print_config:
    for name in config_names:
      path = config_flags.get_config_filename(flags.FLAGS[name])
      print(configfile.describe(flags.FLAGS[name].value, path.split(":")[0], name))
    sys.exit(0)
  return argv


def run(main: Callable[[list], Any], define_flags: Callable[[], Any] | None = None,
        config_files: dict[str, str | None] | None = None):
  """absl's `app.run(main)` with `guard`; flag and config errors also become one line and exit 2.

  `config_files` maps each config-file flag that `define_flags` defines to its default file (or
  None): the file and every `--NAME.FIELD` of the command line are checked before absl sees them
  (ml_collections loads a default file, overrides applied, as soon as its flag is defined). --help
  lists the flags of main's module, also when it runs as a console script.
  """
  config_files = config_files or {}
  try:
    for name, default in config_files.items():
      sys.argv = configfile.check_argv(sys.argv, name, default)
  except ConfigError as e:
    fail(str(e))
  if define_flags is not None:
    define_flags()
  flags.DEFINE_bool("print_config", False, "Print the config (with the overrides given) field by "
                    "field, with each field's comment, and exit.")
  flags.DEFINE_bool("deterministic", False, "Run-to-run identical results on a GPU too (XLA's "
                    "deterministic GPU ops; slower). The CPU is deterministic already "
                    "(docs/methods.md, Determinism).")
  for module in (main.__module__, __name__):  # absl's --help shows sys.argv[0]'s flags
    for flag in flags.FLAGS.get_flags_for_module(module):
      flags.FLAGS.register_key_flag_for_module(sys.argv[0], flag)
  app.run(lambda argv: guard(main, argv),
          flags_parser=lambda argv: _parse_flags(argv, list(config_files)))
