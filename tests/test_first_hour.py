"""A newcomer's first hour (issue 68): evaluate what you trained, progress in a log, the README's
OpenSceneFlow command on a real-layout file, output paths checked before the work, figures marked
tuned."""

import json
import os
import pathlib
import re
import shlex
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

import zup_scene
from jaxflow import evaluate, predict
from jaxflow.configs import default
from jaxflow.errors import ConfigError
from jaxflow.evaluation import av2_eval, export, run_config
from jaxflow.refine import progress

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run(argv, timeout=900, **kwargs):
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
  if "stderr" not in kwargs:
    kwargs["capture_output"] = True
  return subprocess.run(argv, cwd=ROOT, env=env, text=True, timeout=timeout, **kwargs)


# 1. evaluate.py --checkpoint RUN evaluates as the run did.

@pytest.fixture(scope="module")
def trained(tmp_path_factory):
  """A smoke run of 2 steps (its held-out figure in eval.json) and its config."""
  from jaxflow.training import trainer  # pylint: disable=import-outside-toplevel

  config = default.get_config("smoke")
  config.train.num_steps, config.train.checkpoint_every, config.train.log_every = 2, 2, 1
  workdir = tmp_path_factory.mktemp("run")
  trainer.train_and_evaluate(config, workdir)
  return workdir, config


def test_the_helps_first_example_gives_the_trainings_own_heldout_figure(trained, tmp_path):
  """The first example of evaluate.py --help, on a run of the smoke config: the EPE train.py wrote
  (c6d6676 evaluated at its own 8192 points and 32 iterations: another figure)."""
  workdir, config = trained
  example = next(l.strip() for l in evaluate.__doc__.splitlines()
                 if l.strip().startswith("python -m jaxflow.evaluate"))
  assert "--checkpoint runs/default" in example and "synthetic_lidar:64" in example, example
  example = example.replace("runs/default", str(workdir)).replace(
    "synthetic_lidar:64", config.eval.dataset)  # the smoke run's held-out pairs
  argv = shlex.split(example)[1:]  # python -m jaxflow.evaluate ...
  proc = _run([sys.executable, *argv, "--json", str(tmp_path / "r.json")])
  assert proc.returncode == 0, proc.stderr[-3000:]
  trained_epe = json.loads((workdir / "eval.json").read_text())["model"]["epe"]
  results = json.loads((tmp_path / "r.json").read_text())
  assert results["num_points"] == config.eval.num_points == 64
  assert results["num_iters"] == config.eval.num_iters == 4
  assert results["epe"] == pytest.approx(trained_epe, rel=1e-4, abs=1e-6), proc.stderr[-2000:]
  said = [l for l in proc.stderr.splitlines() if "settings from the run's config" in l]
  assert len(said) == 1 and "num_points 64" in said[0] and "num_iters 4" in said[0], proc.stderr
  assert "from the command line: dataset 'synthetic_lidar:4', split 'test'" in said[0], said
  assert "more than 2x" not in proc.stderr


def test_a_flag_overrides_the_run_and_far_settings_are_said(trained):
  workdir, config = trained
  paper = default.get_config("eval")  # evaluate.py's own defaults: 8192 points, 32 iterations
  taken, lines = run_config.apply(workdir, paper, given={"num_points"})
  assert taken.eval.num_points == 8192 and taken.eval.num_iters == config.eval.num_iters
  assert taken.eval.batch_size == paper.eval.batch_size  # sized for the points given, not the run's
  assert run_config.apply(workdir, paper)[0].eval.batch_size == config.eval.batch_size
  assert taken.eval.dataset == config.eval.dataset and "num_points 8192" in lines[0]
  gap = run_config.training_gap(workdir, taken)
  assert gap and "8192 points (trained on 64)" in gap and "iterations" not in gap.split(":")[0]
  assert run_config.training_gap(workdir, run_config.apply(workdir, paper)[0]) is None
  far = run_config.training_gap(workdir, paper)  # 8192 points, 32 iterations: both far
  assert "8192 points (trained on 64)" in far
  assert f"32 iterations (trained with {config.train.num_iters})" in far


# 2. Progress in a log; a raw sweep's first note.

def _sweep_files(tmp_path, n_ground=600):
  scene = zup_scene.sweep_pair(n_ground=n_ground)
  paths = [tmp_path / "s1.npy", tmp_path / "s2.npy"]
  for path, cloud in zip(paths, (scene.pc1, scene.pc2)):
    np.save(path, cloud)
  return paths


def test_a_long_predict_writes_progress_into_a_log_after_a_first_lidar_note(tmp_path):
  """optimise (predict's default) on a raw sweep without --lidar, made long by its settings (a
  descent of 2000 steps), stderr into a file: the first line names --lidar, then a progress line
  every ~10 s (c6d6676: silent until the end)."""
  paths = _sweep_files(tmp_path)
  with open(tmp_path / "log.txt", "w") as log:
    proc = _run([sys.executable, "-m", "jaxflow.predict", *map(str, paths), "--out",
                 str(tmp_path / "f.npy"), "--method.optimise.descent.steps=2000",
                 "--method.optimise.descent.patience=0"], stderr=log, stdout=subprocess.DEVNULL)
  lines = (tmp_path / "log.txt").read_text().splitlines()
  assert proc.returncode == 0, lines[-20:]
  notes = [l for l in lines if l.startswith("note:")]
  assert "raw 360-degree sweep" in notes[0] and "--lidar" in notes[0], notes
  assert len(notes[0].replace(str(paths[0]), "PC1")) < 130, notes[0]  # short
  assert lines.index(notes[0]) < min(i for i, l in enumerate(lines) if "so far" in l), lines
  beats = [l for l in lines if re.match(r"flow of .*s1\.npy \(optimise\): .*, \d+ s so far$", l)]
  assert beats, lines
  assert not any("--lidar" in n for n in notes[1:]), notes  # said once, first


def test_the_sweep_hint_is_for_360_degree_sweeps_only():
  scene = zup_scene.sweep_pair(n_ground=600)
  assert "--lidar" in predict.sweep_hint(scene.pc1, None, "optimise")
  assert predict.sweep_hint(scene.pc1, None, "lidar") is None
  ahead = scene.pc1[scene.pc1[:, 0] > 0]  # a camera's view: half the azimuth
  assert predict.sweep_hint(ahead, None, "optimise") is None
  y_up = scene.pc1[:, [1, 2, 0]]  # the models' frame: not read as a sweep
  assert predict.sweep_hint(y_up, None, "network") is None


def test_working_writes_a_line_per_silence_and_nothing_when_nested(capsys, monkeypatch):
  monkeypatch.setattr(progress, "EVERY_S", 0.3)
  with progress.Working("outer", lambda: "1/2 pairs"):
    with progress.Working("inner"):  # shows nothing: the outer one does
      progress.stage("descent")
      time.sleep(1.5)
  lines = capsys.readouterr().err.splitlines()
  assert 2 <= len(lines) <= 6, lines
  assert all(re.fullmatch(r"outer: descent, 1/2 pairs, \d+ s so far", l) for l in lines), lines
  with progress.Working("quiet", progress=False):
    time.sleep(0.7)
  assert capsys.readouterr().err == ""


# 3. The README's OpenSceneFlow command on a real-layout file.

def _opensf_log(root):
  """One labelled pair in OpenSceneFlow's h5 layout (jaxflow.data.opensf's docstring): an ego that
  drives straight (no frame turns enough to tell the frame of 'lidar', as the PandaSet runs of
  ../shared and straight AV2 logs), z up, the ground kept."""
  scene = zup_scene.sweep_pair(seed=3, yaw_deg=0.0, n_ground=3000)
  motion = np.eye(4)
  motion[:3, :3], motion[:3, 3] = scene.ego_rotation, scene.ego_translation
  car = av2_eval.CATEGORIES.index("REGULAR_VEHICLE")
  (root / "val").mkdir(parents=True)
  with h5py.File(root / "val" / "log.h5", "w") as f:
    first, second = f.create_group("315966265259836000"), f.create_group("315966265359836000")
    for group, cloud in ((first, scene.pc1), (second, scene.pc2)):
      group["lidar"] = np.c_[cloud, np.ones(len(cloud), np.float32)]  # x y z intensity
      group["ground_mask"] = np.abs(cloud[:, 2] + zup_scene.SENSOR_HEIGHT) < 0.05
      group["pose"] = np.eye(4)
    first["ego_motion"] = motion.astype(np.float32)
    first["flow"] = scene.flow
    first["flow_is_valid"] = np.ones(len(scene.pc1), bool)
    first["flow_category_indices"] = np.where(scene.moving1, car, 0).astype(np.uint8)
  return scene


def test_the_readmes_opensf_command_runs_as_written(tmp_path):
  """c6d6676: 'cannot tell the frame of lidar' on such a file; now read as the ego frame with a
  warning, and the lidar method's flow is scored."""
  readme = (ROOT / "README.md").read_text()
  command = re.search(r"`(python3 evaluate\.py --dataset \"opensf:DIR[^`]*)`", readme).group(1)
  scene = _opensf_log(tmp_path / "data")
  argv = shlex.split(command.replace("DIR", str(tmp_path / "data")))
  assert argv[:2] == ["python3", "evaluate.py"], argv
  proc = _run([sys.executable, *argv[1:], "--json", str(tmp_path / "r.json")])
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert "read as the ego frame" in proc.stderr
  results = json.loads((tmp_path / "r.json").read_text())
  challenge = ~(np.abs(scene.pc1[:, 2] + zup_scene.SENSOR_HEIGHT) < 0.05) & (
    np.abs(scene.pc1[:, :2]) <= 50).all(1)
  zero_flow = np.linalg.norm(scene.flow[challenge], axis=1).mean()  # ~1 m: the ego's drive
  assert results["pairs"] == 1 and results["epe"] < 0.2 * zero_flow, (results["epe"], zero_flow)
  assert "av2" in results


# 4. Output paths checked before the work.

def test_a_bad_render_is_refused_at_once(tmp_path):
  """A long job (NSFP, 100000 steps) with --render v.jpg: one line, exit 2, in under 5 s, nothing
  written (c6d6676: refused after the whole run, the flow written)."""
  paths = _sweep_files(tmp_path)
  start = time.perf_counter()
  proc = _run([sys.executable, "-m", "jaxflow.predict", *map(str, paths), "--method", "nsfp",
               "--steps", "100000", "--out", str(tmp_path / "new" / "f.npy"), "--render",
               str(tmp_path / "v.jpg")])
  seconds = time.perf_counter() - start
  lines = proc.stderr.strip().splitlines()
  assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
  assert lines[0] == f"error: --render {tmp_path / 'v.jpg'}: unknown file type '.jpg'; use .png or .html"
  assert seconds < 5.0, seconds
  assert not (tmp_path / "new").exists()  # nothing made before every path was checked


def test_output_paths_refused_or_their_folder_made_with_a_note(tmp_path):
  (tmp_path / "file").write_text("x")
  cases = [(("--json", tmp_path / "r.txt", (".json",), False), "unknown file type '.txt'"),
           (("--out", tmp_path / "file" / "f.npy", (".npy",), False), "is a file, not a folder"),
           (("--save_flows", tmp_path / "file", (), True), "is a file, expected a folder"),
           (("--out", tmp_path, (".npy",), False), "is a folder, expected a file name")]
  for check, message in cases:
    with pytest.raises(ConfigError, match=re.escape(message)):
      export.check_outputs([check, ("--render", tmp_path / "new" / "v.png", (".png",), False)])
    assert not (tmp_path / "new").exists()  # none made while another path is wrong
  notes = export.check_outputs([("--render", tmp_path / "new" / "v.png", (".png",), False),
                                ("--save_flows", tmp_path / "flows", (), True)])
  assert notes == [f"--render: made the folder {tmp_path / 'new'}",
                   f"--save_flows: made the folder {tmp_path / 'flows'}"]
  assert (tmp_path / "new").is_dir() and (tmp_path / "flows").is_dir()
  assert export.outputs_in_argv(["p", "a", "--render=x.png", "--json", "r.json", "--", "--render"],
                                {"render": ((".png",), False), "json": ((".json",), False)}) == [
    ("--render", "x.png", (".png",), False), ("--json", "r.json", (".json",), False)]


# 5. Figures and docs that say no more than was measured.

def test_a_figure_on_the_data_its_settings_were_chosen_on_says_tuned():
  """benchmarks.readme's check: the real AV2 pair's three-way figure (--lidar's settings were
  chosen on it) is marked tuned in the README's block and in docs/users.md; an unmarked one, or a
  tuned one whose label says "nobody tuned on", is a problem (c6d6676's record: 6 problems)."""
  from benchmarks import readme  # pylint: disable=import-outside-toplevel

  record = readme.load(readme.RECORD)
  assert readme.tuned_problems(record) == []
  (real,) = [f for f in record["figures"] if f["id"] == "real_av2_threeway"]
  assert "a tuned figure" in real["label"] and real["tuned"]
  block = readme.block_of((ROOT / "README.md").read_text())
  assert real["label"] in block
  users = " ".join((ROOT / "docs" / "users.md").read_text().split())
  assert "so these are tuned figures): three-way EPE 0.039 m" in users
  unmarked = dict(real, label="three-way EPE, the real labelled Argoverse 2 pair")
  del unmarked["tuned"]
  wrong = dict(real, id="x", label="optimise, synthetic_things val nobody tuned on")
  problems = readme.tuned_problems({"figures": [unmarked, wrong]})
  assert len(problems) == 2 and "record where" in problems[0] and "x: a tuned figure" in problems[1]


def test_the_table_says_rerun_for_one_batch_and_leaves_outliers_out_on_sweeps():
  from jaxflow.evaluation import reporting  # pylint: disable=import-outside-toplevel

  r = dict(epe=0.04, acc_strict=97.9, acc_relax=98.0, outliers=47.0, angle=0.1, pairs=1,
           first_pair_s=9.9, ms_per_pair=123.0, steady="rerun")
  header = reporting.format_table([("synthetic", r)]).splitlines()[0]
  assert "ms/pair rerun" in header and "Outliers(%)" in header and "after" not in header
  sweeps = reporting.format_table([("opensf", dict(r, three_way_local={}, steady="others"))])
  assert "Outliers" not in sweeps and "47.00" not in sweeps and "ms/pair after" in sweeps


def test_users_md_says_what_predict_does():
  users = " ".join((ROOT / "docs" / "users.md").read_text().split())
  from jaxflow.methods import optimise  # pylint: disable=import-outside-toplevel
  assert f"optimise's starting flow {optimise.Optimise().start_iters}" in users
  assert "(a 100k-point frame: 33 s" not in users  # said of which frame, and beside a raw sweep's
  assert "KITTI scene-flow frame 000002" in users and "raw 360-degree sweep" in users
  assert "made, with a note" in users  # a missing output folder (item 4)
