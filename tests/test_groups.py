"""jaxflow.geometry.groups: labellings, connected cells from above, and the one judgement rule."""

import numpy as np

from jaxflow.geometry import groups


def test_members_are_each_groups_points_in_order():
  label = np.array([2, -1, 0, 2, 0, 3, -1, 0])
  got = dict(groups.Groups(label, 5).members())
  for k in range(5):  # group 1 and 4 are empty; -1 is no group
    np.testing.assert_array_equal(got[k], np.flatnonzero(label == k))
  assert list(got) == [0, 1, 2, 3, 4]
  taken = groups.Groups(label, 5).without(label == 0)
  assert (taken.label == 0).sum() == 0 and (taken.label == -1).sum() == 5


def _blob(x, y, n=50, seed=0):
  rng = np.random.default_rng(seed)
  return np.c_[rng.uniform(x, x + 0.5, n), rng.uniform(y, y + 0.5, n), rng.uniform(0, 1, n)]


def test_cell_components_bridge_a_one_cell_gap_only_when_asked():
  # Cells of 0.3 m: the blobs' cells are 0-1 and 3-4 along x (one empty cell, 2, between them).
  two = np.concatenate([_blob(0.0, 0.0), _blob(0.9, 0.0, seed=1)])
  seeds = np.ones(len(two), bool)
  assert groups.cell_components(two, seeds, 0.3, bridge=True).count == 1
  apart = groups.cell_components(two, seeds, 0.3, bridge=False)
  assert apart.count == 2 and len(set(apart.label[:50])) == 1 and len(set(apart.label[50:])) == 1
  far = np.concatenate([_blob(0.0, 0.0), _blob(3.0, 0.0, seed=1)])
  assert groups.cell_components(far, seeds, 0.3, bridge=True).count == 2


def test_cell_components_give_points_in_seeded_cells_the_label_and_no_seeds_none():
  pts = _blob(0.0, 0.0)
  seeds = np.zeros(len(pts), bool)
  assert groups.cell_components(pts, seeds, 0.3, bridge=True).count == 0
  seeds[0] = True
  got = groups.cell_components(pts, seeds, 0.3, bridge=False)
  same_cell = (np.floor(pts[:, :2] / 0.3) == np.floor(pts[0, :2] / 0.3)).all(1)
  np.testing.assert_array_equal(got.label == 0, same_cell)
  assert (got.label[~same_cell] == -1).all()


def test_beats_by_margin_relative_margin_and_significance():
  rng = np.random.default_rng(0)
  other = rng.uniform(0.1, 0.3, 400)
  base = other + 0.1  # the other gains exactly 0.1 a point
  assert groups.beats(base, other, groups.Rule(margin=0.05))
  assert not groups.beats(base, other, groups.Rule(margin=0.15))
  # base's mean is ~0.3: a relative margin of 0.5 asks for ~0.15
  assert not groups.beats(base, other, groups.Rule(margin=0.05, relative_margin=0.5))
  # A gain of 0.1 on average with a spread of 1.0 a point: 400 points give a standard error of
  # ~0.05, so 3 standard errors (~0.15) are not reached and 1 (~0.05) is.
  noisy = other + 0.1 + rng.standard_normal(400) * 1.0
  noisy -= noisy.mean() - other.mean() - 0.1
  assert groups.beats(noisy, other, groups.Rule(margin=0.05, significance=1.0))
  assert not groups.beats(noisy, other, groups.Rule(margin=0.05, significance=3.0))


def test_beats_on_what_pc2_sees():
  base, other = np.full(10, 0.5), np.full(10, 0.1)
  rule = groups.Rule(margin=0.05, min_seen=0.3, min_paired=3)
  hidden = base.copy()
  hidden[:8] = np.nan  # pc2 sees 2 of 10 of the base placement: no evidence, the caller decides
  assert groups.beats(hidden, other, rule) is None
  unseen = other.copy()
  unseen[:8] = np.nan  # ... of the other placement: it cannot win
  assert groups.beats(base, unseen, rule) is False
  a, b = base.copy(), other.copy()
  a[:5], b[5:8] = np.nan, np.nan  # each seen on half and more, both on 2 points only
  assert groups.beats(a, b, rule) is False
  assert groups.beats(a, b, groups.Rule(margin=0.05, min_paired=2)) is True
