"""Both stages of every paper config family at toy size: stage 2 starts from the stage-1 run of the
same family, loads and freezes its backbone and trains a freshly initialised refinement, the one
added to a stage-1 model that had none (PV-RAFT). PV-RAFT and the ablation row `gcl` run both
stages through train.py as a user types them; the other rows run stage 2 in-process (the function
train.py calls) from a stage-1 checkpoint of their own config written without training (training
stage 1 is the same code for every row and costs a compilation each)."""

import json

import jax
import numpy as np
import pytest
from flax import traverse_util

from conftest import ROOT
from jaxflow import train
from jaxflow.configs import ablation, paper
from jaxflow.network import checkpointing, train_state
from jaxflow.network.model import build_model
from jaxflow.training import trainer

import commands

TOY_FIELDS = {"data.dataset": "synthetic_lidar:8", "data.num_points": 256, "train.num_steps": 2,
              "train.checkpoint_every": 2, "eval.dataset": ""}
TOY = [f"--config.{k}={v}" for k, v in TOY_FIELDS.items()]
# family: (stage-1 config, stage-2 config [, its flags]), as the configs' docstrings give them.
THROUGH_TRAIN_PY = {
  "pvraft": ("configs/pvraft.py", "configs/pvraft.py:refine", ["--config.train.stage=2"]),
  "gcl": ("configs/ablation.py:gcl", "configs/ablation.py:gcl,stage2", []),
}
IN_PROCESS = {
  "gcl_rc": (lambda: ablation.get_config("gcl_rc"), lambda: ablation.get_config("gcl_rc,stage2")),
  "full": (paper.get_config, lambda: paper.get_config("stage2")),  # = ablation gcl_rc_sgfi
}


def flat(tree):
  return traverse_util.flatten_dict(tree, sep="/")


def train_py(config, workdir, *flags):
  """`python train.py ...` as typed, run in this process (tests/commands.py)."""
  done = commands.run(train.run, f"--config={config}", f"--workdir={workdir}", *TOY, *flags,
                      cwd=ROOT, prog=commands.script("train.py"))
  assert done.returncode == 0, done.stderr[-3000:]
  return done.stderr


def toy(config, **fields):
  config.update_from_flattened_dict({**TOY_FIELDS, **fields})
  return config


def check_stage2(stage1_dir, stage2_dir, refine: str):
  first, config1, _ = checkpointing.restore_checkpoint(stage1_dir)
  second, config2, step = checkpointing.restore_checkpoint(stage2_dir)
  assert config1.train.stage == 1 and config2.train.stage == 2 and step == 2
  assert config2.model.encoder == config1.model.encoder and config2.model.cell == config1.model.cell
  assert config2.model.refine == refine
  a, b = flat(first.params), flat(second.params)
  backbone = [k for k in b if not k.startswith("refine/")]
  assert backbone and all(np.array_equal(a[k], b[k]) for k in backbone)  # loaded, frozen bitwise
  refine_keys = [k for k in b if k.startswith("refine/")]
  assert refine_keys
  if any(k.startswith("refine/") for k in a):  # stage 1 had an (untrained) refinement
    assert any(not np.array_equal(a[k], b[k]) for k in refine_keys)
  # The refinement trained: a finite loss and a gradient (the refinement's alone) at its steps.
  record = json.loads((stage2_dir / "metrics.jsonl").read_text().splitlines()[-1])
  assert record["stage"] == 2 and record["step"] == 2
  assert np.isfinite(record["loss"]) and record["grad_norm"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("family", sorted(THROUGH_TRAIN_PY))
def test_two_stages_through_train_py(family, tmp_path):
  stage1, stage2, flags = THROUGH_TRAIN_PY[family]
  train_py(stage1, tmp_path / "stage1")
  err = train_py(stage2, tmp_path / "stage2", *flags,
                 f"--config.train.init_from={tmp_path / 'stage1'}")
  assert "stage 2: backbone loaded from" in err and "freshly initialised" in err
  check_stage2(tmp_path / "stage1", tmp_path / "stage2",
               "setconv" if family == "pvraft" else "graph")


@pytest.mark.slow
@pytest.mark.parametrize("family", sorted(IN_PROCESS))
def test_stage2_in_process(family, tmp_path, capsys):
  stage1, stage2 = IN_PROCESS[family]
  config1 = toy(stage1())
  model = build_model(config1.model)
  params = train_state.init_params(model, config1, jax.random.key(7))
  checkpointing.save_params(tmp_path / "stage1", params, config1)
  config = toy(stage2(), **{"train.init_from": str(tmp_path / "stage1")})
  trainer.train_and_evaluate(config, tmp_path / "stage2")
  assert "stage 2: backbone loaded from" in capsys.readouterr().err
  check_stage2(tmp_path / "stage1", tmp_path / "stage2", "graph")
