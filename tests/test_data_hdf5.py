"""HDF5 files: random access, broken files, and the conversion command line (the round trip of
every reader is in test_data_readers.py)."""

import contextlib
import io
import pathlib
import pickle

import h5py
import numpy as np
import pytest

from jaxflow.data import DataError, Pair, open_dataset
from jaxflow.data import convert as convert_module
from jaxflow.data.hdf5 import H5Writer
from jaxflow.data.readers import Dataset

REPO = pathlib.Path(__file__).resolve().parents[1]


def _pairs(count, seed=0):
  rng = np.random.default_rng(seed)
  for i in range(count):
    n, m = int(rng.integers(3, 30)), int(rng.integers(3, 30))
    yield Pair(pc1=rng.normal(size=(n, 3)).astype(np.float32), pc2=rng.normal(size=(m, 3)).astype(np.float32),
               flow=rng.normal(size=(n, 3)).astype(np.float32), mask=rng.random(n) < 0.5, name=f"p{i}")


def _write(path, count=7):
  with H5Writer(path, source="test:x", split="val", description="seven pairs") as writer:
    for pair in _pairs(count):
      writer.append(pair)
  return path


def test_random_access_in_any_order(tmp_path):
  ds = open_dataset(f"h5:{_write(tmp_path / 'a.h5')}")
  ds = pickle.loads(pickle.dumps(ds))  # worker processes reopen the file
  expected = list(_pairs(7))
  assert len(ds) == 7 and ds.split == "val" and "test:x" in ds.describe()
  for i in (6, 0, 3, -1):
    got, want = ds[i], expected[i]
    assert all(np.array_equal(getattr(got, k), getattr(want, k)) for k in ("pc1", "pc2", "flow", "mask"))
    assert got.name == want.name and got.pc1.dtype == np.float32 and got.mask.dtype == bool
  with pytest.raises(IndexError):
    ds[7]
  with pytest.raises(DataError, match="holds split 'val'"):
    open_dataset(f"h5:{tmp_path / 'a.h5'}", "train")


def test_truncated_and_corrupt_files_name_the_file(tmp_path):
  raw = _write(tmp_path / "a.h5").read_bytes()
  (tmp_path / "cut.h5").write_bytes(raw[: len(raw) // 2])
  (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all" * 100)
  with h5py.File(tmp_path / "other.h5", "w") as f:
    f["x"] = np.zeros(3)
  with h5py.File(tmp_path / "noindex.h5", "w") as f:
    f.attrs["format"] = "jaxflow-pairs"
  _write(tmp_path / "short.h5")
  with h5py.File(tmp_path / "short.h5", "a") as f:
    del f["offsets2"]
    f["offsets2"] = np.array([0, 5, 10])
  for name, problem in [("cut.h5", "truncated or corrupt"), ("junk.h5", "cannot open as HDF5"),
                        ("other.h5", "not a jaxflow pairs file"), ("noindex.h5", "incomplete or corrupt"),
                        ("short.h5", "offsets do not match")]:
    with pytest.raises(DataError, match=problem) as info:
      open_dataset(f"h5:{tmp_path / name}")
    assert str(tmp_path / name) in str(info.value)


class _Broken(Dataset):
  """Three pairs; pair 1 raises DataError; checks the final name never exists during conversion."""
  up = "y"

  def __init__(self, out):
    self.out, self.name, self.split = pathlib.Path(out), "broken", "test"

  def __len__(self):
    return 3

  def load(self, i):
    assert not self.out.exists() and self.out.with_name(self.out.name + ".tmp").exists()
    if i == 1:
      raise DataError("/data/0001/pc1.npy", "truncated or corrupt .npy file")
    return list(_pairs(3))[i]


def test_convert_writes_tmp_then_renames(tmp_path, monkeypatch, capsys):
  out = tmp_path / "b.h5"
  monkeypatch.setattr(convert_module, "open_dataset", lambda spec, split: _Broken(out))
  assert convert_module.main(["--dataset", "x:y", "--out", str(out)]) == 2
  err = capsys.readouterr().err.strip().splitlines()
  assert err[-1] == "convert: error: /data/0001/pc1.npy: truncated or corrupt .npy file"
  assert not out.exists() and not (tmp_path / "b.h5.tmp").exists()
  with pytest.warns(UserWarning, match="skipping broken pair 1"):
    assert convert_module.main(["--dataset", "x:y", "--out", str(out), "--skip_broken"]) == 0
  ds = open_dataset(f"h5:{out}")
  assert [p.name for p in ds] == ["p0", "p2"] and list(ds.file.attrs["skipped"]) == [
      "/data/0001/pc1.npy: truncated or corrupt .npy file"]


def test_convert_bad_arguments_exit_2_with_one_line(tmp_path, capsys):
  for argv, problem in [(["--out", "a.h5"], "required: --dataset"),
                        (["--dataset", "synthetic_things:2", "--out", str(tmp_path / "a.npz")], "FILE.h5"),
                        (["--dataset", "synthetic_things:2", "--out", str(tmp_path / "no" / "a.h5")], "missing output"),
                        (["--dataset", f"ft3d:{tmp_path}/none", "--out", str(tmp_path / "a.h5")], "missing dataset root"),
                        (["--dataset", "synthetic_things:2", "--split", "dev", "--out", str(tmp_path / "a.h5")],
                         "unknown split")]:
    assert convert_module.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("convert: error:") and problem in err[0], err


def test_convert_command_line_end_to_end(tmp_path):
  out = tmp_path / "s.h5"
  def run(*args):  # `python -m jaxflow.data.convert ARGS` (sys.exit(main())), in this process
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
      return convert_module.main(list(args)), stderr.getvalue()

  code, stderr = run("--dataset", "synthetic_lidar:2", "--split", "val", "--out", str(out),
                     "--limit", "1")
  assert code == 0, stderr
  assert "1/1" in stderr  # the tqdm bar
  assert len(open_dataset(f"h5:{out}")) == 1
  code, stderr = run("--dataset", "nope:x", "--out", str(out))
  assert code == 2 and stderr.strip().count("\n") == 0 and "Traceback" not in stderr
