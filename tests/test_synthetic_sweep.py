"""The raw 360-degree sweep generator (jaxflow.data.synthetic_sweep)."""

import numpy as np
import pytest

from jaxflow.data import open_dataset
from jaxflow.data import synthetic_sweep as ss
from jaxflow.errors import DataError
from jaxflow.geometry import rigid


@pytest.fixture(scope="module")
def sweep():
  return ss.sweep_pair("val", 0)


def test_a_full_sweep_is_raw_z_up():
  s = ss.sweep_pair("test", 1)  # ~0.1 s on an idle 2-core CPU (benchmarks/METHODS.md): untimed here
  assert 60_000 < len(s.pc1) < 150_000 and 60_000 < len(s.pc2) < 150_000
  r = np.linalg.norm(s.pc1, axis=1)
  assert r.max() <= ss.MAX_RANGE + 0.1 and r.max() > 50
  azimuth = np.arctan2(s.pc1[:, 1], s.pc1[:, 0])
  assert (np.histogram(azimuth, 12, (-np.pi, np.pi))[0] > 100).all()  # 360 degrees
  ground_z = s.pc1[s.ground, 2]  # z up, the sensor ~1.7-2.1 m above the road
  assert -2.6 < np.median(ground_z) < -1.5
  assert 0.2 < s.ground.mean() < 0.8  # the ground is kept


def test_flows_are_rigid_per_object_and_the_ego_motion_is_the_backgrounds(sweep):
  s = sweep
  ego = s.pc1.astype(np.float64) @ s.ego_rotation.T + s.ego_translation - s.pc1
  np.testing.assert_allclose(s.ego_flow, ego, atol=2e-3)  # float32 coordinates at 100 m
  background = s.category == 0
  np.testing.assert_allclose(s.flow[background], s.ego_flow[background], atol=1e-6)
  assert np.linalg.det(s.ego_rotation) == pytest.approx(1.0)
  for inst in np.unique(s.instance[s.instance > 0]):
    sel = s.instance == inst
    if sel.sum() < 10:
      continue
    fit = rigid.kabsch(s.pc1[sel], s.pc1[sel] + s.flow[sel])  # each object moves rigidly
    np.testing.assert_allclose(fit.flow(s.pc1[sel]), s.flow[sel], atol=2e-3)
  assert set(np.unique(s.category)) <= {0, ss.BICYCLIST, ss.PEDESTRIAN, ss.REGULAR_VEHICLE}


def test_the_two_sweeps_are_sampled_independently(sweep):
  from scipy.spatial import cKDTree
  s = sweep
  d, _ = cKDTree(s.pc2).query(s.pc1 + s.flow)
  assert np.mean(d < 1e-3) < 0.01  # no shared rows: hardly any pc2 point is a moved pc1 point
  assert np.median(d) < 0.5  # but pc1 + flow lies on what pc2 sees


def test_splits_are_disjoint_and_pairs_deterministic():
  tiny = ss.Options(scale=0.05)
  a, b = ss.sweep_pair("val", 2, tiny), ss.sweep_pair("val", 2, tiny)
  np.testing.assert_array_equal(a.pc1, b.pc1)
  c = ss.sweep_pair("test", 2, tiny)
  assert a.pc1.shape != c.pc1.shape or not np.allclose(a.pc1, c.pc1)
  assert set(range(ss.SEED_BASE["val"], ss.SEED_BASE["val"] + 10**6)).isdisjoint(
    {ss.SEED_BASE["test"]})


def test_ego_speeds_span_parked_to_fast_and_scenes_hold_movers():
  speeds, dynamic = [], 0
  for i in range(12):
    s = ss.sweep_pair("val", i, ss.Options(scale=0.03))
    speeds.append(np.linalg.norm(s.ego_translation))
    dynamic += (np.linalg.norm(s.flow - s.ego_flow, axis=1) >= 0.05).sum()
  assert min(speeds) < 1.0 and max(speeds) > 1.5 and max(speeds) <= 3.0
  assert dynamic > 0
  parked = ss.sweep_pair("val", 0, ss.Options(speed=(0, 0), scale=0.03))
  assert np.abs(parked.ego_flow).max() < 1e-6


def test_registered_as_a_dataset_with_three_way_labels():
  ds = open_dataset("synthetic_sweep:2", "test")
  pair = ds[0]
  assert pair.has_labels and pair.mask.sum() > 0 and not pair.mask.all()
  with pytest.raises(DataError, match="split"):
    open_dataset("synthetic_sweep:2", "train")
  # A form by name: the pairs of sweep_pair with its options; a bad one is named.
  city = open_dataset("synthetic_sweep:1,form=city", "test")
  truth = ss.sweep_pair("test", 0, ss.FORMS["city"])
  np.testing.assert_array_equal(city[0].pc1, truth.pc1)
  assert city.name == "synthetic_sweep:1,form=city" and "city" in city.describe()
  with pytest.raises(DataError, match="form=one of generated, city, noground"):
    open_dataset("synthetic_sweep:1,form=town", "test")


def test_the_dataset_says_it_is_z_up_and_carries_the_av2_labels():
  """evaluate.py rotates synthetic_sweep's z-up clouds into the models' frame (`Dataset.up`) and
  reports the official breakdown from its categories (the sensor's x, y as the ego's)."""
  ds = open_dataset("synthetic_sweep:1", "test")
  assert ds.up == "z"
  pair, truth = ds[0], ss.sweep_pair("test", 0)
  np.testing.assert_array_equal(pair.category, truth.category)
  np.testing.assert_array_equal(pair.ego_xy, truth.pc1[:, :2])
  assert pair.category.dtype == np.uint8 and (pair.category != 0).any()


def test_the_frame_origin_the_city_and_the_sensors_vary_as_real_sweeps_do():
  plain = ss.sweep_pair("val", 2, ss.Options(scale=0.3))
  ego_frame = ss.sweep_pair("val", 2, ss.Options(origin_height=0.33, scale=0.3))
  shift = ego_frame.pc1 - plain.pc1  # the same scene and rays, the origin lower
  np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-4)
  assert shift[0, :2] == pytest.approx([0, 0], abs=1e-6) and shift[0, 2] > 1.0
  xy = ego_frame.pc1[:, :2]
  under = ego_frame.ground & (np.abs(xy[:, 1]) < 2) & (np.abs(xy[:, 0]) < 10)  # the ego's lane
  assert np.median(ego_frame.pc1[under, 2]) == pytest.approx(-0.33, abs=0.16)  # the crown
  for s in (plain, ego_frame):  # the ego-motion still moves every static point onto its flow
    static = s.category == 0
    moved = s.pc1[static] @ s.ego_rotation.T + s.ego_translation
    np.testing.assert_allclose(moved - s.pc1[static], s.ego_flow[static], atol=1e-4)
  near = lambda s: np.hypot(s.pc1[:, 0], s.pc1[:, 1]) < 20
  dense = ss.sweep_pair("val", 2, ss.Options(dense=True, scale=0.3))
  assert dense.ground[near(dense)].mean() < 0.35 < plain.ground[near(plain)].mean()

  def rings(s):  # occupied 0.2-degree elevation bins of the points beyond 10 m
    far = np.hypot(*s.pc1[:, :2].T) > 10
    return len(np.unique(np.floor(np.degrees(np.arctan2(s.pc1[far, 2], np.hypot(
      *s.pc1[far, :2].T))) / 0.2)))
  one = ss.sweep_pair("val", 2, ss.Options(beams=32, scale=0.3))
  two = ss.sweep_pair("val", 2, ss.Options(beams=32, stacked=True, scale=0.3))
  assert rings(two) > 1.5 * rings(one) and abs(len(two.pc1) / len(one.pc1) - 1) < 0.2


def test_a_pair_taken_backwards_undoes_the_forward_motions():
  """reverse=1: pc1 is the later sweep and its flow goes to the earlier one, so each object's
  backward motion (a rigid fit of its flow) composed with its forward one is the identity, and the
  forward ego-motion takes the backward static flow's ends home."""
  forward = ss.sweep_pair("val", 0, ss.FORMS["city"])
  ds = open_dataset("synthetic_sweep:1,form=city,reverse=1", "val")
  backward = ss.sweep_pair("val", 0, ss.Options(**{**vars(ss.FORMS["city"]), "reverse": True}))
  np.testing.assert_array_equal(ds[0].pc1, backward.pc1)
  assert ds.name == "synthetic_sweep:1,form=city,reverse=1" and "backwards" in ds.describe()
  np.testing.assert_array_equal(backward.pc1, forward.pc2)
  np.testing.assert_array_equal(backward.pc2, forward.pc1)
  home = (backward.pc1 + backward.ego_flow) @ forward.ego_rotation.T + forward.ego_translation
  np.testing.assert_allclose(home, backward.pc1, atol=1e-4)
  moving = 0
  for k in np.unique(forward.instance[forward.instance > 0]):
    there, back = forward.instance == k, backward.instance == k
    if there.sum() < 10 or back.sum() < 10:
      continue
    f = rigid.kabsch(forward.pc1[there].astype(float), (forward.pc1 + forward.flow)[there])
    b = rigid.kabsch(backward.pc1[back].astype(float), (backward.pc1 + backward.flow)[back])
    x = backward.pc1[back].astype(float)
    np.testing.assert_allclose(f.apply(b.apply(x)), x, atol=1e-3)
    moving += np.linalg.norm(backward.flow[back] - backward.ego_flow[back], axis=1).mean() > 0.05
  assert moving >= 3
  with pytest.raises(DataError, match="reverse=0|1"):
    open_dataset("synthetic_sweep:1,reverse=yes", "val")


def test_no_car_stands_on_the_ego_car():
  """The ego car drives at the origin (2 m wide): no object's point lies on its footprint, in
  the narrow city's lanes too (a car there once scored as a mover overlapping the sensor)."""
  for i in range(8):
    for form in ("city", "generated"):
      s = ss.sweep_pair("val", i, ss.Options(**{**vars(ss.FORMS[form]), "scale": 0.2}))
      on = (s.instance > 0) & (np.abs(s.pc1[:, 1]) < 0.9) & (np.abs(s.pc1[:, 0]) < 2.5)
      assert not on.any(), (form, i, np.unique(s.instance[on]))


def _movers(s):
  """(category, speed m a frame, range m, lateral m, forward m) of each moving instance of pc1."""
  speed = np.linalg.norm(s.flow - s.ego_flow, axis=1)
  out = []
  for k in np.unique(s.instance[s.instance > 0]):
    mine = s.instance == k
    centre = s.pc1[mine].mean(0)
    if np.median(speed[mine]) >= 0.05:  # av2's dynamic threshold
      out.append((int(s.category[mine][0]), float(np.median(speed[mine])),
                  float(np.hypot(*centre[:2])), float(centre[1]), float(centre[0])))
  return out


@pytest.mark.parametrize("form", ["generated", "city"])
def test_the_movers_move_at_the_worlds_speeds(form):
  """Cars at every speed from 0.05 to 3 m a frame (many slow: stopping, starting, queueing), a car
  passing close beside the sensor, walkers 10-25 m away: what real streets show and the held-out
  AV2 street's misses were (a slow car, a walker at 18 m, a car passing 5 m beside)."""
  movers = [m for i in range(8)
            for m in _movers(ss.sweep_pair("val", i, ss.Options(**{**vars(ss.FORMS[form]),
                                                                   "scale": 0.2})))]
  cars = np.array([m[1] for m in movers if m[0] == ss.REGULAR_VEHICLE])
  walkers = [m for m in movers if m[0] == ss.PEDESTRIAN]
  assert cars.min() < 0.1 and cars.max() > (1.2 if form == "city" else 2.5)
  assert ((cars >= 0.05) & (cars < 0.3)).sum() >= (0.4 if form == "city" else 0.25) * len(cars)
  passing = [m for m in movers if m[0] == ss.REGULAR_VEHICLE and abs(m[3]) < 6 and abs(m[4]) < 3]
  assert len(passing) >= 2
  far = [m for m in walkers if 10 <= m[2] <= 25]
  assert len(far) >= 4 and all(0.05 <= m[1] <= 0.2 for m in walkers)
