"""Pairs in one HDF5 file, written by `jaxflow.data.convert` and read with random access.

Layout (chosen for random-access speed: a pair is 4 contiguous slices, and opening the file reads
two small offset arrays instead of walking thousands of groups):
  pc1, flow  (sum N) x 3 float32;  mask (sum N) bool;  pc2 (sum M) x 3 float32
  offsets1, offsets2  (P + 1) int64: pair i is rows offsets[i]:offsets[i+1]
  names  (P) str
  rigid_flow (sum N) x 3 float32, foreground (sum N) bool: only when the source's pairs carry
    ego-motion flow and labels (`Pair.has_labels`, e.g. opensf), for the three-way EPE
  attrs: format, version, source (the spec converted), split, description, count, up (the source
    reader's `Dataset.up`: the file's clouds are in its frame)
"""

import pathlib

import h5py
import numpy as np

from jaxflow.data.registry import Dataset, Pair, register
from jaxflow.errors import DataError

FORMAT, VERSION = "jaxflow-pairs", 1
_CHUNK_ROWS = 1 << 15


class H5Writer:
  """Appends Pairs to a new HDF5 file; `close()` writes the index. Use as a context manager."""

  def __init__(self, path, source: str, split: str, description: str = "", up: str = "y"):
    self.path = pathlib.Path(path)
    self.file = h5py.File(self.path, "w")
    self.file.attrs.update(format=FORMAT, version=VERSION, source=source, split=split or "",
                           description=description, up=up)
    for key, cols, dtype in (("pc1", 3, "f4"), ("flow", 3, "f4"), ("pc2", 3, "f4"), ("mask", 0, "?")):
      self._create(key, cols, dtype)
    self.offsets1, self.offsets2, self.names = [0], [0], []
    self.labels = None  # whether the pairs carry rigid_flow and foreground: set by the first

  def _create(self, key, cols, dtype):
    shape, chunks = ((0, cols), (_CHUNK_ROWS, cols)) if cols else ((0,), (_CHUNK_ROWS,))
    self.file.create_dataset(key, shape=shape, maxshape=(None,) + shape[1:], chunks=chunks,
                             dtype=dtype)

  def append(self, pair: Pair):
    if self.labels is None:
      self.labels = pair.has_labels
      if self.labels:
        self._create("rigid_flow", 3, "f4")
        self._create("foreground", 0, "?")
    if pair.has_labels != self.labels:
      raise DataError(self.path, f"pair {pair.name} {'lacks' if self.labels else 'has'} "
                      "rigid_flow/foreground unlike the first pair: a file holds both or neither")
    extra = ((("rigid_flow", pair.rigid_flow, None), ("foreground", pair.foreground, None))
             if self.labels else ())
    for key, array, offsets in (("pc1", pair.pc1, self.offsets1), ("flow", pair.flow, None),
                                ("mask", pair.mask, None), ("pc2", pair.pc2, self.offsets2),
                                *extra):
      ds = self.file[key]
      start = len(ds)
      ds.resize(start + len(array), axis=0)
      ds[start:] = array
      if offsets is not None:
        offsets.append(start + len(array))
    self.names.append(pair.name)

  def close(self):
    if self.file:
      self.file.create_dataset("offsets1", data=np.array(self.offsets1, np.int64))
      self.file.create_dataset("offsets2", data=np.array(self.offsets2, np.int64))
      self.file.create_dataset("names", data=self.names, dtype=h5py.string_dtype())
      self.file.attrs["count"] = len(self.names)
      self.file.close()
      self.file = None

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    if exc[0] is None:
      self.close()
    elif self.file:
      self.file.close()
      self.file = None


class H5Dataset(Dataset):
  """Random-access reader of a converted file: pair i equals the source reader's pair i exactly."""

  def __init__(self, path, split: str | None = None):
    self._args = (path, split)
    self.path = pathlib.Path(path).expanduser()
    if not str(path):
      raise DataError("h5:", "missing file name: expected h5:FILE.h5")
    if not self.path.is_file():
      raise DataError(self.path, "missing HDF5 file")
    try:
      self.file = h5py.File(self.path, "r")
    except OSError as e:
      raise DataError(self.path, f"cannot open as HDF5, truncated or corrupt ({e})") from None
    try:
      self._index(split)
    except BaseException:
      self.file.close()
      raise
    self.name = f"h5:{self.path}"

  def _index(self, split):
    try:
      attrs = dict(self.file.attrs)
      if attrs.get("format") != FORMAT:
        raise DataError(self.path, f"not a jaxflow pairs file (format {attrs.get('format')!r})")
      self.offsets1 = self.file["offsets1"][()]
      self.offsets2 = self.file["offsets2"][()]
      self.names = [n.decode() if isinstance(n, bytes) else str(n) for n in self.file["names"][()]]
      self.arrays = {k: self.file[k] for k in ("pc1", "flow", "mask", "pc2")}
      self.labels = "rigid_flow" in self.file
      if self.labels:
        self.arrays.update(rigid_flow=self.file["rigid_flow"], foreground=self.file["foreground"])
    except (KeyError, OSError) as e:
      raise DataError(self.path, f"incomplete or corrupt jaxflow pairs file ({e})") from None
    n = len(self.names)
    sizes_ok = (len(self.offsets1) == len(self.offsets2) == n + 1
                and self.offsets1[-1] == len(self.arrays["pc1"]) == len(self.arrays["flow"])
                == len(self.arrays["mask"]) and self.offsets2[-1] == len(self.arrays["pc2"])
                and all(len(self.arrays[k]) == self.offsets1[-1]
                        for k in ("rigid_flow", "foreground") if self.labels)
                and (np.diff(self.offsets1) >= 0).all() and (np.diff(self.offsets2) >= 0).all())
    if not sizes_ok:
      raise DataError(self.path, "offsets do not match the stored arrays (truncated or corrupt)")
    self.source, self.split = str(attrs.get("source", "")), str(attrs.get("split", ""))
    self.up = str(attrs["up"]) if "up" in attrs else _unrecorded_up(self.source)
    if split and self.split and split != self.split:
      raise DataError(self.path, f"holds split {self.split!r} of {self.source}, asked for {split!r}")

  def __len__(self):
    return len(self.names)

  def load(self, i):
    a, b = int(self.offsets1[i]), int(self.offsets1[i + 1])
    c, d = int(self.offsets2[i]), int(self.offsets2[i + 1])
    try:
      pc1, flow = self.arrays["pc1"][a:b], self.arrays["flow"][a:b]
      mask, pc2 = self.arrays["mask"][a:b], self.arrays["pc2"][c:d]
      labels = {k: self.arrays[k][a:b] for k in ("rigid_flow", "foreground") if self.labels}
    except (OSError, ValueError) as e:
      raise DataError(self.path, f"pair {i} ({self.names[i]}) unreadable ({e})") from None
    return Pair(pc1=pc1, pc2=pc2, flow=flow, mask=mask, name=self.names[i], **labels)

  def describe(self):
    return f"{self.name}: {len(self)} pairs converted from {self.source} (split {self.split or '-'})"

  def close(self):
    self.file.close()

  def __reduce__(self):  # worker processes reopen the file
    return H5Dataset, self._args


def _unrecorded_up(source: str) -> str:
  """The up axis of a file converted before `up` was recorded, as it was read then: z for opensf's
  ego frame (its default), y (the models' frame) for every other source."""
  if not source.startswith("opensf:"):
    return "y"
  return "y" if "frame=camera" in source.split(",") else "z"


register("h5", lambda path, split: H5Dataset(path, split), needs_root=True)
