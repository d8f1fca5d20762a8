"""opensf: OpenSceneFlow h5 logs, the three-way EPE, conversion, evaluate.py on them, --save-flows.

The fixture is written here with h5py from the documented layout (DESIGN.md section 7), so the
reader is checked against the construction, not against itself.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import jax
import numpy as np
import pytest

from jaxflow import checkpointing, evaluation, export, training
from jaxflow.configs import default
from jaxflow.data import convert, eval_batches, open_dataset
from jaxflow.errors import DataError
from jaxflow.metrics import three_way_epe
from jaxflow.model import build_model

REPO = Path(__file__).absolute().parent.parent
# log -> [(timestamp, labelled)]: numeric order differs from string order (9 < 10 < 11 < 100)
LOGS = {"log_a": [(10, True), (9, True), (100, False), (11, False)],
        "log_b": [(5, True), (6, False)]}
PAIRS = [("log_a", 9, 10), ("log_a", 10, 11), ("log_b", 5, 6)]  # log_a's 11 has no flow


def yaw(degrees, t):
  a = np.radians(degrees)
  m = np.eye(4)
  m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
  m[:3, 3] = t
  return m


def make_frame(rng, labelled, moving=True):
  """~300 points: ground (z -1.8), far points (45 m), a static background box, a parked car
  (category 2) and, when `moving`, a car (category 1) moving 1 m/frame along x."""
  parts = {"ground": rng.uniform(-30, 30, (100, 3)) * [1, 1, 0] + [0, 0, -1.8],
           "far": rng.uniform(-1, 1, (30, 3)) + [45, 0, 0],
           "building": rng.uniform(0, 1, (80, 3)) * [2, 10, 4] + [12, -20, -1.8],
           "parked": rng.uniform(0, 1, (40, 3)) * [4, 2, 1.5] + [-8, 5, -1.8],
           "car": rng.uniform(0, 1, (50 if moving else 0, 3)) * [4, 2, 1.5] + [6, 3, -1.8]}
  kind = np.concatenate([[k] * len(v) for k, v in parts.items()])
  xyz = np.concatenate(list(parts.values())).astype(np.float32)
  frame = {"lidar": np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32),  # + intensity
           "ground_mask": kind == "ground", "pose": np.eye(4, dtype=np.float32)}
  rigid = None
  if labelled:
    ego = yaw(2.0, [1.5, 0.2, 0.0])
    rigid = xyz @ ego[:3, :3].T + ego[:3, 3] - xyz
    flow = rigid + np.where(kind[:, None] == "car", [1.0, 0.0, 0.0], 0.0)
    frame.update(flow=flow.astype(np.float32), flow_is_valid=rng.uniform(size=len(xyz)) > 0.1,
                 flow_category_indices=np.select([kind == "car", kind == "parked"], [1, 2], 0)
                 .astype(np.uint8), ego_motion=ego.astype(np.float32))
  return frame, kind, rigid


@pytest.fixture(scope="module")
def opensf_dir(tmp_path_factory):
  """DIR/val/log_a.h5 (pairs 9-10, 10-11; 11 has no flow), DIR/val/log_b.h5 (5-6, no mover)."""
  root = tmp_path_factory.mktemp("opensf")
  (root / "val").mkdir()
  rng = np.random.default_rng(0)
  truth = {}
  for log, frames in LOGS.items():
    with h5py.File(root / "val" / f"{log}.h5", "w") as f:
      for stamp, labelled in frames:
        frame, kind, rigid = make_frame(rng, labelled, moving=log == "log_a")
        group = f.create_group(str(stamp))
        for k, v in frame.items():
          group.create_dataset(k, data=v)
        truth[log, stamp] = (frame, kind, rigid)
  return root, truth


def test_pairs_cuts_and_labels_follow_the_layout(opensf_dir):
  root, truth = opensf_dir
  ds = open_dataset(f"opensf:{root}", "val")
  assert len(ds) == len(PAIRS) and "3 pairs from 2 logs" in ds.describe()
  for i, (log, t0, t1) in enumerate(PAIRS):
    pair = ds[i]
    frame0, kind0, rigid0 = truth[log, t0]
    frame1, kind1, _ = truth[log, t1]
    kept0 = (kind0 != "ground") & (kind0 != "far")  # by construction: not ground, within 35 m
    kept1 = (kind1 != "ground") & (kind1 != "far")
    assert pair.name == f"{root / 'val' / log}.h5:{t0}"
    np.testing.assert_array_equal(pair.pc1, frame0["lidar"][kept0, :3])
    np.testing.assert_array_equal(pair.pc2, frame1["lidar"][kept1, :3])
    np.testing.assert_array_equal(pair.flow, frame0["flow"][kept0])
    np.testing.assert_array_equal(pair.mask, frame0["flow_is_valid"][kept0])
    np.testing.assert_allclose(pair.rigid_flow, rigid0[kept0], atol=1e-5)
    np.testing.assert_array_equal(pair.foreground, np.isin(kind0[kept0], ["car", "parked"]))
  keep_all = open_dataset(f"opensf:{root},ground=keep,max_range=0", "val")[0]
  assert len(keep_all.pc1) == len(truth["log_a", 9][0]["lidar"])
  camera = open_dataset(f"opensf:{root},frame=camera", "val")[0]
  np.testing.assert_array_equal(camera.pc1, ds[0].pc1[:, [1, 2, 0]])  # ego z up -> camera y up
  np.testing.assert_array_equal(camera.rigid_flow, ds[0].rigid_flow[:, [1, 2, 0]])


def test_errors_name_the_file_and_the_group(opensf_dir, tmp_path):
  root, _ = opensf_dir
  with pytest.raises(DataError, match="missing split folder"):
    open_dataset(f"opensf:{root}", "test")
  with pytest.raises(DataError, match="bad option 'range=3'"):
    open_dataset(f"opensf:{root},range=3", "val")
  (tmp_path / "val").mkdir()
  with h5py.File(tmp_path / "val" / "broken.h5", "w") as f:
    frame, _, _ = make_frame(np.random.default_rng(1), True)
    for stamp in ("1", "2"):
      g = f.create_group(stamp)
      for k, v in frame.items():
        if not (stamp == "1" and k == "flow_is_valid"):
          g.create_dataset(k, data=v if k != "ground_mask" or stamp == "1" else v[:5])
  ds = open_dataset(f"opensf:{tmp_path}", "val")
  with pytest.raises(DataError, match=r"broken.h5: group 1: lacks \['flow_is_valid'\]"):
    ds[0]
  with h5py.File(tmp_path / "val" / "broken.h5", "a") as f:
    f["1"].create_dataset("flow_is_valid", data=frame["flow_is_valid"])
  with pytest.raises(DataError, match=r"broken.h5: group 2: ground_mask has shape \(5,\)"):
    ds[0]


def test_three_way_epe_matches_a_loop_over_points():
  rng = np.random.default_rng(3)
  n = 400
  gt, rigid = rng.normal(0, 1, (n, 3)), rng.normal(0, 1, (n, 3))
  static = rng.uniform(size=n) < 0.5
  gt[static] = rigid[static] + rng.normal(0, 0.01, (static.sum(), 3))  # most within 5 cm
  pred = gt + rng.normal(0, 0.2, (n, 3))
  fg, mask = rng.uniform(size=n) < 0.4, rng.uniform(size=n) < 0.9
  sums, counts = {"fd": 0.0, "fs": 0.0, "bs": 0.0}, {"fd": 0, "fs": 0, "bs": 0}
  for i in range(n):
    if not mask[i]:
      continue
    moving = np.sqrt(np.sum((gt[i] - rigid[i]) ** 2)) >= 0.05
    cls = ("fd" if moving else "fs") if fg[i] else (None if moving else "bs")
    if cls:
      sums[cls] += np.sqrt(np.sum((pred[i] - gt[i]) ** 2))
      counts[cls] += 1
  want = {k: sums[k] / counts[k] for k in sums}
  got = three_way_epe(pred, gt, rigid, fg, mask)
  for k in want:
    assert got[k] == pytest.approx(want[k], rel=1e-9)
  assert got["mean"] == pytest.approx(sum(want.values()) / 3, rel=1e-9)
  no_fd = three_way_epe(pred, gt, rigid, fg & static, mask)  # no foreground point moves
  assert np.isnan(no_fd["fd"]) and no_fd["mean"] == pytest.approx((no_fd["fs"] + no_fd["bs"]) / 2)


def test_evaluation_averages_three_way_over_pairs_leaving_out_empty_classes(opensf_dir):
  root, _ = opensf_dir
  ds = open_dataset(f"opensf:{root}", "val")
  got = evaluation.evaluate_zero_flow(ds, num_points=64, batch_size=2)["three_way"]
  per_pair = [three_way_epe(np.zeros_like(b["flow"][0]), b["flow"][0], b["rigid_flow"][0],
                            b["foreground"][0], b["mask"][0]) for b in eval_batches(ds, 1, 64)]
  assert np.isnan(per_pair[2]["fd"]) and not np.isnan(per_pair[0]["fd"])  # log_b: no mover
  assert got["pairs"] == 3
  assert got["fd"] == pytest.approx((per_pair[0]["fd"] + per_pair[1]["fd"]) / 2, rel=1e-6)
  for k in ("fs", "bs", "mean"):
    assert got[k] == pytest.approx(np.mean([p[k] for p in per_pair]), rel=1e-6)
  assert "three_way" not in evaluation.evaluate_zero_flow(
    open_dataset("synthetic_lidar:2", "test"), num_points=64, batch_size=1)


def test_conversion_keeps_the_ego_motion_and_labels(opensf_dir, tmp_path):
  root, _ = opensf_dir
  out = tmp_path / "opensf.h5"
  assert convert.main(["--dataset", f"opensf:{root}", "--split", "val", "--out", str(out)]) == 0
  source, converted = open_dataset(f"opensf:{root}", "val"), open_dataset(f"h5:{out}")
  assert len(converted) == 3
  for a, b in zip(source, converted):
    for k in ("pc1", "pc2", "flow", "mask", "rigid_flow", "foreground", "name"):
      np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
  kwargs = dict(num_points=64, batch_size=1)
  assert (evaluation.evaluate_zero_flow(converted, **kwargs)["three_way"]
          == evaluation.evaluate_zero_flow(source, **kwargs)["three_way"])


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
  """A stage-1 checkpoint of the smoke model (random weights: the command path is checked)."""
  config = default.get_config("smoke")
  model = build_model(config.model)
  state = training.create_train_state(training.init_params(model, config, jax.random.key(0)),
                                      training.make_optimizer(config, 1))
  path = tmp_path_factory.mktemp("ckpt")
  ckpts = checkpointing.Checkpoints(path / "checkpoints")
  ckpts.save(1, state, config)
  ckpts.close()
  return path


def test_evaluate_py_reports_three_way_and_saves_every_flow(opensf_dir, checkpoint, tmp_path):
  root, _ = opensf_dir
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  out, flows = tmp_path / "r.json", tmp_path / "flows"
  proc = subprocess.run(
    [sys.executable, "evaluate.py", "--config", "configs/default.py:smoke", "--checkpoint",
     str(checkpoint), "--dataset", f"opensf:{root}", "--split", "val", "--json", str(out),
     "--save-flows", str(flows), "--config.eval.num_points=0", "--config.eval.batch_size=1"],
    cwd=REPO, env=env, capture_output=True, text=True, timeout=1200)
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert "three-way" in proc.stdout and "EPE FD" in proc.stdout
  results = json.loads(out.read_text())
  assert results["three_way"]["pairs"] == 3
  ds = open_dataset(f"opensf:{root}", "val")
  assert sorted(p.name for p in flows.iterdir()) == sorted(
    export.flow_stem(p.name) + ".npy" for p in ds)
  for pair in ds:  # whole clouds: one row per point of pc1; the metric is of these flows
    flow = np.load(flows / (export.flow_stem(pair.name) + ".npy"))
    assert flow.shape == pair.pc1.shape and flow.dtype == np.float32
  epe = np.mean([np.linalg.norm(np.load(flows / (export.flow_stem(p.name) + ".npy"))[p.mask]
                                - p.flow[p.mask], axis=1).mean() for p in ds])
  assert results["epe"] == pytest.approx(epe, rel=1e-4)
  # The three-way mean of the saved flows by the challenge's definition, a plain loop: classes
  # foreground-dynamic (|gt - rigid| >= 5 cm), foreground-static and background-static, the mean
  # of the classes a pair has, averaged over the pairs.
  means = []
  for p in ds:
    err = np.linalg.norm(np.load(flows / (export.flow_stem(p.name) + ".npy")) - p.flow, axis=1)
    dynamic = np.linalg.norm(p.flow - p.rigid_flow, axis=1) >= 0.05
    classes = [p.foreground & dynamic, p.foreground & ~dynamic, ~p.foreground & ~dynamic]
    means.append(np.mean([err[c & p.mask].mean() for c in classes if (c & p.mask).any()]))
  assert results["three_way"]["mean"] == pytest.approx(np.mean(means), rel=1e-4)
