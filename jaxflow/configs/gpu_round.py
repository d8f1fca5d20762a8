r"""The next round of the shipped checkpoint, for a lent GPU: the shipped network's stage 1
continued on whole clouds at the test's density and candidates (8192 points, 512 candidates), which
the 2-core CPU rounds could not afford (configs/shipped.py trains on 2048-point windows with 128).

    bash scripts/gpu_round.sh train 8     # on the GPU: resumes, trains 8 minutes, packs into $OUT

Cut by time, not by steps (a device call lasts 10 minutes at most), hence the constant rate and the
large num_steps. Not run on a GPU yet.
"""

from jaxflow.configs import shipped


def get_config():
  config = shipped.small_model_config()
  config.seed = 100  # data order of its own (the CPU rounds used seeds 0-6)
  config.train.init_from = "jaxflow/checkpoints/jaxflow_synthetic"  # whatever round is shipped
  config.data.num_points = 8192
  config.data.crop_from = 0
  config.model.truncate_k = 512  # 1/16 of the cloud, as in every CPU round and the paper
  config.train.num_iters = 16
  config.train.lr = 3e-4
  config.train.schedule = "constant"
  config.train.num_steps = 100_000  # never reached: scripts/gpu_round.sh stops it by time
  config.train.log_every = 25
  config.train.checkpoint_every = 250
  config.train.max_to_keep = 1  # one step folder to pack and bring back
  config.eval.dataset = ""  # scripts/gpu_round.sh eval decides on synthetic_mix:100 val
  return config
