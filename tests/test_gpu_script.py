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


@pytest.mark.slow
def test_dry_device_round_logs_each_step_and_keeps_its_deadline(tmp_path):
  # A deadline that lets the first two steps run: the rest must be skipped, not overrun.
  env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHON": sys.executable, "OUT": str(tmp_path),
         "DRY": "1", "DEADLINE": "40", "PYTHONPATH": str(REPO)}
  proc = subprocess.run(["bash", "scripts/gpu_round.sh", "device"], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=120)
  assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
  log = (tmp_path / "device_round.txt").read_text()
  assert "== devices: exit 0" in log and "CpuDevice" in log
  assert "== gpu_tests: exit 0" in log and "skipped" in log  # the GPU tests skip on a CPU
  assert "== methods: skipped (the round's 40 s are spent)" in log
  assert log.rstrip().splitlines()[-1].startswith("device round: ")
