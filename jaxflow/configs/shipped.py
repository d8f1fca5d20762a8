r"""The config of the shipped checkpoint `jaxflow/checkpoints/jaxflow_synthetic/` (its round 9).

    python train.py --config configs/shipped.py --workdir runs/shipped_r9   # from runs/shipped_r8

configs/default.py's small CPU model, stage 1 on synthetic_mix (FlyingThings-like and LiDAR-like
pairs alternating) on 2048-point windows of clouds sampled to 8192 points, continued from the
previous round's parameters. The checkpoint stores this config itself (config.json and its step
folder; tests/test_shipped.py checks they agree). Rounds 1-8, which led to it, are one table in
docs/history.md; their configs are in the git history (`:roundN` of
`git show f4f8b8e:jaxflow/configs/shipped.py`). scripts/train_shipped.sh runs this and copies the result into the package.
"""

from jaxflow.configs import default


def small_model_config():
  """The small CPU model on synthetic_mix, pinned here so that changes to the main job leave it."""
  config = default.get_config()
  config.model = default.model_config()
  config.model.widths = (16, 32, 64, 64)
  config.model.knn = 16
  config.model.truncate_k = 64
  config.model.corr_knn = 16
  config.data.dataset = "synthetic_mix"  # 4910 training pairs, things / lidar alternating
  config.eval.dataset = "synthetic_mix:16"  # end-of-run check; the card uses evaluate.py
  config.eval.batch_size = 2
  return config


def get_config():
  config = small_model_config()
  config.seed = 9  # this round's data order (each round had its own)
  config.model.truncate_k = 128  # 1/16 of the 2048-point window
  config.model.infer_truncate_k = 512  # 1/16 of the test's 8192 points (chosen on val pairs)
  config.data.num_points = 2048  # windows of clouds sampled to crop_from points: the test density
  config.data.crop_from = 8192
  config.data.crop_mask_outside = True  # the one change from round 8 (docs/history.md)
  config.train.init_from = "runs/shipped_r8"  # round 8's stage 1
  config.train.num_steps = 1400
  config.train.num_iters = 16
  config.train.lr = 3e-4
  config.train.schedule = "cosine"
  config.train.checkpoint_every = 100
  config.eval.split = "val"  # the pairs that decide whether a round is shipped
  config.eval.num_points = 8192
  config.eval.num_iters = 32
  return config
