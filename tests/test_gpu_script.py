"""scripts/gpu_round.sh's `device` round (prepared for a lent GPU): valid bash, and on the CPU with
DRY=1 its steps run in order, each logged with its exit code, within the round's deadline."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).absolute().parent.parent


def test_the_script_parses():
  proc = subprocess.run(["bash", "-n", "scripts/gpu_round.sh"], cwd=REPO, capture_output=True,
                        text=True)
  assert proc.returncode == 0, proc.stderr


def _dry_round(tmp_path, **env):
  env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHON": sys.executable, "OUT": str(tmp_path),
         "DRY": "1", "PYTHONPATH": str(REPO), **env}
  proc = subprocess.run(["bash", "scripts/gpu_round.sh", "device"], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=1200)
  assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
  return (tmp_path / "device_round.txt").read_text()


@pytest.mark.slow
def test_dry_device_round_logs_each_step_in_order(tmp_path):
  # The first two steps run (by count, not by the machine's speed); the others are logged skipped.
  log = _dry_round(tmp_path, MAX_STEPS="2")
  assert "== devices: exit 0" in log and "CpuDevice" in log
  assert "== gpu_tests: exit 0" in log and "skipped" in log  # the GPU tests skip on a CPU
  assert "== methods: skipped (MAX_STEPS=2)" in log
  assert log.rstrip().splitlines()[-1].startswith("device round: ")


def test_a_spent_deadline_skips_every_step(tmp_path):
  log = _dry_round(tmp_path, DEADLINE="5")  # under 10 s left from the start: nothing runs
  assert "== devices: skipped (the round's 5 s are spent)" in log
  assert "== methods: skipped (the round's 5 s are spent)" in log and "exit" not in log


@pytest.mark.slow
def test_dry_bench_prints_the_network_table_and_the_selections(tmp_path):
  env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHON": sys.executable, "OUT": str(tmp_path),
         "DRY": "1", "PYTHONPATH": str(REPO)}
  proc = subprocess.run(["bash", "scripts/gpu_round.sh", "bench"], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=1200)
  assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
  text = (tmp_path / "bench.txt").read_text()
  for row in ("| pvraft | inference, B=1, 2 iterations |", "| pvraft | train, B=2, 1 iterations",
              "| default_full | train, B=2", "| kNN, 32 of 1024 | 2 |"):
    assert row in text, text
  assert "DIFFERS" not in text  # every way of selecting returned lax.top_k's indices
