r"""The main job: the paper's recipe (configs/paper.py) made to fit a 2-core CPU: the graph-based
model with narrow encoders, stage 1 on synthetic LiDAR-like scenes, then evaluation on held-out
pairs against zero flow.

    python train.py --config configs/default.py --workdir runs/default

Measured on the 2-core CPU dev box (shared): 800 steps and the evaluation in 269 s (6 min 29 s on a
user's 2-core machine); EPE 0.236 m
against 0.944 m for zero flow on 64 held-out synthetic_lidar pairs (8 iterations; 0.355 m with 32).

`configs/default.py:smoke` shrinks everything to a run of under a minute on a CPU that still
checkpoints four times (the tests use it). `configs/default.py:eval` is the paper's evaluation
(8192 points, 32 iterations), evaluate.py's default.
"""

import ml_collections

from jaxflow.configs import paper

model_config = paper.model_config  # the paper's full model (configs/shipped.py and tests use it)


def get_config(arg: str = "") -> ml_collections.ConfigDict:
  """arg: "" the main job; "smoke" shrinks it to a CPU run of well under a minute; "eval" keeps the
  main job's model and sets the paper's evaluation (8192 points, 32 iterations: evaluate.py's
  default)."""
  if arg not in ("", "smoke", "eval"):
    raise ValueError(f"configs/default.py takes '', 'smoke' or 'eval', got {arg!r}")
  config = paper.get_config()
  # The main job trains to 2x better than zero flow in under 10 minutes on a 2-core CPU: narrow
  # encoders (SceneFlowNet.widths; the paper's are 32, 64, 128, 256; the first must be a multiple
  # of 16 and the last of 32 for GroupNorm(8)), small neighbourhoods and few candidates.
  # configs/shipped.py (the shipped checkpoint) uses this model as it is.
  config.model.widths = (16, 32, 64, 64)
  config.model.knn = 16
  config.model.truncate_k = 64
  config.model.corr_knn = 16

  # KITTI-like synthetic driving pairs: on this CPU budget the FT3D-like "synthetic_things"
  # (larger, more varied motions) stays near zero-flow accuracy.
  config.data.dataset = "synthetic_lidar"
  config.data.num_points = 384  # points sampled from each cloud.

  config.train.num_epochs = 1  # used when num_steps is 0.
  config.train.num_steps = 800
  config.train.num_iters = 4  # the paper's 8 costs 2x on the CPU.
  # A constant 1e-3 (the paper's): in the main job a decaying rate (or 2e-3) left the model near
  # zero-flow accuracy for 600+ steps; a constant 1e-3 gets past it by ~400.
  config.train.log_every = 50
  config.train.checkpoint_every = 200

  config.eval.dataset = "synthetic_lidar:64"  # held-out pairs evaluated at the end ("" skips).
  config.eval.num_points = 384
  config.eval.num_iters = 8
  config.eval.batch_size = 8

  if arg == "smoke":
    config.model.widths = (16, 16, 16, 32)
    config.model.knn = 8
    config.model.truncate_k = 16
    config.model.corr_knn = 8
    config.data.dataset = "synthetic_lidar:32"
    config.data.num_points = 64
    config.train.num_steps = 24
    config.train.log_every = 2
    config.train.checkpoint_every = 6
    config.eval.dataset = "synthetic_lidar:4"
    config.eval.num_points = 64
    config.eval.num_iters = 4
    config.eval.batch_size = 2
  elif arg == "eval":  # the paper's evaluation
    config.eval.num_points = 8192
    config.eval.num_iters = 32
    config.eval.batch_size = 1
  return config
