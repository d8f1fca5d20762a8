"""Scene-flow metrics (the paper's section 4.3), computed per pair over its valid points.

err = |pred - gt|, rel = err / (|gt| + 1e-4) epe        mean err (m) acc_strict % of points with err
< 0.05 or rel < 0.05 acc_relax  % with err < 0.1 or rel < 0.1 outliers   % with err > 0.3 or rel >
0.1 angle      mean arccos((1 + pred.gt) / (sqrt(1 + |pred|^2) sqrt(1 + |gt|^2))) (rad) A pair with
no valid point gets NaN: it has no defined error.
"""

import jax.numpy as jnp
import numpy as np

from jaxflow.evaluation import tables

METRICS = ("epe", "acc_strict", "acc_relax", "outliers", "angle")


def per_pair_metrics(pred_BxNx3, gt_BxNx3, mask_BxN=None) -> dict:
  """Each metric as a B-vector."""
  err = jnp.linalg.norm(pred_BxNx3 - gt_BxNx3, axis=-1)
  gt_norm = jnp.linalg.norm(gt_BxNx3, axis=-1)
  rel = err / (gt_norm + 1e-4)
  cos = (1.0 + jnp.sum(pred_BxNx3 * gt_BxNx3, axis=-1)) / (
    jnp.sqrt(1.0 + jnp.sum(pred_BxNx3**2, axis=-1)) * jnp.sqrt(1.0 + gt_norm**2)
  )
  per_point = {
    "epe": err,
    "acc_strict": 100.0 * ((err < 0.05) | (rel < 0.05)),
    "acc_relax": 100.0 * ((err < 0.1) | (rel < 0.1)),
    "outliers": 100.0 * ((err > 0.3) | (rel > 0.1)),
    "angle": jnp.arccos(jnp.clip(cos, -1.0, 1.0)),
  }
  if mask_BxN is None:
    mask_BxN = jnp.ones(err.shape, err.dtype)
  mask_BxN = mask_BxN.astype(err.dtype)
  count_B = jnp.sum(mask_BxN, axis=-1)
  safe = jnp.where(count_B > 0, count_B, 1.0)
  return {
    k: jnp.where(count_B > 0, jnp.sum(v * mask_BxN, axis=-1) / safe, jnp.nan)
    for k, v in per_point.items()
  }


def scene_flow_metrics(pred_BxNx3, gt_BxNx3, mask_BxN=None) -> dict:
  """Each metric averaged over the pairs of the batch."""
  return {k: jnp.mean(v) for k, v in per_pair_metrics(pred_BxNx3, gt_BxNx3, mask_BxN).items()}


# OpenSceneFlow's LOCAL reading of the three-way EPE (its v1 table): a 35 m disc (the reader's
# max_range cut) and per-pair means averaged over pairs. The official AV2 numbers (a 70 x 70 m
# Close box, every point weighted equally over the split) are jaxflow.evaluation.av2_eval.
THREE_WAY = ("fd", "fs", "bs", "mean")
DYNAMIC_THRESHOLD = 0.05  # metres: a point is dynamic when |gt - rigid flow| >= this


def three_way_epe(pred_Nx3, gt_Nx3, rigid_Nx3, foreground_N, mask_N=None) -> dict:
  """EPE of one pair's valid points split into foreground-dynamic (fd), foreground-static (fs) and
  background-static (bs), and "mean", the mean of those classes that have a point (NaN when none).

  dynamic: |gt - rigid| >= 0.05 m (rigid = the ego-motion flow); foreground: an object's label.
  A class with no valid point is NaN, left out of the mean (never counted as 0). Background points
  that move (labelling noise) belong to no class, as in the challenge.
  """
  pred, gt, rigid = (np.asarray(a, np.float64) for a in (pred_Nx3, gt_Nx3, rigid_Nx3))
  foreground = np.asarray(foreground_N, bool)
  valid = np.ones(len(gt), bool) if mask_N is None else np.asarray(mask_N) > 0
  err = np.linalg.norm(pred - gt, axis=-1)
  dynamic = np.linalg.norm(gt - rigid, axis=-1) >= DYNAMIC_THRESHOLD
  classes = {"fd": foreground & dynamic, "fs": foreground & ~dynamic, "bs": ~foreground & ~dynamic}
  out = {k: float(err[m & valid].mean()) if (m & valid).any() else float("nan")
         for k, m in classes.items()}
  present = [v for v in out.values() if not np.isnan(v)]
  out["mean"] = float(np.mean(present)) if present else float("nan")
  return out


class ThreeWayAverage:
  """Averages `three_way_epe` over the pairs of evaluation batches: call `add(pred, batch)` once per
  batch (a batch without 'rigid_flow' / 'foreground' is ignored) and `results()` at the end.

  Each class is averaged over the pairs in which it has points; "mean" over the pairs' means.
  `results()` is {"three_way_local": {fd, fs, bs, mean, pairs}}, or {} when no batch had labels.
  """

  def __init__(self):
    self.sums = dict.fromkeys(THREE_WAY, 0.0)
    self.counts = dict.fromkeys(THREE_WAY, 0)
    self.pairs = 0

  def add(self, pred_BxNx3, batch: dict):
    if "rigid_flow" not in batch or "foreground" not in batch:
      return
    pred = np.asarray(pred_BxNx3)
    for i, valid in enumerate(np.asarray(batch["pair_valid"])):
      if not valid:
        continue
      pair = three_way_epe(pred[i], batch["flow"][i], batch["rigid_flow"][i],
                           batch["foreground"][i], batch["mask"][i])
      for k, v in pair.items():
        if not np.isnan(v):
          self.sums[k] += v
          self.counts[k] += 1
      self.pairs += 1

  def reduce(self, sum_fn):
    """Replaces the sums and counts by `sum_fn` of them (the sum over processes)."""
    values = sum_fn([*self.sums.values(), *self.counts.values(), self.pairs])
    n = len(THREE_WAY)
    self.sums = dict(zip(THREE_WAY, map(float, values[:n])))
    self.counts = dict(zip(THREE_WAY, map(int, values[n:2 * n])))
    self.pairs = int(values[-1])

  def results(self) -> dict:
    if not self.pairs:
      return {}
    mean = {k: self.sums[k] / self.counts[k] if self.counts[k] else float("nan") for k in THREE_WAY}
    return {"three_way_local": {**mean, "pairs": self.pairs}}


def format_three_way(rows) -> str:
  """rows: (name, results with "three_way_local") -> a table of the local three-way EPE (m)."""
  header = ("Dataset (OpenSceneFlow local: per-pair means)", "EPE FD", "EPE FS", "EPE BS",
            "three-way", "pairs")
  return tables.markdown_table(header, [
    (name, *(f"{r['three_way_local'][k]:.4f}" for k in THREE_WAY),
     str(r["three_way_local"]["pairs"])) for name, r in rows])
