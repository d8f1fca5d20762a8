"""Rigid groups: a scene split into pieces that move as one, and the one rule that decides whether
a piece's own motion explains it better than another motion (the world's, standing still).

    groups = cell_components(points_Nx3, seeds_N, cell=0.3, bridge=True)
    for k, indices in groups.members(): ...
    beats(base_costs_K, other_costs_K, Rule(margin=0.05))   # True, False, or None: undecided
    keep = given_kept(groups, evidence.costs(pc1 + new), evidence.costs(pc1 + given), rule)

The raw-sweep pipeline (jaxflow.lidar.objects: connected cells seen from above, each group fitted
against standing still) and optimise's rigid bodies (jaxflow.refine.bodies: sequential RANSAC and
an assignment, each body judged against the world's motion) both speak of groups this way and
judge with `beats`; every stage of optimise keeps, group by group, the flow it was given where pc2
does not support its new one (`given_kept`). A cost is per point (a distance to pc2, truncated),
NaN where pc2 could not see the point placed so (`Evidence`): a placement pc2 cannot see is no
evidence either way.
"""

import dataclasses

import numpy as np
from scipy import ndimage

from jaxflow.geometry.visibility import SEEN


@dataclasses.dataclass(frozen=True)
class Groups:
  """A labelling: the group of each point (0 .. count - 1), -1 for points in none."""
  label: np.ndarray
  count: int

  def without(self, points_N) -> "Groups":
    """The same groups with the `points_N` (bool) taken out of them."""
    return Groups(np.where(points_N, -1, self.label), self.count)

  def members(self):
    """(k, indices of its points) of each group in turn, empty ones included (one sort for
    all)."""
    order = np.argsort(self.label, kind="stable")
    bounds = np.searchsorted(self.label[order], np.arange(self.count + 1))
    for k in range(self.count):
      yield k, order[bounds[k]:bounds[k + 1]]


def cell_components(points_Nx3, seeds_N, cell: float, bridge: bool) -> Groups:
  """The 8-connected components of the cells (of `cell` m, seen from above: x and y) that the
  `seeds_N` points occupy, gaps of one cell bridged when `bridge`; every point in a component's
  cells belongs to it, seed or not."""
  if not seeds_N.any():
    return Groups(np.full(len(points_Nx3), -1), 0)
  ij = np.floor(points_Nx3[:, :2] / cell).astype(np.int64)
  ij = ij - ij[seeds_N].min(0)
  shape = ij[seeds_N].max(0) + 1
  inside = (ij >= 0).all(1) & (ij < shape).all(1)
  grid = np.zeros(shape, bool)
  grid[ij[seeds_N, 0], ij[seeds_N, 1]] = True
  if bridge:
    grid = ndimage.binary_dilation(grid, np.ones((3, 3)))
  labels, count = ndimage.label(grid, np.ones((3, 3)))
  out = np.full(len(points_Nx3), -1)
  out[inside] = labels[ij[inside, 0], ij[inside, 1]] - 1
  return Groups(out, count)


@dataclasses.dataclass(frozen=True)
class Rule:
  """How clearly one placement of a group must beat another's (costs in the callers' units)."""
  margin: float  # the least mean gain per point
  relative_margin: float = 0.0  # share of the base's mean cost: the least gain too
  significance: float = 0.0  # standard errors of the paired per-point gain: the least gain too
  min_seen: float = 0.3  # share of a placement's points pc2 must see for it to be judged
  min_paired: int = 1  # points seen in both placements below which the other does not win


def beats(base_K, other_K, rule: Rule) -> bool | None:
  """Whether the `other` placement's per-point costs beat the `base`'s clearly (`rule`), paired
  on the points pc2 sees in both. None when pc2 sees under `min_seen` of the base placement (no
  evidence for it: the caller decides, e.g. the other must fit on its own); False when it sees
  under `min_seen` of the other, or fewer than `min_paired` points of both."""
  base_seen, other_seen = np.isfinite(base_K), np.isfinite(other_K)
  if base_seen.mean() < rule.min_seen:
    return None
  if other_seen.mean() < rule.min_seen:
    return False
  both = base_seen & other_seen
  if both.sum() < rule.min_paired:
    return False
  diff = base_K[both] - other_K[both]
  gain = diff.mean()
  error = diff.std() / np.sqrt(len(diff))
  return bool(gain >= max(rule.margin, rule.relative_margin * base_K[both].mean())
              and gain >= rule.significance * error)


class Evidence:
  """What pc2 shows of points placed somewhere: per point, the distance to pc2's local plane
  (truncated at `truncate` m) where pc2 would see the point there, NaN where it would not (hidden
  behind a nearer return or outside pc2's view). `target`: a registration.PlaneTarget of pc2;
  `view`: a visibility.View of pc2 (None: every placement counts as seen)."""

  def __init__(self, target, view, truncate: float):
    self.target, self.view, self.truncate = target, view, truncate

  def costs(self, placed_Nx3) -> np.ndarray:
    placed = np.asarray(placed_Nx3, np.float64)
    seen = np.ones(len(placed), bool) if self.view is None else self.view.state(placed) == SEEN
    out = np.full(len(placed), np.nan)
    out[seen] = self.target.plane_distance(placed[seen], self.truncate)
    return out


def given_kept(groups: Groups, new_costs_N, given_costs_N, rule: Rule) -> np.ndarray:
  """Per point (bool N), whether its group keeps the placement it was given rather than a new one:
  where the given placement's costs beat the new one's (`rule`), or pc2 sees under `min_seen` of
  the group placed anew and not of it placed as given (nothing supports the new placement, and the
  given is seen; where pc2 sees neither, no evidence refutes the new). Points in no group take the
  new."""
  keep = np.zeros(len(groups.label), bool)
  for _, pts in groups.members():
    if len(pts):
      verdict = beats(new_costs_N[pts], given_costs_N[pts], rule)
      if verdict is None:
        verdict = np.isfinite(given_costs_N[pts]).mean() >= rule.min_seen
      keep[pts] = verdict
  return keep
