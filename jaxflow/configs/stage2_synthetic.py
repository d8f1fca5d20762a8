r"""Stage 2 of the main job: the refinement of configs/default.py's model, trained on synthetic scenes
with the stage-1 network frozen, then evaluated (refined flow) on the held-out synthetic pairs.

    python train.py --config configs/default.py --workdir runs/default
    python train.py --config configs/stage2_synthetic.py --workdir runs/default_stage2 \
        --config.train.init_from=runs/default

`:smoke` gives the smoke-sized version (stage 1 from configs/default.py:smoke).
"""

from jaxflow.configs import default


def get_config(arg: str = ""):
  config = default.get_config(arg)
  config.train.stage = 2
  config.train.init_from = "runs/default"
  if arg != "smoke":
    config.train.num_steps = 300
    config.train.checkpoint_every = 100
  return config
