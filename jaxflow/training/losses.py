"""Training losses (paper eq. 7-9, PV-RAFT's normalisation).

`mask` marks the points whose ground truth counts (B x N, bool or 0/1); the L1 error is averaged
over those points and the three components, across the whole batch.
"""

import jax.numpy as jnp


def masked_l1(pred_BxNx3, gt_BxNx3, mask_BxN=None):
  """mean |pred - gt| over valid points and xyz components."""
  err_BxN = jnp.sum(jnp.abs(pred_BxNx3 - gt_BxNx3), axis=-1)
  if mask_BxN is None:
    return jnp.mean(err_BxN) / 3.0
  mask_BxN = mask_BxN.astype(err_BxN.dtype)
  return jnp.sum(err_BxN * mask_BxN) / (3.0 * jnp.maximum(jnp.sum(mask_BxN), 1.0))


def sequence_loss(flows_BxZxNx3, gt_BxNx3, mask_BxN=None, gamma: float = 0.8):
  """L1 = sum_z gamma^(Z-1-z) * masked_l1(flow_z): the last iteration weighs 1."""
  z = flows_BxZxNx3.shape[1]
  weights = gamma ** jnp.arange(z - 1, -1, -1, dtype=jnp.float32)
  per_iter = jnp.stack([masked_l1(flows_BxZxNx3[:, i], gt_BxNx3, mask_BxN) for i in range(z)])
  return jnp.sum(weights * per_iter)


def refinement_loss(refined_BxNx3, gt_BxNx3, mask_BxN=None):
  """L2 = masked_l1(refined flow)."""
  return masked_l1(refined_BxNx3, gt_BxNx3, mask_BxN)


def total_loss(flows_BxZxNx3, refined_BxNx3, gt_BxNx3, mask_BxN=None, gamma: float = 0.8,
               lambda1: float = 0.8, lambda2: float = 1.0):
  """L = lambda1 L1 + lambda2 L2 (eq. 9), for training both parts at once."""
  return (lambda1 * sequence_loss(flows_BxZxNx3, gt_BxNx3, mask_BxN, gamma)
          + lambda2 * refinement_loss(refined_BxNx3, gt_BxNx3, mask_BxN))
