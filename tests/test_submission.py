"""evaluate.py --submission and predict --lidar --submission, scored by av2's own evaluator.

The logs are written from the documented layout by tests/av2_fixture.py (the current
extract_av2.py's sensor-frame `lidar`, with the challenge's eval_mask); the annotation files
jaxflow writes are checked against that construction, and av2's evaluate_directories +
results_to_dict on the export must give the numbers evaluate.py printed and wrote.
"""

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import av2_fixture
from jaxflow.data import open_dataset
from jaxflow.errors import ConfigError
from jaxflow.evaluation import export, submission

pd = pytest.importorskip("pandas")
pytest.importorskip("pyarrow")
av2_eval_module = pytest.importorskip("av2.evaluation.scene_flow.eval",
                                      reason="the av2 package (.ci/run installs it)")
REPO = Path(__file__).absolute().parent.parent


@pytest.fixture(scope="module")
def checkpoint(smoke_checkpoint):
  return smoke_checkpoint


def run(args, timeout=300):
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  return subprocess.run([sys.executable, *args], cwd=REPO, env=env, capture_output=True,
                        text=True, timeout=timeout)


@pytest.mark.slow
def test_av2s_evaluator_on_the_export_gives_what_evaluate_py_printed(checkpoint, tmp_path):
  root = tmp_path / "opensf"
  truth = av2_fixture.write_split(root, lidar_frame="sensor", eval_every=2)
  out, dest, flows = tmp_path / "r.json", tmp_path / "submit", tmp_path / "flows"
  # frame=camera: the model's frame; the files must still hold ego-frame flows
  spec = f"opensf:{root},region=challenge,frame=camera,calibration={root / 'av2'}"
  proc = run(["evaluate.py", "--config", "configs/default.py:smoke", "--checkpoint",
              str(checkpoint), "--dataset", spec, "--split", "val", "--json", str(out),
              "--submission", str(dest), "--save_flows", str(flows),
              "--config.eval.num_points=0", "--config.eval.batch_size=1"])
  assert proc.returncode == 0, proc.stderr[-3000:]
  results = json.loads(out.read_text())
  annotations = submission.annotations_folder(dest)
  assert str(annotations) in proc.stderr and "av2.evaluation.scene_flow.eval" in proc.stderr

  # the files: one per eval-mask sweep (frames 0, 2 of the first log, 0 of the second)
  eval_sweeps = [(log, t) for log, stamps in zip(av2_fixture.LOG_IDS, av2_fixture.STAMPS)
                 for k, t in enumerate(stamps[:-1]) if k % 2 == 0]
  names = sorted(str(p.relative_to(dest)) for p in dest.rglob("*.feather"))
  assert names == sorted(f"{log}/{t}.feather" for log, t in eval_sweeps)
  for log, t in eval_sweeps:
    s = truth[log, t]
    rows = ~s["ground"] & (np.abs(s["xyz"][:, :2]) <= 50).all(1)  # the eval mask, in file order
    pred = pd.read_feather(dest / log / f"{t}.feather")
    assert list(pred.columns) == ["flow_tx_m", "flow_ty_m", "flow_tz_m", "is_dynamic"]
    assert all(pred[c].dtype == np.float16 for c in submission.FLOW_COLUMNS)
    assert pred["is_dynamic"].dtype == bool and len(pred) == rows.sum()
    saved = np.load(flows / (export.flow_stem(f"{root / 'val' / log}.h5:{t}") + ".npy"))
    np.testing.assert_array_equal(pred[list(submission.FLOW_COLUMNS)].to_numpy(),
                                  saved[:, [2, 0, 1]].astype(np.float16))  # camera -> ego
    ann = pd.read_feather(annotations / log / f"{t}.feather")
    np.testing.assert_array_equal(ann["category_indices"], s["category"][rows])
    np.testing.assert_array_equal(ann["is_valid"], s["valid"][rows])
    np.testing.assert_array_equal(ann["is_close"],
                                  (np.abs(s["xyz"][rows, :2]) <= 35).all(1))  # ego frame
    rigid = s["xyz"][rows] @ av2_fixture.se3(1.5, (1.0, 0.1, 0.0))[:3, :3].T + [1.0, 0.1, 0.0]
    moving = np.linalg.norm(s["flow"][rows] - (rigid - s["xyz"][rows]), axis=1)
    decided = np.abs(moving - 0.05) > 1e-4  # away from the threshold: rounding cannot flip them
    np.testing.assert_array_equal(ann["is_dynamic"][decided], moving[decided] >= 0.05)
    np.testing.assert_array_equal(ann[list(submission.FLOW_COLUMNS)].to_numpy(),
                                  s["flow"][rows].astype(np.float16))

  # av2's own evaluator on the export
  frame = av2_eval_module.evaluate_directories(annotations, dest)
  want = av2_eval_module.results_to_dict(frame)
  assert len(frame) == 8 * len(eval_sweeps)
  for key, value in want.items():
    got = results["av2"][key]
    assert (math.isnan(got) and math.isnan(value)) or got == pytest.approx(value, rel=1e-9), key
  assert not math.isnan(want["EPE 3-Way Average"])
  assert not math.isnan(want["EPE/Foreground/Dynamic"])
  # ... and the table evaluate.py printed (4 decimals)
  printed = re.search(r"\| EPE 3-Way Average +\| +([0-9.]+)", proc.stdout)
  assert printed and float(printed.group(1)) == pytest.approx(want["EPE 3-Way Average"], abs=5e-5)
  fd = re.search(r"\| Foreground/Dynamic +\| +([0-9.]+) \| +([0-9.]+) \| +([0-9.]+)", proc.stdout)
  assert [float(x) for x in fd.groups()] == pytest.approx(
    [want[f"EPE/Foreground/Dynamic{d}"] for d in ("", "/Close", "/Far")], abs=5e-5)
  assert "bucketed" in proc.stdout and results["bucketed"]["pairs"] == len(eval_sweeps)


def test_writer_refuses_samples_and_old_files(tmp_path):
  with pytest.raises(ConfigError, match="num_points=0"):
    submission.SubmissionWriter(tmp_path / "s", 8192)
  with pytest.raises(ConfigError, match=r"needs an Argoverse 2 dataset .*synthetic_lidar"):
    submission.SubmissionWriter(tmp_path / "s", 0, open_dataset("synthetic_lidar:2", "test"))
  (tmp_path / "s" / "log").mkdir(parents=True)
  (tmp_path / "s" / "log" / "1.feather").write_bytes(b"")
  with pytest.raises(ConfigError, match="already holds"):
    submission.SubmissionWriter(tmp_path / "s", 0)


@pytest.mark.slow
def test_predict_lidar_writes_the_submission_layout(checkpoint, tmp_path):
  rng = np.random.default_rng(0)
  s = av2_fixture.scene(rng, av2_fixture.se3(1.0, (0.8, 0.0, 0.0)))
  log = tmp_path / "a1b2c3" / "sensors" / "lidar"
  log.mkdir(parents=True)
  pc1, pc2 = log / "315966265659927216.npy", log / "315966265759927216.npy"
  np.save(pc1, s["xyz"])
  np.save(pc2, s["xyz"] + s["flow"])
  dest, flow_out = tmp_path / "submit", tmp_path / "flow.npy"
  proc = run(["-m", "jaxflow.predict", str(pc1), str(pc2), "--lidar", "--checkpoint",
              str(checkpoint), "--config", "configs/default.py:smoke", "--method", "network",
              "--submission", str(dest), "--out", str(flow_out)])
  assert proc.returncode == 0, proc.stderr[-3000:]
  pred = pd.read_feather(dest / "a1b2c3" / "315966265659927216.feather")
  flow = np.load(flow_out)
  assert len(pred) == len(s["xyz"])
  np.testing.assert_array_equal(pred[list(submission.FLOW_COLUMNS)].to_numpy(),
                                flow.astype(np.float16))
  # Against the scene's truth, not only the run's own output: most points move with the true
  # ego-motion; is_dynamic is the challenge's "departs from the ego-motion's flow by 5 cm or more",
  # here measured against the TRUE ego-motion (the estimate is within a centimetre of it).
  assert np.median(np.linalg.norm(flow - s["flow"], axis=1)) < 0.01
  ego_flow = av2_fixture.apply(av2_fixture.se3(1.0, (0.8, 0.0, 0.0)), s["xyz"]) - s["xyz"]
  dynamic = pred["is_dynamic"].to_numpy()
  assert dynamic.dtype == bool
  assert (dynamic == (np.linalg.norm(flow - ego_flow, axis=1) >= 0.05)).mean() > 0.98
  # The scene's movers: objects of 40 points, some too sparse for the pipeline (0.48 found).
  moving = np.linalg.norm(s["flow"] - ego_flow, axis=1) >= 0.05
  assert moving.any() and dynamic[moving].mean() > 0.3 and dynamic[~moving].mean() < 0.02, (
    dynamic[moving].mean(), dynamic[~moving].mean())
  bad = run(["-m", "jaxflow.predict", str(pc1), str(pc2), "--submission", str(dest)])
  assert bad.returncode != 0 and "--submission needs --lidar" in bad.stderr


def test_argoverse_eval_config_reads_the_challenges_points():
  from jaxflow.configs import argoverse_eval  # pylint: disable=import-outside-toplevel

  config = argoverse_eval.get_config("opensf:/data/av2/sensor")
  assert config.eval.dataset == "opensf:/data/av2/sensor,region=challenge"
  assert config.eval.split == "val" and config.eval.num_points == 0
  assert argoverse_eval.get_config("").eval.dataset == "argoverse:data/argoverse"
