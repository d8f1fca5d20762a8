"""The progress of a long optimisation on stderr (jaxflow.refine.optimiser.optimise_host_loop).

    shown = Progress("mlp optimisation", total_steps, progress=None)
    shown.update(steps_done, lambda: lowest_loss)   # after each block of steps
    shown.close()
    shown.done(steps_done)                          # the closing line, if it wrote lines

On a terminal, tqdm's bar. Off one (stderr into a log file, where a bar does not show) a run
expected to take longer than LOG_AFTER_S writes plain, flushed lines instead: its expected time, an
estimate from its pace over the first PACE_S seconds after its first block (which compiles), then
a line every 10% of the steps and one when it ends. Nothing here runs inside a compiled program: the
caller reports between the blocks it drives from Python.
"""

import sys
import time

from tqdm import tqdm

LOG_AFTER_S = 30.0
PACE_S = 2.0


def _duration(seconds: float) -> str:
  if seconds < 120:
    return f"{seconds:.0f} s"
  return f"{seconds / 60:.1f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def _say(line: str):
  print(line, file=sys.stderr, flush=True)


class Progress:
  """The bar or the lines of `total` steps named `what`; `progress`: True the bar, False nothing,
  None the bar on a terminal and the lines elsewhere (module docstring)."""

  def __init__(self, what: str, total: int, progress: bool | None = None):
    self.what, self.total = what, total
    self.bar = tqdm(total=total, desc=what, unit="step", file=sys.stderr, leave=False,
                    dynamic_ncols=True, mininterval=1.0,
                    disable=None if progress is None else not progress)
    terminal = getattr(sys.stderr, "isatty", lambda: False)()
    self.log = progress is None and not terminal  # lines, once the run looks long
    self.start, self.paced, self.lines, self.decile = time.perf_counter(), None, False, 0

  @property
  def active(self) -> bool:
    """Whether `update` shows anything (the caller may skip fetching its numbers)."""
    return not self.bar.disable or self.log

  def update(self, done: int, loss):
    """After a block: `done` steps so far, `loss()` the lowest loss."""
    if not self.bar.disable:
      self.bar.update(done - self.bar.n)
      self.bar.set_postfix(loss=f"{loss():.4g}", refresh=False)
    if self.log:
      self._log(done, loss)

  def _log(self, done: int, loss):
    now = time.perf_counter()
    if self.paced is None:  # the first block compiles: the pace is measured after it
      self.paced = (now, done)
      return
    (t0, d0), elapsed = self.paced, now - self.start
    if not self.lines:
      if now - t0 < PACE_S or done == d0:
        return
      pace = (now - t0) / (done - d0)
      self.log = elapsed + pace * (self.total - done) >= LOG_AFTER_S  # else a short run: no line
      if not self.log:
        return
      self.lines = True
      _say(f"{self.what}: up to {self.total} steps, expected to take about "
           f"{_duration(elapsed + pace * (self.total - done))} in all (an estimate: {pace:.3g} s "
           f"a step, the pace of steps {d0 + 1}-{done}; early stopping may end it sooner)")
    if 10 * done // self.total > self.decile:
      self.decile = 10 * done // self.total
      left = (now - t0) / (done - d0) * (self.total - done)
      _say(f"{self.what}: {done}/{self.total} steps ({100 * done // self.total}%) in "
           f"{_duration(elapsed)}, lowest loss {loss():.4g}"
           + (f", at most about {_duration(left)} left (an estimate)" if left else ""))

  def close(self):
    if not self.bar.disable:
      self.bar.refresh()  # the last state, drawn however soon it came
    self.bar.close()

  def done(self, done: int):
    """The closing line of a run that wrote lines (`lines`)."""
    if self.lines:
      _say(f"{self.what}: done, {done} steps in {_duration(time.perf_counter() - self.start)}"
           + (" (early stopping)" if done < self.total else ""))
