"""The scene-flow network (the paper's GCL feature generator, PV-RAFT's point-voxel correlation,
the single-gate iterator, the graph refinement): `layers` (their edge reductions: `edges`),
`encoder`, `correlation`, `update`, `refine`, `model` (build_model), the config fields of a model
(`model_fields`), its training state and orbax checkpoints (`train_state`, `checkpointing`). It
imports jaxflow.geometry and jaxflow.errors only; jaxflow.data stays out of it (a model takes
arrays).
"""
