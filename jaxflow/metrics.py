"""Scene-flow metrics (the paper's section 4.3), computed per pair over its valid points.

err = |pred - gt|, rel = err / (|gt| + 1e-4)
epe        mean err (m)
acc_strict % of points with err < 0.05 or rel < 0.05
acc_relax  % with err < 0.1 or rel < 0.1
outliers   % with err > 0.3 or rel > 0.1
angle      mean arccos((1 + pred.gt) / (sqrt(1 + |pred|^2) sqrt(1 + |gt|^2))) (rad)
A pair with no valid point gets NaN: it has no defined error.
"""

import jax.numpy as jnp

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
