"""Every paper config carries the paper's numbers (section 4.1, written out here, not read from the
configs), PV-RAFT's published recipe is its own variant, and the CPU main job derives from the paper
base with its small overrides only."""

import importlib
import pathlib
import re

import numpy as np
import pytest

from jaxflow.configs import ablation, default, ft3d_stage1, ft3d_stage2, kitti_eval, paper, pvraft
from jaxflow.data.readers import ft3d_split_positions
from jaxflow.network.model import build_model
from jaxflow.summary import parameter_counts

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Paper section 4.1 (and Table 1 for the data): field -> value.
PAPER = {
  "train.lr": 1e-3,  # "The initial learning rate was set to 0.001"
  "train.schedule": "constant",  # no decay given
  "train.batch_size": 2,  # "the batch size was set to 2"
  "data.num_points": 8192,  # "we randomly sampled the input point cloud to 8192 points"
  "eval.num_points": 8192,
  # "The updating numbers of the flow iterator were set to 8 and 32 in the training and testing"
  "train.num_iters": 8,
  "eval.num_iters": 32,
  "data.split": "train",  # "one-quarter of the training set (4910 samples)"
  "eval.split": "test",  # "total samples in the test set (3824 samples)"
  "train.num_steps": 0,  # epochs, not steps
  "train.gamma": 0.8,  # eq. 7
  "model.knn": 32,  # PV-RAFT's sizes, which the paper follows
  "model.truncate_k": 512,
  "model.corr_knn": 32,
  "model.corr_levels": 3,
  "model.base_scale": 0.25,
  "model.widths": (),  # each encoder's own widths (graph: 32, 64, 128, 256)
  "model.precision": "highest",  # float32 as PyTorch computes it
}
STAGE = {1: {"train.stage": 1, "train.num_epochs": 30},  # "trained the network ... with 30 epochs"
         2: {"train.stage": 2, "train.num_epochs": 20}}  # "trained the ... refinement ... 20 epochs"

PAPER_CONFIGS = {
  "paper.py": (paper.get_config, 1),
  "paper.py:stage2": (lambda: paper.get_config("stage2"), 2),
  "ft3d_stage1.py": (ft3d_stage1.get_config, 1),
  "ft3d_stage2.py": (ft3d_stage2.get_config, 2),
  "pvraft.py": (pvraft.get_config, 1),
  "pvraft.py:refine": (lambda: pvraft.get_config("refine"), 1),
  "pvraft.py:stage2": (lambda: pvraft.get_config("stage2"), 2),
  **{f"ablation.py:{row}": (lambda row=row: ablation.get_config(row), 1) for row in ablation.ROWS},
  **{f"ablation.py:{row},stage2": (lambda row=row: ablation.get_config(f"{row},stage2"), 2)
     for row in ablation.ROWS},
}
# Tables 5-6: GCL, residual connection, single-gate iterator per row.
ROWS = {"pvraft.py": ("setconv", False, "gru", "none"),
        "ablation.py:gcl": ("graph", False, "gru", "graph"),
        "ablation.py:gcl_rc": ("graph", True, "gru", "graph"),
        "ablation.py:gcl_rc_sgfi": ("graph", True, "single_gate", "graph"),
        "paper.py": ("graph", True, "single_gate", "graph")}


def field(config, dotted):
  for part in dotted.split("."):
    config = config[part]
  return tuple(config) if isinstance(config, (list, tuple)) else config


@pytest.mark.parametrize("name", sorted(PAPER_CONFIGS))
def test_paper_configs_carry_the_papers_numbers(name):
  get, stage = PAPER_CONFIGS[name]
  config = get()
  want = {**PAPER, **STAGE[stage]}
  got = {k: field(config, k) for k in want}
  assert got == want, {k: (got[k], want[k]) for k in want if got[k] != want[k]}
  assert config.data.dataset.startswith("ft3d:") and config.eval.dataset.startswith("ft3d:")
  assert config.train.init_from == ("runs/ft3d_stage1" if name == "ft3d_stage2.py" else "")
  assert config.model.refine != "none" or stage == 1


def test_the_quarter_split_has_the_papers_4910_pairs():
  assert len(ft3d_split_positions("train")) == 4910
  assert len(ft3d_split_positions("train_all")) == 17640  # PV-RAFT's: 19640 less 2000 val


@pytest.mark.parametrize("name", sorted(ROWS))
def test_ablation_rows_are_the_tables_rows(name):
  encoder, residual, cell, refine = ROWS[name]
  m = PAPER_CONFIGS[name][0]().model
  assert (m.encoder, m.residual, m.cell, m.refine) == (encoder, residual, cell, refine)


def test_pvraft_official_is_pvrafts_published_recipe():
  """PV-RAFT's run.sh / tools/engine*.py: stage 1 20 epochs with 8 iterations, stage 2 10 epochs
  with 32, both on the 17640-pair split, Adam 1e-3, batch 2, 8192 points, 32 test iterations."""
  want = {1: {"train.num_epochs": 20, "train.num_iters": 8},
          2: {"train.num_epochs": 10, "train.num_iters": 32}}
  for arg, stage in (("official", 1), ("official,stage2", 2)):
    config = pvraft.get_config(arg)
    for k, v in {**want[stage], "train.stage": stage, "data.split": "train_all", "train.lr": 1e-3,
                 "train.batch_size": 2, "data.num_points": 8192, "eval.num_iters": 32}.items():
      assert field(config, k) == v, (arg, k)
    assert config.model.refine == ("setconv" if stage == 2 else "none")
  with pytest.raises(ValueError, match="configs/pvraft.py takes a comma list"):
    pvraft.get_config("offical")


def test_main_job_is_the_paper_base_with_cpu_overrides():
  """default.py's fields are paper.py's but for the ones it lists; every field it has, the base has
  (one base, small overrides), and :smoke / :eval change only their own fields."""
  base, main = flat(paper.get_config()), flat(default.get_config())
  assert set(base) == set(main)
  changed = {k for k in base if base[k] != main[k]}
  assert changed == {"model.widths", "model.knn", "model.truncate_k", "model.corr_knn",
                     "data.dataset", "data.num_points", "train.num_epochs", "train.num_steps",
                     "train.num_iters", "train.log_every", "train.checkpoint_every",
                     "eval.dataset", "eval.num_points", "eval.num_iters", "eval.batch_size"}
  evaluation = flat(default.get_config("eval"))
  assert {k for k in main if main[k] != evaluation[k]} == {
    "eval.num_points", "eval.num_iters", "eval.batch_size"}
  assert all(evaluation[k] == base[k] for k in ("eval.num_points", "eval.num_iters"))
  assert flat(kitti_eval.get_config())["eval.num_iters"] == 32


def test_every_paper_config_builds_its_model():
  models = {}  # the distinct models of the paper configs (stage 2 shares stage 1's)
  for name, (get, _) in PAPER_CONFIGS.items():
    models.setdefault(str(dict(get().model)), (name, get().model))
  assert len(models) == 5  # full, gcl, gcl_rc, PV-RAFT with and without its refinement
  for _, model in models.values():
    build_model(model, inference=True)


def documented_parameter_counts() -> dict:
  """docs/network.md's table: {"configs/X.py[:arg]": (total, stage 1 or None)}."""
  text = (ROOT / "docs" / "network.md").read_text()
  row = r"^\| `(configs/\w+\.py(?::\w+)?)` \|[^|]*\| ([\d,]+)(?: \(([\d,]+) stage 1\))? \|$"
  rows = re.findall(row, text, re.M)
  number = lambda s: int(s.replace(",", "")) if s else None
  return {name: (number(total), number(stage1)) for name, total, stage1 in rows}


def test_parameter_counts_are_the_documented_ones():
  documented = documented_parameter_counts()
  assert set(documented) == {"configs/pvraft.py", "configs/pvraft.py:refine",
                             "configs/ablation.py:gcl", "configs/ablation.py:gcl_rc",
                             "configs/ablation.py:gcl_rc_sgfi", "configs/default.py"}, documented
  # PV-RAFT's stage-1 network has 192,034 parameters: the official PyTorch model's state_dict
  # (tests/data/pvraft_seed5_n2048_it12.npz) sums to that too (the test below).
  assert documented["configs/pvraft.py"] == (192_034, None)
  for name, (total, stage1) in documented.items():
    path, _, argument = name.partition(":")
    module = importlib.import_module(f"jaxflow.configs.{path[len('configs/'):-len('.py')]}")
    config = module.get_config(argument) if argument else module.get_config()
    counts = parameter_counts(config.model)
    assert sum(counts.values()) == total, (name, sum(counts.values()), total)
    if stage1 is not None:
      assert sum(v for k, v in counts.items() if k != "refine") == stage1, (name, counts)


def test_pvraft_counts_are_the_official_ones():
  """The official network's own tensors (tests/data, PyTorch's state_dicts) count 192,034 for the
  stage-1 network and 47,187 for its refinement: PV-RAFT's counts, independent of jaxflow's."""
  with np.load(ROOT / "tests" / "data" / "pvraft_seed5_n2048_it12.npz") as data:
    stage1, refine = (sum(data[k].size for k in data.files if k.startswith(p))
                      for p in ("rsf/", "refine/"))
  assert stage1 == 192_034 == sum(parameter_counts(pvraft.get_config().model).values())
  assert stage1 + refine == sum(parameter_counts(pvraft.get_config("refine").model).values())


def test_config_arguments_are_checked():
  for bad in (lambda: paper.get_config("stage3"), lambda: ablation.get_config("gcl,stage3"),
              lambda: ablation.get_config("gcn")):
    with pytest.raises(ValueError, match="configs/"):
      bad()


def flat(config) -> dict:
  out = {}
  for k, v in config.items():
    if hasattr(v, "items"):
      out.update({f"{k}.{kk}": vv for kk, vv in flat(v).items()})
    else:
      out[k] = tuple(v) if isinstance(v, (list, tuple)) else v
  return out
