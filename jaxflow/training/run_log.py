"""What the host keeps of a training run: metrics.jsonl, the metrics still on the device, signals."""

import json
import math
import signal
import threading
import time
from pathlib import Path

import jax
import numpy as np

from jaxflow.errors import NonFiniteError


class Interrupted(Exception):
  """Training stopped on SIGTERM/SIGINT after saving a checkpoint at `step`."""

  def __init__(self, signum: int, step: int, path):
    self.signum, self.step = signum, step
    name = signal.Signals(signum).name
    super().__init__(
      f"stopped by {name} at step {step}; checkpoint saved in {path}; "
      "rerun the same command to resume"
    )


class MetricsLog:
  """Appends one JSON object per logged step to WORKDIR/metrics.jsonl (`enabled` False: on the
  processes other than 0 of a multi-process run, which write nothing); `events`
  (jaxflow.training.events.EventWriter): the record's numbers also as TensorBoard scalars PREFIX/NAME."""

  def __init__(self, path: Path, resume_step: int, enabled: bool = True, events=None,
               prefix: str = "train"):
    self.path, self.enabled, self.events, self.prefix = path, enabled, events, prefix
    if enabled and path.exists():  # drop lines logged after the checkpoint resumed (replayed now)
      keep = [l for l in path.read_text().splitlines() if l and json.loads(l)["step"] <= resume_step]
      path.write_text("".join(l + "\n" for l in keep))

  def write(self, record: dict):
    if self.enabled:
      with self.path.open("a") as f:
        f.write(json.dumps(record) + "\n")
      if self.events is not None:
        self.events.scalars(record["step"], record, self.prefix)


def finite(x) -> bool:
  return x is not None and math.isfinite(x)


class PendingMetrics:
  """The train step's metrics since the last fetch, still on the device: `flush(step)` reads them
  in one host sync, logs their means to `log`, and stops on a non-finite loss or gradient
  (`last_good()`: the path of the last checkpoint, for the message)."""

  def __init__(self, log: MetricsLog, schedule, pairs_per_step: int, stage: int, bar, last_good):
    self.log, self.schedule, self.pairs_per_step, self.stage = log, schedule, pairs_per_step, stage
    self.bar, self.last_good = bar, last_good
    self.pending = []  # (step, metrics on device)
    self.window_start = time.perf_counter()

  def append(self, step: int, metrics: dict):
    self.pending.append((step, metrics))
    if len(self.pending) > 2:
      # Waits for the step before last (no transfer; the device keeps the next one queued): keeps
      # the progress bar and a stop signal within two steps of the device.
      jax.block_until_ready(self.pending[-3][1]["loss"])

  def pause(self, seconds: float):
    """Leaves `seconds` (a held-out evaluation) out of pairs_per_s."""
    self.window_start += seconds

  def flush(self, step: int):
    if not self.pending:
      return
    fetched = jax.device_get([m for _, m in self.pending])
    steps = [s for s, _ in self.pending]
    elapsed = time.perf_counter() - self.window_start
    self.pending, self.window_start = [], time.perf_counter()
    record = {
      "step": step,
      "loss": float(np.mean([m["loss"] for m in fetched])),
      "grad_norm": float(np.mean([m["grad_norm"] for m in fetched])),
      "param_norm": float(fetched[-1]["param_norm"]),
      "pairs_per_s": len(steps) * self.pairs_per_step / max(elapsed, 1e-9),
      "lr": float(self.schedule(step - 1)),
      "stage": self.stage,
      "time": time.time(),
    }
    self.log.write({k: (v if not isinstance(v, float) or finite(v) else None)
                    for k, v in record.items()})
    self.bar.set_postfix(loss=f"{record['loss']:.4f}", pairs_s=f"{record['pairs_per_s']:.1f}")
    for s, m in zip(steps, fetched):
      if not (finite(float(m["loss"])) and finite(float(m["grad_norm"]))):
        raise NonFiniteError(
          f"non-finite loss or gradient at step {s} (loss={float(m['loss'])}, "
          f"grad_norm={float(m['grad_norm'])}); that state was not saved; last good checkpoint: "
          f"{self.last_good() or 'none'}"
        )


class StopSignals:
  """Turns SIGTERM/SIGINT into a flag the loop polls; a second signal interrupts at once."""

  def __init__(self):
    self.signum = None
    self._previous = {}

  def _handle(self, signum, frame):
    if self.signum is not None:
      raise KeyboardInterrupt
    self.signum = signum

  def __enter__(self):
    if threading.current_thread() is threading.main_thread():
      for s in (signal.SIGTERM, signal.SIGINT):
        self._previous[s] = signal.signal(s, self._handle)
    return self

  def __exit__(self, *exc):
    for s, h in self._previous.items():
      signal.signal(s, h)
