"""OpenSceneFlow's unified h5 format (Argoverse 2, Waymo, nuScenes, ... as converted by the
OpenSceneFlow toolkit's dataprocess/ scripts), registered as "opensf".

    ds = open_dataset("opensf:/data/av2", "val")             # /data/av2/val/<log>.h5
    ds = open_dataset("opensf:/data/av2,max_range=50,ground=keep,frame=camera", "val")

One `<log>.h5` per log; one group per timestamp (keys sorted numerically: consecutive keys are a
pair) holding `lidar` (N x >= 3, the ego frame of that timestamp), `ground_mask` (N bool), `pose`;
the first frame of a labelled pair also holds `flow` (N x 3: where each point is at the next
timestamp, in the next frame's ego frame, so it includes the ego-motion), `flow_is_valid`,
`flow_category_indices` (0 = background) and `ego_motion` (4 x 4, ego1 <- ego0).

Pairs: every consecutive (t0, t1) of every log whose t0 has `flow`, in file then time order;
pc1 = lidar(t0)[:, :3], pc2 = lidar(t1)[:, :3]. Options after the folder (", key=value"):
  ground=remove (default) | keep: remove each cloud's `ground_mask` points;
  max_range=35 (default; 0 keeps all): keep the points within this many metres in xy;
  frame=ego (default, as stored: x forward, y left, z up) | camera: the clouds and flows rotated
    into the models' frame (x left, y up, z forward: (x, y, z) -> (y, z, x), a proper rotation;
    jaxflow.geometry.frames); evaluation rotates ego clouds into it before the model and the flow
    back after (`Dataset.up`), so either gives the same flow; the metrics do not change under
    it.
  region=disc (default: the cuts above) | challenge: the Argoverse 2 challenge's points, pc1 =
    the frame's `eval_mask` points in file order where the file has them (then only the frames
    with an eval_mask are pairs, as the challenge evaluates), else the non-ground points with
    |x|, |y| <= 50 m (ego frame); pc2 = its non-ground points in that box; ground and max_range
    are not used; a non-finite point there is an error, never dropped (the rows of a submission);
    | sweep: the whole raw sweeps (every finite point, ground and far points included: what the
    `lidar` method takes), scored on the challenge's points only (mask: as region=challenge's pc1);
  lidar=auto (default) | ego | sensor: the frame `lidar` is stored in. OpenSceneFlow's
    dataprocess/extract_av2.py stores the AV2 `lidar` in the up_lidar sensor frame since its commit
    2bd9036 (older files: the ego frame) while `flow`, `pose` and `ego_motion` stay in the ego
    frame, and the file records neither the frame nor the sensor's extrinsic. auto tells them
    apart from the data: the flow of valid background points is exactly the ego-motion flow of
    the ego-frame points, so in an ego-frame file |flow - (ego_motion p - p)| is float rounding
    while in a sensor-frame file it is ~ the ego's rotation x the sensor's offset (a frame whose
    ego turns by at least 0.03 degrees decides); a file none of whose frames decides (an ego
    that stood still or drove straight all through the log) is
    read as the ego frame, with a warning: what every OpenSceneFlow converter but AV2's since
    2bd9036 writes (and the flows of the two frames then differ by under 0.03 degrees x the
    sensor's offset, ~1 mm); lidar=ego says so without the warning. lidar=sensor needs
    calibration=AV2_DIR, the AV2 split the file was made
    from (AV2_DIR/<log>/calibration/egovehicle_SE3_sensor.feather, its up_lidar row; needs
    pyarrow): the clouds are moved into the ego frame with it, so every frame of a pair is the
    ego frame whichever version the file is.
mask = flow_is_valid (and eval_mask where the frame has one); Pair.rigid_flow = ego_motion applied
to pc1, minus pc1; Pair.foreground = flow_category_indices != 0 (the three-way EPE,
`jaxflow.evaluation.metrics.three_way_epe`); Pair.category = flow_category_indices and Pair.ego_xy =
pc1's x, y in the ego frame (the official breakdown, `jaxflow.evaluation.av2_eval`). A pair's name
is FILE:TIMESTAMP (`sweep_id` gives av2's (log_id, timestamp_ns)). Errors name the file and the
group. A split is a subfolder (train, val, test; default train).
"""

import json
import pathlib
import warnings

import h5py
import numpy as np

from jaxflow.data.pointfiles import MIN_POINTS
from jaxflow.data.registry import Dataset, Pair, register
from jaxflow.errors import DataError
from jaxflow.geometry import frames

DEFAULTS = {"ground": "remove", "max_range": 35.0, "frame": "ego", "region": "disc",
            "lidar": "auto", "calibration": ""}
CHOICES = {"ground": ("remove", "keep"), "frame": ("ego", "camera"),
           "region": ("disc", "challenge", "sweep"), "lidar": ("auto", "ego", "sensor")}
CHALLENGE_BOX_M = 50.0  # the challenge's points: non-ground, |x|, |y| <= 50 m (ego frame)
DECISIVE_ROTATION = 5e-4  # rad (0.03 degrees): an ego rotation that tells the lidar frames apart


def parse_spec(arg: str) -> tuple[str, dict]:
  """"DIR[,key=value...]" -> (DIR, options with the defaults filled in)."""
  parts = arg.split(",")
  root, options = parts[0], dict(DEFAULTS)
  for part in parts[1:]:
    key, eq, value = part.partition("=")
    if not eq or key not in DEFAULTS:
      raise DataError(f"opensf:{arg}", f"bad option {part!r}; expected key=value with key one of "
                      f"{', '.join(DEFAULTS)}")
    if key == "max_range":
      try:
        options[key] = float(value)
      except ValueError:
        raise DataError(f"opensf:{arg}", f"max_range={value!r} is not a number") from None
      if options[key] < 0:
        raise DataError(f"opensf:{arg}", f"max_range must be >= 0, got {value}")
    elif key == "calibration":
      options[key] = value
    elif value not in CHOICES[key]:
      raise DataError(f"opensf:{arg}", f"{key}={value!r}; expected one of {CHOICES[key]}")
    else:
      options[key] = value
  if options["lidar"] == "sensor" and not options["calibration"]:
    raise DataError(f"opensf:{arg}", "lidar=sensor needs calibration=AV2_DIR (the AV2 split the "
                    "h5 files were made from: AV2_DIR/<log>/calibration/"
                    "egovehicle_SE3_sensor.feather)")
  return root, options


def _sorted_keys(f, path) -> list[str]:
  try:
    return sorted(f.keys(), key=int)
  except ValueError:
    bad = next(k for k in f.keys() if not k.lstrip("-").isdigit())
    raise DataError(path, f"group {bad!r}: not a timestamp (group keys must be integers)") from None


class OpenSceneFlow(Dataset):
  """OpenSceneFlow h5 logs in ROOT/SPLIT/*.h5 (see the module docstring)."""

  def __init__(self, root, split: str | None = None, **options):
    self.root = pathlib.Path(root).expanduser()
    self.split = split or "train"
    self.options = {**DEFAULTS, **options}
    self.name = f"opensf:{self.root}"
    self.up = "z" if self.options["frame"] == "ego" else "y"  # the ego frame's, or the models'
    folder = self.root / self.split
    if not folder.is_dir():
      raise DataError(folder, f"missing split folder (expected {self.root}/{self.split}/<log>.h5)")
    self.files = sorted(folder.glob("*.h5"))
    if not self.files:
      raise DataError(folder, "no <log>.h5 files")
    if self.options["lidar"] == "sensor" and not self.options["calibration"]:
      raise DataError(self.root, "lidar=sensor needs calibration=AV2_DIR")
    self.pairs = []  # (file, t0, t1)
    for path in self.files:
      try:
        with h5py.File(path, "r") as f:
          keys = _sorted_keys(f, path)
          labelled = [(k0, k1) for k0, k1 in zip(keys, keys[1:]) if "flow" in f[k0]]
          if self.options["region"] != "disc" and any("eval_mask" in f[k] for k in keys):
            labelled = [(k0, k1) for k0, k1 in labelled if "eval_mask" in f[k0]]
          self.pairs += [(path, k0, k1) for k0, k1 in labelled]
      except OSError as e:
        raise DataError(path, f"cannot open as HDF5, truncated or corrupt ({e})") from None
    if not self.pairs:
      raise DataError(folder, "no labelled pairs (no frame with 'flow' followed by another frame)")
    self._to_ego = {}  # file -> 4 x 4 ego <- stored lidar frame (identity: ego-frame lidar)

  def __len__(self):
    return len(self.pairs)

  def load(self, i):
    path, k0, k1 = self.pairs[i]
    try:
      with h5py.File(path, "r") as f:
        to_ego = self._lidar_to_ego(f, path)
        frame0 = _read(f, path, k0, _LABELLED + (("eval_mask",) if "eval_mask" in f[k0] else ()))
        frame1 = _read(f, path, k1, ("lidar", "ground_mask"))
    except OSError as e:
      raise DataError(path, f"group {k0}/{k1}: unreadable ({e})") from None
    for frame in (frame0, frame1):
      frame["lidar"] = _apply(to_ego, frame["lidar"])
    keep1 = self._keep(frame0, path, k0)
    keep2 = self._keep(frame1, path, k1)
    pc1 = frame0["lidar"][keep1]
    motion = frame0["ego_motion"].astype(np.float64)
    rigid = (pc1 @ motion[:3, :3].T + motion[:3, 3] - pc1).astype(np.float32)
    arrays = {"pc1": pc1, "pc2": frame1["lidar"][keep2], "flow": frame0["flow"][keep1],
              "rigid_flow": rigid}
    if self.options["frame"] == "camera":
      arrays = {k: frames.to_model(v, "z") for k, v in arrays.items()}
    mask = frame0["flow_is_valid"][keep1]
    if "eval_mask" in frame0:
      mask = mask & frame0["eval_mask"][keep1]
    if self.options["region"] == "sweep":  # scored on the challenge's points
      mask = mask & _challenge_points(frame0)[keep1]
    category = frame0["flow_category_indices"][keep1].astype(np.uint8)
    return Pair(**arrays, mask=mask, foreground=category != 0, category=category,
                ego_xy=np.ascontiguousarray(pc1[:, :2]), name=f"{path}:{k0}")

  def instances(self, i):
    """The labelled objects of pair i where the file carries them (`flow_instance_id`: 1 + the
    track's index in the file attribute `instances`, rows [uuid, label, category]; 0 none), else
    None: (N int track number per point of load(i)'s pc1, [(uuid, label, category)])."""
    path, k0, _ = self.pairs[i]
    try:
      with h5py.File(path, "r") as f:
        if "flow_instance_id" not in f[k0] or "instances" not in f.attrs:
          return None
        frame = _read(f, path, k0, _LABELLED + (("eval_mask",) if "eval_mask" in f[k0] else ()))
        ids = np.asarray(f[k0]["flow_instance_id"][()]).astype(np.int64).reshape(-1)
        table = _instance_table(f.attrs["instances"], path)
        frame["lidar"] = _apply(self._lidar_to_ego(f, path), frame["lidar"])
    except OSError as e:
      raise DataError(path, f"group {k0}: unreadable ({e})") from None
    if len(ids) != len(frame["lidar"]) or ids.min(initial=0) < 0 or ids.max(initial=0) > len(table):
      raise DataError(path, f"group {k0}: flow_instance_id has shape {ids.shape} and values up to "
                      f"{ids.max(initial=0)}, expected {len(frame['lidar'])} values in 0 .. "
                      f"{len(table)} (the attribute instances' rows)")
    return ids[self._keep(frame, path, k0)], table

  def _keep(self, frame, path, key) -> np.ndarray:
    points = frame["lidar"]
    finite = np.isfinite(points).all(1)
    if "flow" in frame:
      finite &= np.isfinite(frame["flow"]).all(1)
    if self.options["region"] == "sweep":
      keep = finite
      cuts = "region=sweep: the finite points"
    elif self.options["region"] == "challenge":
      keep = _challenge_points(frame)
      if "flow" in frame and not finite[keep].all():
        raise DataError(path, f"group {key}: {int((~finite[keep]).sum())} of the challenge's "
                        "points have a non-finite coordinate or flow")
      keep = keep & finite
      cuts = "region=challenge"
    else:
      keep = finite
      if self.options["ground"] == "remove":
        keep &= ~frame["ground_mask"]
      if self.options["max_range"]:
        keep &= np.hypot(points[:, 0], points[:, 1]) < self.options["max_range"]
      cuts = f"ground={self.options['ground']}, max_range={self.options['max_range']}"
    if keep.sum() < MIN_POINTS:
      raise DataError(path, f"group {key}: only {int(keep.sum())} points left after the cuts "
                      f"({cuts}), need at least {MIN_POINTS}")
    return keep

  def _lidar_to_ego(self, f, path) -> np.ndarray:
    """ego <- stored `lidar` frame of file `path` (identity for ego-frame files), cached."""
    if path not in self._to_ego:
      frame = self.options["lidar"]
      if frame == "auto":
        frame = _detect_lidar_frame(f, path)
        if frame is None:
          warnings.warn(f"{path}: no frame turns enough (0.03 degrees) to tell the frame of "
                        "'lidar'; read as the ego frame (OpenSceneFlow's converters write it, but "
                        "AV2's extract_av2.py since its commit 2bd9036 the sensor frame: then give "
                        "lidar=sensor,calibration=AV2_DIR; lidar=ego: no warning)", stacklevel=2)
          frame = "ego"
        if frame == "sensor" and not self.options["calibration"]:
          raise DataError(path, "'lidar' is in the sensor frame (OpenSceneFlow's extract_av2.py "
                          "since its commit 2bd9036; its flow is in the ego frame) and the file "
                          "does not hold the sensor's extrinsic: give calibration=AV2_DIR, the AV2 "
                          "split it was made from (or lidar=ego if you know it is the ego frame)")
      self._to_ego[path] = (np.eye(4) if frame == "ego"
                            else read_up_lidar_extrinsic(self.options["calibration"], path))
    return self._to_ego[path]

  def describe(self):
    opts = ", ".join(f"{k}={v}" for k, v in self.options.items())
    return (f"{self.name} split={self.split}: {len(self)} pairs from {len(self.files)} logs "
            f"({opts})")

  def __reduce__(self):  # worker processes re-index the folder
    return _reopen, (str(self.root), self.split, self.options)


def _reopen(root, split, options):
  return OpenSceneFlow(root, split, **options)


def sweep_id(name: str) -> tuple[str, int]:
  """av2's (log_id, timestamp_ns) of an opensf pair name FILE:TIMESTAMP (log_id: the file stem)."""
  file, _, stamp = str(name).rpartition(":")
  if not file or not stamp.lstrip("-").isdigit():
    raise DataError(name, "not an opensf pair name (expected <log>.h5:<timestamp_ns>)")
  return pathlib.Path(file).stem, int(stamp)


def _challenge_points(frame) -> np.ndarray:
  """The Argoverse 2 challenge's points of a frame: its eval_mask, else the non-ground points with
  |x|, |y| <= CHALLENGE_BOX_M (ego frame)."""
  if "eval_mask" in frame:
    return frame["eval_mask"].astype(bool)
  return ~frame["ground_mask"] & (np.abs(frame["lidar"][:, :2]) <= CHALLENGE_BOX_M).all(1)


def _instance_table(value, path) -> list[tuple[str, str, str]]:
  """The file attribute `instances` (JSON text, or an array of rows) as [(uuid, label, category)]."""
  if isinstance(value, bytes):
    value = value.decode()
  try:
    rows = json.loads(value) if isinstance(value, str) else np.asarray(value).tolist()
    table = [tuple(v.decode() if isinstance(v, bytes) else str(v) for v in row) for row in rows]
  except (ValueError, TypeError) as e:
    raise DataError(path, f"attribute instances: not a list of [uuid, label, category] ({e})") from None
  if any(len(row) != 3 for row in table):
    raise DataError(path, "attribute instances: rows must be [uuid, label, category]")
  return table


_LABELLED = ("lidar", "ground_mask", "flow", "flow_is_valid", "flow_category_indices", "ego_motion")


def _apply(transform_4x4, points_Nx3) -> np.ndarray:
  if np.array_equal(transform_4x4, np.eye(4)):
    return points_Nx3
  return (points_Nx3 @ transform_4x4[:3, :3].T + transform_4x4[:3, 3]).astype(np.float32)


def _detect_lidar_frame(f, path) -> str | None:
  """"ego" or "sensor" from the first labelled frame of `f` whose ego-motion turns by at least
  DECISIVE_ROTATION (module docstring); None when none decides."""
  keys = _sorted_keys(f, path)
  for k0 in (k for k in keys[:-1] if "flow" in f[k]):
    frame = _read(f, path, k0, _LABELLED)
    motion = frame["ego_motion"].astype(np.float64)
    angle = np.arccos(np.clip((np.trace(motion[:3, :3]) - 1) / 2, -1.0, 1.0))
    if angle < DECISIVE_ROTATION:
      continue
    p = frame["lidar"].astype(np.float64)
    background = (frame["flow_is_valid"] & (frame["flow_category_indices"] == 0)
                  & np.isfinite(p).all(1) & np.isfinite(frame["flow"]).all(1))
    if background.sum() < MIN_POINTS:
      continue
    p = p[background]
    rigid = p @ motion[:3, :3].T + motion[:3, 3] - p
    residual = float(np.median(np.linalg.norm(frame["flow"][background] - rigid, axis=1)))
    if residual <= 2e-5 + 0.02 * angle:  # float32 rounding: the flow was made from these points
      return "ego"
    if residual >= 0.3 * angle:  # the sensor sits metres from the ego origin
      return "sensor"
  return None


def read_up_lidar_extrinsic(av2_dir, h5_path) -> np.ndarray:
  """ego <- up_lidar (4 x 4) of the log `h5_path` was made from:
  AV2_DIR/<log>/calibration/egovehicle_SE3_sensor.feather, the row sensor_name == "up_lidar"
  (quaternion qw qx qy qz, translation tx_m ty_m tz_m)."""
  path = pathlib.Path(av2_dir).expanduser() / pathlib.Path(h5_path).stem / "calibration" / (
    "egovehicle_SE3_sensor.feather")
  try:
    import pyarrow.feather  # pylint: disable=import-outside-toplevel
  except ImportError:
    raise DataError(path, "reading AV2 calibration needs pyarrow (pip install pyarrow)") from None
  try:
    table = pyarrow.feather.read_table(path).to_pydict()
  except (OSError, ValueError) as e:
    raise DataError(path, f"cannot read the AV2 calibration ({e})") from None
  names = list(table.get("sensor_name", []))
  if "up_lidar" not in names:
    raise DataError(path, f"no up_lidar row (sensors: {names})")
  row = names.index("up_lidar")
  try:
    w, x, y, z, *t = (float(table[k][row]) for k in ("qw", "qx", "qy", "qz", "tx_m", "ty_m",
                                                     "tz_m"))
  except KeyError as e:
    raise DataError(path, f"lacks column {e}") from None
  n = np.sqrt(w * w + x * x + y * y + z * z)
  w, x, y, z = w / n, x / n, y / n, z / n
  out = np.eye(4)
  out[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
  out[:3, 3] = t
  return out


# name -> (trailing shape after N, or the whole shape for ego_motion; accepted dtype kinds, words)
_FIELDS = {"lidar": (None, "f", "N x >= 3 floats"), "ground_mask": ((), "biu", "N bools"),
           "flow": ((3,), "f", "N x 3 floats"), "flow_is_valid": ((), "biu", "N bools"),
           "flow_category_indices": ((), "iu", "N integers"),
           "ego_motion": ((4, 4), "f", "4 x 4 floats"), "eval_mask": ((), "biu", "N bools")}


def _read(f, path, key, names) -> dict:
  """The arrays `names` of group `key`, checked (lidar: its first 3 columns, float32; masks as
  bool); a missing or malformed one is a DataError naming the file and the group."""
  group = f[key]
  if not isinstance(group, h5py.Group):
    raise DataError(path, f"group {key}: is not a group")
  missing = [n for n in names if n not in group]
  if missing:
    raise DataError(path, f"group {key}: lacks {missing} (has {sorted(group.keys())})")
  out = {}
  for name in names:
    a = group[name][()]
    shape, kinds, words = _FIELDS[name]
    if name == "lidar":
      ok = a.ndim == 2 and a.shape[1] >= 3
    elif name == "ego_motion":
      ok = a.shape == shape
    else:
      if name == "eval_mask" and a.ndim == 2 and a.shape[1:] == (1,):
        a = a[:, 0]  # the challenge's mask files are N x 1
      ok = a.shape == (len(out["lidar"]), *shape)
    if not ok or a.dtype.kind not in kinds:
      n = len(out["lidar"]) if "lidar" in out else "N"
      raise DataError(path, f"group {key}: {name} has shape {a.shape} and dtype {a.dtype}, "
                      f"expected {words.replace('N', str(n), 1)}")
    if name == "lidar":
      a = a[:, :3]
    out[name] = a.astype(bool) if "b" in kinds else a.astype(np.float32) if kinds == "f" else a
  return out


def _open(arg: str, split: str | None) -> OpenSceneFlow:
  root, options = parse_spec(arg)
  if not root:
    raise DataError(f"opensf:{arg}", "missing root: expected opensf:DIR")
  return OpenSceneFlow(root, split, **options)


register("opensf", _open, needs_root=True)
