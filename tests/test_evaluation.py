"""evaluate.py, jaxflow.evaluation.evaluator and jaxflow.evaluation.reporting: determinism, padding, the table, the
shared flags, bad checkpoints."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxflow import evaluate
from jaxflow.configs import default
from jaxflow.data import eval_batches, open_dataset
from jaxflow.errors import CheckpointError, ConfigError
from jaxflow.evaluation import evaluator, reporting
from jaxflow.evaluation.metrics import METRICS
from jaxflow.network import checkpointing
from jaxflow.network.model import build_model

REPO = Path(__file__).absolute().parent.parent
from conftest import CACHE  # (the one compilation cache of this checkout)
import commands
jax.config.update("jax_compilation_cache_dir", CACHE)
STEP = 1  # the step of conftest's smoke_checkpoint


@pytest.fixture(scope="module")
def workdir(smoke_checkpoint):
  """A checkpoint of the smoke model: evaluation's plumbing needs no trained weights (training
  end to end: tests/test_training.py)."""
  return smoke_checkpoint


def evaluate_cli(*args):
  """`python evaluate.py ARGS` in the repository, run in this process (tests/commands.py)."""
  return commands.run(evaluate.run, *args, cwd=REPO, prog=commands.script("evaluate.py"))


def evaluate_subprocess(*args):
  """`python evaluate.py ARGS` as a process of its own (each use says why)."""
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  return subprocess.run([sys.executable, "evaluate.py", *map(str, args)], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=1200)


@pytest.mark.slow
def test_same_command_twice_gives_identical_numbers(workdir, tmp_path):
  results = []
  for i in range(2):  # in this process, then in a process of its own (nothing of the first kept)
    out = tmp_path / f"{i}.json"
    proc = (evaluate_cli, evaluate_subprocess)[i](
      "--config", "configs/default.py:smoke", "--checkpoint", workdir, "--dataset",
      "synthetic_lidar:5", "--json", out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| Dataset" in proc.stdout and "EPE(m)" in proc.stdout and "ms/pair" in proc.stdout
    results.append(json.loads(out.read_text()))
  a, b = results
  assert set(a) >= {"epe", "acc_strict", "acc_relax", "outliers", "angle", "pairs", "ms_per_pair",
                    "first_pair_s"}
  assert a["pairs"] == 5 and a["output"] == "coarse" and a["step"] == STEP
  for r in results:  # the times
    r.pop("ms_per_pair"), r.pop("first_pair_s")
  assert a == b


def test_padding_pairs_are_excluded():
  ds = open_dataset("synthetic_lidar:5", split="test")
  one = evaluator.evaluate_zero_flow(ds, num_points=64, batch_size=1)
  three = evaluator.evaluate_zero_flow(ds, num_points=64, batch_size=3)  # 1 padding pair
  assert one["pairs"] == three["pairs"] == 5
  for k in METRICS:
    np.testing.assert_allclose(one[k], three[k], rtol=1e-5)


def test_model_results_match_a_direct_computation(workdir):
  """evaluate() averages per-pair metrics over pairs (here against numpy on the same pairs)."""
  state, config, _ = checkpointing.restore_checkpoint(workdir)
  model = build_model(config.model)
  ds = open_dataset("synthetic_lidar:3", split="test")
  got = evaluator.evaluate(model, state.params, ds, num_points=64, batch_size=2, num_iters=2)
  apply = jax.jit(lambda p, a, b: model.apply({"params": p}, a, b, num_iters=2, refine=False))
  epes = []
  for batch in eval_batches(ds, 1, 64, seed=0):  # the same seeded point samples, one at a time
    flow = np.asarray(apply(state.params, batch["pc1"], batch["pc2"])["flows"][0, -1])
    err = np.linalg.norm(flow - batch["flow"][0], axis=-1)
    epes.append(np.sum(err * batch["mask"][0]) / np.sum(batch["mask"][0]))
  np.testing.assert_allclose(got["epe"], np.mean(epes), rtol=1e-4)
  assert got["pairs"] == 3 and got["ms_per_pair"] > 0


def test_a_second_evaluation_of_an_equal_model_traces_nothing(workdir):
  """The network is traced once a process: a second evaluate() with a model built again from the
  same config (evaluate.py's commands in one process, a notebook's second call) reuses it, also
  rotated from a z-up dataset; a model with other fields is traced anew."""
  state, config, _ = checkpointing.restore_checkpoint(workdir)
  y_up = open_dataset("synthetic_lidar:2", split="test")
  z_up = open_dataset("synthetic_sweep:2", split="test")
  assert (y_up.up, z_up.up) == ("y", "z")
  traces = []
  listener = lambda event, _, **kw: event.endswith("trace_duration") and traces.append(event)
  jax.monitoring.register_event_duration_secs_listener(listener)

  def run(model_config, dataset):
    before = len(traces)  # (3 iterations: no other test of this process evaluates so)
    evaluator.evaluate(build_model(model_config), state.params, dataset, num_points=64,
                       batch_size=2, num_iters=3)
    return len(traces) - before

  try:
    assert run(config.model, y_up) > 0 and run(config.model, y_up) == 0
    run(config.model, z_up)
    assert run(config.model, z_up) == 0
    other = config.model.copy_and_resolve_references()
    other.truncate_k = config.model.truncate_k // 2
    assert run(other, y_up) > 0
  finally:
    jax.monitoring.unregister_event_duration_listener(listener)


def test_an_old_config_with_test_time_is_refused_naming_the_method(workdir):
  config = default.get_config("smoke")
  with config.unlocked():
    config.eval.test_time = {"steps": 15}
  with pytest.raises(ConfigError, match="config.eval.test_time was removed.*--method optimise"):
    evaluator.evaluate_checkpoint(workdir, config, "synthetic_lidar:2", "test")


@pytest.mark.slow
def test_shared_flags_mean_the_config_fields_and_outputs_go_where_asked(workdir, tmp_path):
  """--iters / --max_points / --seed are config.eval.num_iters / num_points / seed (as in
  predict); --save_flows and --render_dir receive one file per pair."""
  out = tmp_path / "flags.json"
  proc = evaluate_cli("--config", "configs/default.py:smoke", "--checkpoint", workdir,
                      "--dataset", "synthetic_lidar:3", "--iters", 2, "--max_points", 48,
                      "--seed", 3, "--json", out, "--save_flows", tmp_path / "flows",
                      "--render_dir", tmp_path / "views")
  assert proc.returncode == 0, proc.stderr[-3000:]
  config = default.get_config("smoke")
  config.eval.num_iters, config.eval.num_points, config.eval.seed = 2, 48, 3
  direct = evaluator.evaluate_checkpoint(workdir, config, "synthetic_lidar:3")
  got = json.loads(out.read_text())
  assert got["num_iters"] == 2 and got["num_points"] == 48
  np.testing.assert_allclose(got["epe"], direct["epe"], rtol=1e-6)
  flows = sorted((tmp_path / "flows").glob("*.npy"))
  assert len(flows) == 3 and all(np.load(f).shape == (48, 3) for f in flows)
  assert len(list((tmp_path / "views").glob("*.png"))) == 6  # NAME.png and NAME_top.png a pair


def test_infer_truncate_k_sets_the_candidates_when_evaluating_only(workdir):
  config = default.get_config("smoke")  # truncate_k 16, infer_truncate_k 0
  model, params, saved, _, _ = checkpointing.load_for_inference(workdir)
  assert model.truncate_k == saved.model.truncate_k == 16
  with config.unlocked():
    config.model.infer_truncate_k = 4  # a runtime field: no contradiction with the checkpoint
  fewer, _, _, _, _ = checkpointing.load_for_inference(workdir, config, ["infer_truncate_k"])
  assert fewer.truncate_k == 4
  assert build_model(config.model).truncate_k == 16  # training keeps truncate_k
  ds = open_dataset("synthetic_lidar:2", split="test")
  ev = lambda m: evaluator.evaluate(m, params, ds, num_points=64, batch_size=2, num_iters=2)
  reference = saved.model.copy_and_resolve_references()
  reference.truncate_k = 4  # the same network built with 4 candidates directly
  assert ev(fewer)["epe"] == ev(build_model(reference))["epe"] != ev(model)["epe"]
  with config.unlocked():
    config.model.infer_truncate_k = -1
  with pytest.raises(ValueError, match="infer_truncate_k"):
    build_model(config.model, inference=True)
  # Checkpoints written before the fields existed compare as infer_truncate_k 0, no remat.
  old = saved.copy_and_resolve_references()
  with old.unlocked():
    del old.model["infer_truncate_k"], old.model["remat_iterations"]
  assert not checkpointing.model_differences(old, default.get_config("smoke"))
  assert checkpointing.model_differences(old, config) == ["infer_truncate_k: 0 != -1"]


@pytest.mark.slow
def test_cli_keeps_the_checkpoints_candidates_unless_given(workdir, tmp_path):
  run, step_dir = copy_run(workdir, tmp_path)
  meta = step_dir / "config" / "metadata"
  stored = json.loads(meta.read_text())
  stored["model"]["infer_truncate_k"] = 4  # as a checkpoint trained for 4 test-time candidates
  meta.write_text(json.dumps(stored))
  config = default.get_config("smoke")
  ds = open_dataset("synthetic_lidar:2", split="test")
  epes = {}
  for k in (4, 16):
    reference = config.model.copy_and_resolve_references()
    reference.truncate_k = k
    state, _, _ = checkpointing.restore_checkpoint(run)
    epes[k] = evaluator.evaluate(build_model(reference), state.params, ds,
                                  num_points=config.eval.num_points, batch_size=config.eval.batch_size,
                                  num_iters=config.eval.num_iters)["epe"]
  assert epes[4] != epes[16]
  # An explicit config file (infer_truncate_k 0) keeps the checkpoint's 4; the command line sets 16.
  for extra, k in (((), 4), (("--config.model.infer_truncate_k=16",), 16)):
    out = tmp_path / f"{k}.json"
    proc = evaluate_cli("--config", "configs/default.py:smoke", "--checkpoint", run,
                        "--dataset", "synthetic_lidar:2", "--json", out, *extra)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert np.isclose(json.loads(out.read_text())["epe"], epes[k], rtol=1e-6), k


def test_format_table_has_the_papers_columns():
  r = dict(epe=0.04421, acc_strict=83.8, acc_relax=95.98, outliers=26.37, angle=0.1234, pairs=3824,
           first_pair_s=9.876, ms_per_pair=12.34)
  lines = reporting.format_table([("FT3D", r)]).splitlines()
  assert [c.strip() for c in lines[0].strip("|").split("|")] == [
    "Dataset", "EPE(m)", "AccS(%)", "AccR(%)", "Outliers(%)", "θε(rad)", "pairs", "first pair s",
    "ms/pair after"]
  assert [c.strip() for c in lines[2].strip("|").split("|")] == [
    "FT3D", "0.0442", "83.80", "95.98", "26.37", "0.1234", "3824", "9.88", "12.3"]


def copy_run(workdir, tmp_path):
  dst = tmp_path / "run"
  shutil.copytree(workdir, dst)
  return dst, dst / "checkpoints" / str(STEP)


def test_cli_silences_the_reports_of_abandoned_reads():
  """What orbax's abandoned reads leave at exit (a coroutine never awaited, a closed event loop)
  adds no line after the one-line error (the truncated case below hits it only sometimes). A
  subprocess (no jax imported): what the interpreter reports at exit is the subject."""
  code = ("from jaxflow import cli\n"
          "async def read(): pass\n"
          "pending = read()\n"
          "def main():\n"
          "  raise cli.ConfigError('bad checkpoint')\n"
          "cli.guard(main)\n")
  proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                        timeout=1200)
  assert proc.returncode == 2 and proc.stderr.strip().splitlines() == ["error: bad checkpoint"]


# orbax's reads abandoned by a failed restore report into its closed event loop (jaxflow.cli).
@pytest.mark.filterwarnings("ignore:(?s).*Event loop is closed:pytest.PytestUnraisableExceptionWarning")
def test_bad_checkpoints_raise_checkpoint_error_naming_path(workdir, tmp_path):
  config = default.get_config("smoke")
  ev = lambda path, fields=(): evaluator.evaluate_checkpoint(
    path, config, "synthetic_lidar:2", "test", model_fields=fields)
  with pytest.raises(CheckpointError, match="no such"):
    ev(tmp_path / "missing")
  # A model field contradicting the checkpoint.
  with config.unlocked():
    config.model.knn = 4
  with pytest.raises(CheckpointError, match=r"contradicts.*knn: 4 != 8"):
    ev(workdir, ["knn"])
  config = default.get_config("smoke")
  # Truncated array data.
  run, step_dir = copy_run(workdir, tmp_path / "a")
  for f in (step_dir / "state").rglob("*"):
    if f.is_file() and f.parent.name == "d":
      f.write_bytes(f.read_bytes()[:7])
  with pytest.raises(CheckpointError, match=rf"{step_dir}.*cannot restore"):
    ev(run)
  # A missing item.
  run, step_dir = copy_run(workdir, tmp_path / "b")
  shutil.rmtree(step_dir / "state")
  with pytest.raises(CheckpointError, match=rf"{step_dir}.*missing the 'state' item"):
    ev(step_dir)
  # A stored config that does not match the stored arrays.
  run, step_dir = copy_run(workdir, tmp_path / "c")
  meta = step_dir / "config" / "metadata"
  stored = json.loads(meta.read_text())
  stored["model"]["widths"] = [16, 16, 32, 64]
  meta.write_text(json.dumps(stored))
  with pytest.raises(CheckpointError, match=rf"{step_dir}.*cannot restore"):
    ev(run)


def test_no_checkpoint_and_none_shipped_is_a_clear_error(monkeypatch, tmp_path):
  monkeypatch.setattr(checkpointing, "SHIPPED_CHECKPOINT", tmp_path / "jaxflow_synthetic")
  with pytest.raises(CheckpointError, match="no checkpoint given and no shipped checkpoint"):
    evaluator.evaluate_checkpoint(None, default.get_config("eval"), "synthetic_lidar:2")


@pytest.mark.slow
def test_cli_bad_checkpoint_is_one_line_and_exit_2(workdir, tmp_path):
  run, step_dir = copy_run(workdir, tmp_path)
  (step_dir / "_CHECKPOINT_METADATA").unlink()
  proc = evaluate_cli("--checkpoint", run, "--dataset", "synthetic_lidar:2")
  assert proc.returncode == 2
  lines = proc.stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("error: ") and str(step_dir) in lines[0], proc.stderr
  proc = evaluate_cli("--checkpoint", workdir, "--dataset", "synthetic_lidar:2",
                      "--config.model.knn=4")
  assert proc.returncode == 2
  lines = proc.stderr.strip().splitlines()
  assert len(lines) == 1 and "knn: 4 != 8" in lines[0], proc.stderr
  # Truncated arrays: orbax's other reads, abandoned when the restore fails, must not add
  # tracebacks after the one line (a subprocess: they report at garbage collection and exit).
  run, step_dir = copy_run(workdir, tmp_path / "truncated")
  for f in (step_dir / "state").rglob("*"):
    if f.is_file() and f.parent.name == "d":
      f.write_bytes(f.read_bytes()[:7])
  proc = evaluate_subprocess("--checkpoint", run, "--dataset", "synthetic_lidar:2")
  assert proc.returncode == 2
  lines = proc.stderr.strip().splitlines()
  assert len(lines) == 1 and "cannot restore the train state" in lines[0], proc.stderr
