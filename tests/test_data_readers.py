"""Benchmark readers on small files written here in the exact layouts, on the real samples in
../shared/data when present, and the HDF5 round trip of every reader."""

import pathlib
import warnings

import numpy as np
import pytest

from jaxflow.data import DataError, Pair, open_dataset
from jaxflow.data import readers
from jaxflow.data.convert import convert

SHARED = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"
FT3D_REAL = SHARED / "FlyingThings3D_subset_processed_35m"
KITTI_REAL = SHARED / "KITTI_processed_occ_final"


def write_pair_folder(folder, pc1, pc2):
  folder.mkdir(parents=True)
  np.save(folder / "pc1.npy", pc1)
  np.save(folder / "pc2.npy", pc2)


def random_cloud(seed, n=50, scale=10.0):
  return (np.random.default_rng(seed).normal(size=(n, 3)) * scale).astype(np.float32)


def make_ft3d(root, train=(), val=()):
  """HPLFlowNet FT3D layout: stored clouds have z < 0 (the reader negates x and z)."""
  for sub, numbers in (("train", train), ("val", val)):
    for n in numbers:
      pc1 = random_cloud(n) - np.float32([0, 0, 20])
      write_pair_folder(root / sub / f"{n:07d}", pc1, pc1 + random_cloud(n + 1000) * 0.05)
  return root


# FT3D


def test_ft3d_split_sizes_match_design():
  train, val = readers.ft3d_split_positions("train"), readers.ft3d_split_positions("val")
  train_all = readers.ft3d_split_positions("train_all")
  assert (len(train), len(set(train)), len(val), len(set(val)), len(train_all)) == (4910, 4910, 2000, 2000, 17640)
  assert not set(train) & set(val) and not set(train_all) & set(val)
  assert set(train) <= set(train_all)
  assert np.array_equal(val, np.linspace(0, 19639, 2000).astype(int))
  assert (np.asarray(train)[[0, 1, 2]] == [1, 4, 8]).all()  # 0 is a validation index: replaced by 1


def test_ft3d_flip_cut_flow_by_hand(tmp_path):
  pc1 = np.float32([[1, 2, -10], [3, 4, -34.9], [5, 6, -35], [7, 8, -20], [0, 0, -5]])
  pc2 = np.float32([[1.5, 2, -11], [3, 4, -34], [5, 6, -30], [7, 8, -36], [0, 1, -5]])
  write_pair_folder(tmp_path / "train" / "0000004", pc1, pc2)
  ds = open_dataset(f"ft3d:{tmp_path}", "train")
  pair = ds[0]
  keep = [0, 1, 4]  # row 2: pc1.z = 35 (not < 35); row 3: pc2.z = 36
  flip = np.float32([-1, 1, -1])
  assert np.array_equal(pair.pc1, pc1[keep] * flip) and np.array_equal(pair.pc2, pc2[keep] * flip)
  assert np.array_equal(pair.flow, (pc2[keep] - pc1[keep]) * flip) and pair.mask.all()
  assert pair.pc1.dtype == pair.flow.dtype == np.float32 and pair.mask.dtype == bool
  assert pair.name == str(tmp_path / "train" / "0000004")


def test_ft3d_partial_splits_use_folder_numbers(tmp_path):
  # 0 and 9 are validation positions, 4 and 8941 (replacing validation 8940) in the quarter, 2 only in train_all.
  make_ft3d(tmp_path, train=(0, 2, 4, 9, 8941), val=(0, 1))
  names = {s: [pathlib.Path(p.name).name for p in open_dataset(f"ft3d:{tmp_path}", s)]
           for s in ("train", "val", "train_all", "test")}
  assert names == {"train": ["0000004", "0008941"], "val": ["0000000", "0000009"],
                   "train_all": ["0000002", "0000004", "0008941"], "test": ["0000000", "0000001"]}
  text = open_dataset(f"ft3d:{tmp_path}").describe()
  assert "2 pairs" in text and "partial: 5 of 19640" in text


def test_ft3d_file_problems_name_the_file(tmp_path):
  good = random_cloud(0)
  cases = [
      ("pc2.npy", None, "missing file"),
      ("pc1.npy", b"", "empty file"),
      ("pc1.npy", "cut", "truncated or corrupt"),
      ("pc1.npy", np.zeros((50, 4), np.float32), r"shape \(50, 4\), expected N x 3"),
      ("pc2.npy", good[:40], "40 rows but the first cloud has 50"),
      ("pc1.npy", np.full((50, 3), np.nan, np.float32), "only 0 point"),
  ]
  for k, (name, content, problem) in enumerate(cases):
    folder = tmp_path / str(k) / "train" / "0000004"
    write_pair_folder(folder, good, good)
    if content is None:
      (folder / name).unlink()
    elif isinstance(content, bytes):
      (folder / name).write_bytes(content)
    elif isinstance(content, str):
      (folder / name).write_bytes((folder / name).read_bytes()[:-7])
    else:
      np.save(folder / name, content)
    with warnings.catch_warnings(), pytest.raises(DataError, match=problem) as info:
      warnings.simplefilter("ignore")
      open_dataset(f"ft3d:{tmp_path / str(k)}")[0]
    assert str(folder) in str(info.value), problem


def test_ft3d_converts_dtypes_and_drops_nonfinite_rows(tmp_path):
  pc1 = random_cloud(0, scale=3.0).astype(np.float64) - [0, 0, 20]
  pc2 = (pc1 + 0.1).astype(np.float64)
  pc2[7, 1] = np.inf
  write_pair_folder(tmp_path / "train" / "0000004", pc1, pc2)
  with pytest.warns(UserWarning, match="dropped 1 of 50"):
    pair = open_dataset(f"ft3d:{tmp_path}")[0]
  assert pair.pc1.dtype == np.float32 and len(pair.pc1) == len(pair.pc2) == 49
  ints = np.arange(30).reshape(10, 3) - 30  # int64 clouds
  write_pair_folder(tmp_path / "train" / "0000008", ints, ints)
  pair = open_dataset(f"ft3d:{tmp_path}")[1]
  assert pair.pc1.dtype == np.float32 and len(pair.pc1) == 10 and np.array_equal(pair.pc1[0], [30, -29, 28])


def test_open_dataset_errors_name_the_problem(tmp_path):
  for spec, problem in [("nope:/x", "unknown dataset format 'nope'"), (f"ft3d:{tmp_path}/none", "missing dataset root"),
                        ("ft3d:", "missing root"), (f"ft3d:{tmp_path}", "missing FT3D folder"),
                        ("files:a.npy", "files:PC1,PC2"), ("synthetic_things:x", "COUNT"),
                        ("synthetic_cats", "unknown dataset format .synthetic_cats."), (f"h5:{tmp_path}/x.h5", "missing HDF5 file")]:
    with pytest.raises(DataError, match=problem):
      open_dataset(spec)
  make_ft3d(tmp_path, train=(4,))
  with pytest.raises(DataError, match="unknown FT3D split 'dev'"):
    open_dataset(f"ft3d:{tmp_path}", "dev")


# KITTI


def test_kitti_ground_and_depth_cut_by_hand(tmp_path):
  pc1 = np.float32([[0, -1.5, 10], [1, -1.5, 10], [2, 0, 34.9], [3, 0, 36], [4, -2, 20], [5, 1, 5], [6, -1, 8]])
  pc2 = np.float32([[0, -1.5, 11], [1, -1.3, 10], [2, 0, 35], [3, 0, 30], [4, -1.41, 21], [5, 1, 5.5], [6, -2, 8]])
  write_pair_folder(tmp_path / "000002", pc1, pc2)
  write_pair_folder(tmp_path / "000000", pc1, pc2)  # not a benchmark frame
  with pytest.warns(UserWarning, match="only 1 of the 142"):
    ds = open_dataset(f"kitti:{tmp_path}")
  assert len(ds) == 1 and "1 of 142" in ds.describe() and "1 folders outside" in ds.describe()
  pair = ds[0]
  keep = [1, 5, 6]  # 0, 4: ground in both frames; 2: pc2.z = 35; 3: pc1.z = 36
  assert np.array_equal(pair.pc1, pc1[keep]) and np.array_equal(pair.flow, pc2[keep] - pc1[keep])
  assert len(readers.KITTI_FRAMES) == len(set(readers.KITTI_FRAMES)) == 142


def test_kitti_without_benchmark_frames(tmp_path):
  write_pair_folder(tmp_path / "000000", random_cloud(0), random_cloud(0))
  with pytest.raises(DataError, match="none of the 142"):
    open_dataset(f"kitti:{tmp_path}")


# Argoverse, FlowNet3D, files


def test_argoverse_npz_and_track_indices(tmp_path):
  pc1, pc2 = random_cloud(1, 20), random_cloud(2, 25)
  flow = random_cloud(3, 20) * 0.01
  flow[4] = np.nan  # dropped: track index 6 becomes 5, index 4 disappears
  np.savez(tmp_path / "log1_0.npz", pc1=pc1, pc2=pc2, flow=flow, mask1_tracks_flow=np.array([1, 4, 6]),
           mask2_tracks_flow=np.array([0, 24]))
  ds = open_dataset(f"argoverse:{tmp_path}")
  with pytest.warns(UserWarning, match="dropped 1 of 20"):
    pair = ds[0]
  keep = np.arange(20) != 4
  assert np.array_equal(pair.pc1, pc1[keep]) and np.array_equal(pair.flow, flow[keep]) and pair.mask.all()
  with pytest.warns(UserWarning):
    idx1, idx2 = ds.tracks(0)
  assert idx1.tolist() == [1, 5] and idx2.tolist() == [0, 24]
  np.savez(tmp_path / "log1_1.npz", pc1=pc1, pc2=pc2)
  with pytest.raises(DataError, match=r"log1_1.npz: lacks arrays \['flow'\]"):
    ds = open_dataset(f"argoverse:{tmp_path}")
    ds[1]


def test_flownet3d_ft3do_and_kittio(tmp_path):
  ft, ki = tmp_path / "ft3do", tmp_path / "kittio"
  ft.mkdir(), ki.mkdir()
  pc1, pc2 = random_cloud(1, 30), random_cloud(2, 35)
  valid = np.arange(30) % 3 > 0
  for prefix in ("TRAIN", "TEST"):
    np.savez(ft / f"{prefix}_A_0000_left_0006.npz", points1=pc1, points2=pc2, color1=pc1 * 0, color2=pc2 * 0,
             flow=pc1 * 0.01, valid_mask1=valid)
  np.savez(ki / "000000.npz", pos1=pc1, pos2=pc2, gt=pc1 * 0.02)
  train, test = open_dataset(f"flownet3d:{ft}"), open_dataset(f"flownet3d:{ft}", "test")
  assert len(train) == len(test) == 1 and "TEST_" in test[0].name
  pair = train[0]
  assert np.array_equal(pair.mask, valid) and np.array_equal(pair.pc2, pc2) and np.array_equal(pair.flow, pc1 * 0.01)
  pair = open_dataset(f"flownet3d:{ki}")[0]
  assert pair.mask.all() and np.array_equal(pair.flow, pc1 * 0.02)
  with pytest.raises(DataError, match="only the test split"):
    open_dataset(f"flownet3d:{ki}", "train")


def test_files_dataset(tmp_path):
  np.save(tmp_path / "a.npy", random_cloud(1, 10))
  (tmp_path / "b.xyz").write_text("".join(f"{x} {y} {z}\n" for x, y, z in random_cloud(2, 12)))
  ds = open_dataset(f"files:{tmp_path}/a.npy,{tmp_path}/b.xyz")
  pair = ds[0]
  assert len(ds) == 1 and pair.pc1.shape == (10, 3) and pair.pc2.shape == (12, 3)
  assert not pair.flow.any() and not pair.mask.any()


# Real samples (skipped where ../shared/data is absent)


@pytest.mark.skipif(not FT3D_REAL.is_dir(), reason="real FT3D samples absent")
def test_real_ft3d_pair_0004164():
  ds = open_dataset(f"ft3d:{FT3D_REAL}", "train_all")
  pair = next(p for p in ds if p.name.endswith("0004164"))
  assert (pair.pc1[:, 2] > 0).all() and (pair.pc2[:, 2] > 0).all()
  assert (pair.pc1[:, 2] < 35).all() and (pair.pc2[:, 2] < 35).all()
  assert len(pair.pc1) == 16384 and 0.2 < np.linalg.norm(pair.flow, axis=1).mean() < 1.8 + 0.2


@pytest.mark.skipif(not KITTI_REAL.is_dir(), reason="real KITTI sample absent")
def test_real_kitti_000002_point_count():
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    ds = open_dataset(f"kitti:{KITTI_REAL}")
  pair = ds[0]
  assert pair.name.endswith("000002") and len(pair.pc1) == len(pair.pc2) == 40526


# HDF5 round trip of every reader


def _assert_same(a: Pair, b: Pair):
  for key in ("pc1", "pc2", "flow", "mask"):
    x, y = getattr(a, key), getattr(b, key)
    assert x.dtype == y.dtype and np.array_equal(x, y), key
  assert a.name == b.name


def test_hdf5_round_trip_of_every_reader(tmp_path):
  make_ft3d(tmp_path / "ft3d", train=(4, 8, 12))
  (tmp_path / "kitti").mkdir()
  write_pair_folder(tmp_path / "kitti" / "000002", random_cloud(5, 80), random_cloud(5, 80) + 0.1)
  write_pair_folder(tmp_path / "kitti" / "000003", random_cloud(6, 70), random_cloud(6, 70) + 0.1)
  (tmp_path / "argo").mkdir()
  np.savez(tmp_path / "argo" / "a.npz", pc1=random_cloud(1, 20), pc2=random_cloud(2, 22), flow=random_cloud(3, 20))
  (tmp_path / "fn3d").mkdir()
  np.savez(tmp_path / "fn3d" / "TRAIN_a.npz", points1=random_cloud(1, 9), points2=random_cloud(2, 11),
           flow=random_cloud(3, 9), valid_mask1=np.arange(9) % 2 == 0)
  np.save(tmp_path / "a.npy", random_cloud(7, 15))
  specs = [(f"ft3d:{tmp_path}/ft3d", "train"), (f"kitti:{tmp_path}/kitti", None), (f"argoverse:{tmp_path}/argo", None),
           (f"flownet3d:{tmp_path}/fn3d", "train"), (f"files:{tmp_path}/a.npy,{tmp_path}/a.npy", None),
           ("synthetic_things:2", "val"), ("synthetic_lidar:2", "test"), ("synthetic_mix:3", "train")]
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    for k, (spec, split) in enumerate(specs):
      out = tmp_path / f"out{k}.h5"
      convert(spec, split, out, progress=False)
      source, h5 = open_dataset(spec, split), open_dataset(f"h5:{out}")
      assert len(source) == len(h5) > 0 and h5.source == spec and spec in h5.describe()
      assert h5.up == source.up  # the file's clouds are in its source's frame
      for i in range(len(source)):
        _assert_same(h5[i], source[i])
