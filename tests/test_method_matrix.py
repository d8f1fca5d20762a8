"""Every registered method on every dataset layout, batch 1 and 2, through evaluate.py's
evaluation (evaluator.evaluate_checkpoint, what its main calls) at toy size; and the commands that
crashed on the LiDAR layout (z up) run as a user types them."""

import json
from pathlib import Path

import numpy as np
import pytest

import h5py

from jaxflow import evaluate
from jaxflow.configs import default
from jaxflow.evaluation import evaluator
from jaxflow.methods import registry
from tests.test_data_opensf import LOGS, make_frame
from tests.test_data_readers import make_ft3d, random_cloud, write_pair_folder

import commands

REPO = Path(__file__).absolute().parent.parent
# Each method as small as it goes: an optimiser's steps capped, the network's iterations 1, the
# distance grid 2^15 nodes (its default 2^22 took a third of the optimise row's time at 64 points).
STEPS = {"nsfp": 3, "optimise": 3}
FIELDS = {"optimise": {"descent.max_cells": 2**15}}


def write_opensf(root: Path) -> Path:
  """DIR/val/<log>.h5 in OpenSceneFlow's layout (tests/test_data_opensf.py's frames)."""
  (root / "val").mkdir(parents=True)
  rng = np.random.default_rng(0)
  for log, frames in LOGS.items():
    with h5py.File(root / "val" / f"{log}.h5", "w") as f:
      for stamp, labelled in frames:
        group = f.create_group(str(stamp))
        for k, v in make_frame(rng, labelled, moving=log == "log_a")[0].items():
          group.create_dataset(k, data=v)
  return root


@pytest.fixture(scope="module")
def layouts(tmp_path_factory):
  """{name: (dataset spec, split)} of every reader, written in its documented layout."""
  root = tmp_path_factory.mktemp("layouts")
  make_ft3d(root / "ft3d", val=(4, 8, 12))
  for i, n in ((2, 80), (3, 70)):  # two of KITTI's 142 benchmark frames
    write_pair_folder(root / "kitti" / f"00000{i}", random_cloud(i, n), random_cloud(i, n) + 0.1)
  (root / "argo").mkdir()
  (root / "fn3d").mkdir()
  for i in range(3):
    np.savez(root / "argo" / f"{i}.npz", pc1=random_cloud(i, 60), pc2=random_cloud(i + 9, 62),
             flow=random_cloud(i + 5, 60) * 0.01)
    np.savez(root / "fn3d" / f"TEST_{i}.npz", points1=random_cloud(i, 60),
             points2=random_cloud(i + 9, 61), flow=random_cloud(i + 5, 60) * 0.01,
             valid_mask1=np.arange(60) % 3 != 0)
  opensf = write_opensf(root / "opensf")
  return {"ft3d": (f"ft3d:{root / 'ft3d'}", "test"), "kitti": (f"kitti:{root / 'kitti'}", None),
          "argoverse": (f"argoverse:{root / 'argo'}", None),
          "flownet3d": (f"flownet3d:{root / 'fn3d'}", "test"),
          "opensf_ego": (f"opensf:{opensf},lidar=ego", "val"),
          "opensf_camera": (f"opensf:{opensf},lidar=ego,frame=camera", "val"),
          "opensf_sweep": (f"opensf:{opensf},lidar=ego,region=sweep", "val"),
          "synthetic_lidar": ("synthetic_lidar:3", "test"),
          "synthetic_sweep": ("synthetic_sweep:2", "val")}


def _config(batch_size: int):
  config = default.get_config("eval")
  config.eval.update(num_points=64, num_iters=1, batch_size=batch_size)
  return config


@pytest.mark.parametrize("method", registry.METHODS)
@pytest.mark.filterwarnings("ignore:.*KITTI benchmark frames")
def test_every_method_on_every_layout(method, layouts, smoke_checkpoint):
  """Each reader x batch 1 and 2: a finite EPE over every pair, the method named in the results;
  the LiDAR layouts (z up) get the official table's numbers."""
  chosen = registry.settings(method, steps=STEPS.get(method), fields=FIELDS.get(method))
  for name, (spec, split) in layouts.items():
    for batch_size in (1, 2):
      results = evaluator.evaluate_checkpoint(smoke_checkpoint, _config(batch_size), spec, split,
                                              method=method, method_settings=chosen)
      assert results["method"] == method and results["pairs"] >= 2, (name, batch_size)
      assert np.isfinite(results["epe"]), (name, batch_size, results)
      if name.startswith("opensf") or name == "synthetic_sweep":
        assert np.isfinite(results["av2"]["EPE 3-Way Average"]), (name, results["av2"])


def _evaluate(*args, tmp_path):
  """`python evaluate.py ARGS --json OUT`, run in this process (tests/commands.py)."""
  out = tmp_path / "results.json"
  proc = commands.run(evaluate.run, *args, "--json", out, cwd=REPO,
                      prog=commands.script("evaluate.py"))
  assert proc.returncode == 0, proc.stderr[-3000:]
  return proc.stdout, json.loads(out.read_text())


@pytest.mark.parametrize("method, extra", [("optimise", ["--steps", "3", "--iters", "1"]),
                                           ("nsfp", ["--steps", "3"]), ("lidar", [])])
def test_evaluate_runs_each_method_on_the_lidar_layout(method, extra, layouts, smoke_checkpoint,
                                                       tmp_path):
  """The issue's commands (optimise and nsfp crashed on z-up clouds) and the lidar method on whole
  raw sweeps scored on the challenge's points: the official table printed."""
  spec = layouts["opensf_sweep" if method == "lidar" else "opensf_ego"][0]
  region = [] if method == "lidar" else [",region=challenge"]
  stdout, results = _evaluate("--dataset", spec + "".join(region), "--split", "val", "--method",
                              method, "--checkpoint", str(smoke_checkpoint), "--max_points", "0",
                              *extra, tmp_path=tmp_path)
  assert "av2 official" in stdout and "bucketed 2024" in stdout, stdout
  assert [len(bands) for bands in results["bucketed"]["speeds"].values()] == [4] * 5  # by speed
  assert results["method"] == method and results["pairs"] == 3
  assert results["av2"]["challenge_points"]
