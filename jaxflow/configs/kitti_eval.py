r"""Evaluation on KITTI Scene Flow 2015 (HPLFlowNet format, the 142 benchmark frames) as in the
paper's Table 2: 8192 points per cloud, 32 iterations, one pair at a time (configs/paper.py's
evaluation).

    python evaluate.py --config configs/kitti_eval.py --checkpoint runs/ft3d_stage2 \
        --dataset kitti:data/KITTI_processed_occ_final

The model comes from the checkpoint; this config's model is the paper's, so a checkpoint of another
model is refused: evaluate those with --config.eval.FIELD=... overrides instead of this file.
"""

from jaxflow.configs import paper


def get_config(arg: str = ""):
  config = paper.get_config()
  config.eval.dataset = f"kitti:{arg or 'data/KITTI_processed_occ_final'}"
  config.eval.split = "test"
  return config
