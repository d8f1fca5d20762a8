"""Stopping and resuming: SIGKILL or SIGTERM mid-run, then the same command, ends with exactly the
parameters of an uninterrupted run; half-written checkpoints are never loaded."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxflow.errors import CheckpointError
from jaxflow.network import checkpointing
from jaxflow.training import trainer

REPO = Path(__file__).absolute().parent.parent
from conftest import CACHE  # (the one compilation cache of this checkout)
jax.config.update("jax_compilation_cache_dir", CACHE)
TOTAL_STEPS = 24  # configs/default.py:smoke
EVERY = 6


def train_command(workdir):
  return [sys.executable, "train.py", "--config", "configs/default.py:smoke",
          "--workdir", str(workdir), "--config.eval.dataset="]


def env():
  return dict(os.environ, JAX_PLATFORMS="cpu",
              PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))


def run(workdir):
  proc = subprocess.run(train_command(workdir), cwd=REPO, env=env(), capture_output=True,
                        text=True, timeout=1200)
  assert proc.returncode == 0, proc.stderr[-3000:]
  return proc


def start_and_signal(workdir, signum):
  """Starts training and sends `signum` as soon as the first checkpoint is committed."""
  proc = subprocess.Popen(train_command(workdir), cwd=REPO, env=env(), stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)
  first = workdir / "checkpoints" / str(EVERY)
  deadline = time.monotonic() + 1200
  while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
    time.sleep(0.01)
  proc.send_signal(signum)
  out, err = proc.communicate(timeout=1200)
  assert not (workdir / "checkpoints" / str(TOTAL_STEPS)).exists(), "the run ended before the signal"
  return proc.returncode, err


def final_state(workdir):
  state, _, step = checkpointing.restore_checkpoint(workdir)
  assert step == TOTAL_STEPS
  return jax.device_get(state)


def assert_identical(a, b):
  la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
  assert len(la) == len(lb)
  for x, y in zip(la, lb):
    assert np.asarray(x).tobytes() == np.asarray(y).tobytes()


@pytest.fixture(scope="module")
def uninterrupted_dir(tmp_path_factory):
  workdir = tmp_path_factory.mktemp("uninterrupted")
  run(workdir)
  return workdir


@pytest.fixture(scope="module")
def uninterrupted(uninterrupted_dir):
  return final_state(uninterrupted_dir)


@pytest.mark.slow
def test_sigkill_then_same_command_resumes_to_identical_parameters(uninterrupted, tmp_path):
  code, _ = start_and_signal(tmp_path, signal.SIGKILL)
  assert code == -signal.SIGKILL
  proc = run(tmp_path)
  assert "resuming from" in proc.stderr
  assert_identical(final_state(tmp_path), uninterrupted)  # params, optimiser state and step


@pytest.mark.slow
def test_sigterm_saves_a_checkpoint_and_resume_matches(uninterrupted, tmp_path):
  code, err = start_and_signal(tmp_path, signal.SIGTERM)
  assert code == 128 + signal.SIGTERM, err[-2000:]
  line = [l for l in err.splitlines() if l.startswith("stopped by SIGTERM at step ")]
  assert line, err[-2000:]
  step = int(line[0].split("at step ")[1].split(";")[0])
  assert EVERY <= step < TOTAL_STEPS
  assert "Traceback" not in err
  state, _, restored_step = checkpointing.restore_checkpoint(tmp_path / "checkpoints" / str(step))
  assert restored_step == step and int(state.step) == step
  run(tmp_path)
  assert_identical(final_state(tmp_path), uninterrupted)
  # metrics.jsonl has each logged step once, although steps after the checkpoint ran twice (the
  # stop also logged its own step).
  steps = [int(l.split('"step": ')[1].split(",")[0])
           for l in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  assert steps == sorted(set(steps)) and set(range(2, TOTAL_STEPS + 1, 2)) <= set(steps)


@pytest.mark.slow
def test_half_written_checkpoints_are_not_loaded(uninterrupted_dir, tmp_path):
  workdir = tmp_path / "run"
  shutil.copytree(uninterrupted_dir, workdir)
  run_dir = workdir / "checkpoints"
  # orbax's own temporary folder of a step that was being written: ignored.
  tmp = run_dir / f"{TOTAL_STEPS + EVERY}.orbax-checkpoint-tmp-1234567"
  (tmp / "state").mkdir(parents=True)
  (tmp / "state" / "garbage").write_bytes(b"\0" * 10)
  ckpts = checkpointing.Checkpoints(run_dir)
  assert ckpts.latest_step() == TOTAL_STEPS
  ckpts.close()
  _, _, step = checkpointing.restore_checkpoint(workdir)
  assert step == TOTAL_STEPS
  # A numbered step folder without orbax's commit metadata (copied half-way): a clear error.
  bad = run_dir / str(TOTAL_STEPS + 2 * EVERY)
  shutil.copytree(run_dir / str(TOTAL_STEPS), bad)
  (bad / "_CHECKPOINT_METADATA").unlink()
  with pytest.raises(CheckpointError, match=rf"{bad}.*incomplete"):
    checkpointing.restore_checkpoint(workdir)
  _, _, step = checkpointing.restore_checkpoint(run_dir / str(TOTAL_STEPS))  # an explicit step
  assert step == TOTAL_STEPS


def smoke_config(**overrides):
  from jaxflow.configs import default

  config = default.get_config("smoke")
  config.eval.dataset = ""
  for key, value in overrides.items():
    section, field = key.split("__")
    config[section][field] = value
  return config


@pytest.mark.slow
def test_resume_with_another_recipe_is_refused_unless_asked(uninterrupted_dir, tmp_path):
  from jaxflow.errors import ConfigError

  workdir = tmp_path / "run"
  shutil.copytree(uninterrupted_dir, workdir)
  before = (workdir / "config.json").read_bytes()
  other = smoke_config(data__dataset="synthetic_lidar:16", train__lr=2e-3, train__log_every=3)
  with pytest.raises(ConfigError) as e:
    trainer.train_and_evaluate(other, workdir)
  message = str(e.value)
  assert "\n" not in message and "resume_with_new_recipe" in message
  assert "data.dataset: 'synthetic_lidar:32' != 'synthetic_lidar:16'" in message
  assert "train.lr: 0.001 != 0.002" in message and "log_every" not in message
  assert (workdir / "config.json").read_bytes() == before  # nothing written on a refusal
  # Asked explicitly, and run longer: the change is recorded beside the new checkpoint.
  extended = TOTAL_STEPS + 2
  asked = smoke_config(train__lr=2e-3, train__num_steps=extended, train__resume_with_new_recipe=True)
  trainer.train_and_evaluate(asked, workdir)
  written = json.loads((workdir / "config.json").read_text())
  _, stored, step = checkpointing.restore_checkpoint(workdir)
  assert step == extended and written["train"]["lr"] == stored.train.lr == 2e-3
  assert written["recipe_changes"] == [{"step": TOTAL_STEPS, "changed": ["train.lr: 0.001 != 0.002"]}]
  assert checkpointing.config_to_dict(stored)["recipe_changes"] == written["recipe_changes"]
  # The earlier checkpoints keep the recipe they were trained with.
  _, older, _ = checkpointing.restore_checkpoint(workdir / "checkpoints" / str(TOTAL_STEPS))
  assert older.train.lr == 1e-3 and "recipe_changes" not in older
