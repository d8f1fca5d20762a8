"""An object's horizontal translation between the sweeps, searched on a grid of shifts against
ego-compensated pc2 (jaxflow.lidar.objects' "search" start).

    motions = best_shifts(tree2, points_Kx3, 3.5, settings)  # within +-3.5 m, best first
    halves_agree(tree2, other_half_Kx3, motions[0], 3.5, settings)

`settings` is the objects block (jaxflow.lidar.settings.Objects): its `search` block and the
judge's truncation.
"""

import numpy as np

from jaxflow.geometry import rigid


def best_shifts(tree, points_Kx3, search: float, settings) -> list[rigid.Motion]:
  """The best horizontal translation within +-`search` m (3-D cost) near each of the
  `search.keep` best nodes of a coarse grid, best first: the coarse costs truncated at its step (a
  shift within a cell of the right one still finds the object: truncated nearer, a narrow basin
  falls between two nodes and the sampling picks the node), then a fine grid around each node at
  the judge's truncation. Several, because an object's shape also fits its like (the parked car
  beside it) and only the caller can tell which place pc1 saw empty."""
  truncate, coarse = settings.judge.truncate, settings.search.coarse_step

  def costs(shifts, cut):
    d, _ = tree.nearest((points_Kx3[None] + shifts[:, None]).reshape(-1, 3), cut)
    cost = np.minimum(d, cut).reshape(len(shifts), -1).mean(1)
    return cost + 1e-4 * np.linalg.norm(shifts, axis=1)  # ties: the smaller move

  grid = lambda half, step: np.arange(-half, half + 1e-9, step)
  dx, dy = np.meshgrid(grid(search, coarse), grid(search, coarse), indexing="ij")
  shifts = np.c_[dx.ravel(), dy.ravel(), np.zeros(dx.size)]
  kept = shifts[np.argsort(costs(shifts, coarse), kind="stable")[:settings.search.keep]]
  fine_steps = grid(coarse, settings.search.step / 2)
  fx, fy = np.meshgrid(fine_steps, fine_steps, indexing="ij")
  fine = np.c_[fx.ravel(), fy.ravel(), np.zeros(fx.size)]
  found = []
  for node in kept:
    near = node + fine
    cost = costs(near, truncate)
    found.append((float(cost.min()), near[int(np.argmin(cost))]))
  return [rigid.Motion(np.eye(3), shift) for _, shift in sorted(found, key=lambda f: f[0])]


def halves_agree(tree, judged_Kx3, motion: rigid.Motion, search_m: float, settings) -> bool:
  """Whether the search on an object's judged half finds, among its `search.keep` shifts, the one
  `motion` (searched on the other half) gives its centre, within `search.agree` m: a mover's
  halves both find its motion, while the best of many shifts of a sparse thing standing still fits
  its own sampling by chance."""
  centre = judged_Kx3.mean(0)
  moved = motion.apply(centre[None])[0, :2] - centre[:2]
  own = best_shifts(tree, judged_Kx3[:settings.search.points], search_m, settings)
  return any(np.linalg.norm(moved - m.translation[:2]) <= settings.search.agree for m in own)
