r"""Paper stage 2 on FlyingThings3D: load stage 1, freeze it, train the graph refinement with the
refinement loss for 20 epochs (Adam 1e-3, batch 2, 8192 points, 8 iterations):
configs/paper.py:stage2 with the dataset root as its argument.

    python train.py --config configs/ft3d_stage2.py:/data/FlyingThings3D_subset_processed_35m \
        --workdir runs/ft3d_stage2 --config.train.init_from=runs/ft3d_stage1
"""

from jaxflow.configs import ft3d_stage1, paper


def get_config(arg: str = ""):
  config = paper.to_stage2(ft3d_stage1.get_config(arg))
  config.train.init_from = "runs/ft3d_stage1"  # the stage-1 workdir (or one of its step folders)
  return config
