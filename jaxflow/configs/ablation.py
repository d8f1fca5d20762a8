r"""The ablation rows of the paper's Tables 5-6, one config argument per row, each trained with the
paper's recipe (configs/paper.py: FT3D, 8192 points, 8 / 32 iterations, 30 + 20 epochs).

    python train.py --config configs/ablation.py:gcl --workdir runs/ablation_gcl
    python train.py --config configs/ablation.py:gcl,stage2 --workdir runs/ablation_gcl_stage2 \
        --config.train.init_from=runs/ablation_gcl
    python train.py --config configs/ablation.py:gcl_rc --workdir runs/ablation_gcl_rc
    python train.py --config configs/ablation.py:gcl_rc_sgfi --workdir runs/full

row        GCL  RC  SGFI   = PV-RAFT plus
pvraft     -    -   -      (configs/pvraft.py)
gcl        x    -   -      graph encoder, no residual connections, GRU iterator
gcl_rc     x    x   -      graph encoder with residual connections, GRU iterator
gcl_rc_sgfi x   x   x      the full model (configs/paper.py)
Rows with GCL use the graph-based refinement in stage 2 (`,stage2`); append `,product` (e.g.
`gcl_rc_sgfi,product`) for 3D-GCN's product similarity instead of the paper's sum. The dataset
root is configs/paper.py's; another with `--config.data.dataset=ft3d:ROOT
--config.eval.dataset=ft3d:ROOT`.
"""

from jaxflow.configs import paper

ROWS = {
  "gcl": dict(residual=False, cell="gru"),
  "gcl_rc": dict(residual=True, cell="gru"),
  "gcl_rc_sgfi": dict(residual=True, cell="single_gate"),
}
OPTIONS = ("product", "stage2")


def get_config(arg: str = "gcl_rc_sgfi"):
  row, *options = (arg or "gcl_rc_sgfi").split(",")
  if row not in ROWS:
    raise ValueError(f"configs/ablation.py: unknown row {row!r}; choose one of {', '.join(ROWS)}")
  unknown = [o for o in options if o not in OPTIONS]
  if unknown:
    raise ValueError(f"configs/ablation.py: unknown option {unknown[0]!r}; options: "
                     f"{', '.join(OPTIONS)}")
  config = paper.get_config("stage2" if "stage2" in options else "")
  config.model.encoder = "graph"
  config.model.refine = "graph"
  for field, value in ROWS[row].items():
    config.model[field] = value
  if "product" in options:
    config.model.gcl_similarity = "product"
  return config
