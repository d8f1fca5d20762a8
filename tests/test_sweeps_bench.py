"""benchmarks/sweeps.py reports both directions: the default pipeline on each pair taken backwards,
row by row beside the forward one, and the bucketed table by class and by speed band."""

import json
import subprocess
import sys

import numpy as np
import pytest

from jaxflow.data import synthetic_sweep as ss
from jaxflow.lidar import sweep


@pytest.mark.slow
def test_the_backward_row_is_the_pipeline_on_the_pair_taken_backwards(tmp_path):
  out = tmp_path / "sweeps.json"
  run = subprocess.run([sys.executable, "benchmarks/sweeps.py", "--split", "val", "--pairs", "1",
                        "--directions", "backward", "--json", str(out)],
                       capture_output=True, text=True, check=True)
  assert "PEDESTRIAN" in run.stdout  # the bucketed table by class
  assert "movers by class and speed" in run.stdout  # ... and by speed band
  speeds = json.loads(out.read_text())["official"]["ego + objects (default), backward"]["speeds"]
  assert [b["speeds"][0] for b in speeds["CAR"]] == [0.04, 0.32, 1.0, 2.0]
  rows = json.loads(out.read_text())["per_pair"]
  assert list(rows) == ["ego + objects (default), backward"]
  backward = ss.sweep_pair("val", 0, ss.Options(reverse=True))
  forward = ss.sweep_pair("val", 0)
  np.testing.assert_array_equal(backward.pc1, forward.pc2)  # pc1 is the later sweep
  flow = sweep.raw_sweep_flow(None, backward.pc1, backward.pc2)[0]
  epe = np.linalg.norm(flow - backward.flow, axis=1).mean()
  assert rows["ego + objects (default), backward"][0]["epe"] == pytest.approx(epe, abs=1e-6)


def test_a_direction_the_benchmark_does_not_know_is_refused():
  run = subprocess.run([sys.executable, "benchmarks/sweeps.py", "--directions", "sideways"],
                       capture_output=True, text=True)
  assert run.returncode != 0 and "--directions" in run.stderr
