"""benchmarks/yardstick.py: its count of the sorts and top-k calls an optimised HLO holds."""

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import jax

from benchmarks import yardstick
from jaxflow.geometry import neighbours

REPO = Path(__file__).absolute().parent.parent


def test_selections_reads_sorts_and_top_k_calls():
  hlo = "\n".join([
    "  %p = f32[4,4096]{1,0} parameter(0)",
    "  %sort.1 = (f32[8,256]{1,0}, s32[8,256]{1,0}) sort(%a, %b), dimensions={1}, is_stable=true",
    '  %custom-call = (f32[4,32]{1,0}, s32[4,32]{1,0}) custom-call(%p), custom_call_target="TopK"',
    "  %add = f32[4,4096]{1,0} add(%p, %p)",
  ])
  assert yardstick.selections(hlo) == (2, 4096)


def test_a_blockwise_knn_orders_no_row_as_long_as_the_cloud():
  points = jax.random.uniform(jax.random.PRNGKey(0), (1, 4096, 3))
  longest = {}
  for form in ("sort", "blockwise"):
    knn = jax.jit(functools.partial(neighbours.matmul_knn, k=32, selection=form))
    longest[form] = yardstick.selections(knn.lower(points, points).compile().as_text())[1]
  assert longest == {"sort": 4096, "blockwise": 512}  # blocks of 256, then 16 x 32 survivors


def test_the_command_writes_its_figures_at_toy_size(tmp_path):
  out = tmp_path / "yardstick.json"
  proc = subprocess.run([sys.executable, "-m", "benchmarks.yardstick", "--points", "256",
                         "--iters", "2", "--train_iters", "1", "--configs", "pvraft",
                         "--json", str(out)], cwd=REPO, capture_output=True, text=True,
                        timeout=600, env={**os.environ, "JAX_PLATFORMS": "cpu"})
  assert proc.returncode == 0, proc.stderr[-2000:]
  rows = json.loads(out.read_text())["rows"]
  assert [r["program"] for r in rows] == ["inference B=1", "train step B=2"]
  assert all(r["temp_mib"] > 0 and r["gflops"] > 0 and r["selections"] >= 3 for r in rows)
  assert "| pvraft, train step B=2 |" in proc.stdout
