"""jaxflow: graph-based scene flow estimation in JAX/Flax.

The package, lowest layer first (a module imports its own package and the layers below it only;
tests/test_imports.py checks this):

    errors
    configs/      the configs: training, the paper's runs, the sweep pipeline's settings
    runtime/      config files, compilation cache, determinism, host memory, many processes
    geometry/     neighbours, rigid motions, registration, frames, visibility
    data/         datasets, point files, sampling, batching
    network/      the model, its layers, checkpoints
    lidar/        raw sweeps: ground, ego-motion, objects
    viz/          pictures and the 3D viewer
    refine/       the per-pair flow refinement engines: objectives, optimisers, rigid bodies
    methods/      the flow methods by name (network, nsfp, optimise, lidar)
    evaluation/   metrics, the evaluation loop, reports, flow files, AV2 submissions
    training/     the training loop, losses, logs, events
    cli, inference                                  flags; flow for your own clouds (the API)
    predict, evaluate, train, summary, import_pvraft; nsfp    the commands (python -m jaxflow.X)
"""

__version__ = "0.1.0"
