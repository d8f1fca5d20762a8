"""read_points on every format, written here byte by byte (an independent writer), and broken files."""

import struct
import warnings

import numpy as np
import pytest

from jaxflow.data import DataError, read_points

XYZ = np.array([[0.5, -1.25, 3.0], [2.0, 0.0, -4.5], [1e-3, 7.75, 10.0], [-3.5, 2.5, 0.125]])


def _ply_header(fmt, count, props, extra=""):
  lines = ["ply", f"format {fmt} 1.0", "comment written by hand", f"element vertex {count}"]
  lines += [f"property {t} {n}" for t, n in props]
  return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


def test_npy_float64_int_and_extra_columns(tmp_path):
  np.save(tmp_path / "a.npy", XYZ)
  np.save(tmp_path / "b.npy", np.arange(12).reshape(3, 4))
  a, b = read_points(tmp_path / "a.npy"), read_points(tmp_path / "b.npy")
  assert a.dtype == np.float32 and np.array_equal(a, XYZ.astype(np.float32))
  assert b.dtype == np.float32 and np.array_equal(b, [[0, 1, 2], [4, 5, 6], [8, 9, 10]])


def test_ply_ascii_with_extra_properties(tmp_path):
  head = _ply_header("ascii", 4, [("float", "x"), ("float", "y"), ("float", "z"), ("uchar", "red")],
                     extra="element face 1\nproperty list uchar int vertex_indices\n")
  body = "".join(f"{x} {y} {z} 200\n" for x, y, z in XYZ) + "3 0 1 2\n"
  (tmp_path / "a.ply").write_bytes(head + body.encode())
  assert np.array_equal(read_points(tmp_path / "a.ply"), XYZ.astype(np.float32))


def test_ply_binary_mixed_types(tmp_path):
  # x as double, y as float, an int property between, z as float: any numeric type is accepted.
  head = _ply_header("binary_little_endian", 4, [("double", "x"), ("float", "y"), ("int", "id"), ("float", "z")])
  body = b"".join(struct.pack("<dfif", x, y, i, z) for i, (x, y, z) in enumerate(XYZ))
  (tmp_path / "a.ply").write_bytes(head + body)
  assert np.array_equal(read_points(tmp_path / "a.ply"), XYZ.astype(np.float32))


def test_ply_big_endian_int_coordinates(tmp_path):
  rows = [(1, -2, 3), (4, 5, -6), (0, 300, -300)]
  head = _ply_header("binary_big_endian", 3, [("short", "x"), ("short", "y"), ("short", "z")])
  (tmp_path / "a.ply").write_bytes(head + b"".join(struct.pack(">hhh", *r) for r in rows))
  assert np.array_equal(read_points(tmp_path / "a.ply"), rows)


def _pcd(fields, sizes, types, counts, n, data_kind):
  return (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {' '.join(fields)}\n"
          f"SIZE {' '.join(map(str, sizes))}\nTYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\n"
          f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data_kind}\n").encode()


def test_pcd_ascii(tmp_path):
  head = _pcd(["x", "y", "z", "intensity"], [4, 4, 4, 4], ["F", "F", "F", "F"], [1, 1, 1, 1], 4, "ascii")
  body = "".join(f"{x} {y} {z} 0.5\n" for x, y, z in XYZ)
  (tmp_path / "a.pcd").write_bytes(head + body.encode())
  assert np.array_equal(read_points(tmp_path / "a.pcd"), XYZ.astype(np.float32))


def test_pcd_binary_fields_in_any_order(tmp_path):
  head = _pcd(["rgb", "z", "x", "normal", "y"], [4, 4, 8, 4, 4], ["U", "F", "F", "F", "F"], [1, 1, 1, 3, 1],
              4, "binary")
  body = b"".join(struct.pack("<Ifd3ff", 7, z, x, 0, 0, 1, y) for x, y, z in XYZ)
  (tmp_path / "a.pcd").write_bytes(head + body)
  assert np.array_equal(read_points(tmp_path / "a.pcd"), XYZ.astype(np.float32))


def test_kitti_bin_and_text_formats(tmp_path):
  xyzi = np.concatenate([XYZ, np.full((4, 1), 0.3)], axis=1).astype("<f4")
  (tmp_path / "a.bin").write_bytes(xyzi.tobytes())
  (tmp_path / "a.xyz").write_text("# comment\n" + "".join(f"{x} {y}\t{z}\n" for x, y, z in XYZ))
  (tmp_path / "a.txt").write_text("".join(f"{x},{y},{z},1,2\n" for x, y, z in XYZ) + "\n")
  for name in ("a.bin", "a.xyz", "a.txt"):
    assert np.array_equal(read_points(tmp_path / name), XYZ.astype(np.float32)), name


def test_nonfinite_rows_dropped_and_counted(tmp_path):
  xyz = XYZ.copy()
  xyz[1, 2] = np.nan
  xyz[3, 0] = np.inf
  (tmp_path / "a.xyz").write_text("".join(f"{x} {y} {z}\n" for x, y, z in np.concatenate([xyz, XYZ])))
  with pytest.warns(UserWarning, match=r"a\.xyz: dropped 2 of 8"):
    points = read_points(tmp_path / "a.xyz")
  assert np.array_equal(points, np.concatenate([XYZ[[0, 2]], XYZ]).astype(np.float32))


@pytest.mark.parametrize("name, content, problem", [
    ("empty.ply", b"", "empty file"),
    ("empty.xyz", b"# nothing\n\n", "no point rows"),
    ("cols.txt", b"1 2\n3 4\n", "2 values"),
    ("ragged.txt", b"1 2 3\n4 5\n", "line 2"),
    ("word.xyz", b"1 2 3\n4 five 6\n", "non-numeric"),
    ("odd.bin", b"\0" * 20, "multiple of 16"),
    ("a.las", b"LASF", "unknown point file type"),
    ("few.xyz", b"1 2 3\n4 5 6\n", "need at least 3"),
    ("nan.xyz", b"nan 1 1\n1 nan 1\n1 1 inf\n1 2 3\n", "only 1 point.s. left after dropping"),
])
def test_broken_text_and_simple_files(tmp_path, name, content, problem):
  (tmp_path / name).write_bytes(content)
  with warnings.catch_warnings(), pytest.raises(DataError, match=problem) as info:
    warnings.simplefilter("ignore")
    read_points(tmp_path / name)
  assert name in str(info.value)


def test_broken_ply_and_pcd(tmp_path):
  props = [("float", "x"), ("float", "y"), ("float", "z")]
  body = b"".join(struct.pack("<fff", *p) for p in XYZ)
  cases = {
      "short.ply": (_ply_header("binary_little_endian", 5, props) + body, "truncated"),
      "long.ply": (_ply_header("binary_little_endian", 3, props) + body, "declares 3 vertices"),
      "lies.ply": (_ply_header("ascii", 6, props) + b"1 2 3\n4 5 6\n", "truncated"),
      "noz.ply": (_ply_header("ascii", 1, props[:2]) + b"1 2\n", "lack x, y or z"),
      "nohead.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\n", "end_header"),
      "notply.ply": (b"solid cube\n", "does not start with 'ply'"),
      "comp.pcd": (_pcd(["x", "y", "z"], [4] * 3, ["F"] * 3, [1] * 3, 4, "binary_compressed") + b"\0" * 40,
                   "binary_compressed is not supported"),
      "short.pcd": (_pcd(["x", "y", "z"], [4] * 3, ["F"] * 3, [1] * 3, 5, "binary") + body, "truncated"),
      "lies.pcd": (_pcd(["x", "y", "z"], [4] * 3, ["F"] * 3, [1] * 3, 2, "ascii") + b"1 2 3\n" * 3,
                   "declares 2 points"),
  }
  for name, (content, problem) in cases.items():
    (tmp_path / name).write_bytes(content)
    with pytest.raises(DataError, match=problem) as info:
      read_points(tmp_path / name)
    assert str(tmp_path / name) in str(info.value), name


def test_missing_truncated_and_object_npy(tmp_path):
  with pytest.raises(DataError, match="missing file"):
    read_points(tmp_path / "nope.npy")
  np.save(tmp_path / "a.npy", XYZ)
  raw = (tmp_path / "a.npy").read_bytes()
  (tmp_path / "cut.npy").write_bytes(raw[:-10])
  with pytest.raises(DataError, match="truncated or corrupt"):
    read_points(tmp_path / "cut.npy")
  np.save(tmp_path / "flat.npy", np.arange(6.0))
  with pytest.raises(DataError, match=r"shape \(6,\)"):
    read_points(tmp_path / "flat.npy")
  np.save(tmp_path / "str.npy", np.array([["a", "b", "c"]]))
  with pytest.raises(DataError, match="dtype"):
    read_points(tmp_path / "str.npy")
