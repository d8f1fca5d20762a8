"""What a new user met (issue 56, item 5): progress in a log, the notes and errors of predict,
evaluate.py's help and its two times, and the docs that said otherwise than the code."""

import dataclasses
import json
import pathlib
import re
import time

import jax.numpy as jnp
import numpy as np
import pytest

import zup_scene
from jaxflow import data, evaluate, inference
from jaxflow.data import registry as data_registry
from jaxflow.data import synthetic_sweep
from jaxflow.errors import DataError
from jaxflow.evaluation import evaluator, reporting
from jaxflow.lidar import sweep
from jaxflow.methods import registry
from jaxflow.refine import optimiser, progress

ROOT = pathlib.Path(__file__).resolve().parents[1]
USERS = (ROOT / "docs" / "users.md").read_text()
TRAINING = (ROOT / "docs" / "training.md").read_text()


def _toy_pair(n=64, seed=0):
  rng = np.random.default_rng(seed)
  pc1 = rng.normal(size=(1, n, 3)).astype(np.float32)
  return jnp.asarray(pc1), jnp.asarray(pc1 + np.float32([0.1, 0.0, 0.05]))


def test_a_long_nsfp_run_logs_its_expected_time_and_every_tenth_of_its_steps(capsys, monkeypatch):
  """1. Off a terminal (capsys: stderr is not one) a run expected to be long writes plain lines:
  the estimate first, then one line per 10% of the steps; the flow is the silent run's, bit for
  bit."""
  pc1, pc2 = _toy_pair()
  chosen = dataclasses.replace(optimiser.NSFP, steps=40, patience=0, width=16, depth=2)
  quiet = optimiser.optimise_host_loop(jnp.zeros_like(pc1), pc1, pc2, chosen, progress=False)
  assert capsys.readouterr().err == ""
  monkeypatch.setattr(progress, "LOG_AFTER_S", 0.0)  # every run counts as long
  monkeypatch.setattr(progress, "PACE_S", 0.0)
  # As the nsfp method runs it (predict --method nsfp, evaluate.py --method nsfp).
  flow, _ = registry.flow_fn("nsfp", None, chosen, with_info=True)(None, pc1, pc2)
  lines = capsys.readouterr().err.splitlines()
  assert "expected to take about" in lines[0] and "an estimate" in lines[0], lines
  tenths = [l for l in lines if "/40 steps (" in l]
  assert len(tenths) >= 9 and "40/40 steps (100%)" in tenths[-1], lines
  assert lines[-1].startswith("mlp optimisation: done, 40 steps"), lines
  np.testing.assert_array_equal(np.asarray(flow), np.asarray(quiet[0]))


def _zup_cloud():
  return zup_scene.sweep_pair(n_ground=600).pc1[::8]  # flat along z: a street seen by a LiDAR


def test_a_z_up_cloud_without_lidar_is_told_that_lidar_exists(monkeypatch):
  """2. The note of a cloud read z up names --lidar, the pipeline for raw sweeps."""
  pc1 = _zup_cloud()
  monkeypatch.setattr(inference.Predictor, "_predict", lambda self, a, b, **_: inference.Prediction(
    np.zeros_like(a), (), (len(a), len(b))))  # the note comes before the method
  predictor = inference.load_predictor(method="nsfp")
  notes = predictor.predict(pc1, pc1, names=("sweep1.bin", "sweep2.bin")).notes
  assert len(notes) == 1 and "sweep1.bin is flat along z" in notes[0], notes
  assert "--lidar" in notes[0] and "360-degree" in notes[0], notes


def test_lidar_on_too_few_points_gives_the_pipelines_own_minimum(tmp_path):
  """3. --lidar on 5 points: the pipeline's minimum in its words, before any checkpoint is read;
  that minimum is the ego-motion's own (one point fewer: its fit gives up)."""
  five = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
  deferred = inference.load_predictor(str(tmp_path / "no_checkpoint"), method="lidar",
                                     method_fields={"method": "optimise"})  # predict --lidar's
  with pytest.raises(DataError) as caught:
    deferred.predict(five, five, names=("a.npy", "b.npy"))
  least = sweep.min_points()
  assert str(caught.value).startswith(f"a.npy: only 5 points; the raw-sweep pipeline")
  assert f"at least {least}" in str(caught.value) and "knn" not in str(caught.value)
  assert deferred.source == "no checkpoint loaded"
  rng = np.random.default_rng(1)
  for n, gives_up in ((least - 1, True), (least, False)):
    pc1 = np.c_[rng.uniform(-20, 20, (n, 2)), rng.uniform(-1.5, 1.0, n)].astype(np.float32)
    _, info = sweep.raw_sweep_flow(None, pc1, pc1 + np.float32([0.5, 0, 0]))
    assert any("too few points" in note for note in info.notes) == gives_up, (n, info.notes)


def test_evaluate_help_lists_every_dataset_format_with_its_spec():
  """4. --dataset's help is the registry's: every format, its spec."""
  text = evaluate._dataset_help()  # pylint: disable=protected-access
  assert set(data.formats()) == set(data_registry.USAGE)  # every reader's format has its usage
  for name in data.formats():
    assert re.search(rf"(^|; ){name}(:|\[:)", text.split("The formats: ")[1]), name
  for spec in ("ft3d:DIR", "kitti:DIR", "synthetic_lidar[:N]", "h5:FILE.h5", "opensf:DIR",
               "files:PC1,PC2", "synthetic_sweep:N", "reverse=1", *synthetic_sweep.FORMS):
    assert spec in text, spec


class _Compiles:
  """A Python-driven `predict` whose first call on a shape takes 0.3 s more (its compilation)."""

  def __init__(self):
    self.calls, self.shapes = 0, set()

  def __call__(self, pc1, pc2):
    self.calls += 1
    if pc1.shape not in self.shapes:
      self.shapes.add(pc1.shape)
      time.sleep(0.3)
    return jnp.zeros_like(pc1)


def _batches(count):
  rng = np.random.default_rng(0)
  return [{"pc1": rng.normal(size=(1, 32, 3)).astype(np.float32),
           "pc2": rng.normal(size=(1, 32, 3)).astype(np.float32),
           "flow": np.zeros((1, 32, 3), np.float32), "mask": np.ones((1, 32), np.float32),
           "pair_valid": np.ones(1, np.float32), "names": [f"p{i}"]} for i in range(count)]


def test_evaluation_times_the_first_pair_with_its_compilation_and_the_others_apart():
  """5. `first pair s` holds the compilation, `ms/pair after` the steady state; the first pair is
  computed once (with more than one batch)."""
  predict = _Compiles()
  got = evaluator._run(predict, (), _batches(3))  # pylint: disable=protected-access
  assert predict.calls == 3 and got["pairs"] == 3
  assert got["first_pair_s"] >= 0.3 and got["ms_per_pair"] < 150, got
  one = evaluator._run(_Compiles(), (), _batches(1))  # pylint: disable=protected-access
  assert one["first_pair_s"] >= 0.3 and one["ms_per_pair"] < 150, one  # that batch again
  table = reporting.format_table([("toy", got)])
  assert "first pair s" in table and "ms/pair after" in table
  assert "first pair s" in TRAINING and "ms/pair after" in TRAINING and "first_pair_s" in TRAINING


def test_non_finite_rows_are_kept_as_nan_rows_as_the_docs_say(tmp_path):
  """6. A non-finite row of PC1's file is a NaN row of the output, and users.md says so."""
  points = np.random.default_rng(0).normal(size=(10, 3)).astype(np.float32)
  points[[2, 7], 1] = np.nan
  np.save(tmp_path / "pc1.npy", points)
  kept, note, rows = inference.read_cloud(tmp_path / "pc1.npy")
  out = inference.file_rows(np.ones_like(kept), rows)
  assert note and len(kept) == 8 and out.shape == (10, 3)
  assert np.isnan(out[[2, 7]]).all() and np.isfinite(np.delete(out, [2, 7], 0)).all()
  assert "one row per remaining point" not in USERS
  assert "kept in the\n  output as a NaN row" in USERS


def test_the_notebook_says_the_models_frame_is_x_left():
  """7. The quickstart's frame is the models' (jaxflow.geometry.frames): x left, y up, z forward."""
  cells = json.loads((ROOT / "notebooks" / "quickstart.ipynb").read_text())["cells"]
  text = " ".join("".join(c["source"]) for c in cells if c["cell_type"] == "markdown")
  assert "x left, y up, z forward" in text and "x right" not in text


def test_a_mover_beyond_max_range_moves_as_the_docs_say():
  """8. On a 360-degree sweep `max_range` cuts what a method sees, not where objects are sought:
  the crossing box, 15-17 m out, moves with max_range 14 m; the docs and the flag say so."""
  scene = zup_scene.sweep_pair(n_ground=2000)
  flow, info = sweep.raw_sweep_flow(None, scene.pc1, scene.pc2, max_range=14.0)
  far = np.hypot(scene.pc1[:, 0], scene.pc1[:, 1]) >= 14.0
  box = scene.moving1 & far & (scene.pc1[:, 1] < -2)  # the crossing box, all of it beyond
  assert box.sum() > 500 and info.far[0] > 0
  error = np.linalg.norm(flow - scene.flow, axis=1)
  still = np.linalg.norm(scene.ego_flow - scene.flow, axis=1)
  assert np.median(error[box]) < 0.1 < np.median(still[box])  # moved, not the ego-motion flow
  static = far & ~scene.moving1
  assert np.median(np.linalg.norm(flow - scene.ego_flow, axis=1)[static]) < 0.02
  assert "moving objects are sought in the whole sweep, beyond `--max_range`" in USERS


def test_training_doc_names_what_measures_the_main_job_and_every_tensorboard_prefix():
  """9. No stale EPE for the main job: the command that measures it. 10. Every TensorBoard
  prefix the training writes (eval_zero_flow too) is documented."""
  row = next(l for l in TRAINING.splitlines() if l.startswith("| `configs/default.py` |"))
  assert "0.236" not in row and "--workdir runs/default" in row and "eval.json" in row
  source = "".join(p.read_text() for p in (ROOT / "jaxflow" / "training").glob("*.py"))
  prefixes = set(re.findall(r'\.scalars\([^)]*"(\w+)"\)', source) +
                 re.findall(r'prefix="(\w+)"', source))
  assert {"train", "eval", "eval_zero_flow"} <= prefixes, prefixes
  for prefix in prefixes:
    assert f"`{prefix}/" in TRAINING, prefix
