"""Many processes on the CPU (jaxflow.runtime.distributed): two local train.py processes joined by
--coordinator on 127.0.0.1 (gloo collectives) train as one process with two devices does, write a
checkpoint that one process evaluates, and resume together after one of them is SIGKILLed."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from conftest import xla_flags
from jaxflow.runtime import distributed
from jaxflow.configs import default
from jaxflow.data import BatchLoader, eval_batches, open_dataset
from jaxflow.errors import ConfigError
from jaxflow.evaluation import evaluator
from jaxflow.network import checkpointing

REPO = Path(__file__).absolute().parent.parent
STEPS, EVERY = 12, 4
FLAGS = ["--config", "configs/default.py:smoke", f"--config.train.num_steps={STEPS}",
         f"--config.train.checkpoint_every={EVERY}", f"--config.train.log_every={EVERY}"]
TIMEOUT = 1200


def free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def env(**extra):
  return dict(os.environ, JAX_PLATFORMS="cpu", **extra,
              PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))


def start_two(workdir, *extra, command=None):
  """Two train.py processes of one run (or of `command`); their output goes to files beside the
  workdir."""
  port, procs = free_port(), []
  command = command or ["train.py", *FLAGS, "--workdir", str(workdir)]
  for i in range(2):
    log = open(f"{workdir}.{i}.{time.monotonic_ns()}.log", "w")
    cmd = [sys.executable, *command, *extra,
           "--coordinator", f"127.0.0.1:{port}", "--num_processes", "2", "--process_id", str(i)]
    procs.append(subprocess.Popen(cmd, cwd=REPO, env=env(), stdout=log, stderr=subprocess.STDOUT,
                                  text=True))
    procs[-1].log = log
  return procs


def wait_all(procs):
  outputs = []
  for p in procs:
    p.wait(timeout=TIMEOUT)
    p.log.close()
    outputs.append(Path(p.log.name).read_text())
    assert p.returncode == 0, outputs[-1][-3000:]
  return outputs


def final_params(workdir):
  state, _, step = checkpointing.restore_checkpoint(workdir)
  assert step == STEPS
  return jax.device_get(state)


def kill_one_at_the_first_checkpoint(procs, workdir):
  """SIGKILLs process 1 once the first checkpoint exists; process 0 stops at its next collective
  (or is killed too)."""
  first = workdir / "checkpoints" / str(EVERY)
  deadline = time.monotonic() + TIMEOUT
  while not first.exists() and procs[1].poll() is None and time.monotonic() < deadline:
    time.sleep(0.01)
  procs[1].send_signal(signal.SIGKILL)
  procs[1].wait()
  try:
    procs[0].wait(timeout=5)
  except subprocess.TimeoutExpired:
    procs[0].send_signal(signal.SIGKILL)
    procs[0].wait()
  for p in procs:
    p.log.close()
  assert first.exists() and not (workdir / "checkpoints" / str(STEPS)).exists()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  """(2-process workdir, 1-process-2-devices workdir, the restarted processes' outputs), both runs
  with the end-of-run evaluation. The two processes are interrupted: one is SIGKILLed after the
  first checkpoint, then both are started again with the same command and finish the run."""
  root = tmp_path_factory.mktemp("distributed")
  two = root / "two"
  killed = start_two(two)
  with open(root / "one.log", "w") as log:  # runs while the two processes do
    one = subprocess.Popen(
      [sys.executable, "train.py", *FLAGS, "--workdir", str(root / "one")], cwd=REPO,
      env=env(XLA_FLAGS=xla_flags("--xla_force_host_platform_device_count=2")), stdout=log,
      stderr=subprocess.STDOUT, text=True)
    kill_one_at_the_first_checkpoint(killed, two)
    resumed = wait_all(start_two(two))
    one.wait(timeout=TIMEOUT)
  assert one.returncode == 0, (root / "one.log").read_text()[-3000:]
  return two, root / "one", resumed


@pytest.mark.slow
def test_two_processes_reach_the_heldout_epe_of_one_process_with_two_devices(runs):
  two, one, _ = runs
  epe = {w: json.loads((w / "eval.json").read_text())["model"]["epe"] for w in (two, one)}
  assert epe[two] == pytest.approx(epe[one], rel=1e-4)
  # Process 0 alone wrote the files: each logged step once, the config beside the checkpoints.
  steps = [json.loads(l)["step"] for l in (two / "metrics.jsonl").read_text().splitlines()]
  assert steps == list(range(EVERY, STEPS + 1, EVERY))
  assert json.loads((two / "config.json").read_text())["train"]["num_steps"] == STEPS


@pytest.mark.slow
def test_a_two_process_checkpoint_evaluates_in_one_process_and_in_two(runs, tmp_path):
  two, _, _ = runs
  config = default.get_config("smoke")
  config.eval.dataset = "synthetic_lidar:5"  # 3 batches of 2: process 0 takes two, process 1 one
  one = evaluator.evaluate_checkpoint(two, config)
  assert one["step"] == STEPS and one["pairs"] == 5
  wait_all(start_two(tmp_path / "eval", command=[
    "evaluate.py", "--config", "configs/default.py:smoke", "--checkpoint", str(two),
    "--dataset", "synthetic_lidar:5", "--json", str(tmp_path / "eval.json")]))
  both = json.loads((tmp_path / "eval.json").read_text())
  assert both["pairs"] == 5
  for k in ("epe", "acc_strict", "acc_relax", "outliers", "angle"):
    assert both[k] == pytest.approx(one[k], rel=1e-5, abs=1e-7), k
  stored = json.loads((two / "eval.json").read_text())["model"]
  config.eval.dataset = "synthetic_lidar:4"  # the run's own held-out pairs
  assert evaluator.evaluate_checkpoint(two, config)["epe"] == pytest.approx(stored["epe"], rel=1e-5)


@pytest.mark.slow
def test_sigkill_of_one_process_then_a_restart_of_both_resumes(runs):
  two, one, outputs = runs
  assert all("resuming from" in out for out in outputs)
  # The interrupted two processes end where one uninterrupted process with two devices does.
  for a, b in zip(jax.tree.leaves(final_params(two)), jax.tree.leaves(final_params(one))):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)


def test_process_rows_of_a_batch_make_the_whole_batch():
  ds = open_dataset("synthetic_lidar:8")
  whole = BatchLoader(ds, 4, 32, seed=3, prefetch=0).batch(5)
  parts = [BatchLoader(ds, 4, 32, seed=3, prefetch=0, rows=r).batch(5) for r in ((0, 1), (1, 4))]
  for k in ("pc1", "pc2", "flow", "mask"):
    np.testing.assert_array_equal(np.concatenate([p[k] for p in parts]), whole[k])
  shards = [list(eval_batches(ds, 3, 32, shard=(i, 2))) for i in range(2)]
  real = lambda batches: [n for b in batches for n, v in zip(b["names"], b["pair_valid"]) if v]
  assert sorted(real(shards[0] + shards[1])) == sorted(real(eval_batches(ds, 3, 32)))
  assert len(real(shards[0] + shards[1])) == len(ds)


def test_partial_process_flags_are_refused(monkeypatch):
  for name in ("SLURM_NTASKS", "OMPI_COMM_WORLD_SIZE", "TPU_WORKER_HOSTNAMES"):
    monkeypatch.delenv(name, raising=False)
  with pytest.raises(ConfigError, match="go together"):
    distributed.initialize("127.0.0.1:1234", 2, None)
  with pytest.raises(ConfigError, match="process_id"):
    distributed.initialize("127.0.0.1:1234", 2, 2)
  assert distributed.initialize() == jax.process_count() == 1  # nothing detected: one process
