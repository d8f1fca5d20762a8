"""The scene-flow network: encoders, point-voxel correlation, Z iterations as one scan, refinement.

    model = build_model(config.model)
    variables = model.init(rng, pc1, pc2, num_iters=1)
    out = model.apply(variables, pc1, pc2, num_iters=32)   # out["flows"]: B x Z x N x 3

Top-level parameter names: feature_encoder, context_encoder, correlation, update, refine.
"""

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import ml_collections

from jaxflow.geometry import neighbours, ops, select
from jaxflow.network.correlation import (VOXEL_CELLS, PointVoxelCorrelation, planar,
                                         truncated_correlation)
from jaxflow.network.encoder import GraphEncoder, SetConvEncoder
from jaxflow.network.layers import lax_precision
from jaxflow.network.refine import GraphRefinement, SetConvRefinement
from jaxflow.network.update import UpdateBlock

DEFAULT_WIDTHS = {"graph": (32, 64, 128, 256), "setconv": (32, 64, 128)}
BACKBONE = ("feature_encoder", "context_encoder", "correlation", "update")


class SceneFlowNet(nn.Module):
  """Graph-based scene flow network; with encoder="setconv", cell="gru", refine="setconv" it is
  PV-RAFT. The context features (width C) split into the initial hidden state tanh(first C/2)
  and the context input relu(last C/2). `precision` is that of every matmul, the kNN's included
  (layers.PRECISIONS); `voxel_cells` the voxel branch's form (correlation.VOXEL_CELLS); `selection`
  how the kNN graphs and the candidates are selected (select.FORMS). What kind
  each field is (architecture, parameter-free, runtime): jaxflow.network.model_fields."""

  encoder: str = "graph"
  widths: Sequence[int] = ()
  residual: bool = True
  gcl_supports: int = 3
  gcl_similarity: str = "sum"
  knn: int = 32
  cell: str = "single_gate"
  truncate_k: int = 512
  corr_knn: int = 32
  corr_levels: int = 3
  base_scale: float = 0.25
  refine: str = "graph"
  refine_widths: Sequence[int] = ()
  corr_chunk: int = 0
  remat_iterations: bool = False
  precision: str = "highest"
  voxel_cells: str = "auto"
  selection: str = "auto"

  def setup(self):
    lax_precision(self.precision)  # a clear error for a misspelt name, before anything traces
    if self.voxel_cells not in VOXEL_CELLS:
      raise ValueError(f"model.voxel_cells must be one of {', '.join(VOXEL_CELLS)}, got "
                       f"{self.voxel_cells!r}")
    if self.selection not in select.FORMS:
      raise ValueError(f"model.selection must be one of {', '.join(select.FORMS)}, got "
                       f"{self.selection!r}")
    if self.encoder not in DEFAULT_WIDTHS:
      raise ValueError(f"model.encoder must be 'graph' or 'setconv', got {self.encoder!r}")
    widths = tuple(self.widths) or DEFAULT_WIDTHS[self.encoder]
    if self.encoder == "graph":
      if len(widths) < 3:
        raise ValueError(f"model.widths of the graph encoder needs >= 3 entries, got {widths}")
      make = lambda name: GraphEncoder(
        widths, self.residual, self.gcl_supports, self.gcl_similarity, self.precision, name=name
      )
    else:
      make = lambda name: SetConvEncoder(widths, self.precision, name=name)
    self.feature_encoder = make("feature_encoder")
    self.context_encoder = make("context_encoder")
    self.correlation = PointVoxelCorrelation(
      knn=self.corr_knn, levels=self.corr_levels, base_scale=self.base_scale,
      precision=self.precision, voxel_cells=self.voxel_cells,
    )
    self.update = UpdateBlock(cell=self.cell, precision=self.precision)
    if self.refine == "graph":
      self.refine_module = GraphRefinement(
        tuple(self.refine_widths) or (256, 128, 64), self.gcl_supports, self.gcl_similarity,
        self.precision, name="refine",
      )
    elif self.refine == "setconv":
      self.refine_module = SetConvRefinement(precision=self.precision, name="refine")
    elif self.refine != "none":
      raise ValueError(f"model.refine must be 'graph', 'setconv' or 'none', got {self.refine!r}")

  def _chunk(self, a_BxNx3, b_BxMx3) -> int:
    """Rows a pairwise kernel of a against b takes at a time (corr_chunk 0: by the clouds' sizes
    and the device's memory, ops.auto_chunk)."""
    return ops.auto_chunk(a_BxNx3.shape[0], a_BxNx3.shape[1], b_BxMx3.shape[1], self.corr_chunk)

  def _graphs(self, pc1_BxNx3, pc2_BxMx3, graphs):
    """(nbr1 B x N x knn, nbr2 B x M x knn): each cloud's kNN graph, or `graphs` as given."""
    if graphs is not None:
      return graphs
    return tuple(neighbours.matmul_knn(pc, pc, self.knn, self._chunk(pc, pc), self.precision,
                                       self.selection)
                 for pc in (pc1_BxNx3, pc2_BxMx3))

  def _context(self, pc1_BxNx3, nbr1_BxNxK):
    """(h0, context input): the context features' first half through tanh (the initial hidden
    state), the second through relu."""
    context = self.context_encoder(pc1_BxNx3, nbr1_BxNxK)
    hidden = context.shape[-1] // 2
    return jnp.tanh(context[..., :hidden]), nn.relu(context[..., hidden:])

  def _iterate(self, h0, context_in, corr_BxNxK, cand_xyz_3xBxNxK, pc1_BxNx3, nbr1_BxNxK,
               num_iters: int, unroll: bool, entering):
    """The flow after each of `num_iters` update iterations (Z x B x N x 3): one scan, or a
    Python loop with `unroll` (the same step)."""

    def step(mdl, carry, entering_BxNx3):
      h, coords = carry
      # RAFT's detach: each iteration's gradient reaches the parameters through its own update
      # only, not back through the earlier estimates (tests/test_gradients.py pins it).
      coords = jax.lax.stop_gradient(coords) if entering_BxNx3 is None else entering_BxNx3
      corr = mdl.correlation(corr_BxNxK, cand_xyz_3xBxNxK, coords)
      flow = coords - pc1_BxNx3
      h, delta = mdl.update(h, context_in, corr, flow, pc1_BxNx3, nbr1_BxNxK)
      coords = coords + delta
      return (h, coords), coords - pc1_BxNx3

    if unroll:
      carry, flows = (h0, pc1_BxNx3), []
      for i in range(num_iters):
        carry, flow = step(self, carry, None if entering is None else entering[i])
        flows.append(flow)
      return jnp.stack(flows)
    if self.remat_iterations:
      # The backward recomputes each iteration from its carry instead of keeping its
      # activations (B x N x K x C per iteration): less memory for ~one more forward.
      step = nn.remat(step, prevent_cse=False)
    scan = nn.scan(
      step, variable_broadcast="params", split_rngs={"params": False}, length=num_iters
    )
    return scan(self, (h0, pc1_BxNx3), entering)[1]

  def __call__(self, pc1_BxNx3, pc2_BxMx3, num_iters: int = 8, refine: bool | None = None,
               freeze_backbone: bool = False, graphs=None, unroll: bool = False, entering=None):
    """Returns {"flows": B x Z x N x 3} and, when refining, {"refined": B x N x 3}.

    refine=None refines when the model has a refinement module. freeze_backbone stops gradients
    at the coarse flow (stage 2). `graphs` = (nbr1 B x N x knn, nbr2 B x M x knn) replaces the
    kNN search, e.g. to reuse graphs or to reproduce another implementation's tie-breaking.
    For the tests of the iteration: `unroll` runs the iterations as a Python loop instead of one
    scan (the same step); `entering` (Z x B x N x 3) gives the estimate (pc1 + flow) entering each
    iteration instead of the previous iteration's.
    """
    if refine is None:
      refine = self.refine != "none"
    if refine and self.refine == "none":
      raise ValueError("refine=True asked of a model configured with refine='none'")
    nbr1_BxNxK, nbr2_BxMxK = self._graphs(pc1_BxNx3, pc2_BxMx3, graphs)
    f1 = self.feature_encoder(pc1_BxNx3, nbr1_BxNxK)
    f2 = self.feature_encoder(pc2_BxMx3, nbr2_BxMxK)
    corr_BxNxK, cand_xyz_BxNxKx3 = truncated_correlation(
      f1, f2, pc2_BxMx3, self.truncate_k, self._chunk(pc1_BxNx3, pc2_BxMx3), self.precision,
      self.selection
    )
    cand_xyz_3xBxNxK = jnp.stack(planar(cand_xyz_BxNxKx3))  # once, not in every iteration
    h0, context_in = self._context(pc1_BxNx3, nbr1_BxNxK)
    flows_ZxBxNx3 = self._iterate(h0, context_in, corr_BxNxK, cand_xyz_3xBxNxK, pc1_BxNx3,
                                  nbr1_BxNxK, num_iters, unroll, entering)
    out = {"flows": jnp.moveaxis(flows_ZxBxNx3, 0, 1)}
    if refine:
      coarse = flows_ZxBxNx3[-1]
      if freeze_backbone:
        coarse = jax.lax.stop_gradient(coarse)
      out["refined"] = self.refine_module(coarse, pc1_BxNx3, nbr1_BxNxK)
    return out


def build_model(model_config: ml_collections.ConfigDict, inference: bool = False) -> SceneFlowNet:
  """The network described by a config's `model` section; `inference`: as it evaluates and
  predicts (`infer_truncate_k` candidates, when set, instead of `truncate_k`)."""
  fields = dict(model_config)
  infer_truncate_k = fields.pop("infer_truncate_k", 0)
  if not isinstance(infer_truncate_k, int) or infer_truncate_k < 0:
    raise ValueError(f"infer_truncate_k must be an integer >= 0, got {infer_truncate_k!r}")
  if inference and infer_truncate_k:
    fields["truncate_k"] = infer_truncate_k
  fields["widths"] = tuple(fields.get("widths") or ())
  fields["refine_widths"] = tuple(fields.get("refine_widths") or ())
  known = set(SceneFlowNet.__dataclass_fields__) - {"parent", "name"}
  unknown = sorted(set(fields) - known)
  if unknown:
    raise ValueError(f"unknown model config fields: {', '.join(unknown)}")
  return SceneFlowNet(**fields)
