"""Quiets the reports orbax's abandoned reads leave after a checkpoint read fails (the failure
itself is raised and reported once, by jaxflow.cli)."""

import logging as pylogging
import sys
import warnings


def drop_closed_loop_reports():
  """Drops the "Event loop is closed" errors that orbax's abandoned reads report.

  When one array of a checkpoint cannot be read, orbax raises (a CheckpointError here) and closes
  its event loop while tensorstore's reads of the other arrays are still running; each of them then
  reports a RuntimeError into the closed loop as an unraisable exception, a traceback after the
  one-line error, the coroutines it abandons warn at exit that they were never awaited, and the
  reads that failed too log "Task exception was never retrieved" when garbage collected (at any
  time, often at exit). The failure itself has been raised; these reports add nothing.
  """
  warnings.filterwarnings("ignore", message=r"coroutine '.*' was never awaited",
                          category=RuntimeWarning)
  previous = sys.unraisablehook
  if getattr(previous, "drops_closed_loop_reports", False):
    return  # installed by an earlier call
  pylogging.getLogger("asyncio").addFilter(_keep_unless_abandoned_read)

  def hook(unraisable):
    e = unraisable.exc_value
    if not (isinstance(e, RuntimeError) and str(e) == "Event loop is closed"):
      previous(unraisable)

  hook.drops_closed_loop_reports = True
  sys.unraisablehook = hook


def _keep_unless_abandoned_read(record: pylogging.LogRecord) -> bool:
  text = record.getMessage()
  return not (text.startswith("Task exception was never retrieved")
              and "coro=<async_deserialize()" in text)
