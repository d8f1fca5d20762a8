"""Rigid motions of point sets: the least-squares fit (Kabsch) and a robust fit of the static part.

    motion = fit_static_motion(pc1_Nx3, flow_Nx3)   # the ego-motion hidden in a scene's flow
    rigid_flow_Mx3 = motion.flow(points_Mx3)        # the flow a static point would have
"""

import dataclasses

import numpy as np

from jaxflow.rigid_clusters import kabsch_rotation

STATIC_THRESHOLD = 0.1  # metres: a point within this of the rigid motion counts as static


@dataclasses.dataclass(frozen=True)
class Motion:
  """x -> rotation @ x + translation, with the points it was fitted to (`inliers`, bool N)."""
  rotation: np.ndarray  # 3 x 3, det +1
  translation: np.ndarray  # 3
  inliers: np.ndarray | None = None

  def apply(self, points_Nx3) -> np.ndarray:
    """The moved points (float64 N x 3)."""
    return np.asarray(points_Nx3, np.float64) @ self.rotation.T + self.translation

  def flow(self, points_Nx3) -> np.ndarray:
    """The flow of points moving with this motion (float32 N x 3)."""
    return (self.apply(points_Nx3) - np.asarray(points_Nx3, np.float64)).astype(np.float32)

  @property
  def angle_deg(self) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1) / 2, -1.0, 1.0))))


def kabsch(src_Nx3, dst_Nx3, weights_N=None) -> Motion:
  """The rotation and translation minimising sum w |R src + t - dst|^2 (Kabsch / Umeyama without
  scale): SVD of the weighted cross-covariance, the sign of the last axis fixed so det R = +1."""
  src, dst = np.asarray(src_Nx3, np.float64), np.asarray(dst_Nx3, np.float64)
  if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
    raise ValueError(f"kabsch: need two N x 3 arrays with N >= 3, got {src.shape} and {dst.shape}")
  w = np.ones(len(src)) if weights_N is None else np.asarray(weights_N, np.float64)
  w = w / w.sum()
  mu_src, mu_dst = w @ src, w @ dst
  cov = (src - mu_src).T @ ((dst - mu_dst) * w[:, None])
  rotation = kabsch_rotation(cov[None])[0]  # the one Kabsch, NumPy float64 here
  return Motion(rotation, mu_dst - rotation @ mu_src)


def fit_static_motion(points_Nx3, flow_Nx3, threshold: float = STATIC_THRESHOLD,
                      rounds: int = 4) -> Motion:
  """The rigid motion of the static part of a scene from its per-point flow.

  Moving objects are outliers: start from the fit to every point, then `rounds` times refit to the
  half of the points that the current motion explains best (trimmed least squares: the static
  world is usually most of a driving scene); the result is the fit to the points within
  `threshold` of that motion (its `inliers`), or to the best half when fewer than 10% are.
  """
  src = np.asarray(points_Nx3, np.float64)
  dst = src + np.asarray(flow_Nx3, np.float64)
  motion = kabsch(src, dst)
  half = np.ones(len(src), bool)
  for _ in range(rounds):
    residual = np.linalg.norm(motion.apply(src) - dst, axis=1)
    half = residual <= np.median(residual)
    if half.sum() < 3:
      break
    motion = kabsch(src[half], dst[half])
  residual = np.linalg.norm(motion.apply(src) - dst, axis=1)
  inliers = residual < threshold
  if inliers.sum() < max(3, 0.1 * len(src)):
    inliers = half
  final = kabsch(src[inliers], dst[inliers])
  return Motion(final.rotation, final.translation, inliers)
