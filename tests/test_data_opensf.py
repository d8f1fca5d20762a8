"""opensf: OpenSceneFlow h5 logs, the three-way EPE, conversion, evaluate.py on them, --save_flows.

The fixture is written here with h5py from the documented layout (OpenSceneFlow's converters), so
the reader is checked against the construction, not against itself.
"""

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from jaxflow import evaluate
from jaxflow.data import convert, eval_batches, open_dataset, opensf
from jaxflow.errors import DataError
from jaxflow.evaluation import evaluator, export
from jaxflow.evaluation.metrics import three_way_epe

import commands

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
  got = evaluator.evaluate_zero_flow(ds, num_points=64, batch_size=2)["three_way_local"]
  per_pair = [three_way_epe(np.zeros_like(b["flow"][0]), b["flow"][0], b["rigid_flow"][0],
                            b["foreground"][0], b["mask"][0]) for b in eval_batches(ds, 1, 64)]
  assert np.isnan(per_pair[2]["fd"]) and not np.isnan(per_pair[0]["fd"])  # log_b: no mover
  assert got["pairs"] == 3
  assert got["fd"] == pytest.approx((per_pair[0]["fd"] + per_pair[1]["fd"]) / 2, rel=1e-6)
  for k in ("fs", "bs", "mean"):
    assert got[k] == pytest.approx(np.mean([p[k] for p in per_pair]), rel=1e-6)
  assert "three_way_local" not in evaluator.evaluate_zero_flow(
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
  assert (evaluator.evaluate_zero_flow(converted, **kwargs)["three_way_local"]
          == evaluator.evaluate_zero_flow(source, **kwargs)["three_way_local"])


@pytest.fixture(scope="module")
def checkpoint(smoke_checkpoint):
  return smoke_checkpoint


@pytest.mark.slow
def test_evaluate_py_reports_three_way_and_saves_every_flow(opensf_dir, checkpoint, tmp_path):
  root, _ = opensf_dir
  out, flows = tmp_path / "r.json", tmp_path / "flows"
  proc = commands.run(  # `python evaluate.py ...`, in this process (tests/commands.py)
    evaluate.run, "--config", "configs/default.py:smoke", "--checkpoint", checkpoint,
    "--dataset", f"opensf:{root}", "--split", "val", "--json", out, "--save_flows", flows,
    "--config.eval.num_points=0", "--config.eval.batch_size=1", cwd=REPO,
    prog=commands.script("evaluate.py"))
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert "av2 official" in proc.stdout and "EPE 3-Way Average" in proc.stdout
  assert "OpenSceneFlow local" not in proc.stdout  # the local reading: only without av2 labels
  results = json.loads(out.read_text())
  assert results["three_way_local"]["pairs"] == 3 and results["av2"]["pairs"] == 3
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
  assert results["three_way_local"]["mean"] == pytest.approx(np.mean(means), rel=1e-4)


# The two layouts of OpenSceneFlow's extract_av2.py (tests/av2_fixture.py, from the documented
# layout): `lidar` in the ego frame (before its commit 2bd9036) or in the up_lidar sensor frame.
import av2_fixture  # noqa: E402


@pytest.fixture(scope="module")
def av2_dirs(tmp_path_factory):
  pytest.importorskip("pyarrow")  # the AV2 calibration is a feather file
  out = {}
  for frame in ("ego", "sensor"):
    root = tmp_path_factory.mktemp(frame)
    out[frame] = root, av2_fixture.write_split(root, lidar_frame=frame, eval_every=2, seed=5)
  return out


def test_both_lidar_frames_read_as_the_ego_frame(av2_dirs):
  (ego_root, truth), (sensor_root, _) = av2_dirs["ego"], av2_dirs["sensor"]
  ego = open_dataset(f"opensf:{ego_root}", "val")
  sensor = open_dataset(f"opensf:{sensor_root},calibration={sensor_root / 'av2'}", "val")
  assert len(ego) == len(sensor) == 5
  for a, b in zip(ego, sensor):  # auto-detected: both files give the ego-frame truth
    log, stamp = opensf.sweep_id(a.name)
    s = truth[log, stamp]
    kept = ~s["ground"] & (np.hypot(s["xyz"][:, 0], s["xyz"][:, 1]) < 35)
    np.testing.assert_allclose(a.pc1, s["xyz"][kept], atol=1e-6)
    np.testing.assert_allclose(b.pc1, s["xyz"][kept], atol=1e-4)
    for k in ("pc2", "rigid_flow", "ego_xy"):
      np.testing.assert_allclose(getattr(b, k), getattr(a, k), atol=1e-4)
    np.testing.assert_array_equal(a.flow, s["flow"][kept])
    np.testing.assert_array_equal(b.category, s["category"][kept])
    np.testing.assert_array_equal(a.foreground, s["category"][kept] != 0)
    # the rigid flow of the background is its flow: the frames agree with flow and ego_motion
    background = s["category"][kept] == 0
    np.testing.assert_allclose(b.rigid_flow[background], b.flow[background], atol=1e-4)
  as_ego = open_dataset(f"opensf:{sensor_root},lidar=ego", "val")[0]  # a wrong explicit choice
  assert np.median(as_ego.pc1[:, 2]) < np.median(ego[0].pc1[:, 2]) - 1.0  # 1.64 m lower
  with pytest.raises(DataError, match="sensor frame .* give calibration=AV2_DIR"):
    open_dataset(f"opensf:{sensor_root}", "val")[0]
  with pytest.raises(DataError, match="lidar=sensor needs calibration"):
    open_dataset(f"opensf:{sensor_root},lidar=sensor", "val")
  with pytest.raises(DataError, match="egovehicle_SE3_sensor.feather: cannot read"):
    open_dataset(f"opensf:{sensor_root},lidar=sensor,calibration={sensor_root}", "val")[0]


def test_a_file_that_cannot_tell_its_frame_is_read_as_the_ego_frame_with_a_warning(tmp_path):
  """Issue 68, item 3: no frame turns (a straight drive): both frames fit the flow; read as the ego
  frame, as lidar=ego reads it, with a warning naming the file and lidar=sensor."""
  (tmp_path / "val").mkdir()
  straight = av2_fixture.se3(0.0, (1.0, 0.0, 0.0))  # no rotation: both frames fit the flow
  av2_fixture.write_log(tmp_path / "val" / "log.h5", np.random.default_rng(0), (1, 2),
                        lidar_frame="sensor", ego_motion=straight)
  with pytest.warns(UserWarning, match=r"log.h5: no frame turns enough .*read as the ego frame.*"
                    r"lidar=sensor,calibration=AV2_DIR"):
    auto = open_dataset(f"opensf:{tmp_path}", "val")[0]
  given = open_dataset(f"opensf:{tmp_path},lidar=ego", "val")[0]
  np.testing.assert_array_equal(auto.pc1, given.pc1)
  np.testing.assert_array_equal(auto.flow, given.flow)


def test_region_challenge_and_eval_mask(av2_dirs):
  root, truth = av2_dirs["ego"]
  challenge = open_dataset(f"opensf:{root},region=challenge", "val")
  # only the frames with an eval_mask are pairs (labelled frames 0 and 2 of the first log, 0 of
  # the second), and pc1 is the mask's points in file order
  expected = [(log, t) for log, stamps in zip(av2_fixture.LOG_IDS, av2_fixture.STAMPS)
              for k, t in enumerate(stamps[:-1]) if k % 2 == 0]
  assert [opensf.sweep_id(p.name) for p in challenge] == expected
  for pair in challenge:
    s = truth[opensf.sweep_id(pair.name)]
    rows = ~s["ground"] & (np.abs(s["xyz"][:, :2]) <= 50).all(1)
    np.testing.assert_array_equal(pair.pc1, s["xyz"][rows])
    np.testing.assert_array_equal(pair.mask, s["valid"][rows])
    assert (np.abs(pair.pc2[:, :2]) <= 50).all()
  # the disc reading honours eval_mask where the frame has one: those points only are evaluated
  with h5py.File(next((root / "val").glob(f"{av2_fixture.LOG_IDS[0]}.h5")), "a") as f:
    group = f[str(av2_fixture.STAMPS[0][0])]
    mask = group["eval_mask"][()][:, 0]
    mask[: len(mask) // 2] = False
    del group["eval_mask"]
    group.create_dataset("eval_mask", data=mask[:, None])
  s = truth[av2_fixture.LOG_IDS[0], av2_fixture.STAMPS[0][0]]
  disc = open_dataset(f"opensf:{root}", "val")[0]
  kept = ~s["ground"] & (np.hypot(s["xyz"][:, 0], s["xyz"][:, 1]) < 35)
  np.testing.assert_array_equal(disc.mask, (s["valid"] & mask)[kept])
  assert open_dataset(f"opensf:{root},region=challenge", "val")[0].pc1.shape[0] == mask.sum()


def test_region_challenge_without_eval_mask_is_the_box(opensf_dir):
  root, truth = opensf_dir
  pair = open_dataset(f"opensf:{root},region=challenge", "val")[0]
  frame, kind, _ = truth["log_a", 9]
  xyz = frame["lidar"][:, :3]
  rows = ~frame["ground_mask"] & (np.abs(xyz[:, :2]) <= 50).all(1)
  np.testing.assert_array_equal(pair.pc1, xyz[rows])
  assert (kind[rows] == "far").any()  # the 45 m points are the challenge's, not the 35 m disc's
