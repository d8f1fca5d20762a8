"""Rigid motions of point sets: the least-squares fit (Kabsch), a robust fit of the static part and
the rotation of a rotation vector (NumPy or jax).

    motion = fit_static_motion(pc1_Nx3, flow_Nx3)   # the ego-motion hidden in a scene's flow
    rigid_flow_Mx3 = motion.flow(points_Mx3)        # the flow a static point would have
"""

import dataclasses
import functools

import numpy as np


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

  def inverse(self) -> "Motion":
    """x -> R^T (x - t): undoes this motion."""
    return Motion(self.rotation.T, -self.rotation.T @ self.translation)

  def then(self, after: "Motion") -> "Motion":
    """This motion followed by `after`: x -> after(self(x))."""
    return Motion(after.rotation @ self.rotation, after.rotation @ self.translation + after.translation)

  def in_frame(self, p_3x3) -> "Motion":
    """This motion in the coordinates y = P x of a rotation (or axis permutation) P."""
    p = np.asarray(p_3x3, np.float64)
    return Motion(p @ self.rotation @ p.T, p @ self.translation, self.inliers)

  @classmethod
  def of(cls, rotation, translation) -> "Motion":
    """A motion from any 3 x 3 rotation and 3-vector (as float64)."""
    return cls(np.asarray(rotation, np.float64), np.asarray(translation, np.float64))

  @property
  def angle_deg(self) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1) / 2, -1.0, 1.0))))

  @property
  def yaw_deg(self) -> float:
    """The heading change about z in degrees (signed; a z-up frame's turn of the x axis)."""
    return float(np.degrees(np.arctan2(self.rotation[1, 0], self.rotation[0, 0])))


def rotations_from_vectors(vectors_Nx3, precision: str = "highest"):
  """The rotation matrices (N x 3 x 3) of rotation vectors (axis times angle in radians), by
  Rodrigues' formula: exact and smooth at 0. NumPy in, NumPy out (float64; `precision` unused);
  a jax array in, jax out at `precision` (the optimiser's rigid model, inside jit)."""
  if isinstance(vectors_Nx3, np.ndarray):
    xp, matmul = np, np.matmul
  else:  # jax only here, as kabsch_rotation
    import jax  # pylint: disable=import-outside-toplevel
    xp = jax.numpy
    matmul = functools.partial(jax.numpy.matmul, precision=jax.lax.Precision(precision))
  theta2 = xp.sum(vectors_Nx3**2, axis=-1)[:, None, None]
  theta = xp.sqrt(xp.maximum(theta2, 1e-12))
  small = theta2 < 1e-8
  a = xp.where(small, 1.0 - theta2 / 6.0, xp.sin(theta) / theta)
  b = xp.where(small, 0.5 - theta2 / 24.0, (1.0 - xp.cos(theta)) / xp.maximum(theta2, 1e-12))
  x, y, z = vectors_Nx3[:, 0], vectors_Nx3[:, 1], vectors_Nx3[:, 2]
  zero = xp.zeros_like(x)
  k = xp.stack([xp.stack([zero, -z, y], -1), xp.stack([z, zero, -x], -1),
                xp.stack([-y, x, zero], -1)], -2)
  return xp.eye(3) + a * k + b * matmul(k, k)


def kabsch_rotation(cov_Sx3x3, precision: str = "highest"):
  """The rotations R (S x 3 x 3) minimising sum_i |R a_i - b_i|^2 given the cross-covariances
  H = sum_i a_i b_i^T (S x 3 x 3) of centred source points a and target points b: with the SVD
  H = U S V^T, R = V diag(1, 1, d) U^T, d = sign det(V U^T) (a reflection becomes the nearest
  rotation; d = 1 for a degenerate H). NumPy in, NumPy out (rigid.kabsch, float64); a jax array
  in, jax out (fit, inside jit)."""
  if isinstance(cov_Sx3x3, np.ndarray):
    xp, einsum = np, np.einsum
  else:  # jax only here: the NumPy paths (the sweeps) do not load it
    import jax  # pylint: disable=import-outside-toplevel
    xp, einsum = jax.numpy, functools.partial(jax.numpy.einsum, precision=jax.lax.Precision(precision))
  u, _, vt = xp.linalg.svd(cov_Sx3x3)
  d = xp.sign(xp.linalg.det(u) * xp.linalg.det(vt))  # det(V U^T), without a product
  d = xp.where(d == 0, 1.0, d)
  fix_Sx3 = xp.concatenate([xp.ones_like(d)[:, None].repeat(2, axis=1), d[:, None]], axis=1)
  return einsum("sji,sj,skj->sik", vt, fix_Sx3, u)  # V diag(1, 1, d) U^T


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
