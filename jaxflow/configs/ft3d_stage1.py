r"""Paper stage 1 on FlyingThings3D (HPLFlowNet format): the full model without refinement, Adam 1e-3,
batch 2, 8192 points, 8 iterations, 30 epochs of the quarter training split (4910 pairs), sequence loss.

    python train.py --config configs/ft3d_stage1.py:/data/FlyingThings3D_subset_processed_35m \
        --workdir runs/ft3d_stage1

The argument is the dataset root (default data/FlyingThings3D_subset_processed_35m). At the end the
model is evaluated on the FT3D test set (val/, 3824 pairs) with 32 iterations.
"""

from jaxflow.configs import default

DEFAULT_ROOT = "data/FlyingThings3D_subset_processed_35m"


def get_config(arg: str = ""):
  root = arg or DEFAULT_ROOT
  config = default.get_config()
  config.model = default.model_config()  # the paper's widths and neighbourhoods
  config.data.dataset = f"ft3d:{root}"
  config.data.split = "train"
  config.data.num_points = 8192
  config.train.batch_size = 2
  config.train.num_steps = 0  # train for num_epochs
  config.train.num_epochs = 30
  config.train.lr = 1e-3
  config.train.schedule = "constant"  # the paper gives Adam at 1e-3 and no decay
  config.train.log_every = 100
  config.train.checkpoint_every = 1000
  config.eval.dataset = f"ft3d:{root}"
  config.eval.split = "test"
  config.eval.num_points = 8192
  config.eval.num_iters = 32
  config.eval.batch_size = 1
  return config
