r"""The shipped checkpoint `checkpoints/jaxflow_synthetic/`: configs/default.py's small CPU model
trained on synthetic_mix (FlyingThings-like and LiDAR-like pairs alternating), stage 1 then stage 2.

    python train.py --config configs/shipped.py --workdir runs/shipped
    python train.py --config configs/shipped.py:stage2 --workdir runs/shipped_stage2 \
        --config.train.init_from=runs/shipped

scripts/train_shipped.sh holds the exact rounds (and the copy into checkpoints/); see the model card
checkpoints/jaxflow_synthetic/MODEL_CARD.md for what they gave.
"""

from configs import default


def get_config(arg: str = ""):
  """arg "" is stage 1; "stage2" trains the graph refinement on the frozen stage-1 network."""
  if arg not in ("", "stage2"):
    raise ValueError(f"configs/shipped.py takes '' or 'stage2', got {arg!r}")
  # The small CPU model, pinned here so that later changes to the main job do not change this recipe.
  config = default.get_config()
  config.model = default.model_config()
  config.model.widths = (16, 32, 64, 64)
  config.model.knn = 16
  config.model.truncate_k = 64
  config.model.corr_knn = 16
  config.train.lr = 1e-3
  config.train.schedule = "cosine"  # decays to 0 over each run
  config.train.num_iters = 8
  config.data.dataset = "synthetic_mix"  # 4910 training pairs, things / lidar alternating
  config.data.num_points = 1024  # ~2 s a step of 2 pairs on the shared 2-core CPU
  config.data.augment.rotation_deg = 5.0  # small yaw: real scenes are not all axis-aligned
  config.data.augment.scale = (0.95, 1.05)
  config.train.num_steps = 600  # a later round can raise it (--config.train.num_steps) and resume
  config.train.log_every = 25
  config.train.checkpoint_every = 100
  config.train.max_to_keep = 2
  config.eval.dataset = "synthetic_mix:16"  # end-of-run check; the card uses evaluate.py
  config.eval.num_points = 1024
  config.eval.num_iters = 32  # the stage-1 round's end-of-run check
  config.eval.batch_size = 2
  if arg == "stage2":
    config.train.stage = 2
    config.train.init_from = "runs/shipped"
    config.train.num_steps = 150
    config.train.num_iters = 4  # as the shipped stage-2 round ran (the coarse flow it refines)
    config.eval.num_iters = 8
    config.train.checkpoint_every = 50
  return config
