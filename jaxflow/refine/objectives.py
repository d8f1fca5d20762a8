"""The self-supervised objectives of flow optimisation (jaxflow.refine.optimiser: NSFP, test time).

- `chamfer_terms`: the truncated two-way Chamfer with the matches held fixed (the matches:
  jaxflow.geometry.neighbours.nearest, searched where `search` says).
- `smoothness`: mean L1 difference of the flow over pc1's k-nearest graph
  (neighbours.nearest_others).
- the distance grid of the fast objective: jaxflow.refine.distance_grid.
"""

import jax.numpy as jnp

from jaxflow.geometry import neighbours, ops


def matched_sq(query_BxNx3, points_BxMx3, idx_BxNx1):
  """|query - points[idx]|^2, B x N: differentiable in both clouds, the match held fixed."""
  return jnp.sum((query_BxNx3 - ops.gather(points_BxMx3, idx_BxNx1)[:, :, 0]) ** 2, axis=-1)


def truncated_mean(sq_BxN, truncate: float):
  """Mean over points of the squared distances clipped at truncate^2 (a far point stops pulling)."""
  return jnp.mean(jnp.minimum(sq_BxN, truncate**2), axis=1)


def chamfer_terms(a_BxNx3, b_BxMx3, match, truncate: float):
  """Truncated two-way Chamfer (B): a -> b plus b -> a, with `match` = (nearest(a, b),
  nearest(b, a)) held fixed."""
  a_to_b, b_to_a = match
  return (truncated_mean(matched_sq(a_BxNx3, b_BxMx3, a_to_b), truncate)
          + truncated_mean(matched_sq(b_BxMx3, a_BxNx3, b_to_a), truncate))


def chamfer(a_BxNx3, b_BxMx3, truncate: float, search: str = "auto"):
  """Truncated two-way Chamfer distance (B) with the nearest points searched now."""
  match = (neighbours.nearest(a_BxNx3, b_BxMx3, search),
           neighbours.nearest(b_BxMx3, a_BxNx3, search))
  return chamfer_terms(a_BxNx3, b_BxMx3, match, truncate)


def smoothness(flow_BxNx3, nbr_BxNxK):
  """Mean L1 difference between each point's flow and its neighbours' (B)."""
  diff = ops.gather(flow_BxNx3, nbr_BxNxK) - flow_BxNx3[:, :, None]
  return jnp.mean(jnp.sum(jnp.abs(diff), axis=-1), axis=(1, 2))
