r"""Paper stage 2 on FlyingThings3D: load stage 1, freeze it, train the graph refinement with the
refinement loss for 20 epochs (Adam 1e-3, batch 2, 8192 points, 8 iterations).

    python train.py --config configs/ft3d_stage2.py:/data/FlyingThings3D_subset_processed_35m \
        --workdir runs/ft3d_stage2 --config.train.init_from=runs/ft3d_stage1
"""

from jaxflow.configs import ft3d_stage1


def get_config(arg: str = ""):
  config = ft3d_stage1.get_config(arg)
  config.train.stage = 2
  config.train.init_from = "runs/ft3d_stage1"  # the stage-1 workdir (or one of its step folders)
  config.train.num_epochs = 20
  return config
