"""The progress of long work on stderr: an optimisation's steps (`Progress`,
jaxflow.refine.optimiser.optimise_host_loop) and work whose steps cannot be counted (`Working`:
predict's flow of a pair, whatever the method; evaluate.py's pairs).

    shown = Progress("mlp optimisation", total_steps, progress=None)
    shown.update(steps_done, lambda: lowest_loss)   # after each block of steps
    shown.close()
    shown.done(steps_done)                          # the closing line, if it wrote lines

    with Working("flow of a.ply (optimise)"):       # a bar, or a line every EVERY_S seconds
      stage("descent done")                         # the stage reached, said by the Working shown
      ...

On a terminal, tqdm's bar. Off one (stderr into a log file, where a bar does not show) a run
expected to take longer than LOG_AFTER_S writes plain, flushed lines instead: its expected time, an
estimate from its pace over the first PACE_S seconds after its first block (which compiles), then
a line every 10% of the steps and one when it ends. Nothing here runs inside a compiled program: the
caller reports between the blocks it drives from Python. `Working` covers the rest, compiled stages
included: a thread beside the work draws its bar (the stage, the time so far) on a terminal, and off
one writes a plain line (the stage, the time so far) whenever EVERY_S seconds passed without a line
of progress (a `Progress`'s lines count).
"""

import sys
import threading
import time

from tqdm import tqdm

LOG_AFTER_S = 30.0
PACE_S = 2.0
EVERY_S = 10.0  # off a terminal, the longest silence of long work
_last_line = [time.perf_counter()]  # when the last line of progress was written
_working = []  # the Working now shown (the outermost: an inner one shows nothing)


def _duration(seconds: float) -> str:
  if seconds < 120:
    return f"{seconds:.0f} s"
  return f"{seconds / 60:.1f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def _say(line: str):
  print(line, file=sys.stderr, flush=True)
  _last_line[0] = time.perf_counter()


def _terminal() -> bool:
  return getattr(sys.stderr, "isatty", lambda: False)()


def stage(name: str):
  """Names what the Working now shown is doing (nothing when none is)."""
  if _working:
    _working[0].now = name


class Working:
  """A context in which long work shows that it goes on (module docstring): `what` names it;
  `done()`, when given, says how far it is (e.g. "3/64 pairs"); `progress`: True the bar, False
  nothing, None the bar on a terminal and the lines elsewhere. Inside another Working it shows
  nothing (the outer one does)."""

  def __init__(self, what: str, done=None, progress: bool | None = None):
    self.what, self.done, self.now = what, done, None
    self.bar = progress is True or (progress is None and _terminal())
    self.log = progress is None and not self.bar
    self._stop, self._thread, self._shown = threading.Event(), None, None

  def _state(self) -> str:
    parts = [p for p in (self.now, self.done and self.done()) if p]
    return ", ".join(parts)

  def _beat(self):
    start = time.perf_counter()
    while not self._stop.wait(1.0 if self.bar else min(1.0, max(0.05, EVERY_S))):
      now = time.perf_counter()
      if self._shown is not None:
        self._shown.set_description_str(f"{self.what}: {self._state() or 'working'}",
                                        refresh=False)
        self._shown.refresh()
      elif now - max(start, _last_line[0]) >= EVERY_S:
        _say(f"{self.what}: {self._state() or 'working'}, {_duration(now - start)} so far")

  def __enter__(self):
    if _working or not (self.bar or self.log):
      return self
    _working.append(self)
    if self.bar:
      self._shown = tqdm(desc=self.what, bar_format="{desc} [{elapsed}]", file=sys.stderr,
                         leave=False)
    self._thread = threading.Thread(target=self._beat, name="jaxflow-progress", daemon=True)
    self._thread.start()
    return self

  def __exit__(self, *exc):
    if self._thread is not None:
      self._stop.set()
      self._thread.join()
      _working.remove(self)
      if self._shown is not None:
        self._shown.close()
    return False


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
