r"""PV-RAFT exactly (paper Tables 5-6, row 1) at the paper's sizes: SetConv encoder 32-64-128,
GRU, hidden 64, k = 32 graphs, 512 correlation candidates.

The plain config is PV-RAFT's stage-1 network (the official RSF, 192,034 parameters);
`:refine` adds PV-RAFT's SetConv refinement for stage 2 (the official RSF_refine).

    python -m jaxflow.summary --config configs/pvraft.py
    python train.py --config configs/pvraft.py --workdir runs/pvraft
    python train.py --config configs/pvraft.py:refine --workdir runs/pvraft_stage2 \
        --config.train.stage=2 --config.train.init_from=runs/pvraft
"""

from jaxflow.configs import default


def get_config(arg: str = ""):
  if arg not in ("", "refine"):
    raise ValueError(f"configs/pvraft.py takes '' or 'refine', got {arg!r}")
  config = default.get_config()
  config.model = default.model_config()  # the paper's sizes, not the main job's small CPU model
  config.model.encoder = "setconv"
  config.model.residual = False
  config.model.cell = "gru"
  config.model.refine = "setconv" if arg == "refine" else "none"
  return config
