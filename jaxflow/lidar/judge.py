"""How a placement of an object is judged against pc2: per-point costs, and the rule another
placement must pass to replace one (jaxflow.lidar.objects, jaxflow.lidar.along).

    c = costs(tree, points_Kx3, view, ego_motion, truncation(points_Kx3, points_Kx3, settings))
    clearly_better(still_costs, moved_costs, settings)   # moved replaces standing still

`settings` is the objects block (jaxflow.lidar.settings.Objects); the names are fields of its
`judge` block (Judge), but `min_points`.
"""

import numpy as np

from jaxflow.geometry import groups, neighbours


def costs(tree, points_Kx3, visibility, to2, truncate) -> np.ndarray:
  """Truncated 3-D distance of each point to ego-compensated pc2, NaN where pc2 could not see it
  (a box slid along its own side still matches seen from above, not in 3-D), in units of
  `truncate` (far objects are sampled sparsely: their distances are larger whatever the motion)."""
  d, _ = tree.nearest(points_Kx3, truncate)
  d = np.minimum(d, truncate) / truncate
  d[visibility.hidden(to2.apply(points_Kx3))] = np.nan
  return d


def mean(costs, min_seen: float) -> float:
  """A motion's cost: the mean over the visible points (1, the truncation, when fewer than
  `min_seen` of them are)."""
  seen = np.isfinite(costs)
  return float(costs[seen].mean()) if seen.mean() >= min_seen else 1.0


def rule(settings) -> groups.Rule:
  """The objects block's judgement: a motion beats standing still by `margin`, by
  `relative_margin` of still's cost and by `significance` standard errors."""
  judging = settings.judge
  return groups.Rule(judging.margin, judging.relative_margin, judging.significance,
                     judging.min_seen, settings.min_points // 2)


def clearly_better(base, other, settings) -> bool:
  """groups.beats under the objects block's rule; where pc2 cannot see the base placement (a car
  come nearer along the line of sight hides its old place), the other must fit within
  `hidden_fit` on its own."""
  verdict = groups.beats(base, other, rule(settings))
  judging = settings.judge
  return mean(other, judging.min_seen) <= judging.hidden_fit if verdict is None else verdict


def truncation(pts_Kx3, queries_Qx3, s) -> float:
  """An object's cost truncation (m): `spacings` of its median point spacing (each query's
  nearest other point of the object), within truncate .. max_truncate."""
  spacing = np.median(neighbours.Tree(pts_Kx3).knn(queries_Qx3, 2, distances=True)[0][:, 1])
  judging = s.judge
  return float(np.clip(judging.spacings * spacing, judging.truncate, judging.max_truncate))
