"""Movers by name (jaxflow.evaluation.movers): each labelled mover of an OpenSceneFlow log with
instance ids, from a tiny h5 file written from the documented layout (../shared/data/README.md's
PandaSet files: `flow_instance_id` = 1 + the track's row in the attribute `instances`)."""

import json
import pathlib
import subprocess
import sys

import h5py
import numpy as np
import pytest

from jaxflow import evaluate
from jaxflow.data import open_dataset
from jaxflow.evaluation import av2_eval, movers

import commands

ROOT = pathlib.Path(__file__).resolve().parents[1]

VEHICLE = av2_eval.CATEGORIES.index("REGULAR_VEHICLE")
PERSON = av2_eval.CATEGORIES.index("PEDESTRIAN")
TRACKS = [["c0ffee00-0000-4000-8000-000000000001", "Car", "REGULAR_VEHICLE"],
          ["parked00-0000-4000-8000-000000000002", "Car", "REGULAR_VEHICLE"],
          ["walker00-0000-4000-8000-000000000003", "Pedestrian", "PEDESTRIAN"]]
# track number (1 + row) -> (points, corner, size, motion m a frame along x, category)
OBJECTS = {1: (60, (6, 3), (4, 2, 1.5), 0.5, VEHICLE), 2: (40, (-8, 5), (4, 2, 1.5), 0.0, VEHICLE),
           3: (30, (10, -4), (0.5, 0.5, 1.7), 0.12, PERSON)}


def _frame(rng):
  """One sweep (ego frame, z up, the ego standing still): ground, a building, the three tracks."""
  parts = [np.c_[rng.uniform(-25, 25, (250, 2)), rng.normal(-1.8, 0.02, 250)],
           rng.uniform(0, 1, (120, 3)) * [2, 10, 4] + [12, -20, -1.8]]
  ids = [np.zeros(250, int), np.zeros(120, int)]
  for track, (n, (x, y), size, _, _) in OBJECTS.items():
    parts.append(rng.uniform(0, 1, (n, 3)) * size + [x, y, -1.8])
    ids.append(np.full(n, track))
  return np.concatenate(parts).astype(np.float32), np.concatenate(ids)


@pytest.fixture(scope="module")
def log(tmp_path_factory):
  """DIR/val/log.h5: frames 0 -> 1 (1 the same points, each track moved by its motion)."""
  root = tmp_path_factory.mktemp("movers")
  (root / "val").mkdir()
  rng = np.random.default_rng(0)
  points, ids = _frame(rng)
  motion = np.zeros((len(points), 3), np.float32)
  for track, (*_, speed, _) in OBJECTS.items():
    motion[ids == track, 0] = speed
  category = np.zeros(len(points), np.uint8)
  for track, (*_, cat) in OBJECTS.items():
    category[ids == track] = cat
  valid = np.ones(len(points), bool)
  valid[np.flatnonzero(ids == 1)[:10]] = False  # 10 of the car's points carry no label
  ground = np.arange(len(points)) < 250
  with h5py.File(root / "val" / "log.h5", "w") as f:
    f.attrs["instances"] = json.dumps(TRACKS)
    first, second = f.create_group("100"), f.create_group("200")
    for group, cloud in ((first, points), (second, points + motion)):
      group["lidar"], group["ground_mask"] = cloud, ground
      group["pose"] = np.eye(4)
    first["flow"], first["flow_is_valid"], first["flow_category_indices"] = motion, valid, category
    first["flow_instance_id"] = ids.astype(np.int16)
    first["ego_motion"] = np.eye(4, dtype=np.float32)
  return root, points, ids, motion, valid


def test_each_mover_gets_its_track_speed_points_and_where_it_lands(log):
  root, points, ids, motion, valid = log
  ds = open_dataset(f"opensf:{root},region=sweep,lidar=ego", "val")
  got_ids, table = ds.instances(0)
  np.testing.assert_array_equal(got_ids, ids)  # every point kept (region=sweep)
  pair = ds[0]
  still = np.zeros_like(pair.flow)  # a method that moves nothing: every mover missed
  rows = movers.pair_movers(pair.pc1, pair.pc2, still, pair.flow, pair.rigid_flow, valid, ids,
                            table, name="p")
  assert [r["track"] for r in rows] == [TRACKS[0][0], TRACKS[2][0]]  # the parked car is no mover
  car, walker = rows
  assert car["label"] == "Car" and walker["category"] == "PEDESTRIAN"
  assert car["points"] == 50 and walker["points"] == 30  # the car's unlabelled points left out
  assert car["speed"] == pytest.approx(0.5, abs=1e-6) and walker["epe"] == pytest.approx(0.12,
                                                                                      abs=1e-6)
  assert car["pred_speed"] == 0 and car["epe"] == pytest.approx(0.5, abs=1e-6)
  car_xy = points[(ids == 1) & valid, :2]
  assert car["range"] == pytest.approx(np.median(np.hypot(*car_xy.T)), abs=1e-5)
  # Its label lands on the next sweep's points (they are the same points moved), the still flow
  # where the car was: the label right, the method missing it.
  assert car["land_label"] < 1e-6 and car["land_pred"] == car["land_static"] > 0.1
  named = movers.Movers.__new__(movers.Movers)
  named.rows = rows
  assert [(t["missed"], t["label_off"]) for t in named.tracks()] == [(1, 0), (1, 0)]
  # A flow that follows the points while the car's label says 0.8 m a frame (a box that runs
  # ahead): nothing missed, the car's label off (its prediction lands, the label does not).
  label = pair.flow.copy()
  label[ids == 1, 0] = 0.8
  named.rows = movers.pair_movers(pair.pc1, pair.pc2, pair.flow, label, pair.rigid_flow, valid,
                                  ids, table)
  assert all(r["land_pred"] < 1e-6 for r in named.rows)
  assert [(t["missed"], t["label_off"]) for t in named.tracks()] == [(0, 1), (0, 0)]


def test_evaluate_lists_the_movers_by_name(log, tmp_path):
  root, *_ = log
  spec = f"opensf:{root},region=sweep,lidar=ego"
  out = tmp_path / "r.json"
  done = commands.run(evaluate.run, "--dataset", spec, "--split", "val", "--method", "lidar",
                      "--max_points", 0, "--json", out)
  assert done.returncode == 0, done.stderr
  assert "movers by name" in done.stdout and "c0ffee00" in done.stdout
  assert "walker00" in done.stdout and "parked00" not in done.stdout
  results = json.loads(out.read_text())["movers"]
  assert {r["track"] for r in results["pairs"]} == {TRACKS[0][0], TRACKS[2][0]}
  assert {t["track"][:8]: t["points"] for t in results["tracks"]} == {"c0ffee00": 50,
                                                                      "walker00": 30}
  # Sampled clouds no longer match the file's ids: no list, a note naming what to give.
  done = commands.run(evaluate.run, "--dataset", spec, "--split", "val", "--method", "lidar",
                      "--max_points", 64)
  assert done.returncode == 0, done.stderr
  assert "movers by name" not in done.stdout and "--max_points 0" in done.stderr


def test_the_benchmark_takes_a_pair_backwards_with_each_track_s_inverse_motion(log, tmp_path):
  """benchmarks/pandaset.py's backward labels: a later point of a track moves by the inverse of
  its labelled motion (here 0.5 and 0.12 m along x, so -0.5 and -0.12), the rest by the
  ego-motion's inverse (the ego stands still: 0); a track with no earlier points is not scored."""
  from benchmarks import pandaset  # pylint: disable=import-outside-toplevel

  root, points, ids, motion, valid = log
  (tmp_path / "val").mkdir()
  with h5py.File(root / "val" / "log.h5", "r") as src, \
       h5py.File(tmp_path / "val" / "log.h5", "w") as f:
    f.attrs["instances"] = src.attrs["instances"]
    for key in ("100", "200"):
      src.copy(src[key], f, name=key)
    later = f["200"]  # the later sweep labelled too (its own ids), and a third sweep after it
    newcomer = np.where(ids == 0, 0, ids).astype(np.int16)
    newcomer[250:255] = 4  # 5 building points: a track the earlier sweep has no points of
    f.attrs["instances"] = json.dumps(TRACKS + [["new00000-0000", "Car", "REGULAR_VEHICLE"]])
    for name in ("flow", "flow_is_valid", "flow_category_indices", "ego_motion"):
      later[name] = src["100"][name][()]
    later["flow_instance_id"] = newcomer
    f.create_group("300")["lidar"] = points
    f["300"]["ground_mask"], f["300"]["pose"] = np.zeros(len(points), bool), np.eye(4)
  ds = open_dataset(f"opensf:{tmp_path},region=sweep,lidar=ego", "val")
  pc1, pc2, flow, rigid_flow, _, scored, got_ids, _ = pandaset.backward_pair(ds, 0)
  np.testing.assert_allclose(pc1, points + motion)  # the later sweep first
  np.testing.assert_allclose(pc2, points)
  expected = np.zeros_like(motion)
  for track, (*_, speed, _) in OBJECTS.items():
    expected[ids == track, 0] = -speed
  np.testing.assert_allclose(flow, expected, atol=1e-5)
  np.testing.assert_allclose(rigid_flow, 0, atol=1e-6)
  assert (got_ids[250:255] == 4).all() and not scored[250:255].any()  # no earlier points
  assert scored[255:370].all()  # the rest of the building is scored
  assert pandaset.backward_pair(ds, 1) is None  # the last sweep carries no ids


def test_the_pandaset_benchmark_command_runs_at_toy_size(tmp_path):
  """The command README.md and benchmarks/REAL_SWEEPS.md show, on one generated test pair (no
  ../shared needed), with a lidar setting (--set) and a seed given: its row's recall and false
  alarms are its own counts' ratios; a --set without a value is refused."""
  out = tmp_path / "p.json"
  proc = subprocess.run([sys.executable, "-m", "benchmarks.pandaset", "--only", "generator",
                         "--pairs", "1", "--directions", "forward", "--json", str(out),
                         "--set", "objects.judge.evidence=150", "--seed", "1"],
                        cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)
  assert proc.returncode == 0, proc.stderr[-2000:]
  assert "| generator test, forward | CAR |" in proc.stdout, proc.stdout
  written = json.loads(out.read_text())
  assert written["args"]["set"] == ["objects.judge.evidence=150"] and written["args"]["seed"] == 1
  (name, row), = written["rows"].items()
  counts = row["counts"]
  assert name == "generator test, forward" and row["pairs"] == 1 and counts["moving"] > 100
  assert row["recall"] == pytest.approx(counts["moved"] / counts["moving"])
  assert row["false_alarms_static_objects"] == pytest.approx(
    counts["static_objects_moved"] / counts["static_objects"])
  assert 0.9 <= row["recall"] <= 1 and row["false_alarms_background"] < 0.01
  bad = subprocess.run([sys.executable, "-m", "benchmarks.pandaset", "--set", "evidence"], cwd=ROOT,
                       capture_output=True, text=True, timeout=600, check=False)
  assert bad.returncode == 2 and "--set takes FIELD=VALUE" in bad.stderr, bad.stderr
