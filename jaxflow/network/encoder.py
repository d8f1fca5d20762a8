"""Feature encoders: PV-RAFT's SetConv encoder and the paper's graph-based feature generator."""

from typing import Sequence

import flax.linen as nn

from jaxflow.network.layers import GCL, GroupNorm, SetConv, dense, leaky_relu


class SetConvEncoder(nn.Module):
  """PV-RAFT (FLOT) encoder: SetConv 3 -> 32 -> 64 -> 128 on the cloud's kNN graph."""

  widths: Sequence[int] = (32, 64, 128)
  precision: str = "highest"

  @nn.compact
  def __call__(self, xyz_BxNx3, nbr_BxNxK):
    x = xyz_BxNx3
    for i, width in enumerate(self.widths):
      x = SetConv(width, self.precision, name=f"feat_conv{i + 1}")(x, xyz_BxNx3, nbr_BxNxK)
    return x


class GraphEncoder(nn.Module):
  """Graph-based feature generator (paper 3.1.2): SetConv 32, 64, then GCL 128, 256.

  Each GCL is followed by GroupNorm and LeakyReLU; with `residual`, the block is
  y = LeakyReLU(GroupNorm(GCL(x)) + shortcut(x)), shortcut a bias-free projection where the width
  changes (ResNet's placement: the sum goes through the activation).
  """

  widths: Sequence[int] = (32, 64, 128, 256)
  residual: bool = True
  supports: int = 3
  similarity: str = "sum"
  precision: str = "highest"

  @nn.compact
  def __call__(self, xyz_BxNx3, nbr_BxNxK):
    x = xyz_BxNx3
    *setconv_widths, w3, w4 = self.widths
    for i, width in enumerate(setconv_widths):
      x = SetConv(width, self.precision, name=f"feat_conv{i + 1}")(x, xyz_BxNx3, nbr_BxNxK)
    for i, width in enumerate((w3, w4)):
      gcl = GCL(width, self.supports, self.similarity, self.precision, name=f"gcl{i + 1}")
      y = gcl(x, xyz_BxNx3, nbr_BxNxK)
      y = GroupNorm(name=f"gcl{i + 1}_norm")(y)
      if self.residual:
        shortcut = x
        if x.shape[-1] != width:
          shortcut = dense(width, self.precision, use_bias=False, name=f"gcl{i + 1}_shortcut")(x)
        y = y + shortcut
      x = leaky_relu(y)
    return x
