r"""Evaluation on Argoverse scene flow (NSFP's preprocessing, 212 test pairs): every point of pc1
that has flow (no sampling: num_points 0), 32 iterations, one pair at a time.

    python evaluate.py --config configs/argoverse_eval.py --checkpoint runs/ft3d_stage2 \
        --dataset argoverse:data/argoverse

Whole clouds have a different size in every pair: each size is compiled once (compilation is not
timed). model.corr_chunk builds the correlation in row blocks so memory grows with N, not N x M; it
changes no parameter, so it is taken from this config rather than from the checkpoint.
"""

from jaxflow.configs import paper


def get_config(arg: str = ""):
  config = paper.get_config()
  config.model.corr_chunk = 2048
  config.eval.dataset = f"argoverse:{arg or 'data/argoverse'}"
  config.eval.split = "test"
  config.eval.num_points = 0  # 0: whole clouds
  return config
