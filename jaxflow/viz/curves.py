"""The learning curve of a run: WORKDIR/metrics.jsonl -> WORKDIR/learning_curve.png."""

import json
import os
from pathlib import Path


def plot_learning_curve(workdir) -> Path | None:
  """Loss and gradient norm against step (log scale); the held-out EPE logged during training
  (WORKDIR/eval_metrics.jsonl) as points joined by a line, and the end-of-run evaluation EPEs as
  horizontal lines when WORKDIR/eval.json exists. Returns the PNG's path, or None before anything
  was logged."""
  workdir = Path(workdir)
  metrics = workdir / "metrics.jsonl"
  if not metrics.exists():
    return None
  records = [json.loads(l) for l in metrics.read_text().splitlines() if l.strip()]
  if not records:
    return None
  from matplotlib.figure import Figure  # no pyplot: the session's backend stays (a notebook's)

  fig = Figure(figsize=(10, 3.6))
  ax_loss, ax_grad = fig.subplots(1, 2)
  for stage in sorted({r["stage"] for r in records}):
    rs = [r for r in records if r["stage"] == stage and r["loss"] is not None]
    ax_loss.plot([r["step"] for r in rs], [r["loss"] for r in rs], label=f"train loss (stage {stage})")
    rs = [r for r in rs if r["grad_norm"] is not None]
    ax_grad.plot([r["step"] for r in rs], [r["grad_norm"] for r in rs], label=f"stage {stage}")
  heldout = workdir / "eval_metrics.jsonl"
  if heldout.exists():
    rs = [json.loads(l) for l in heldout.read_text().splitlines() if l.strip()]
    if rs:
      ax_loss.plot([r["step"] for r in rs], [r["epe"] for r in rs], "o-", c="k", ms=3, lw=1,
                   label="held-out EPE (m)")
  eval_json = workdir / "eval.json"
  if eval_json.exists():
    results = json.loads(eval_json.read_text())
    for name, style in (("model", "-."), ("zero_flow", ":")):
      if name in results:
        ax_loss.axhline(results[name]["epe"], ls=style, c="k", lw=1, label=f"eval EPE, {name}")
  for ax, title in ((ax_loss, "loss"), (ax_grad, "gradient norm")):
    ax.set_xlabel("step")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
  fig.tight_layout()
  path = workdir / "learning_curve.png"
  tmp = workdir / "learning_curve.tmp.png"
  fig.savefig(tmp, dpi=100)
  os.replace(tmp, path)
  return path
