r"""The paper's recipe (section 4.1), the one base every config derives from: the full model (GCL +
residual connections + single-gate iterator) on FlyingThings3D, Adam 1e-3, batch 2, 8192 points,
8 iterations in training and 32 at test time. Stage 1 trains the network without the refinement
for 30 epochs of the quarter training split (4910 pairs); stage 2 loads it, freezes it and trains
the refinement for 20 epochs.

    python train.py --config configs/paper.py --workdir runs/paper
    python train.py --config configs/paper.py:stage2 --workdir runs/paper_stage2 \
        --config.train.init_from=runs/paper

The ablation rows (configs/ablation.py), PV-RAFT (configs/pvraft.py), the FT3D configs and the CPU
main job (configs/default.py) are this config with a few fields overridden. Where the paper is
silent the value is PV-RAFT's (its network and training code), and the comment says so.
"""

import ml_collections

FT3D_ROOT = "data/FlyingThings3D_subset_processed_35m"  # HPLFlowNet's preprocessing
STAGE2_EPOCHS = 20  # paper 4.1: the refinement is trained for 20 epochs


def model_config() -> ml_collections.ConfigDict:
  """The paper's full model (GCL + residual connections + single-gate iterator)."""
  m = ml_collections.ConfigDict()
  m.encoder = "graph"  # "graph": SetConv 32, 64 then GCL 128, 256; "setconv": PV-RAFT 32, 64, 128.
  # Encoder widths; () = the encoder's own (graph: 32, 64, 128, 256; setconv: 32, 64, 128).
  m.widths = ()
  m.residual = True  # residual connections around the GCLs of the graph encoder (paper's RC).
  m.gcl_supports = 3  # L, the number of kernel supports of each GCL.
  m.gcl_similarity = "sum"  # "sum": paper eq. 5; "product": 3D-GCN's ReLU(cos) * <f_j, w(e_l)>.
  m.knn = 32  # neighbours of each point in its own cloud, itself included (PV-RAFT's k).
  m.cell = "single_gate"  # "single_gate" (paper's SGFI, eq. 6) or "gru" (PV-RAFT).
  m.truncate_k = 512  # correlation candidates kept per pc1 point (PV-RAFT's).
  # > 0: the candidates kept when the model evaluates or predicts (not in training); no parameter
  # depends on it. A network trained on windows of the test density meets many more distractors in
  # a whole cloud, and needs more candidates there (configs/shipped.py). 0: truncate_k.
  m.infer_truncate_k = 0
  m.corr_knn = 32  # point branch: candidates nearest to the current estimate (PV-RAFT's).
  m.corr_levels = 3  # voxel branch: levels with cell size base_scale * 2**level (PV-RAFT's).
  m.base_scale = 0.25  # metres (PV-RAFT's).
  m.refine = "graph"  # "graph" (paper 3.1.5), "setconv" (PV-RAFT's) or "none".
  m.refine_widths = ()  # graph refinement GCL widths; () = the paper's 256, 128, 64.
  # The kNN graphs and the top-k correlation are built this many rows at a time (memory ~ N); 0:
  # rows chosen from the clouds' sizes and the device's memory (whole below 64 MiB a matrix).
  m.corr_chunk = 0
  # True: the gradient recomputes each iteration instead of storing its activations. Same values;
  # a PV-RAFT training step on an H200 (B=2, 8192 points) 15.4 -> 5.3 GB of temporaries in the
  # same time, 98 vs 100 ms (benchmarks/NETWORK_GPU.md); on the CPU 3.3 -> 1.4 GiB. Not the
  # default: two CPU processes training together abort with it (gloo: a collective's size
  # mismatch; tests/test_distributed.py).
  m.remat_iterations = False
  # Every matmul of the network and its kNN: "highest" (exact float32 on every backend, what the
  # official PyTorch code computes and the CPU tests check), "high" (TF32 on Ampere/Hopper GPUs),
  # "default" (the backend's fastest: TF32 on A100/H100, bfloat16 on TPUs). Below "highest" the
  # kNN graphs and the top-k candidates change (docs/training.md, "Precision").
  m.precision = "highest"
  # The voxel branch's form: "auto" (by the device it is compiled for: a scatter on the CPU, a
  # comparison with every cell elsewhere), "scatter" or "compare". Same values either way.
  m.voxel_cells = "auto"
  # How the kNN graphs and the top-k candidates are selected: "auto" (by the device it is compiled
  # for: blocks of a few hundred entries on a GPU or TPU, lax.top_k on the CPU), "blockwise" or
  # "sort" (lax.top_k: a full sort of each row on a GPU). The same neighbours in the same order.
  m.selection = "auto"
  return m


def get_config(arg: str = "") -> ml_collections.ConfigDict:
  """arg: "" stage 1, "stage2" stage 2 (the refinement, backbone frozen)."""
  if arg not in ("", "stage2"):
    raise ValueError(f"configs/paper.py takes '' or 'stage2', got {arg!r}")
  config = ml_collections.ConfigDict()
  config.seed = 0  # parameter init and the training data order.
  config.model = model_config()

  config.data = ml_collections.ConfigDict()
  config.data.dataset = f"ft3d:{FT3D_ROOT}"  # FORMAT[:ARG] (jaxflow.data.open_dataset).
  config.data.split = "train"  # FT3D "train": the paper's quarter, 4910 pairs (data/readers.py).
  config.data.num_points = 8192  # points sampled from each cloud (paper 4.1, after PV-RAFT).
  # > 0: sample each cloud to crop_from points (the density to learn) and train on a window of
  # num_points of them around a random point (data.sampling.crop_pair); 0: sample num_points.
  config.data.crop_from = 0
  # With crop_from: mask out of the loss the window's points whose flow leaves pc2's window (their
  # match is not in the network's view). False keeps rounds 2-8 of configs/shipped.py as they ran.
  config.data.crop_mask_outside = False
  config.data.augment = ml_collections.ConfigDict()  # training augmentation; identity = off.
  config.data.augment.rotation_deg = 0.0  # uniform rotation about the vertical axis, +- degrees.
  config.data.augment.scale = (1.0, 1.0)  # uniform scale range (low, high).
  config.data.augment.jitter = 0.0  # Gaussian per-point noise, metres.
  config.data.skip_broken = False  # True: report unreadable pairs and train on; False: stop.
  config.data.prefetch = 2  # batches prepared ahead by the loader.

  config.train = ml_collections.ConfigDict()
  config.train.stage = 1  # 1: network without refinement, sequence loss; 2: refinement only.
  # A workdir or step folder: stage 2 takes its backbone (required); stage 1 warm-starts from all
  # its parameters (a new round with another recipe), "" = from scratch.
  config.train.init_from = ""
  config.train.batch_size = 2  # pairs per step, split over all devices (paper 4.1).
  config.train.num_epochs = 30  # stage 1 (paper 4.1); used when num_steps is 0.
  config.train.num_steps = 0  # > 0: train this many steps (instead of num_epochs).
  config.train.num_iters = 8  # flow iterations Z in training (paper 4.1).
  config.train.gamma = 0.8  # sequence-loss weight decay over iterations (paper eq. 7).
  config.train.lr = 1e-3  # Adam (paper 4.1).
  # "constant" or "cosine" (decay to 0 at the last step). The paper gives Adam at 1e-3 and no
  # decay; PV-RAFT's cosine is stepped per epoch over 20 x 17640 "epochs", i.e. constant too.
  config.train.schedule = "constant"
  config.train.log_every = 100  # steps between metric fetches (and metrics.jsonl lines).
  config.train.checkpoint_every = 1000  # steps between checkpoints (and one at the end).
  config.train.max_to_keep = 3  # checkpoints kept.
  # True: resume a workdir whose checkpoints were trained with another data/train recipe, and record
  # the change in the stored config (`recipe_changes`); False refuses (docs/training.md, Resuming).
  config.train.resume_with_new_recipe = False

  config.eval = ml_collections.ConfigDict()
  config.eval.dataset = f"ft3d:{FT3D_ROOT}"  # held-out pairs evaluated at the end ("" skips).
  config.eval.split = "test"  # FT3D "test": the 3824 pairs of val/ (paper Table 1).
  config.eval.num_points = 8192  # 0: whole clouds (batch_size 1).
  config.eval.num_iters = 32  # flow iterations at test time (paper 4.1).
  config.eval.batch_size = 1
  config.eval.seed = 0  # point sampling of the evaluation pairs.
  # > 0: evaluate on these pairs every this many steps during training too (held-out EPE as it
  # trains: WORKDIR/eval_metrics.jsonl and the learning curve); 0: only at the end.
  config.eval.every = 0
  if arg == "stage2":
    to_stage2(config)
  return config


def to_stage2(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
  """Stage 2 of `config` (in place): the refinement trained with the refinement loss (paper eq. 8)
  on the frozen stage-1 network given by --config.train.init_from, for 20 epochs."""
  config.train.stage = 2
  config.train.num_epochs = STAGE2_EPOCHS
  return config


def use_root(config: ml_collections.ConfigDict, root: str) -> ml_collections.ConfigDict:
  """`config` training and evaluating on the FT3D copy at `root` (in place)."""
  config.data.dataset = f"ft3d:{root}"
  config.eval.dataset = f"ft3d:{root}"
  return config
