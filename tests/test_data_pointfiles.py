"""read_points on every format, written here byte by byte (an independent writer), and broken files."""

import struct
import warnings

import numpy as np
import pytest

from jaxflow.data import DataError, read_points
from jaxflow import predict
from jaxflow.errors import ConfigError

import commands

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
    ("odd.bin", b"\0" * 18, "not a multiple of 4"),
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


# --- .bin layouts: fixtures written from the documented layouts ---------------------------------
# KITTI velodyne: float32 x, y, z, intensity (in [0, 1]) a point, little-endian, no header (the
# devkit's `np.fromfile(path, np.float32).reshape(-1, 4)`). nuScenes LIDAR_TOP: float32 x, y, z,
# intensity (0-255), ring (0-31). Both in scan order: beam by beam, around the sensor.


def _sweep(beams, elevation_deg, height_m, azimuths=360, seed=0):
  """x y z of a spinning LiDAR `height_m` above flat ground, walls 12-40 m away (scan order)."""
  rng = np.random.default_rng(seed)
  elevation, azimuth = np.meshgrid(np.deg2rad(np.linspace(*elevation_deg, beams)),
                                   np.linspace(-np.pi, np.pi, azimuths, endpoint=False),
                                   indexing="ij")
  wall_m = rng.uniform(12, 40, azimuths)[None]
  to_ground_m = np.where(elevation < 0, height_m / np.tan(np.maximum(-elevation, 1e-6)), np.inf)
  horizontal_m = np.minimum(to_ground_m, wall_m)
  xyz = np.stack([horizontal_m * np.cos(azimuth), horizontal_m * np.sin(azimuth),
                  horizontal_m * np.tan(elevation)], axis=-1).reshape(-1, 3)
  return xyz.astype(np.float32), np.repeat(np.arange(beams), azimuths).astype(np.float32)


@pytest.fixture
def sweeps(tmp_path):
  """{name: (path, xyz)}: a KITTI, a nuScenes and a bare xyz .bin; 23040 / 11520 points, which
  divide by 3, 4 and 5, so every wrong column count divides the file too."""
  rng = np.random.default_rng(1)
  kitti_xyz, _ = _sweep(64, (-24.8, 2.0), 1.73)  # HDL-64E
  nusc_xyz, ring = _sweep(32, (-30.0, 10.0), 1.84)  # HDL-32E
  layouts = {
    "kitti.bin": (kitti_xyz, np.c_[kitti_xyz, rng.uniform(0, 1, len(kitti_xyz))]),
    "nuscenes.bin": (nusc_xyz, np.c_[nusc_xyz, rng.integers(0, 256, len(nusc_xyz)), ring]),
    "xyz.bin": (kitti_xyz, kitti_xyz),
  }
  out = {}
  for name, (xyz, table) in layouts.items():
    (tmp_path / name).write_bytes(np.ascontiguousarray(table, dtype="<f4").tobytes())
    out[name] = (tmp_path / name, xyz)
  return out


@pytest.mark.parametrize("name, columns", [("kitti.bin", None), ("kitti.bin", 4),
                                           ("nuscenes.bin", 5), ("xyz.bin", 3)])
def test_bin_layouts_read_with_their_columns(sweeps, name, columns):
  path, xyz = sweeps[name]
  np.testing.assert_array_equal(read_points(path, columns=columns), xyz)


@pytest.mark.parametrize("name, columns, fits", [
  ("xyz.bin", None, "--columns 3"),  # the case: x y z read as KITTI's 4 columns
  ("xyz.bin", 5, "--columns 3"),
  ("nuscenes.bin", None, "--columns 5"),
  ("nuscenes.bin", 3, "--columns 5"),
  ("kitti.bin", 3, "--columns 4"),
  ("kitti.bin", 5, "--columns 4"),
])
def test_bin_read_with_the_wrong_columns_is_refused_naming_the_right_ones(sweeps, name, columns,
                                                                       fits):
  path, _ = sweeps[name]
  with pytest.raises(DataError, match=f"try {fits} ") as info:
    read_points(path, columns=columns)
  message = str(info.value)
  assert message.startswith(str(path)) and f"read as {columns or 4} float32 values" in message
  assert message.count("--columns") == 1, message  # only the layout that fits is offered


def test_bin_whose_size_fits_no_row_names_the_layouts_that_do(tmp_path, sweeps):
  xyz = sweeps["xyz.bin"][1][:1001]  # 3003 values: rows of 3 only
  (tmp_path / "odd.bin").write_bytes(xyz.astype("<f4").tobytes())
  with pytest.raises(
      DataError, match=r"12012 bytes\) do not divide into rows of 4; try --columns 3"):
    read_points(tmp_path / "odd.bin")
  np.testing.assert_array_equal(read_points(tmp_path / "odd.bin", columns=3), xyz)


def test_bin_of_float64_values_is_refused(tmp_path, sweeps):
  path, xyz = sweeps["kitti.bin"]
  table = np.frombuffer(path.read_bytes(), "<f4").reshape(-1, 4)
  (tmp_path / "f64.bin").write_bytes(table.astype("<f8").tobytes())
  with pytest.raises(DataError, match=r"f64\.bin: .* lie beyond 10000 m; no layout .* fits"):
    read_points(tmp_path / "f64.bin")


def test_bin_with_a_negative_intensity_names_the_column(tmp_path):
  table = np.c_[XYZ, [0.5, -0.2, 0.1, 0.3]].astype("<f4")  # 1 of 4 points, far above 0.1%
  (tmp_path / "neg.bin").write_bytes(table.tobytes())
  with pytest.raises(DataError, match=r"column 4 \(intensity\) is negative at 25\.0% of"):
    read_points(tmp_path / "neg.bin")


@pytest.mark.parametrize("columns", [2, 0, 4.0, True])
def test_columns_must_be_an_integer_of_at_least_3(sweeps, columns):
  with pytest.raises(ConfigError, match="--columns must be an integer >= 3"):
    read_points(sweeps["kitti.bin"][0], columns=columns)


def test_columns_is_ignored_by_formats_with_a_header(tmp_path):
  (tmp_path / "a.xyz").write_text("".join(f"{x} {y} {z}\n" for x, y, z in XYZ))
  np.testing.assert_array_equal(read_points(tmp_path / "a.xyz", columns=5), XYZ.astype(np.float32))


def test_predict_refuses_a_three_column_bin_and_takes_columns(sweeps):
  """The command line: the refusal before any model is loaded, and --columns reaches the reader."""
  path, _ = sweeps["xyz.bin"]
  for extra, read_as in (([], 4), (["--columns", "5"], 5)):
    done = commands.run(predict.run, path, path, "--out", path.with_suffix(".npy"), *extra)
    assert done.returncode == 2, done.stderr
    assert f"{path}: read as {read_as} float32 values" in done.stderr, done.stderr
    assert "try --columns 3 (x y z)" in done.stderr and "Traceback" not in done.stderr


def test_real_kitti_frame_as_xyz_bin_is_refused_by_default(shared_dir, tmp_path):
  """The real KITTI frame of ../shared (100,480 points, a multiple of 4) written as bare x y z."""
  xyz = np.load(shared_dir / "data" / "KITTI_processed_occ_final" / "000002" / "pc1.npy")
  assert len(xyz) % 4 == 0
  (tmp_path / "frame.bin").write_bytes(xyz.astype("<f4").tobytes())
  with pytest.raises(DataError, match="try --columns 3"):
    read_points(tmp_path / "frame.bin")
  np.testing.assert_array_equal(read_points(tmp_path / "frame.bin", columns=3), xyz)
