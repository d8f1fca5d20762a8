"""Robust rigid registration of points onto a target: one Gauss-Newton core, the residuals as rows.

    target = PlaneTarget(pc2_Mx3)                       # pc2's points, normals and k-d tree
    motion = robust_fit(src_Kx3, start, target.plane_rows, scales=[0.2] * 10 + [0.05] * 10)
    cost_K = target.plane_distance(motion.apply(src_Kx3), truncate=0.3)

A residual row is a signed distance r along a unit direction n at one moved point q:
point-to-plane (n: the target point's normal), point-to-line seen from above (n: across the line,
horizontal), point-to-point (a row per axis, or the closed-form `point_weight` part). Each round
weighs the rows by Geman-McClure at that round's scale, solves the damped normal equations of
the rotation (about the origin or the points' centroid) and the translation (6 unknowns, or yaw and a horizontal translation
for `dof="yaw_xy"`, z up) and composes the step onto the motion. Users: the rigid bodies of
`optimise` (jaxflow.refine.bodies: point-to-plane + point-to-point, 6 dof) and the moving
objects of raw sweeps (jaxflow.lidar.objects: point-to-line seen from above, yaw_xy); the
sensor's own motion is small_gicp's GICP (jaxflow.lidar.ego), scored by `plane_distance`.
"""

import dataclasses

import numpy as np

from jaxflow.geometry import neighbours, rigid

DOFS = ("6", "yaw_xy")


@dataclasses.dataclass(frozen=True)
class Rows:
  """Residual rows of the moved points: r (R), direction n (R x 3), the point of each row (R),
  the rows inside the match gate (R bool; None: all) and each row's point minus its match (R x 3,
  for the point-to-point part; None: none)."""
  residual: np.ndarray
  direction: np.ndarray
  index: np.ndarray
  gate: np.ndarray | None = None
  offset: np.ndarray | None = None


def geman_mcclure(residual_R, scale: float) -> np.ndarray:
  """The IRLS weight of Geman-McClure's loss: 1 / (1 + (r / scale)^2)^2."""
  return 1.0 / (1.0 + (residual_R / scale) ** 2) ** 2


def _cross(a_Nx3, b_Nx3):
  """Row-wise a x b (np.cross without its axis handling, which dominated the fit's time)."""
  return np.stack([a_Nx3[:, 1] * b_Nx3[:, 2] - a_Nx3[:, 2] * b_Nx3[:, 1],
                   a_Nx3[:, 2] * b_Nx3[:, 0] - a_Nx3[:, 0] * b_Nx3[:, 2],
                   a_Nx3[:, 0] * b_Nx3[:, 1] - a_Nx3[:, 1] * b_Nx3[:, 0]], 1)


def _skew(v_3):
  """[v]_x: the matrix of x -> v x x."""
  return np.array([[0.0, -v_3[2], v_3[1]], [v_3[2], 0.0, -v_3[0]], [-v_3[1], v_3[0], 0.0]])


def _add_point_to_point(h_6x6, g_6, q_Rx3, offset_Rx3, w_R):
  """The point-to-point rows of every row's point, d(q_axis) / d(omega, t) = (q x e_axis, e_axis),
  summed in closed form: sum w [[|q|^2 I - q q^T, [q]_x], [-[q]_x, I]] and sum w (q x d, d)."""
  qw = q_Rx3 * w_R[:, None]
  h_6x6[:3, :3] += np.eye(3) * np.sum(qw * q_Rx3) - q_Rx3.T @ qw
  skew = _skew(qw.sum(0))
  h_6x6[:3, 3:] += skew
  h_6x6[3:, :3] -= skew
  h_6x6[3:, 3:] += np.eye(3) * w_R.sum()
  g_6[:3] += np.sum(_cross(qw, offset_Rx3), 0)
  g_6[3:] += w_R @ offset_Rx3


def robust_fit(points_Kx3, start: rigid.Motion, rows_of, scales, dof: str = "6",
               about_centroid: bool = False, point_weight: float = 0.0, damping: float = 1e-6,
               min_rows: int = 3, min_weight: float = 0.0, converged: float = 0.0) -> rigid.Motion:
  """`start` refined by one Gauss-Newton round per entry of `scales` (metres, the robust scale of
  that round): `rows_of(moved_Kx3, scale)` gives the Rows. The rotation turns about the origin, or
  about the moved points' centroid (`about_centroid`: better conditioned for a small object far
  from the origin). Stops early when fewer than `min_rows` rows or less than `min_weight` total
  weight remain, or when no unknown changes by more than `converged`. `point_weight`: the weight
  of the point-to-point rows beside each row (6 dof; Rows.offset needed)."""
  if dof not in DOFS:
    raise ValueError(f"registration dof must be one of {', '.join(DOFS)}, got {dof!r}")
  if point_weight and dof != "6":
    raise ValueError(f"registration point_weight needs dof '6', got dof {dof!r}")
  points = np.asarray(points_Kx3, np.float64)
  rotation = np.asarray(start.rotation, np.float64).copy()
  translation = np.asarray(start.translation, np.float64).copy()
  for scale in scales:
    moved = points @ rotation.T + translation
    centre = moved.mean(0) if about_centroid else np.zeros(3)
    rows = rows_of(moved, scale)
    if len(rows.residual) < min_rows:
      break
    r, n = rows.residual, rows.direction
    w = geman_mcclure(r, scale)
    if rows.gate is not None:
      w = w * rows.gate
    if w.sum() < min_weight:
      break
    q = moved[rows.index] - centre
    if dof == "6":
      jac = np.concatenate([_cross(q, n), n], 1)
    else:  # the z component of (q x n), and the horizontal translation
      jac = np.c_[q[:, 0] * n[:, 1] - q[:, 1] * n[:, 0], n[:, 0], n[:, 1]]
    h = jac.T @ (jac * w[:, None]) + damping * np.eye(jac.shape[1])
    g = jac.T @ (w * r)
    if point_weight:
      _add_point_to_point(h, g, q, rows.offset, point_weight * w)
    step = -np.linalg.solve(h, g)
    if dof == "6":
      d_rot, d_t = rigid.rotations_from_vectors(step[None, :3])[0], step[3:]
    else:
      c, s = np.cos(step[0]), np.sin(step[0])
      d_rot, d_t = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.r_[step[1:], 0.0]
    rotation = d_rot @ rotation
    translation = d_rot @ (translation - centre) + centre + d_t
    if np.abs(step).max() < converged:
      break
  return rigid.Motion(rotation, translation)


class PlaneTarget:
  """A target cloud prepared once: its points, k-d tree and normals (given, or the least-spread
  direction of each point's `normal_neighbours` nearest)."""

  def __init__(self, points_Mx3, normals_Mx3=None, normal_neighbours: int = 10):
    self.tree = neighbours.Tree(points_Mx3)
    self.points = self.tree.points
    if normals_Mx3 is None:
      normals_Mx3 = neighbours.local_spread(self.points, normal_neighbours, self.tree)[1][:, :, 0]
    self.normals = np.asarray(normals_Mx3, np.float64)

  def plane_distance(self, moved_Nx3, truncate: float, reach: float | None = None) -> np.ndarray:
    """Per point: its distance to the plane of its nearest target point, at most `truncate`
    (also where no target point is within `reach`, default `truncate`). Not the distance to the
    point: where two sweeps sample a surface at other places (a LiDAR's rings on a facade), that
    distance favours motions that line the samples up."""
    out = np.full(len(moved_Nx3), truncate, np.float64)
    if not len(self.points):
      return out
    d, j = self.tree.nearest(moved_Nx3, truncate if reach is None else reach)
    near = np.isfinite(d)
    gap = np.abs(np.sum((moved_Nx3[near] - self.points[j[near]]) * self.normals[j[near]], 1))
    out[near] = np.minimum(gap, truncate)
    return out

  def plane_rows(self, moved_Kx3, scale: float, gate: float = 4.0) -> Rows:
    """Point-to-plane rows of every moved point against its nearest target point; matches beyond
    `gate` x scale are gated out; the offsets serve the point-to-point part."""
    d, j = self.tree.nearest(moved_Kx3)
    diff = moved_Kx3 - self.points[j]
    n = self.normals[j]
    return Rows(np.sum(diff * n, 1), n, np.arange(len(moved_Kx3)), d < gate * scale, diff)
