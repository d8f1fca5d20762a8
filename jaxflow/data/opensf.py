"""OpenSceneFlow's unified h5 format (Argoverse 2, Waymo, nuScenes, ... as converted by the
OpenSceneFlow toolkit; DESIGN.md section 7), registered as "opensf".

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
    jaxflow.frames); evaluation rotates ego clouds into it before the model and the flow back
    after (frames.dataset_up), so either gives the same flow; the metrics do not change under it.
mask = flow_is_valid; Pair.rigid_flow = ego_motion applied to pc1, minus pc1; Pair.foreground =
flow_category_indices != 0 (the three-way EPE, `jaxflow.metrics.three_way_epe`). Errors name the
file and the group. A split is a subfolder (train, val, test; default train).
"""

import pathlib

import h5py
import numpy as np

from jaxflow.data.pointfiles import MIN_POINTS
from jaxflow.data.registry import Dataset, Pair, register
from jaxflow.errors import DataError

DEFAULTS = {"ground": "remove", "max_range": 35.0, "frame": "ego"}
CHOICES = {"ground": ("remove", "keep"), "frame": ("ego", "camera")}
TO_CAMERA = [1, 2, 0]  # ego (x forward, y left, z up) -> (x left, y up, z forward): frames


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
    elif value not in CHOICES[key]:
      raise DataError(f"opensf:{arg}", f"{key}={value!r}; expected one of {CHOICES[key]}")
    else:
      options[key] = value
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
    folder = self.root / self.split
    if not folder.is_dir():
      raise DataError(folder, f"missing split folder (expected {self.root}/{self.split}/<log>.h5)")
    self.files = sorted(folder.glob("*.h5"))
    if not self.files:
      raise DataError(folder, "no <log>.h5 files")
    self.pairs = []  # (file, t0, t1)
    for path in self.files:
      try:
        with h5py.File(path, "r") as f:
          keys = _sorted_keys(f, path)
          self.pairs += [(path, k0, k1) for k0, k1 in zip(keys, keys[1:]) if "flow" in f[k0]]
      except OSError as e:
        raise DataError(path, f"cannot open as HDF5, truncated or corrupt ({e})") from None
    if not self.pairs:
      raise DataError(folder, "no labelled pairs (no frame with 'flow' followed by another frame)")

  def __len__(self):
    return len(self.pairs)

  def load(self, i):
    path, k0, k1 = self.pairs[i]
    try:
      with h5py.File(path, "r") as f:
        frame0 = _read(f, path, k0, ("lidar", "ground_mask", "flow", "flow_is_valid",
                                     "flow_category_indices", "ego_motion"))
        frame1 = _read(f, path, k1, ("lidar", "ground_mask"))
    except OSError as e:
      raise DataError(path, f"group {k0}/{k1}: unreadable ({e})") from None
    keep1 = self._keep(frame0, path, k0)
    keep2 = self._keep(frame1, path, k1)
    pc1 = frame0["lidar"][keep1]
    motion = frame0["ego_motion"].astype(np.float64)
    rigid = (pc1 @ motion[:3, :3].T + motion[:3, 3] - pc1).astype(np.float32)
    arrays = {"pc1": pc1, "pc2": frame1["lidar"][keep2], "flow": frame0["flow"][keep1],
              "rigid_flow": rigid}
    if self.options["frame"] == "camera":
      arrays = {k: np.ascontiguousarray(v[:, TO_CAMERA]) for k, v in arrays.items()}
    return Pair(**arrays, mask=frame0["flow_is_valid"][keep1],
                foreground=frame0["flow_category_indices"][keep1] != 0, name=f"{path}:{k0}")

  def _keep(self, frame, path, key) -> np.ndarray:
    points = frame["lidar"]
    keep = np.isfinite(points).all(1)
    if "flow" in frame:
      keep &= np.isfinite(frame["flow"]).all(1)
    if self.options["ground"] == "remove":
      keep &= ~frame["ground_mask"]
    if self.options["max_range"]:
      keep &= np.hypot(points[:, 0], points[:, 1]) < self.options["max_range"]
    if keep.sum() < MIN_POINTS:
      raise DataError(path, f"group {key}: only {int(keep.sum())} points left after the cuts "
                      f"(ground={self.options['ground']}, max_range={self.options['max_range']}), "
                      f"need at least {MIN_POINTS}")
    return keep

  def describe(self):
    opts = ", ".join(f"{k}={v}" for k, v in self.options.items())
    return (f"{self.name} split={self.split}: {len(self)} pairs from {len(self.files)} logs "
            f"({opts})")

  def __reduce__(self):  # worker processes re-index the folder
    return _reopen, (str(self.root), self.split, self.options)


def _reopen(root, split, options):
  return OpenSceneFlow(root, split, **options)


# name -> (trailing shape after N, or the whole shape for ego_motion; accepted dtype kinds, words)
_FIELDS = {"lidar": (None, "f", "N x >= 3 floats"), "ground_mask": ((), "biu", "N bools"),
           "flow": ((3,), "f", "N x 3 floats"), "flow_is_valid": ((), "biu", "N bools"),
           "flow_category_indices": ((), "iu", "N integers"),
           "ego_motion": ((4, 4), "f", "4 x 4 floats")}


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
