"""Flow refinement (stage 2): the paper's graph-based module and PV-RAFT's SetConv module."""

import flax.linen as nn

from jaxflow.network.layers import GCL, GroupNorm, SetConv, dense, leaky_relu


class GraphRefinement(nn.Module):
  """Paper 3.1.5: GCL 3 -> 256 -> 128 -> 64 (each with GroupNorm + LeakyReLU), dense 64 -> 3;
  the output is added to the coarse flow."""

  widths: tuple = (256, 128, 64)
  supports: int = 3
  similarity: str = "sum"
  precision: str = "highest"

  @nn.compact
  def __call__(self, flow_BxNx3, xyz_BxNx3, nbr_BxNxK):
    x = flow_BxNx3
    for i, width in enumerate(self.widths):
      gcl = GCL(width, self.supports, self.similarity, self.precision, name=f"gcl{i + 1}")
      x = leaky_relu(GroupNorm(name=f"gcl{i + 1}_norm")(gcl(x, xyz_BxNx3, nbr_BxNxK)))
    return flow_BxNx3 + dense(3, self.precision, name="fc")(x)


class SetConvRefinement(nn.Module):
  """PV-RAFT's refinement: SetConv 3 -> 32 -> 64 -> 128, linear 128 -> 3, residual."""

  widths: tuple = (32, 64, 128)
  precision: str = "highest"

  @nn.compact
  def __call__(self, flow_BxNx3, xyz_BxNx3, nbr_BxNxK):
    x = flow_BxNx3
    for i, width in enumerate(self.widths):
      x = SetConv(width, self.precision, name=f"ref_conv{i + 1}")(x, xyz_BxNx3, nbr_BxNxK)
    return flow_BxNx3 + dense(3, self.precision, name="fc")(x)
