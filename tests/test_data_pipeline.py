"""sample_pair, augmentation, BatchLoader (determinism, resume, broken pairs) and eval_batches."""

import warnings

import numpy as np
import pytest

from jaxflow.data import BatchLoader, DataError, Pair, eval_batches, sample_pair
from jaxflow.data.readers import Dataset
from jaxflow.data.sampling import augment_pair, crop_pair
from jaxflow.errors import ConfigError


class Numbered(Dataset):
  """Pair i: pc1 rows (i, row, 0), flow = 2 * pc1 + 1, pc2 rows (i, -row, 1); sizes vary; some broken."""

  def __init__(self, n=10, sizes=None, broken=()):
    self.n, self.sizes, self.broken = n, sizes or {}, set(broken)
    self.name = "numbered"

  def __len__(self):
    return self.n

  def load(self, i):
    if i in self.broken:
      raise DataError(f"/data/{i:04d}/pc1.npy", "truncated or corrupt .npy file")
    m = self.sizes.get(i, 40)
    rows = np.arange(m, dtype=np.float32)
    pc1 = np.stack([np.full(m, i, np.float32), rows, np.zeros(m, np.float32)], axis=1)
    pc2 = np.stack([np.full(m + 3, i, np.float32), -np.arange(m + 3, dtype=np.float32), np.ones(m + 3, np.float32)], 1)
    return Pair(pc1=pc1, pc2=pc2, flow=2 * pc1 + 1, mask=rows % 2 == 0, name=f"pair{i}")


def test_sample_pair_keeps_pc1_rows_together_and_samples_pc2_independently():
  pair = Numbered()[3]
  sampled, replaced = sample_pair(pair, 16, np.random.default_rng(0))
  assert replaced == 0 and sampled.pc1.shape == sampled.pc2.shape == (16, 3)
  assert np.array_equal(sampled.flow, 2 * sampled.pc1 + 1)  # flow and mask follow the pc1 rows
  assert np.array_equal(sampled.mask, sampled.pc1[:, 1] % 2 == 0)
  assert len(set(sampled.pc1[:, 1])) == 16 and len(set(sampled.pc2[:, 1])) == 16  # without replacement
  assert not np.array_equal(sampled.pc1[:, 1], -sampled.pc2[:, 1])  # independent indices


def test_sample_pair_with_replacement_counts_clouds():
  pair = Numbered(sizes={0: 10})[0]  # pc1 10 points, pc2 13
  sampled, replaced = sample_pair(pair, 12, np.random.default_rng(1))
  assert replaced == 1 and set(sampled.pc1[:, 1]) == set(range(10))  # every point at least once
  sampled, replaced = sample_pair(pair, 20, np.random.default_rng(1))
  assert replaced == 2 and sampled.name == "pair0"


def test_augmentation_transforms_flow_consistently():
  rng = np.random.default_rng(0)
  pc1, pc2, flow = (rng.normal(size=(30, 3)).astype(np.float32) for _ in range(3))
  pair = Pair(pc1=pc1, pc2=pc2, flow=flow, mask=np.ones(30, bool), name="random")
  aug = augment_pair(pair, {"rotation_deg": 30, "scale": (0.9, 1.1)}, np.random.default_rng(5))
  # Recover the similarity transform from pc1 and check pc1 + flow maps the same way.
  m, *_ = np.linalg.lstsq(pair.pc1.astype(float), aug.pc1.astype(float), rcond=None)
  np.testing.assert_allclose((pair.pc1 + pair.flow) @ m, aug.pc1 + aug.flow, atol=1e-4)
  np.testing.assert_allclose(pair.pc2 @ m, aug.pc2, atol=1e-4)
  assert not np.allclose(m, np.eye(3)) and np.allclose(m[1], [0, m[1, 1], 0], atol=1e-6)  # about y
  jittered = augment_pair(pair, {"jitter": 0.01}, np.random.default_rng(5))
  assert np.array_equal(jittered.flow, pair.flow) and 0 < np.abs(jittered.pc1 - pair.pc1).max() <= 0.03 + 1e-6
  assert augment_pair(pair, {}, np.random.default_rng(5)) is pair
  with pytest.raises(ConfigError, match="unknown keys"):
    BatchLoader(Numbered(), 2, 8, seed=0, augment={"flip": True})


def test_crop_pair_takes_the_windows_nearest_the_centre_and_its_image():
  rng = np.random.default_rng(0)
  pc1 = rng.uniform(-5, 5, (300, 3)).astype(np.float32)
  flow = np.full((300, 3), [2.0, 0.0, 0.0], np.float32)  # the whole scene moves 2 m in x
  pc2 = (pc1 + flow)[rng.permutation(300)][:280]
  pair = Pair(pc1=pc1, pc2=pc2, flow=flow, mask=np.arange(300) % 3 == 0, name="scene")
  crop = crop_pair(pair, 50, np.random.default_rng(7))
  assert crop.pc1.shape == crop.pc2.shape == (50, 3) and crop.name == "scene"
  # Rows stay together: flow and mask are those of the pc1 rows kept.
  rows = [int(np.flatnonzero((pc1 == p).all(1))[0]) for p in crop.pc1]
  assert np.array_equal(crop.flow, flow[rows])
  assert np.array_equal(crop.mask, np.array(rows) % 3 == 0)
  # Independent check: some pc1 point c has exactly these 50 nearest neighbours (a plain loop), and
  # pc2's window is the 50 pc2 points nearest c + 2 m in x.
  centres = []
  for c in range(300):
    order = sorted(range(300), key=lambda j: float(np.sum((pc1[j] - pc1[c]) ** 2)))
    if set(order[:50]) == set(rows):
      centres.append(c)
  assert len(centres) >= 1
  target = pc1[centres[0]] + flow[centres[0]]
  want = sorted(range(280), key=lambda j: float(np.sum((pc2[j] - target) ** 2)))[:50]
  assert {tuple(p) for p in crop.pc2} == {tuple(pc2[j]) for j in want}
  # Most pc1 points of the window land inside the pc2 window's extent: it follows the motion.
  moved = crop.pc1 + crop.flow
  inside = np.all((moved >= crop.pc2.min(0) - 0.5) & (moved <= crop.pc2.max(0) + 0.5), axis=1)
  assert inside.mean() > 0.8
  with pytest.raises(ConfigError, match="fewer than the window"):
    crop_pair(pair, 290, np.random.default_rng(0))  # pc2 has 280


class Jumps(Dataset):
  """Pair i: 400 points in a 10 m cube moving 2 m in x, a fifth of them 30 m instead."""

  name = "jumps"

  def __len__(self):
    return 4

  def load(self, i):
    rng = np.random.default_rng(i + 1)
    pc1 = rng.uniform(0, 10, (400, 3)).astype(np.float32)
    far = rng.random(400) < 0.2  # far beyond any 50-point window
    flow = np.where(far[:, None], [30.0, 0, 0], [2.0, 0, 0]).astype(np.float32)
    return Pair(pc1=pc1, pc2=pc1 + flow, flow=flow, mask=np.ones(400, bool), name=f"jump{i}")


def test_crop_pair_masks_the_points_whose_flow_leaves_the_pc2_window():
  pair = Jumps()[0]
  for seed in range(6):
    plain = crop_pair(pair, 50, np.random.default_rng(seed))
    masked = crop_pair(pair, 50, np.random.default_rng(seed), mask_outside=True)
    # The same windows; only the mask changes.
    assert np.array_equal(plain.pc1, masked.pc1) and np.array_equal(plain.pc2, masked.pc2)
    assert plain.mask.all()
    # pc2's window gathers the points moved like the centre, so the window's points kept are
    # exactly those that moved like it (the centre among them); each window holds both groups.
    kept_motions = set(masked.flow[masked.mask, 0].tolist())
    assert len(kept_motions) == 1
    assert np.array_equal(masked.mask, masked.flow[:, 0] == kept_motions.pop())
    assert 0 < masked.mask.sum() < 50


def test_loader_crops_windows_at_the_sampled_density():
  ds = Numbered(n=6, sizes={i: 200 for i in range(6)})
  plain = BatchLoader(ds, 2, 16, seed=3, prefetch=0)
  cropped = BatchLoader(ds, 2, 16, seed=3, prefetch=0, crop_from=120)
  a, b = cropped.batch(1), cropped.batch(1)
  assert a["pc1"].shape == (2, 16, 3) and np.array_equal(a["pc1"], b["pc1"])  # deterministic
  assert np.array_equal(a["flow"], 2 * a["pc1"] + 1)
  # Pair rows are (i, row, 0): a window of 16 of 120 rows sampled from 200 spans far fewer rows
  # than 16 rows sampled from all 200.
  span = lambda batch: np.ptp(batch["pc1"][:, :, 1], axis=1)
  assert span(a).max() < 60 and span(plain.batch(1)).min() > 100
  # crop_mask_outside reaches crop_pair: the same windows, the jumping points out of the loss.
  loaders = [BatchLoader(Jumps(), 2, 50, seed=3, prefetch=0, crop_from=400, crop_mask_outside=m)
             for m in (False, True)]
  kept, masked = (loader.batch(0) for loader in loaders)
  assert np.array_equal(kept["pc1"], masked["pc1"]) and kept["mask"].all()
  assert 0 < masked["mask"].sum() < kept["mask"].sum()
  with pytest.raises(ConfigError, match="crop_from"):
    BatchLoader(ds, 2, 16, seed=0, crop_from=8)


def _ids(batch):
  return batch["pc1"][:, 0, 0].astype(int).tolist()


def test_batch_is_a_function_of_seed_and_step():
  ds = Numbered(n=10)
  a, b = BatchLoader(ds, 3, 16, seed=7), BatchLoader(ds, 3, 16, seed=7, prefetch=0)
  assert a.steps_per_epoch == 3  # 10 // 3: the last incomplete batch dropped
  epoch0 = sum((_ids(a.batch(s)) for s in range(3)), [])
  assert len(set(epoch0)) == 9
  assert epoch0 == a.order(0)[:9].tolist() and a.order(0).tolist() != a.order(1).tolist()
  for step in (0, 4, 11):
    x, y = a.batch(step), b.batch(step)
    assert all(np.array_equal(x[k], y[k]) for k in ("pc1", "pc2", "flow", "mask")) and x["replaced"] == 0
  assert x["pc1"].dtype == x["mask"].dtype == np.float32 and x["mask"].shape == (3, 16)
  c = BatchLoader(ds, 3, 16, seed=8)
  assert not np.array_equal(a.batch(0)["pc1"], c.batch(0)["pc1"])
  assert _ids(BatchLoader(ds, 3, 16, seed=7, shuffle=False).batch(1)) == [3, 4, 5]


def test_iterate_prefetches_the_same_batches_and_resumes():
  loader = BatchLoader(Numbered(n=8), 2, 8, seed=3, prefetch=3)
  it = loader.iterate(start_step=5)
  got = [next(it) for _ in range(4)]
  it.close()
  assert [s for s, _ in got] == [5, 6, 7, 8]
  for step, batch in got:
    assert np.array_equal(batch["pc2"], loader.batch(step)["pc2"])


def test_skip_broken_replaces_by_the_next_pair_in_order():
  ds = Numbered(n=6, broken={2})
  loader = BatchLoader(ds, 6, 8, seed=0, shuffle=False, skip_broken=True)
  with pytest.warns(UserWarning, match="skipping broken pair: /data/0002/pc1.npy"):
    batch = loader.batch(0)
  assert _ids(batch) == [0, 1, 3, 3, 4, 5] and len(loader.broken) == 1 and "0002/pc1.npy" in loader.broken[0]
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # reported once only
    assert _ids(loader.batch(1)) == [0, 1, 3, 3, 4, 5]
  strict = BatchLoader(ds, 2, 8, seed=0, shuffle=False)
  it = strict.iterate()
  next(it)
  with pytest.raises(DataError, match="0002/pc1.npy"):  # raised in the worker, surfaces here
    next(it)


def test_worker_processes_give_the_same_batches_and_errors(tmp_path):
  loader = BatchLoader(Numbered(n=8, broken={5}), 2, 8, seed=3, workers=2, skip_broken=True)
  it = loader.iterate(start_step=2)
  with pytest.warns(UserWarning, match="skipping broken pair: /data/0005"):
    got = [next(it) for _ in range(5)]
  it.close()
  assert [s for s, _ in got] == [2, 3, 4, 5, 6] and len(loader.broken) == 1
  reference = BatchLoader(Numbered(n=8, broken={5}), 2, 8, seed=3, skip_broken=True)
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    for step, batch in got:
      assert all(np.array_equal(batch[k], reference.batch(step)[k]) for k in ("pc1", "pc2", "flow", "mask"))
  strict = BatchLoader(Numbered(n=4, broken={1}), 4, 8, seed=0, workers=1)
  with pytest.raises(DataError, match="0001/pc1.npy: truncated"):
    next(strict.iterate())


def test_replaced_counts_small_clouds():
  loader = BatchLoader(Numbered(n=4, sizes={1: 5}), 4, 20, seed=0, shuffle=False)
  assert loader.batch(0)["replaced"] == 2  # pair 1: pc1 has 5 points, pc2 8, both < 20; the others 40 and 43
  loader = BatchLoader(Numbered(n=4, sizes={1: 5}), 4, 6, seed=0, shuffle=False)
  assert loader.batch(0)["replaced"] == 1


def test_eval_batches_cover_every_pair_once_with_padding():
  ds = Numbered(n=5)
  batches = list(eval_batches(ds, 2, 16, seed=1))
  again = list(eval_batches(ds, 2, 16, seed=1, prefetch=0))
  assert [b["names"] for b in batches] == [["pair0", "pair1"], ["pair2", "pair3"], ["pair4", "pair4"]]
  assert [b["pair_valid"].tolist() for b in batches] == [[1, 1], [1, 1], [1, 0]]
  for x, y in zip(batches, again):
    assert all(np.array_equal(x[k], y[k]) for k in ("pc1", "pc2", "flow", "mask"))
  first, _ = sample_pair(ds[3], 16, np.random.default_rng((1, 3)))
  assert np.array_equal(batches[1]["pc2"][1], first.pc2)
  whole = list(eval_batches(ds, 1, None))
  assert len(whole) == 5 and whole[0]["pc1"].shape == (1, 40, 3) and whole[0]["pc2"].shape == (1, 43, 3)
  with pytest.raises(ConfigError, match="batch_size 1"):
    eval_batches(ds, 2, None)
  with pytest.raises(DataError, match="0001/pc1.npy"):
    list(eval_batches(Numbered(n=3, broken={1}), 1, 8))


def test_loader_argument_errors():
  with pytest.raises(ConfigError, match="fewer than batch_size"):
    BatchLoader(Numbered(n=3), 4, 8, seed=0)
  with pytest.raises(ConfigError):
    BatchLoader(Numbered(n=3), 1, 0, seed=0)
