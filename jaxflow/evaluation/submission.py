"""The Argoverse 2 scene-flow challenge's files: predictions in the submission layout and, for a
dataset with labels, the matching annotation files, so that av2's own evaluator scores them.

    DIR/<log_id>/<timestamp_ns>.feather              flow_tx_m, flow_ty_m, flow_tz_m (float16),
                                                     is_dynamic (bool): one row per point evaluated
    DIR_annotations/<log_id>/<timestamp_ns>.feather  category_indices (uint8), is_close, is_dynamic,
                                                     is_valid (bool), flow_t*_m (float16)

    python -m av2.evaluation.scene_flow.eval DIR_annotations DIR    # av2's evaluator

(av2's `evaluate_directories(ANNOTATIONS, DIR)` + `results_to_dict` give the numbers evaluate.py
printed as "av2 official": the rows are the same points with the same float16 flows.) The rows
follow pc1's order; with opensf's region=challenge and whole clouds (num_points 0) they are the
challenge's eval-mask points of sweep 0 in file order, the rows the challenge expects. is_dynamic of
a prediction: |flow - ego-motion flow| >= 0.05 m (`jaxflow.evaluation.av2_eval.pair_labels`).
Writing feather needs pyarrow (`pip install pyarrow`, in the dev extra); nothing here needs the av2
package.
"""

import pathlib

import numpy as np

from jaxflow.errors import ConfigError
from jaxflow.evaluation import av2_eval
from jaxflow.geometry import frames

FLOW_COLUMNS = ("flow_tx_m", "flow_ty_m", "flow_tz_m")


def annotations_folder(folder) -> pathlib.Path:
  """Where the annotation files of submission folder DIR go: DIR_annotations beside it."""
  folder = pathlib.Path(folder)
  return folder.with_name(folder.name + "_annotations")


def _write(path: pathlib.Path, columns: dict):
  try:
    import pyarrow  # pylint: disable=import-outside-toplevel
    import pyarrow.feather  # pylint: disable=import-outside-toplevel
  except ImportError:
    raise ConfigError("--submission writes feather files, which needs pyarrow: pip install "
                      "'jaxflow[av2]' (or pyarrow)") from None
  try:
    path.parent.mkdir(parents=True, exist_ok=True)
    pyarrow.feather.write_feather(pyarrow.table(columns), str(path))
  except OSError as e:
    raise ConfigError(f"--submission {path}: cannot write ({e.strerror or e})") from None


def write_prediction(folder, log_id: str, timestamp_ns: int, flow_Nx3,
                     is_dynamic_N) -> pathlib.Path:
  """FOLDER/<log_id>/<timestamp_ns>.feather of one sweep pair's predicted flow (float16 columns)."""
  flow = np.asarray(flow_Nx3).astype(np.float16)
  path = pathlib.Path(folder) / str(log_id) / f"{int(timestamp_ns)}.feather"
  _write(path, {**{c: flow[:, k] for k, c in enumerate(FLOW_COLUMNS)},
                "is_dynamic": np.asarray(is_dynamic_N, bool)})
  return path


def write_annotation(folder, log_id: str, timestamp_ns: int, labels: dict) -> pathlib.Path:
  """FOLDER/<log_id>/<timestamp_ns>.feather in av2's annotation layout, from `pair_labels`."""
  gt = np.asarray(labels["gt"]).astype(np.float16)
  path = pathlib.Path(folder) / str(log_id) / f"{int(timestamp_ns)}.feather"
  _write(path, {"category_indices": labels["category"].astype(np.uint8),
                "is_close": labels["is_close"].astype(bool),
                "is_dynamic": labels["is_dynamic"].astype(bool),
                "is_valid": labels["is_valid"].astype(bool),
                **{c: gt[:, k] for k, c in enumerate(FLOW_COLUMNS)}})
  return path


class SubmissionWriter:
  """Receives every evaluated pair (`add(name, labels)`: `av2_eval.Official`'s on_pair) and writes
  its prediction and annotation files, the flows in the ego frame (opensf's frame=camera is turned
  back). Pair names are opensf's FILE:TIMESTAMP. The flows must be whole clouds: num_points
  (config.eval.num_points) 0, else a ConfigError (a sample is not rows of the sweep)."""

  def __init__(self, folder, num_points, dataset=None):
    if num_points:
      raise ConfigError(f"--submission needs every point of each sweep: give "
                        f"--config.eval.num_points=0 (it is {num_points})")
    name = getattr(dataset, "name", "")
    if dataset is not None and not name.startswith("opensf:"):
      raise ConfigError(f"--submission needs an Argoverse 2 dataset with labels (opensf:DIR), got "
                        f"{name or type(dataset).__name__}")
    self.folder = pathlib.Path(folder)
    self.annotations = annotations_folder(self.folder)
    self.files = 0
    for f in (self.folder, self.annotations):  # old files would be scored with the new ones
      if f.exists() and any(f.rglob("*.feather")):
        raise ConfigError(f"--submission {self.folder}: {f} already holds .feather files; give a "
                          "new folder or empty it")
    options = getattr(dataset, "options", None)
    up = "z" if dataset is None else dataset.up
    # columns that bring a flow of the reader's frame back to the ego frame (z up)
    self.to_ego = None if up == "z" else frames.permutation(up, "z")
    self.note = None
    if options is None or options.get("region") != "challenge":
      self.note = ("--submission: the rows are the points evaluated, not the challenge's eval-mask "
                   "points; for a challenge submission open the dataset with region=challenge "
                   "(opensf:DIR,region=challenge)")

  def add(self, name, labels: dict):
    from jaxflow.data.opensf import sweep_id  # pylint: disable=import-outside-toplevel

    log_id, stamp = sweep_id(name)
    if self.to_ego is not None:  # av2's files hold ego-frame flows
      labels = {**labels, "pred": labels["pred"][:, self.to_ego],
                "gt": labels["gt"][:, self.to_ego]}
    write_prediction(self.folder, log_id, stamp, labels["pred"], labels["pred_dynamic"])
    write_annotation(self.annotations, log_id, stamp, labels)
    self.files += 1

  def summary(self) -> str:
    return (f"{self.folder}: {self.files} prediction files in the AV2 submission layout, "
            f"{self.annotations}: their annotations; av2's check: python -m "
            f"av2.evaluation.scene_flow.eval {self.annotations} {self.folder}")


def user_pair(folder, pc1_path, pc1_Nx3, flow_Nx3, sweep) -> list:
  """predict's --submission (None: nothing, []): `write_user_pair` with the ego-motion of
  `sweep` (sweep.SweepInfo of predict --lidar; None without --lidar: a ConfigError)."""
  if not folder:
    return []
  if not sweep:
    raise ConfigError("--submission needs --lidar (is_dynamic uses the sweeps' ego-motion)")
  return [write_user_pair(folder, pc1_path, flow_Nx3, sweep.motion.flow(pc1_Nx3))]


def write_user_pair(folder, pc1_path, flow_Nx3, ego_flow_Nx3) -> pathlib.Path:
  """predict's --submission: FOLDER/<log_id>/<timestamp_ns>.feather for the user's sweep PC1, one
  row per point of PC1 in file order; is_dynamic = |flow - ego_flow| >= 0.05 m. <timestamp_ns> is
  PC1's file stem (AV2 sweeps are named so), <log_id> the nearest folder above it not named
  'lidar' or 'sensors' (AV2: <log_id>/sensors/lidar/<timestamp_ns>.feather)."""
  path = pathlib.Path(pc1_path).absolute()
  if not path.stem.isdigit():
    raise ConfigError(f"--submission: {pc1_path}: the file name must be the sweep's timestamp in "
                      "ns (as AV2 names sweeps: <log_id>/sensors/lidar/<timestamp_ns>.feather)")
  log = next((p.name for p in path.parents if p.name not in ("lidar", "sensors")), "")
  if not log:
    raise ConfigError(f"--submission: {pc1_path}: no folder above it to name the log")
  flow = np.asarray(flow_Nx3, np.float32)
  dynamic = np.linalg.norm(flow - np.asarray(ego_flow_Nx3, np.float32), axis=-1) >= (
    av2_eval.DYNAMIC_THRESHOLD)
  return write_prediction(folder, log, int(path.stem), flow, dynamic)
