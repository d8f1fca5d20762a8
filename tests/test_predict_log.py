"""`predict` on a list of sweeps (jaxflow.predict_log): one flow a consecutive pair, the method
loaded once, the order as given, and bad lists refused with one line naming the file."""

import numpy as np
import pytest

from jaxflow import inference, predict

import commands

# The sensor's pose at each sweep in a fixed world: (yaw degrees, x, y). Each step moves
# differently, so a flow written for the wrong pair (or in the wrong order) cannot match its
# step's motion.
POSES = ((0.0, 0.0, 0.0), (2.0, 1.0, 0.0), (3.0, 1.5, 0.3))


def _rotation(yaw_deg):
  a = np.radians(yaw_deg)
  return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def _world(rng):
  """A static street: boxes at fixed places (the sweeps' shared structure)."""
  return np.concatenate([rng.uniform(0, 1, (80, 3)) * [3, 2, 1.6] + [x, y, -1.7]
                         for x, y in ((6, 2), (-8, 4), (3, -9), (-4, -7))])


def _sweep(world, pose, rng):
  """The world seen from `pose` (sensor frame, z up), with a fresh sampling of the ground."""
  yaw, x, y = pose
  ground = np.c_[rng.uniform(-25, 25, (250, 2)) + [x, y], rng.normal(-1.7, 0.02, 250)]
  points = np.concatenate([ground, world])
  return ((points - [x, y, 0]) @ _rotation(yaw)).astype(np.float32)  # R^T (w - T)


def static_flow(points, pose1, pose2):
  """The true flow of static points seen at pose1 to pose2's frame: R2^T (R1 p + T1 - T2) - p."""
  (a1, x1, y1), (a2, x2, y2) = pose1, pose2
  world = points @ _rotation(a1).T + [x1, y1, 0]
  return (world - [x2, y2, 0]) @ _rotation(a2) - points


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
  d = tmp_path_factory.mktemp("log")
  rng = np.random.default_rng(0)
  world = _world(rng)
  paths = []
  for i, pose in enumerate(POSES):
    paths.append(d / f"s{i}.npy")
    np.save(paths[-1], _sweep(world, pose, rng))
  (d / "broken.npy").write_bytes(b"\x93NUMPY garbage")
  (d / "other").mkdir()
  np.save(d / "other" / "s1.npy", np.load(paths[1]))  # the same name as s1, another folder
  return d, paths


def _flow_error(path_out, path1, pose1, pose2):
  points = np.load(path1)
  return np.linalg.norm(np.load(path_out) - static_flow(points, pose1, pose2), axis=1).mean()


def test_a_log_writes_each_consecutive_pair_once_loaded(sweeps, tmp_path, monkeypatch):
  d, paths = sweeps
  loads = []
  real_load = inference.load_predictor
  monkeypatch.setattr(inference, "load_predictor",
                      lambda *a, **k: loads.append(1) or real_load(*a, **k))
  out = tmp_path / "flows"
  done = commands.run(predict.run, *paths, "--lidar", "--out", out)
  assert done.returncode == 0, done.stderr
  assert sorted(p.name for p in out.iterdir()) == ["s0.npy", "s1.npy"]
  assert len(loads) == 1  # the method loaded once for the whole log
  assert f"3 sweeps in the order given (2 pairs): {paths[0]}, {paths[1]}, {paths[2]}" in done.stderr
  # Each pair's flow is its own step's motion (a 1 m step, then a 0.6 m one): within a cm on
  # average (a flow of the other step is off by decimetres).
  assert _flow_error(out / "s0.npy", paths[0], POSES[0], POSES[1]) < 0.01
  assert _flow_error(out / "s1.npy", paths[1], POSES[1], POSES[2]) < 0.01


def test_sweeps_are_taken_in_the_order_given(sweeps, tmp_path):
  d, paths = sweeps
  out = tmp_path / "backwards"
  done = commands.run(predict.run, paths[2], paths[1], paths[0], "--lidar", "--out", out)
  assert done.returncode == 0, done.stderr
  assert f"in the order given (2 pairs): {paths[2]}, {paths[1]}, {paths[0]}" in done.stderr
  assert sorted(p.name for p in out.iterdir()) == ["s1.npy", "s2.npy"]
  assert _flow_error(out / "s2.npy", paths[2], POSES[2], POSES[1]) < 0.01
  assert _flow_error(out / "s1.npy", paths[1], POSES[1], POSES[0]) < 0.01


def _refused(done, *words):
  assert done.returncode == 2, done.stderr
  lines = [line for line in done.stderr.splitlines() if line.startswith("error:")]
  assert len(lines) == 1 and all(w in lines[0] for w in words), done.stderr


def test_bad_lists_are_refused_naming_the_file(sweeps, tmp_path):
  d, paths = sweeps
  out = tmp_path / "out"
  _refused(commands.run(predict.run, paths[0], "--lidar", "--out", out), str(paths[0]),
           "one sweep alone")
  _refused(commands.run(predict.run, paths[0], d / "missing.npy", paths[2], "--lidar", "--out",
                        out), str(d / "missing.npy"), "missing")
  _refused(commands.run(predict.run, paths[0], d / "broken.npy", paths[2], "--lidar", "--out",
                        out), str(d / "broken.npy"))
  _refused(commands.run(predict.run, paths[0], paths[1], d / "other" / "s1.npy", "--lidar",
                        "--out", out), str(d / "other" / "s1.npy"), "same name")
  assert not out.exists()  # nothing written before the list was checked
  full = tmp_path / "full"
  full.mkdir()
  (full / "notes.txt").write_text("mine")
  _refused(commands.run(predict.run, *paths, "--lidar", "--out", full), str(full), "other files",
           "notes.txt")
  _refused(commands.run(predict.run, *paths, "--lidar", "--out", tmp_path / "flow.npy"),
           "--out", "folder")
  _refused(commands.run(predict.run, *paths, "--lidar", "--out", out, "--render", "x.png"),
           "--render")
