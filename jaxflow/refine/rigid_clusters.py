"""Piecewise rigidity: clusters of pc1 that move together, and one rigid motion per cluster.

FT3D and driving scenes are made of rigid pieces. `clusters` links each point
to those of its k nearest that are within `radius` m and whose flows differ by less than
`flow_tolerance` m, and labels the connected components (min-label propagation, all in jit).
`fit` gives each cluster the least-squares rigid motion of its points' flows (Kabsch): rotation R,
centroid c and translation t, so that p -> R (p - c) + c + t, with jaxflow's one Kabsch
(jaxflow.geometry.rigid.kabsch_rotation). Every matmul runs at `precision` (exact float32 by
default). jaxflow.refine.optimiser's `rigid` model then
optimises a correction of each cluster's motion against pc2 (6 numbers a cluster, not 3 a point).
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxflow.geometry import neighbours, ops, rigid
from jaxflow.refine import objectives


@dataclasses.dataclass(frozen=True)
class Settings:
  neighbours: int = 8
  radius: float = 0.5  # metres between linked points
  flow_tolerance: float = 0.3  # metres between the flows of linked points
  min_points: int = 8  # smaller clusters keep a pure translation (their mean flow)
  propagation: int = 64  # label-propagation rounds at most (each also jumps labels to labels)
  search: str = "auto"  # where the kNN graph is searched (jaxflow.geometry.neighbours.SEARCHES)

  def __post_init__(self):
    for name in ("neighbours", "min_points", "propagation"):
      if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
        raise ValueError(f"rigid {name} must be an integer >= 1, got {getattr(self, name)!r}")
    for name in ("radius", "flow_tolerance"):
      if not getattr(self, name) >= 0:
        raise ValueError(f"rigid {name} must be >= 0, got {getattr(self, name)!r}")
    neighbours.check_search(self.search, "rigid search")


def clusters(pc1_BxNx3, flow_BxNx3, settings: Settings, nbr_BxNxK=None):
  """Cluster label of each point (B x N, int32): the smallest point index of its component.
  `nbr_BxNxK`: each point's `settings.neighbours` + 1 nearest, itself included (None: searched)."""
  k = min(settings.neighbours + 1, pc1_BxNx3.shape[1])
  if nbr_BxNxK is None:
    nbr_BxNxK = neighbours.knn(pc1_BxNx3, pc1_BxNx3, k, settings.search)
  near = jnp.sum((ops.gather(pc1_BxNx3, nbr_BxNxK) - pc1_BxNx3[:, :, None]) ** 2, -1)
  same = jnp.sum((ops.gather(flow_BxNx3, nbr_BxNxK) - flow_BxNx3[:, :, None]) ** 2, -1)
  linked_BxNxK = (near <= settings.radius**2) & (same <= settings.flow_tolerance**2)
  n = pc1_BxNx3.shape[1]

  def one(nbr_NxK, linked_NxK):
    def spread(state):
      labels, _, rounds = state
      theirs = jnp.where(linked_NxK, labels[nbr_NxK], n)
      new = jnp.minimum(labels, jnp.min(theirs, axis=1))
      # The kNN graph is not symmetric: a point also hands its label to the neighbours it links.
      new = new.at[nbr_NxK.ravel()].min(jnp.where(linked_NxK, new[:, None], n).ravel())
      new = new[new]  # pointer jumping: components of long chains merge in log rounds
      return new, jnp.any(new != labels), rounds + 1

    state = (jnp.arange(n, dtype=jnp.int32), jnp.array(True), 0)
    state = jax.lax.while_loop(lambda s: s[1] & (s[2] < settings.propagation), spread, state)
    return state[0]

  return jax.vmap(one)(nbr_BxNxK, linked_BxNxK)


def fit(pc1_BxNx3, flow_BxNx3, labels_BxN, min_points: int, precision: str = "highest"):
  """Per label (B x N slots; slot l is cluster l): R (B x N x 3 x 3), centroid, translation, each
  the least-squares rigid motion p -> R (p - c) + c + t of the cluster's points onto p + flow."""

  def one(p_Nx3, f_Nx3, lab_N):
    n = p_Nx3.shape[0]
    seg = lambda x: jax.ops.segment_sum(x, lab_N, num_segments=n)
    count = seg(jnp.ones(n, jnp.float32))
    safe = jnp.maximum(count, 1.0)[:, None]
    cen_Nx3 = seg(p_Nx3) / safe
    q_Nx3 = p_Nx3 + f_Nx3
    qcen_Nx3 = seg(q_Nx3) / safe
    a_Nx3, b_Nx3 = p_Nx3 - cen_Nx3[lab_N], q_Nx3 - qcen_Nx3[lab_N]
    cov_Nx3x3 = seg(a_Nx3[:, :, None] * b_Nx3[:, None, :])
    r_Nx3x3 = rigid.kabsch_rotation(cov_Nx3x3, precision)
    enough = (count >= min_points)[:, None, None]
    r_Nx3x3 = jnp.where(enough & jnp.all(jnp.isfinite(r_Nx3x3), axis=(1, 2), keepdims=True),
                        r_Nx3x3, jnp.eye(3))
    return r_Nx3x3, cen_Nx3, qcen_Nx3 - cen_Nx3

  return jax.vmap(one)(pc1_BxNx3, flow_BxNx3, labels_BxN)


def rigid_flow(p_Nx3, labels_N, r_Nx3x3, cen_Nx3, t_Nx3, precision: str = "highest"):
  """Flow of each point under its cluster's motion p -> R (p - c) + c + t."""
  moved = jnp.einsum("nij,nj->ni", r_Nx3x3[labels_N], p_Nx3 - cen_Nx3[labels_N],
                     precision=jax.lax.Precision(precision))
  return moved + cen_Nx3[labels_N] + t_Nx3[labels_N] - p_Nx3


def choose(labels_BxN, flows, pc1_BxNx3, pc2_BxMx3, truncate: float, search: str = "auto",
           matches=None):
  """Per cluster, the candidate flow (of `flows`, each B x N x 3) whose warped points lie nearest
  pc2 on average (truncated squared distance to the nearest pc2 point); ties go to the first.
  `matches`: each flow's neighbours.nearest(pc1 + flow, pc2) (None: searched)."""
  costs = []
  for i, flow in enumerate(flows):
    warped = pc1_BxNx3 + flow
    match = neighbours.nearest(warped, pc2_BxMx3, search) if matches is None else matches[i]
    sq_BxN = objectives.matched_sq(warped, pc2_BxMx3, match)
    per = jax.vmap(lambda c, lab: jax.ops.segment_sum(c, lab, num_segments=c.shape[0]))
    costs.append(per(jnp.minimum(sq_BxN, truncate**2), labels_BxN))
  best_BxN = jnp.argmin(jnp.stack(costs), axis=0)  # per cluster slot
  pick_BxN = jnp.take_along_axis(best_BxN, labels_BxN, axis=1)
  return jnp.select([pick_BxN[..., None] == i for i in range(len(flows))], list(flows))
