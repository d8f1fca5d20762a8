"""Point files a user has: .npy, .ply, .pcd, LiDAR .bin, .xyz/.txt -> N x 3 float32.

A `.bin` file has no header: it is float32 rows of `columns` values, x y z first. 4 (the default):
KITTI velodyne, x y z intensity; 5: nuScenes, x y z intensity ring; 3: x y z alone. The same bytes
read with the wrong count are garbage that looks like numbers, so the layout is checked
(`bin_layout_problem`): the size must divide into rows, coordinates must be those of a sweep (none
beyond 10 km), an intensity or ring column must be non-negative, and 3 columns are refused when the
bytes read as 4 or 5 columns give a non-negative intensity. A file that fails names the `--columns`
that fit. (A 3-column cloud with no negative coordinate at all is the case left undetectable.)

Only x, y, z are read: extra columns (intensity, colour, normals) are ignored on purpose, since the
model sees geometry only. Integer and float64 coordinates are converted to float32. Rows with a
non-finite coordinate are dropped and counted with a `warnings.warn` naming the file (organised
.pcd clouds mark missing returns with NaN, so this is normal input, not an error); a cloud left with
fewer than `MIN_POINTS` points raises `DataError`. Every problem raises `DataError(path, problem)`.
"""

import pathlib
import warnings

import numpy as np

from jaxflow.errors import ConfigError, DataError

MIN_POINTS = 3  # fewer points than this cannot describe a surface: the file is treated as broken.
BIN_COLUMNS = 4  # KITTI velodyne's layout, the default of a .bin file
BIN_LAYOUTS = {3: "x y z", 4: "x y z intensity, KITTI's", 5: "x y z intensity ring, nuScenes'"}
MAX_COORDINATE_M = 1e4  # a sweep's points lie within 10 km; beyond, a float32 reading is garbage
TOLERATED_FRACTION = 1e-3  # of implausible values, before a layout is refused

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def to_float32(array, path, what: str = "points") -> np.ndarray:
  """Numeric array -> float32; anything else (object, string, bool, complex) is an error."""
  array = np.asarray(array)
  if array.dtype.kind not in "iuf":
    raise DataError(path, f"{what} have dtype {array.dtype}, expected integer or float numbers")
  return np.ascontiguousarray(array, dtype=np.float32)


def check_cloud(array, path, what: str = "points", extra_columns: bool = False,
                rows: bool = False) -> np.ndarray:
  """An N x 3 cloud (N x >= 3 with `extra_columns`, then cut to xyz) as float32, finite rows kept;
  `rows`: (cloud, which of the array's rows were kept, N bool)."""
  array = to_float32(array, path, what)
  ok_cols = array.ndim == 2 and (array.shape[1] >= 3 if extra_columns else array.shape[1] == 3)
  if not ok_cols:
    expected = "N x 3 (or more columns)" if extra_columns else "N x 3"
    raise DataError(path, f"{what} have shape {array.shape}, expected {expected}")
  xyz_Nx3 = array[:, :3]
  finite_N = np.isfinite(xyz_Nx3).all(axis=1)
  xyz_Nx3 = np.ascontiguousarray(drop_nonfinite(xyz_Nx3, finite_N, path, what))
  return (xyz_Nx3, finite_N) if rows else xyz_Nx3


def drop_nonfinite(array, finite_N, path, what: str = "points"):
  """Keeps the rows marked finite; warns with the count of dropped rows; too few left -> DataError."""
  n = len(finite_N)
  dropped = n - int(finite_N.sum())
  if dropped:
    which = "points" if what == "points" else f"points ({what} rows)"
    warnings.warn(f"{path}: dropped {dropped} of {n} {which} with a non-finite value", stacklevel=3)
    array = array[finite_N]
  if n == 0:
    raise DataError(path, f"{what}: no points (empty array)")
  if len(array) < MIN_POINTS:
    left = " left after dropping non-finite rows" if dropped else ""
    raise DataError(path, f"{what}: only {len(array)} point(s){left}, need at least {MIN_POINTS}")
  return array


def load_npy(path) -> np.ndarray:
  """np.load with every failure (missing, empty, truncated, pickled) reported as DataError."""
  path = pathlib.Path(path)
  check_file(path)
  try:
    array = np.load(path, allow_pickle=False)
  except (ValueError, EOFError, OSError) as e:
    raise DataError(path, f"truncated or corrupt .npy file ({e})") from None
  if not isinstance(array, np.ndarray):
    raise DataError(path, "is an .npz archive, expected one .npy array")
  return array


def read_points(path, columns: int | None = None, rows: bool = False) -> np.ndarray:
  """Reads a point file into N x 3 float32 (see module docstring for formats and conventions).

  columns: float32 values a point of a `.bin` file (None: BIN_COLUMNS, KITTI's 4); the other formats
  say their layout themselves and ignore it. rows: (points, which of the file's rows they are, a
  bool per row: False where a non-finite row was dropped).
  """
  path = pathlib.Path(path)
  integer = isinstance(columns, (int, np.integer)) and not isinstance(columns, bool)
  if columns is not None and (not integer or columns < 3):
    raise ConfigError(f"--columns must be an integer >= 3 (x y z first), got {columns!r}")
  check_file(path)
  suffix = path.suffix.lower()
  if suffix not in _READERS:
    raise DataError(path, f"unknown point file type {suffix or '(none)'!r}; expected one of "
                    + ", ".join(sorted(_READERS)))
  if suffix == ".bin":
    return check_cloud(_read_bin(path, columns or BIN_COLUMNS), path, extra_columns=True, rows=rows)
  return check_cloud(_READERS[suffix](path), path, extra_columns=True, rows=rows)


def check_file(path):
  """A DataError naming `path` unless it is a non-empty regular file (what every reader needs)."""
  path = pathlib.Path(path)
  if not path.exists():
    raise DataError(path, "missing file")
  if not path.is_file():
    raise DataError(path, "not a regular file")
  if path.stat().st_size == 0:
    raise DataError(path, "empty file")


def _read_npy(path):
  array = load_npy(path)
  if array.dtype.names:  # structured array with named x, y, z fields
    if not {"x", "y", "z"} <= set(array.dtype.names):
      raise DataError(path, f"structured array has fields {array.dtype.names}, expected x, y, z")
    array = np.stack([array[k].astype(np.float64) for k in "xyz"], axis=-1)
  return array


def _layout(columns: int) -> str:
  return f"{columns} float32 values a point" + (f" ({BIN_LAYOUTS[columns]})"
                                               if columns in BIN_LAYOUTS else "")


def bin_layout_problem(values, columns: int) -> str | None:
  """Why the flat float32 `values` do not read as `columns`-value points of a sweep (None: do)."""
  if values.size % columns:
    return (f"its {values.size} values ({4 * values.size} bytes) do not divide into rows of "
            f"{columns}")
  table = values.reshape(-1, columns).astype(np.float64)
  xyz = table[:, :3][np.isfinite(table[:, :3]).all(axis=1)]
  far = np.mean(np.abs(xyz) > MAX_COORDINATE_M) if xyz.size else 0.0
  if far > TOLERATED_FRACTION:
    return f"{far:.1%} of the coordinates lie beyond {MAX_COORDINATE_M:.0f} m"
  for j, name in ((3, "intensity"), (4, "ring")):
    if columns == 5 or (j == 3 and columns > 3):  # the documented layouts' non-negative columns
      negative = np.mean(table[:, j] < 0)
      if negative > TOLERATED_FRACTION:
        return f"column {j + 1} ({name}) is negative at {negative:.1%} of the points"
  if columns == 3:  # a file of 4 or 5 columns read as 3 mixes its intensities into x, y and z
    negative = np.mean(table < 0, axis=0)
    fits = [c for c in (4, 5) if bin_layout_problem(values, c) is None]
    if fits and negative.max() > TOLERATED_FRACTION:
      return (f"read as {fits[0]} columns its column 4 is a non-negative intensity, while read "
              "as 3 every column would mix coordinates and intensities")
  return None


def _read_bin(path, columns: int):
  raw = path.read_bytes()
  values = np.frombuffer(raw, dtype="<f4") if len(raw) % 4 == 0 else None
  problem = (bin_layout_problem(values, columns) if values is not None
             else f"size {len(raw)} bytes is not a multiple of 4 (float32 values)")
  if problem is None:
    return values.reshape(-1, columns)
  fits = [c for c in BIN_LAYOUTS
          if c != columns and values is not None and bin_layout_problem(values, c) is None]
  hint = (" or ".join(f"--columns {c} ({BIN_LAYOUTS[c]})" for c in fits) if fits
          else "no layout of 3, 4 or 5 float32 values a point fits: is it a float32 point file?")
  raise DataError(path, f"read as {_layout(columns)}: {problem}; "
                  + (f"try {hint}" if fits else hint))


def _read_text(path):
  try:
    text = path.read_text()
  except UnicodeDecodeError:
    raise DataError(path, "not a text file (expected x y z rows, whitespace or comma separated)") \
        from None
  rows, width = [], None
  for number, line in enumerate(text.splitlines(), 1):
    line = line.split("#", 1)[0].replace(",", " ").split()
    if not line:
      continue
    if width is None:
      width = len(line)
      if width < 3:
        raise DataError(path, f"line {number} has {width} values, expected at least 3 (x y z)")
    elif len(line) != width:
      raise DataError(path, f"line {number} has {len(line)} values, the first row has {width}")
    rows.append(line)
  if not rows:
    raise DataError(path, "no point rows (only blank or comment lines)")
  try:
    return np.array(rows, dtype=np.float64)
  except ValueError as e:
    raise DataError(path, f"non-numeric value ({e})") from None


def _header(path, raw: bytes, end_marker: bytes, first_line: bytes | None):
  """Splits raw bytes into (header lines, offset of the data) at the line starting with end_marker."""
  if first_line is not None and not raw.startswith(first_line):
    raise DataError(path, f"does not start with {first_line.decode()!r}")
  lines, offset = [], 0
  while True:
    nl = raw.find(b"\n", offset)
    if nl < 0:
      raise DataError(path, f"header has no {end_marker.decode()!r} line (truncated?)")
    line = raw[offset:nl].decode("ascii", "replace").strip()
    offset = nl + 1
    lines.append(line)
    if line.split(" ")[0].encode() == end_marker:
      return lines, offset


def _ply_header(path, lines):
  """(format, elements) of a PLY header's lines: elements [name, count, [(prop, type) or (prop,
  "list")]], in the file's order."""
  fmt, elements = None, []
  for line in lines[1:-1]:
    words = line.split()
    if not words or words[0] in ("comment", "obj_info"):
      continue
    if words[0] == "format":
      fmt = words[1] if len(words) > 1 else None
    elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
      elements.append([words[1], int(words[2]), []])
    elif words[0] == "property" and elements:
      if words[1] == "list":
        elements[-1][2].append((words[-1], "list"))
      elif len(words) == 3 and words[1] in _PLY_TYPES:
        elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
      else:
        raise DataError(path, f"unsupported PLY property line {line!r}")
    else:
      raise DataError(path, f"unexpected PLY header line {line!r}")
  if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
    raise DataError(path, f"unsupported PLY format {fmt!r}")
  return fmt, elements


def _ply_vertex(path, elements) -> int:
  """The index of the vertex element, which must have x, y and z, and no list property in it
  or before it (its data could not be found)."""
  names = [e[0] for e in elements]
  if "vertex" not in names:
    raise DataError(path, "PLY header declares no vertex element")
  v = names.index("vertex")
  props = elements[v][2]
  prop_names = [p for p, _ in props]
  if not {"x", "y", "z"} <= set(prop_names):
    raise DataError(path, f"PLY vertex properties {prop_names} lack x, y or z")
  if any(t == "list" for _, t in props) or any(t == "list" for e in elements[:v] for _, t in e[2]):
    raise DataError(path, "PLY vertex data after or with list properties is not supported")
  return v


def _ply_ascii(path, data: bytes, elements, v: int):
  """x, y, z (N x 3 float64) of the vertex element `v` of an ascii PLY body."""
  count, props = elements[v][1], elements[v][2]
  prop_names = [p for p, _ in props]
  body = data.decode("ascii", "replace").split("\n")
  body = [b for b in body if b.strip()]
  skip = sum(e[1] for e in elements[:v])
  rows = body[skip:skip + count]
  if len(rows) < count:
    raise DataError(path, f"truncated: header declares {count} vertices, file holds {len(rows)}")
  if len(elements) == 1 and len(body) > count:
    raise DataError(path, f"header declares {count} vertices but the file holds {len(body)} rows")
  try:
    values = np.array(" ".join(rows).split(), dtype=np.float64)
  except ValueError as e:
    raise DataError(path, f"non-numeric vertex value ({e})") from None
  if values.size != count * len(props):
    raise DataError(path, f"vertex rows hold {values.size} values, expected {count} x {len(props)}")
  table = values.reshape(count, len(props))
  return np.stack([table[:, prop_names.index(k)] for k in "xyz"], axis=-1)


def _ply_binary(path, data: bytes, elements, v: int, order: str):
  """x, y, z (N x 3 float64) of the vertex element `v` of a binary PLY body (`order`: "<" little
  endian, ">" big)."""
  count, props = elements[v][1], elements[v][2]
  skip = sum(e[1] * np.dtype([(p, order + t) for p, t in e[2]]).itemsize for e in elements[:v])
  dtype = np.dtype([(p, order + t) for p, t in props])
  data = data[skip:]
  need = count * dtype.itemsize
  if len(data) < need:
    raise DataError(path, f"truncated: header declares {count} vertices ({need} bytes), "
                    f"file holds {len(data)} bytes of vertex data")
  if len(elements) == 1 and len(data) > need:
    raise DataError(path, f"header declares {count} vertices ({need} bytes) but the file holds "
                    f"{len(data)} bytes of data")
  table = np.frombuffer(data, dtype=dtype, count=count)
  return np.stack([table[k].astype(np.float64) for k in "xyz"], axis=-1)


def _read_ply(path):
  raw = path.read_bytes()
  lines, offset = _header(path, raw, b"end_header", b"ply")
  fmt, elements = _ply_header(path, lines)
  v = _ply_vertex(path, elements)
  if fmt == "ascii":
    return _ply_ascii(path, raw[offset:], elements, v)
  return _ply_binary(path, raw[offset:], elements, v, "<" if fmt == "binary_little_endian" else ">")


def _read_pcd(path):
  raw = path.read_bytes()
  lines, offset = _header(path, raw, b"DATA", None)
  head = {}
  for line in lines:
    words = line.split()
    if words and not words[0].startswith("#"):
      head[words[0].upper()] = words[1:]
  fields = head.get("FIELDS", [])
  if not {"x", "y", "z"} <= set(fields):
    raise DataError(path, f"PCD FIELDS {fields} lack x, y or z")
  sizes, types = head.get("SIZE", []), head.get("TYPE", [])
  counts = head.get("COUNT", ["1"] * len(fields))
  if not len(fields) == len(sizes) == len(types) == len(counts):
    raise DataError(path, "PCD FIELDS, SIZE, TYPE and COUNT have different lengths")
  try:
    n = int(head["POINTS"][0]) if "POINTS" in head else int(head["WIDTH"][0]) * int(head["HEIGHT"][0])
    counts = [int(c) for c in counts]
  except (KeyError, IndexError, ValueError):
    raise DataError(path, "PCD header lacks a valid POINTS (or WIDTH and HEIGHT)") from None
  data_kind = head["DATA"][0].lower() if head["DATA"] else ""
  if data_kind == "binary_compressed":
    raise DataError(path, "PCD DATA binary_compressed is not supported; save as ascii or binary")
  width = sum(counts)
  col = {f: sum(counts[:i]) for i, f in enumerate(fields)}
  if data_kind == "ascii":
    body = [b for b in raw[offset:].decode("ascii", "replace").split("\n") if b.strip()]
    if len(body) != n:
      raise DataError(path, f"header declares {n} points, the file holds {len(body)} rows")
    try:
      values = np.array(" ".join(body).split(), dtype=np.float64)
    except ValueError as e:
      raise DataError(path, f"non-numeric value ({e})") from None
    if values.size != n * width:
      raise DataError(path, f"rows hold {values.size} values, expected {n} x {width}")
    table = values.reshape(n, width)
    return np.stack([table[:, col[k]] for k in "xyz"], axis=-1)
  if data_kind != "binary":
    raise DataError(path, f"unsupported PCD DATA {data_kind!r}")
  try:
    dtype = np.dtype([(f"{f}_{i}", "<" + _PCD_TYPES[(t.upper(), int(s))], (c,) if c > 1 else ())
                      for i, (f, s, t, c) in enumerate(zip(fields, sizes, types, counts))])
  except (KeyError, ValueError):
    raise DataError(path, f"unsupported PCD SIZE/TYPE {sizes}/{types}") from None
  data = raw[offset:]
  need = n * dtype.itemsize
  if len(data) != need:
    problem = "truncated" if len(data) < need else "too long"
    raise DataError(path, f"{problem}: header declares {n} points ({need} bytes), "
                    f"file holds {len(data)} bytes of data")
  table = np.frombuffer(data, dtype=dtype, count=n)
  names = {f: f"{f}_{i}" for i, f in enumerate(fields)}
  return np.stack([table[names[k]].astype(np.float64) for k in "xyz"], axis=-1)


_READERS = {".npy": _read_npy, ".ply": _read_ply, ".pcd": _read_pcd, ".bin": _read_bin,
            ".xyz": _read_text, ".txt": _read_text}
