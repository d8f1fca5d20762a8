"""Flows and clouds as files other tools read: `save_flow` (--out of predict and jaxflow.nsfp),
`FlowSaver` (the flow of every pair, `--save_flows DIR` of predict and evaluate.py), `write_ply`,
`save_motion` (predict --lidar --ego_out); `check_outputs`: every output path of predict and
evaluate.py checked before any work (one line naming the flag; a missing folder made, and said).

One `.npy` per pair (float32 N x 3, row i the flow of pc1's point i as the model saw it), named by
the pair: `flow_stem(pair.name)`, the pair's name with every run of characters other than letters,
digits, '.', '-' and '_' replaced by '_' (e.g. "/data/KITTI/000002" -> "data_KITTI_000002.npy",
"/data/av2/val/log.h5:315966" -> "data_av2_val_log.h5_315966.npy").
"""

import os
import pathlib
import re

import numpy as np

from jaxflow.errors import ConfigError


FLOW_SUFFIXES = (".npy", ".txt", ".csv")


def check_flow_path(out: pathlib.Path):
  """A ConfigError naming --out unless `out` is a file name with a suffix save_flow writes (checked
  before any work is done)."""
  if out.is_dir():
    raise ConfigError(f"--out {out}: is a folder, expected a file name such as flow.npy")
  if out.suffix.lower() not in FLOW_SUFFIXES:
    raise ConfigError(f"--out {out}: unknown file type {out.suffix or '(no suffix)'!r}; "
                      f"use one of {', '.join(FLOW_SUFFIXES)}")


def _missing_folder(flag: str, path: pathlib.Path, folder: pathlib.Path) -> pathlib.Path | None:
  """None when `folder` exists and is writable; `folder` when it is missing (to be made); a
  ConfigError naming `flag` when it cannot be written."""
  if folder.is_dir():
    if not os.access(folder, os.W_OK | os.X_OK):
      raise ConfigError(f"{flag} {path}: cannot write into {folder} (no permission)")
    return None
  existing = next(p for p in (folder, *folder.parents) if p.exists())
  if not existing.is_dir():
    raise ConfigError(f"{flag} {path}: {existing} is a file, not a folder")
  if not os.access(existing, os.W_OK | os.X_OK):
    raise ConfigError(f"{flag} {path}: cannot create {folder} in {existing} (no permission)")
  return folder


def check_output(flag: str, path, suffixes=(), folder: bool = False) -> pathlib.Path | None:
  """Checks an output path before any work (predict's and evaluate.py's --out, --render, --json,
  --save_flows, ...): a file name with one of `suffixes` (any when empty) in a writable place, or
  with `folder`, a folder. Returns the folder to make when it is missing (check_outputs makes it);
  anything wrong is a ConfigError naming `flag`, one line."""
  path = pathlib.Path(path)
  if folder:
    if path.exists() and not path.is_dir():
      raise ConfigError(f"{flag} {path}: is a file, expected a folder")
    return _missing_folder(flag, path, path.absolute())
  if path.is_dir() or not path.name:
    raise ConfigError(f"{flag} {path}: is a folder, expected a file name")
  if suffixes and path.suffix.lower() not in suffixes:
    raise ConfigError(f"{flag} {path}: unknown file type {path.suffix or '(no suffix)'!r}; use "
                      f"{' or '.join(suffixes)}")
  if path.exists() and not os.access(path, os.W_OK):
    raise ConfigError(f"{flag} {path}: cannot overwrite it (no permission)")
  return _missing_folder(flag, path, path.absolute().parent)


def check_outputs(checks, make: bool = True) -> list[str]:
  """`check_output` of every (flag, path, suffixes, folder) with a path, then, with `make`, the
  missing folders made (none unless all are good): the notes saying which (docs/users.md: a
  missing folder is made, and said)."""
  missing = {}
  for flag, path, suffixes, folder in checks:
    if path:
      made = check_output(flag, path, suffixes, folder)
      if made is not None:
        missing.setdefault(made, flag)
  notes = []
  for folder, flag in missing.items() if make else ():
    try:
      folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
      raise ConfigError(f"{flag}: cannot create the folder {folder} ({e.strerror or e})") from None
    notes.append(f"{flag}: made the folder {folder}")
  return notes


def outputs_in_argv(argv, spec: dict) -> list[tuple]:
  """The (flag, path, suffixes, folder) of argv's output flags (`spec`: {name: (suffixes,
  folder)}), spelled --NAME=PATH or --NAME PATH: for check_outputs before the flags are parsed
  (before jax loads: a wrong path is said at once)."""
  checks = []
  args = list(argv[1:])
  for i, arg in enumerate(args):
    if arg == "--":
      break
    name, eq, value = arg.lstrip("-").partition("=")
    if arg.startswith("-") and name in spec:
      value = value if eq else (args[i + 1] if i + 1 < len(args) else "")
      checks.append((f"--{name}", value, *spec[name]))
  return checks


def save_flow(out: pathlib.Path, flow_Nx3):
  """.npy (float32 N x 3) or text (.txt: x y z per line, .csv: comma separated); an unwritable path
  is a ConfigError naming --out."""
  out = pathlib.Path(out)
  check_flow_path(out)
  try:
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".npy":
      with open(out, "wb") as f:
        np.save(f, flow_Nx3)
    else:
      np.savetxt(out, flow_Nx3, fmt="%.6f", delimiter="," if out.suffix.lower() == ".csv" else " ")
  except OSError as e:
    raise ConfigError(f"--out {out}: cannot write ({e.strerror or e})") from None


def save_motion(out, motion) -> pathlib.Path:
  """A rigid motion (rotation R, translation t: x -> R x + t) as a 4 x 4 matrix in a text file
  (predict's --ego_out); an unwritable path is a ConfigError naming --ego_out."""
  out = pathlib.Path(out)
  matrix = np.eye(4)
  matrix[:3, :3], matrix[:3, 3] = motion.rotation, motion.translation
  try:
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(out, matrix, fmt="%.9f", header="x2 = R x1 + t: [[R, t], [0, 0, 0, 1]]")
  except OSError as e:
    raise ConfigError(f"--ego_out {out}: cannot write ({e.strerror or e})") from None
  return out


def flow_stem(name: str) -> str:
  """A file name (without .npy) for a pair name."""
  return re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("_.") or "pair"


class FlowSaver:
  """Writes flows to `folder` (created), one FILE.npy per pair; two pairs that would share a file
  name are an error (never a silent overwrite)."""

  def __init__(self, folder):
    self.folder = pathlib.Path(folder)
    try:
      self.folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
      raise ConfigError(f"--save_flows {self.folder}: cannot create ({e.strerror or e})") from None
    self.written: dict[str, str] = {}  # stem -> pair name

  def save(self, name: str, flow_Nx3) -> pathlib.Path:
    stem = flow_stem(name)
    if self.written.get(stem, name) != name:
      raise ConfigError(f"--save_flows: pairs {self.written[stem]!r} and {name!r} map to the same "
                        f"file {stem}.npy")
    self.written[stem] = name
    path = self.folder / f"{stem}.npy"
    try:
      np.save(path, np.asarray(flow_Nx3, np.float32))
    except OSError as e:
      raise ConfigError(f"--save_flows {path}: cannot write ({e.strerror or e})") from None
    return path

  def add(self, batch: dict, pred_BxNx3):
    """The real (not padding) pairs of an evaluation batch."""
    pred = np.asarray(pred_BxNx3)
    for i, name in enumerate(batch["names"]):
      if batch["pair_valid"][i]:
        self.save(name, pred[i])


def write_ply(path, points_Nx3) -> pathlib.Path:
  """Writes points as a binary little-endian PLY (float x, y, z): readable by read_points, MeshLab,
  CloudCompare; e.g. write_ply("moved.ply", pc1 + flow)."""
  points_Nx3 = np.ascontiguousarray(points_Nx3, dtype="<f4")
  if points_Nx3.ndim != 2 or points_Nx3.shape[1] != 3:
    raise ValueError(f"write_ply: expected N x 3 points, got shape {points_Nx3.shape}")
  header = ("ply\nformat binary_little_endian 1.0\ncomment written by jaxflow\n"
            f"element vertex {len(points_Nx3)}\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n")
  path = pathlib.Path(path)
  path.write_bytes(header.encode("ascii") + points_Nx3.tobytes())
  return path
