"""What each `config.model` field is: the one table training, evaluation and checkpoints read.

Kinds:
- "architecture": defines the network and what its parameters mean (shapes, neighbourhoods,
  scales). A warm start, a stage 2 and an evaluation take it from the checkpoint and refuse a
  config that contradicts it.
- "parameter_free": no parameter depends on it but it is part of the trained recipe (candidates
  per point): a warm start may change it (and says so); evaluation keeps the checkpoint's.
- "runtime": changes neither the parameters nor what was trained: memory, speed, arithmetic.
  Evaluation and predict take it from the user's config when given, resume ignores it.

`added` is the value a field had in checkpoints written before it existed (their stored config
lacks it); None for fields every checkpoint has.
"""

import dataclasses
from typing import Any


@dataclasses.dataclass(frozen=True)
class Field:
  kind: str  # "architecture" | "parameter_free" | "runtime"
  added: Any = None  # the value of a checkpoint that predates the field; None: always stored


MODEL_FIELDS = {
  "encoder": Field("architecture"),
  "widths": Field("architecture"),
  "residual": Field("architecture"),
  "gcl_supports": Field("architecture"),
  "gcl_similarity": Field("architecture"),
  "knn": Field("architecture"),
  "cell": Field("architecture"),
  "corr_levels": Field("architecture"),
  "base_scale": Field("architecture"),
  "refine": Field("architecture"),
  "refine_widths": Field("architecture"),
  "truncate_k": Field("parameter_free"),
  "corr_knn": Field("parameter_free"),
  "corr_chunk": Field("runtime"),
  "infer_truncate_k": Field("runtime", added=0),
  "remat_iterations": Field("runtime", added=False),
  "precision": Field("runtime", added="highest"),
  "voxel_cells": Field("runtime", added="auto"),
  "selection": Field("runtime", added="auto"),
}

# The refinement's own fields: stage 2 initialises the refinement afresh, so they may differ from
# the stage-1 run it starts from (e.g. PV-RAFT's stage 1 has refine='none').
REFINE_FIELDS = ("refine", "refine_widths")

# Fields no parameter depends on: a warm start may change them.
PARAMETER_FREE_FIELDS = tuple(k for k, f in MODEL_FIELDS.items() if f.kind != "architecture")
# Fields evaluation takes from the user's config rather than the checkpoint; resume ignores them.
RUNTIME_MODEL_FIELDS = tuple(k for k, f in MODEL_FIELDS.items() if f.kind == "runtime")
# Fields added after checkpoints were written without them, with the value they had then.
ADDED_MODEL_FIELDS = {k: f.added for k, f in MODEL_FIELDS.items() if f.added is not None}
