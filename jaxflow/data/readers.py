"""Benchmark datasets (FT3D, KITTI, Argoverse, FlowNet3D's FT3Do/KITTIo) as `Pair`s, registered
with `jaxflow.data.registry`.

Every reader returns full-resolution clouds after its own cuts (each reader's docstring says which),
float32 with a bool mask, and names the file in every error. Readers are lazy: opening lists the
folders, `ds[i]` reads pair i.
"""

import pathlib
import re
import warnings
import zipfile

import numpy as np

from jaxflow.data.pointfiles import MIN_POINTS, drop_nonfinite, load_npy, read_points, to_float32
from jaxflow.data.registry import Dataset, Pair, register
from jaxflow.errors import DataError

DEPTH_LIMIT = 35.0  # metres: both FT3D and KITTI keep pc1.z < 35 and pc2.z < 35.
GROUND_Y = -1.4  # KITTI: a point is ground when pc1.y and pc2.y are both below this.

FT3D_TRAIN_TOTAL = 19640  # folders in FlyingThings3D_subset_processed_35m/train
FT3D_VAL_COUNT = 2000
FT3D_TEST_TOTAL = 3824  # folders in .../val, the test set
FT3D_SPLITS = ("train", "val", "test", "train_all")

# The 142 KITTI Scene Flow 2015 frames of the HPLFlowNet benchmark.
KITTI_FRAMES = (2, 3, *range(7, 82), *range(83, 87), *range(88, 99), *range(105, 133),
                *range(141, 151), 155, *range(157, 165), 168, 169, 199)


def ft3d_keep(pc1_Nx3, pc2_Nx3) -> np.ndarray:
  """FT3D cut (after the x, z flip): keep pc1.z < 35 and pc2.z < 35."""
  return (pc1_Nx3[:, 2] < DEPTH_LIMIT) & (pc2_Nx3[:, 2] < DEPTH_LIMIT)


def kitti_keep(pc1_Nx3, pc2_Nx3) -> np.ndarray:
  """KITTI cuts: drop ground (pc1.y and pc2.y both < -1.4), keep pc1.z < 35 and pc2.z < 35."""
  ground_N = (pc1_Nx3[:, 1] < GROUND_Y) & (pc2_Nx3[:, 1] < GROUND_Y)
  return ~ground_N & ft3d_keep(pc1_Nx3, pc2_Nx3)


def ft3d_split_positions(split: str, total: int = FT3D_TRAIN_TOTAL) -> np.ndarray:
  """Positions (in the sorted train/ listing) of an FT3D split.

  "val": the 2000 positions np.linspace(0, 19639, 2000).astype(int). "train_all": all the others
  (17640, what FLOT's and PV-RAFT's loaders train on). "train": the paper's quarter, 4910 pairs:
  4910 = 19640 / 4 is every 4th position of the full list (0, 4, 8, ...), while every 4th of the
  17640 non-validation pairs would give only 4410. The 500 of those positions that are validation
  indices are each replaced by the next position (never a validation index: they lie >= 9 apart,
  and never ≡ 0 mod 4), so "train" has exactly 4910 pairs and is disjoint from "val".
  """
  val = np.linspace(0, total - 1, FT3D_VAL_COUNT).astype(int)
  if split == "val":
    return val
  is_val = np.zeros(total + 1, bool)
  is_val[val] = True
  if split == "train_all":
    return np.flatnonzero(~is_val[:total])
  if split == "train":
    quarter = np.arange(0, total, 4)
    return np.where(is_val[quarter], quarter + 1, quarter)
  raise ValueError(split)


def _numbered_dirs(folder: pathlib.Path, digits: int | None = None):
  pattern = re.compile(r"\d+" if digits is None else rf"\d{{{digits}}}")
  return sorted(p for p in folder.iterdir() if p.is_dir() and pattern.fullmatch(p.name))


def _check_root(root) -> pathlib.Path:
  root = pathlib.Path(root).expanduser()
  if not root.exists():
    raise DataError(root, "missing dataset root")
  return root


def _check_shape(array, path, what: str, rows: int | None = None) -> np.ndarray:
  array = to_float32(array, path, what)
  if array.ndim != 2 or array.shape[1] != 3:
    raise DataError(path, f"{what} has shape {array.shape}, expected N x 3")
  if rows is not None and len(array) != rows:
    raise DataError(path, f"{what} has {len(array)} rows but the first cloud has {rows}: "
                    "rows must correspond")
  if len(array) == 0:
    raise DataError(path, f"{what} is empty (0 points)")
  return array


def read_corresponding(folder: pathlib.Path):
  """pc1.npy, pc2.npy of an HPLFlowNet folder (rows correspond), non-finite rows dropped from both."""
  p1, p2 = folder / "pc1.npy", folder / "pc2.npy"
  pc1 = _check_shape(load_npy(p1), p1, "pc1")
  pc2 = _check_shape(load_npy(p2), p2, "pc2", rows=len(pc1))
  finite_N = np.isfinite(pc1).all(1) & np.isfinite(pc2).all(1)
  pc1 = drop_nonfinite(pc1, finite_N, folder, "pc1/pc2")
  return pc1, (pc2 if finite_N.all() else pc2[finite_N])


def _cut_pair(pc1, pc2, keep_N, folder, what: str) -> Pair:
  rows = np.flatnonzero(keep_N)
  pc1, pc2 = pc1.take(rows, axis=0), pc2.take(rows, axis=0)  # take: faster than boolean rows
  if len(pc1) < MIN_POINTS:
    raise DataError(folder, f"only {len(pc1)} points left after {what}, need at least {MIN_POINTS}")
  return Pair(pc1=pc1, pc2=pc2, flow=pc2 - pc1, mask=np.ones(len(pc1), bool), name=str(folder))


class FT3D(Dataset):
  """HPLFlowNet FlyingThings3D: ROOT/{train,val}/NNNNNNN/pc1.npy, pc2.npy.

  x and z negated on load (stored x right, y up, z backward -> x left, y up, z forward: a rotation
  about y, jaxflow.geometry.frames), pc1.z < 35 and pc2.z < 35 kept, flow = pc2 - pc1, mask all
  True. The stored frame: HPLFlowNet's pixel2pc turns FlyingThings3D's (negative) disparities d
  into x = (u - cx) / |d|, y = -(v - cy) / |d|, z = -f / |d| (u right, v down in the image). Splits (see `ft3d_split_positions`): "train" (4910), "val" (2000), "train_all" (17640) from
  train/; "test" is val/ (3824). With fewer than 19640 train/ folders the split rules use each
  folder's number as its position (the full set is numbered 0 .. 19639), and describe() says the
  split is partial.
  """
  up = "y"  # x left, y up, z forward: the models' frame

  def __init__(self, root, split: str | None = None):
    self.root = _check_root(root)
    self.split = split or "train"
    if self.split not in FT3D_SPLITS:
      raise DataError(self.root, f"unknown FT3D split {self.split!r}; expected one of {FT3D_SPLITS}")
    self.name = f"ft3d:{self.root}"
    sub = self.root / ("val" if self.split == "test" else "train")
    if not sub.is_dir():
      raise DataError(sub, "missing FT3D folder")
    found = _numbered_dirs(sub)
    self.found = len(found)
    if self.split == "test":
      self.folders, total = found, FT3D_TEST_TOTAL
      self.note = "" if len(found) == total else f"partial: {len(found)} of {total} val/ folders"
      return
    total = FT3D_TRAIN_TOTAL
    if len(found) == total:
      positions, self.note = np.arange(total), ""
    else:
      numbers = [int(p.name) for p in found]
      if all(n < total for n in numbers):
        positions, how = np.array(numbers, int), "positions from folder numbers"
      else:
        positions, how = np.arange(len(found)), "positions from the sorted listing"
      self.note = f"partial: {len(found)} of {total} train/ folders, {how}"
    wanted = np.zeros(max(total, int(positions.max(initial=0)) + 1) + 1, bool)
    wanted[ft3d_split_positions(self.split, total)] = True
    self.folders = [f for f, pos in zip(found, positions) if wanted[pos]]

  def __len__(self):
    return len(self.folders)

  def load(self, i):
    folder = self.folders[i]
    pc1, pc2 = read_corresponding(folder)
    for cloud in (pc1, pc2):  # in place, column by column: both are fresh arrays
      cloud[:, 0] *= -1
      cloud[:, 2] *= -1
    return _cut_pair(pc1, pc2, ft3d_keep(pc1, pc2), folder, "the 35 m depth cut")

  def describe(self):
    note = f" ({self.note})" if self.note else ""
    return f"{self.name} split={self.split}: {len(self)} pairs from {self.found} folders found{note}"


class KITTI(Dataset):
  """HPLFlowNet KITTI Scene Flow 2015: ROOT/NNNNNN/pc1.npy, pc2.npy, the 142 benchmark frames only.

  No flip (stored x left, y up, z forward: HPLFlowNet's files hold the camera's x right, y down,
  z forward with x and y negated, a rotation about z, jaxflow.geometry.frames);
  ground removed (pc1.y and pc2.y both < -1.4); pc1.z < 35 and pc2.z < 35 kept; flow = pc2 - pc1;
  mask all True. Folders outside the benchmark list are ignored; a root with only some benchmark
  frames is read with a warning, and describe() says how many.
  """
  up = "y"  # x left, y up, z forward: the models' frame, ground near y = -1.6

  def __init__(self, root, split: str | None = None):
    self.root = _check_root(root)
    if split not in (None, "test"):
      raise DataError(self.root, f"KITTI has only the test split, got {split!r}")
    self.name = f"kitti:{self.root}"
    found = _numbered_dirs(self.root, digits=6)
    frames = set(KITTI_FRAMES)
    self.folders = [p for p in found if int(p.name) in frames]
    self.ignored = len(found) - len(self.folders)
    if not self.folders:
      raise DataError(self.root, f"none of the {len(KITTI_FRAMES)} KITTI benchmark frames "
                      "(folders NNNNNN with pc1.npy, pc2.npy) found")
    if len(self.folders) < len(KITTI_FRAMES):
      warnings.warn(f"{self.root}: only {len(self.folders)} of the {len(KITTI_FRAMES)} KITTI "
                    "benchmark frames found", stacklevel=2)

  def __len__(self):
    return len(self.folders)

  def load(self, i):
    folder = self.folders[i]
    pc1, pc2 = read_corresponding(folder)
    return _cut_pair(pc1, pc2, kitti_keep(pc1, pc2), folder, "ground removal and the 35 m cut")

  def describe(self):
    notes = []
    if len(self) < len(KITTI_FRAMES):
      notes.append(f"partial: {len(self)} of {len(KITTI_FRAMES)} benchmark frames")
    if self.ignored:
      notes.append(f"{self.ignored} folders outside the benchmark list ignored")
    note = f" ({'; '.join(notes)})" if notes else ""
    return f"{self.name}: {len(self)} pairs{note}"


def _load_npz(path: pathlib.Path):
  try:
    with np.load(path, allow_pickle=False) as z:
      return {k: z[k] for k in z.files}
  except (ValueError, EOFError, OSError, zipfile.BadZipFile, KeyError) as e:
    raise DataError(path, f"truncated or corrupt .npz file ({e})") from None


def _need(arrays: dict, keys, path):
  missing = [k for k in keys if k not in arrays]
  if missing:
    raise DataError(path, f"lacks arrays {missing} (has {sorted(arrays)})")


def _rows_with_flow(pc1, flow, path, extra=()):
  """Drops rows where pc1 or flow is non-finite (from extras too): pc1, flow, extras, kept rows."""
  finite_N = np.isfinite(pc1).all(1) & np.isfinite(flow).all(1)
  pc1 = drop_nonfinite(pc1, finite_N, path, "pc1/flow")
  if finite_N.all():
    return pc1, flow, list(extra), finite_N
  return pc1, flow[finite_N], [e[finite_N] for e in extra], finite_N


def _remap(idx, kept_N, key, path):
  """Index array (or bool mask) into the stored rows -> indices into the kept rows."""
  idx = np.asarray(idx)
  if idx.dtype == bool and idx.shape == kept_N.shape:
    idx = np.flatnonzero(idx)
  n = len(kept_N)
  if idx.dtype.kind not in "iu" or idx.ndim != 1 or (idx.size and not 0 <= idx.min() <= idx.max() < n):
    raise DataError(path, f"{key} is not an index array into the {n} points")
  new_index_N = np.cumsum(kept_N) - 1
  return new_index_N[idx[kept_N[idx]]]


def _npz_files(root: pathlib.Path, pattern: str):
  if root.is_file():
    return [root]
  return sorted(root.rglob(pattern))


class Argoverse(Dataset):
  """NSFP's Argoverse scene flow: one .npz per pair (pc1, pc2, flow, mask1/2_tracks_flow).

  Ground is already removed and flow includes ego-motion; mask is all True (evaluation uses every
  pc1 point that has flow). The track masks are not part of Pair: `tracks(i)` returns them as
  integer index arrays into pair i's pc1 and pc2 (after any non-finite rows are dropped), for
  NSFP-style sampling (80% of a sampled cloud from tracked points).
  """
  up = "y"  # as stored, not rotated: the models' frame assumed

  def __init__(self, root, split: str | None = None):
    self.root = _check_root(root)
    self.name = f"argoverse:{self.root}"
    self.files = _npz_files(self.root, "*.npz")
    if not self.files:
      raise DataError(self.root, "no .npz pairs found")

  def __len__(self):
    return len(self.files)

  def _read(self, i):
    path = self.files[i]
    arrays = _load_npz(path)
    _need(arrays, ("pc1", "pc2", "flow"), path)
    pc1 = _check_shape(arrays["pc1"], path, "pc1")
    flow = _check_shape(arrays["flow"], path, "flow", rows=len(pc1))
    pc2 = _check_shape(arrays["pc2"], path, "pc2")
    pc1, flow, _, kept1 = _rows_with_flow(pc1, flow, path)
    kept2 = np.isfinite(pc2).all(1)
    pc2 = drop_nonfinite(pc2, kept2, path, "pc2")
    empty = np.zeros(0, np.int64)
    tracks = [_remap(arrays.get("mask1_tracks_flow", empty), kept1, "mask1_tracks_flow", path),
              _remap(arrays.get("mask2_tracks_flow", empty), kept2, "mask2_tracks_flow", path)]
    pair = Pair(pc1=pc1, pc2=pc2, flow=flow, mask=np.ones(len(pc1), bool), name=str(path))
    return pair, tracks

  def load(self, i):
    return self._read(i)[0]

  def tracks(self, i):
    """(idx1, idx2): indices of pc1 and pc2 points on tracked objects (NSFP's track masks)."""
    return tuple(self._read(i)[1])

  def describe(self):
    return f"{self.name}: {len(self)} pairs"


class FlowNet3D(Dataset):
  """FlowNet3D's occluded variants, one .npz per pair, clouds as stored (no flip, no cut).

  FT3Do: points1, points2, color1, color2, flow, valid_mask1 (mask = valid_mask1, the non-occluded
  points); files TRAIN_*.npz and TEST_*.npz select the split ("train" by default). KITTIo:
  pos1, pos2, gt (mask all True); all *.npz of the root form the one (test) split.
  """
  up = "y"  # as stored, not rotated: the models' frame assumed

  def __init__(self, root, split: str | None = None):
    self.root = _check_root(root)
    self.name = f"flownet3d:{self.root}"
    files = _npz_files(self.root, "*.npz")
    prefixed = [f for f in files if f.name.startswith(("TRAIN_", "TEST_"))]
    if prefixed:
      self.split = split or "train"
      if self.split not in ("train", "test"):
        raise DataError(self.root, f"unknown FT3Do split {self.split!r}; expected 'train' or 'test'")
      files = [f for f in prefixed if f.name.startswith(self.split.upper() + "_")]
    else:
      if split not in (None, "test"):
        raise DataError(self.root, f"no TRAIN_/TEST_ files here: only the test split, got {split!r}")
      self.split = "test"
    if not files:
      raise DataError(self.root, f"no .npz pairs found for split {self.split!r}")
    self.files = files

  def __len__(self):
    return len(self.files)

  def load(self, i):
    path = self.files[i]
    arrays = _load_npz(path)
    if "points1" in arrays:
      _need(arrays, ("points1", "points2", "flow"), path)
      pc1 = _check_shape(arrays["points1"], path, "points1")
      pc2 = _check_shape(arrays["points2"], path, "points2")
      flow = _check_shape(arrays["flow"], path, "flow", rows=len(pc1))
      mask = np.asarray(arrays.get("valid_mask1", np.ones(len(pc1), bool)))
      if mask.shape not in ((len(pc1),), (len(pc1), 1)):
        raise DataError(path, f"valid_mask1 has shape {mask.shape}, expected ({len(pc1)},)")
      mask = mask.reshape(-1).astype(bool)
    else:
      _need(arrays, ("pos1", "pos2", "gt"), path)
      pc1 = _check_shape(arrays["pos1"], path, "pos1")
      pc2 = _check_shape(arrays["pos2"], path, "pos2")
      flow = _check_shape(arrays["gt"], path, "gt", rows=len(pc1))
      mask = np.ones(len(pc1), bool)
    pc1, flow, (mask,), _ = _rows_with_flow(pc1, flow, path, extra=(mask,))
    pc2 = drop_nonfinite(pc2, np.isfinite(pc2).all(1), path, "pc2")
    return Pair(pc1=pc1, pc2=pc2, flow=flow, mask=mask, name=str(path))

  def describe(self):
    return f"{self.name} split={self.split}: {len(self)} pairs"


class Files(Dataset):
  """Two point files a user has, for inference: flow is unknown (zeros) and mask all False."""
  up = "y"  # as stored, not rotated: the models' frame assumed (predict's --up reads others)

  def __init__(self, pc1_path, pc2_path):
    self.paths = (pathlib.Path(pc1_path).expanduser(), pathlib.Path(pc2_path).expanduser())
    for p in self.paths:
      if not p.exists():
        raise DataError(p, "missing file")
    self.name = f"files:{self.paths[0]},{self.paths[1]}"

  def __len__(self):
    return 1

  def load(self, i):
    pc1, pc2 = (read_points(p) for p in self.paths)
    n = len(pc1)
    return Pair(pc1=pc1, pc2=pc2, flow=np.zeros((n, 3), np.float32), mask=np.zeros(n, bool),
                name=f"{self.paths[0]},{self.paths[1]}")


def _files(arg: str, split: str | None) -> Files:
  paths = arg.split(",")
  if len(paths) != 2 or not all(paths):
    raise DataError(f"files:{arg}", "expected files:PC1,PC2")
  return Files(*paths)


register("ft3d", FT3D, needs_root=True)
register("kitti", KITTI, needs_root=True)
register("argoverse", Argoverse, needs_root=True)
register("flownet3d", FlowNet3D, needs_root=True)
register("files", _files, needs_root=True)
