r"""Paper stage 1 on FlyingThings3D (HPLFlowNet format): configs/paper.py with the dataset root as
its argument (default data/FlyingThings3D_subset_processed_35m). The full model without
refinement, Adam 1e-3, batch 2, 8192 points, 8 iterations, 30 epochs of the quarter training split
(4910 pairs), sequence loss; evaluated at the end on the FT3D test set (val/, 3824 pairs) with 32
iterations.

    python train.py --config configs/ft3d_stage1.py:/data/FlyingThings3D_subset_processed_35m \
        --workdir runs/ft3d_stage1
"""

from jaxflow.configs import paper

DEFAULT_ROOT = paper.FT3D_ROOT


def get_config(arg: str = ""):
  return paper.use_root(paper.get_config(), arg or DEFAULT_ROOT)
