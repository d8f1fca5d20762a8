r"""The ablation rows of the paper's Tables 5-6, one config argument per row.

    python train.py --config configs/ablation.py:gcl --workdir runs/ablation_gcl
    python train.py --config configs/ablation.py:gcl_rc --workdir runs/ablation_gcl_rc
    python train.py --config configs/ablation.py:gcl_rc_sgfi --workdir runs/full

row        GCL  RC  SGFI   = PV-RAFT plus
pvraft     -    -   -      (configs/pvraft.py)
gcl        x    -   -      graph encoder, no residual connections, GRU iterator
gcl_rc     x    x   -      graph encoder with residual connections, GRU iterator
gcl_rc_sgfi x   x   x      the full model (configs/default.py)
Rows with GCL use the graph-based refinement in stage 2; append `,product` (e.g.
`gcl_rc_sgfi,product`) for 3D-GCN's product similarity instead of the paper's sum.
The training/data settings are those of configs/default.py; add the FT3D settings with
`--config.data...` overrides or start from configs/ft3d_stage1.py.
"""

from jaxflow.configs import default

ROWS = {
  "gcl": dict(residual=False, cell="gru"),
  "gcl_rc": dict(residual=True, cell="gru"),
  "gcl_rc_sgfi": dict(residual=True, cell="single_gate"),
}


def get_config(arg: str = "gcl_rc_sgfi"):
  row, *options = (arg or "gcl_rc_sgfi").split(",")
  if row not in ROWS:
    raise ValueError(f"configs/ablation.py: unknown row {row!r}; choose one of {', '.join(ROWS)}")
  config = default.get_config()
  config.model = default.model_config()  # the paper's sizes, not the main job's small CPU model
  config.model.encoder = "graph"
  config.model.refine = "graph"
  for field, value in ROWS[row].items():
    config.model[field] = value
  if "product" in options:
    config.model.gcl_similarity = "product"
  return config
