"""Shared command-line wrapper: a user's mistake is one line on stderr and exit code 2.

    from jaxflow import cli
    if __name__ == "__main__":
      cli.run(main)            # absl: parses flags, then main(argv)

    cli.guard(main, args)      # any other parser: calls main(args) with the same error handling

`jaxflow.errors.JaxflowError` (bad file, argument, checkpoint, non-finite training) and absl flag
errors print `error: <message>` and exit with 2, without a traceback; anything else is a bug and
keeps its traceback.
"""

import sys
from typing import Any, Callable

from absl import app, flags, logging

from jaxflow.errors import JaxflowError

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
  one-line error. The failure itself has been raised; these reports add nothing.
  """
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


def _parse_flags(argv):
  try:
    argv = flags.FLAGS(argv)
  except flags.Error as e:
    text = str(e)
    if "Traceback (most recent call last)" in text:  # ml_collections: get_config() raised
      lines = [l.strip() for l in text.splitlines() if l.strip()]
      text = lines[0].split("Traceback")[0] + " " + lines[-1]
    fail(text)
  except (AttributeError, KeyError) as e:  # ml_collections: --config.FIELD names no field
    field = str(e).strip("'\" ")
    given = [a for a in argv[1:] if a.startswith("--") and field in a.split("=")[0].split(".")]
    fail(f"unknown config field {field!r}" + (f" in {given[0]}" if given else ""))
  for name in flags.FLAGS:
    value = flags.FLAGS[name].value
    if type(value).__name__ == "_ErrorConfig":  # ml_collections defers a config file's failure
      try:
        value.keys()
      except Exception as e:  # pylint: disable=broad-except
        lines = [l.strip() for l in str(e).splitlines() if l.strip()]
        fail(f"--{name}: cannot load the config file: {lines[-1] if lines else e}")
  if not flags.FLAGS["verbosity"].present:  # orbax and jax log every step of a save at INFO
    logging.set_verbosity(logging.WARNING)
  return argv


def run(main: Callable[[list], Any]):
  """absl's `app.run(main)` with `guard`; flag errors also become one line and exit code 2."""
  app.run(lambda argv: guard(main, argv), flags_parser=_parse_flags)
