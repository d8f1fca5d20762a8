"""The one Kabsch (rigid.kabsch_rotation) recovers known motions: through rigid.kabsch
(NumPy, float64) and rigid_clusters.fit (jax, per cluster), against closed-form rotations."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow.geometry import rigid
from jaxflow.refine import rigid_clusters


def rotation(axis, angle):
  """Rodrigues' closed form: I + sin(a) K + (1 - cos(a)) K^2 for the unit axis' cross matrix K."""
  x, y, z = np.asarray(axis, float) / np.linalg.norm(axis)
  k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
  return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_rigid_kabsch_recovers_a_known_motion_and_refuses_a_reflection():
  rng = np.random.default_rng(0)
  src = rng.uniform(-30, 30, (200, 3))  # tens of metres, as a sweep
  r, t = rotation([0.2, -0.3, 1.0], np.radians(7.5)), np.array([1.2, -0.4, 0.05])
  motion = rigid.kabsch(src, src @ r.T + t)
  np.testing.assert_allclose(motion.rotation, r, atol=1e-12)
  np.testing.assert_allclose(motion.translation, t, atol=1e-10)
  np.testing.assert_allclose(motion.angle_deg, 7.5, atol=1e-9)
  # Weights: the outliers given no weight do not move the fit.
  dst = src @ r.T + t
  dst[:20] += 5.0
  w = np.r_[np.zeros(20), np.ones(180)]
  np.testing.assert_allclose(rigid.kabsch(src, dst, w).rotation, r, atol=1e-12)
  # A mirror image: the nearest proper rotation (det +1), never the reflection.
  mirrored = src * [1, 1, -1]
  fitted = rigid.kabsch(src, mirrored).rotation
  np.testing.assert_allclose(np.linalg.det(fitted), 1.0, atol=1e-12)
  np.testing.assert_allclose(fitted @ fitted.T, np.eye(3), atol=1e-12)


def test_fit_recovers_each_clusters_motion_with_the_same_kabsch():
  rng = np.random.default_rng(1)
  pc1 = rng.uniform(-20, 20, (90, 3)).astype(np.float32)
  labels = np.repeat([0, 30, 60], 30)  # slot l is cluster l (the smallest index of its points)
  motions = [(rotation([0, 0, 1], np.radians(5)), [0.5, 0, 0]),
             (rotation([1, 1, 0], np.radians(-3)), [0, 1.0, 0.2]), (np.eye(3), [0.3, 0.3, 0.0])]
  flow = np.zeros_like(pc1)
  for (r, t), start in zip(motions, (0, 30, 60)):
    p = pc1[start:start + 30].astype(np.float64)
    c = p.mean(0)
    flow[start:start + 30] = (p - c) @ r.T + c + t - p
  r_got, cen, t_got = (np.asarray(a[0]) for a in rigid_clusters.fit(
    jnp.asarray(pc1[None]), jnp.asarray(flow[None]), jnp.asarray(labels[None]), 8))
  for (r, t), slot in zip(motions, (0, 30, 60)):
    np.testing.assert_allclose(r_got[slot], r, atol=2e-5)
    np.testing.assert_allclose(t_got[slot], t, atol=2e-4)
    np.testing.assert_allclose(cen[slot], pc1[slot:slot + 30].mean(0), atol=1e-4)
  np.testing.assert_array_equal(r_got[1], np.eye(3))  # an empty slot: the identity
  # The NumPy and jax paths of the one implementation agree on the same covariances.
  cov = rng.normal(size=(5, 3, 3))
  np.testing.assert_allclose(np.asarray(rigid.kabsch_rotation(jnp.asarray(cov))),
                             rigid.kabsch_rotation(cov), atol=1e-5)


def test_motion_inverse_composition_frame_and_yaw():
  """The motion algebra against applying the matrices by hand; the yaw of a turn about z."""
  rng = np.random.default_rng(3)
  x = rng.uniform(-30, 30, (50, 3))
  a = rigid.Motion.of(rotation([0, 0, 1], 0.3), [1.0, -2.0, 0.5])
  b = rigid.Motion.of(rotation([1, 2, 0], -0.2), [0.0, 0.4, -1.0])
  np.testing.assert_allclose(a.inverse().apply(a.apply(x)), x, atol=1e-12)
  np.testing.assert_allclose(a.then(b).apply(x), (x @ a.rotation.T + a.translation)
                             @ b.rotation.T + b.translation, atol=1e-12)
  p = np.eye(3)[[2, 0, 1]]  # a cyclic axis permutation (a rotation)
  np.testing.assert_allclose(a.in_frame(p).apply(x @ p.T), a.apply(x) @ p.T, atol=1e-12)
  assert a.angle_deg == pytest.approx(np.degrees(0.3))
  assert a.yaw_deg == pytest.approx(np.degrees(0.3))
  assert rigid.Motion.of(rotation([0, 0, 1], -2.5), np.zeros(3)).yaw_deg == pytest.approx(
      np.degrees(-2.5))


def test_rotation_vectors_give_the_closed_form_rotations():
  """rigid.rotations_from_vectors, NumPy (float64) and jax (float32), against known rotations
  (a quarter turn about z takes x to y), the axis-angle closed form and scipy's rotation vector,
  at large and tiny angles (the series branch)."""
  from scipy.spatial.transform import Rotation
  quarter = rigid.rotations_from_vectors(np.array([[0.0, 0.0, np.pi / 2]]))[0]
  np.testing.assert_allclose(quarter @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
  np.testing.assert_allclose(quarter @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-15)
  axis = np.array([1.0, 2.0, 2.0]) / 3.0
  np.testing.assert_allclose(rigid.rotations_from_vectors((0.7 * axis)[None])[0],
                             rotation(axis, 0.7), atol=1e-12)
  rng = np.random.default_rng(5)
  vectors = rng.normal(0, 1, (200, 3)) * rng.choice([1e-7, 1e-3, 1.0, 3.0], (200, 1))
  want = Rotation.from_rotvec(vectors).as_matrix()
  got = rigid.rotations_from_vectors(vectors)
  assert isinstance(got, np.ndarray) and got.dtype == np.float64
  np.testing.assert_allclose(got, want, atol=1e-14)
  np.testing.assert_allclose(got @ got.transpose(0, 2, 1), np.broadcast_to(np.eye(3), got.shape),
                             atol=1e-14)
  np.testing.assert_allclose(np.linalg.det(got), 1.0, atol=1e-14)
  in_jax = rigid.rotations_from_vectors(jnp.asarray(vectors, jnp.float32))
  assert not isinstance(in_jax, np.ndarray) and in_jax.dtype == jnp.float32
  np.testing.assert_allclose(np.asarray(in_jax), want, atol=2e-6)
