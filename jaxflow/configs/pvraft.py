r"""PV-RAFT exactly (paper Tables 5-6, row 1) at the paper's sizes: SetConv encoder 32-64-128,
GRU, hidden 64, k = 32 graphs, 512 correlation candidates, trained with the paper's recipe
(configs/paper.py).

The plain config is PV-RAFT's stage-1 network (the official RSF, 192,034 parameters); `:refine`
adds PV-RAFT's SetConv refinement (the official RSF_refine); `:stage2` is `:refine` in stage 2
(20 epochs, the backbone of --config.train.init_from frozen; a stage-1 run without refinement is
what it starts from).

    python -m jaxflow.summary --config configs/pvraft.py
    python train.py --config configs/pvraft.py --workdir runs/pvraft
    python train.py --config configs/pvraft.py:stage2 --workdir runs/pvraft_stage2 \
        --config.train.init_from=runs/pvraft

`official` (`:official`, `:official,stage2`) is PV-RAFT's own published recipe (its run.sh and
tools/engine*.py) where it differs from the paper's: stage 1 for 20 epochs on all 17,640 training
pairs (FT3D's train/ less the 2,000 validation pairs: split "train_all"), stage 2 for 10 epochs
with 32 iterations in training too. Both train Adam 1e-3 (PV-RAFT's cosine schedule, stepped per
epoch over num_epochs x 17,640 steps, moves it by less than 1e-8 relative), batch 2, 8192 points,
32 test iterations.
"""

from jaxflow.configs import paper

OPTIONS = ("refine", "stage2", "official")
OFFICIAL = {1: dict(num_epochs=20, num_iters=8), 2: dict(num_epochs=10, num_iters=32)}


def get_config(arg: str = ""):
  options = [o for o in arg.split(",") if o]
  unknown = [o for o in options if o not in OPTIONS]
  if unknown:
    raise ValueError(f"configs/pvraft.py takes a comma list of {', '.join(OPTIONS)} (or ''), "
                     f"got {arg!r}")
  stage2 = "stage2" in options
  config = paper.get_config("stage2" if stage2 else "")
  config.model.encoder = "setconv"
  config.model.residual = False
  config.model.cell = "gru"
  config.model.refine = "setconv" if stage2 or "refine" in options else "none"
  if "official" in options:
    config.data.split = "train_all"
    for field, value in OFFICIAL[config.train.stage].items():
      config.train[field] = value
  return config
