r"""Evaluation on Argoverse scene flow: every point of pc1 that has flow (no sampling: num_points 0),
32 iterations, one pair at a time. Two datasets:

    # NSFP's preprocessing of Argoverse 1 (212 test pairs)
    python evaluate.py --config configs/argoverse_eval.py --checkpoint runs/ft3d_stage2 \
        --dataset argoverse:data/argoverse
    # Argoverse 2 in OpenSceneFlow's h5 layout, on the challenge's points (opensf region=challenge,
    # val split), with the official numbers and, with --submission, the challenge's files
    python evaluate.py --config configs/argoverse_eval.py:opensf:/data/av2/sensor \
        --checkpoint runs/X --submission /tmp/av2_val

Whole clouds have a different size in every pair: each size is compiled once (compilation is not
timed). model.corr_chunk builds the correlation in row blocks so memory grows with N, not N x M; it
changes no parameter, so it is taken from this config rather than from the checkpoint.
"""

from jaxflow.configs import paper


def get_config(arg: str = ""):
  config = paper.get_config()
  config.model.corr_chunk = 2048
  if arg.startswith("opensf:"):  # Argoverse 2: the challenge's points unless a region is given
    config.eval.dataset = arg if "region=" in arg else f"{arg},region=challenge"
    config.eval.split = "val"
  else:
    config.eval.dataset = f"argoverse:{arg or 'data/argoverse'}"
    config.eval.split = "test"
  config.eval.num_points = 0  # 0: whole clouds
  return config
