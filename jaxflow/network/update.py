"""The update block run at every iteration: motion encoder, recurrent cell and flow head."""

import flax.linen as nn
import jax.numpy as jnp

from jaxflow.network.layers import SetConv, dense


class MotionEncoder(nn.Module):
  """relu(dense(J)) and relu(dense(flow)) -> relu(dense(. -> features - 3)), then the raw flow."""

  features: int = 64
  precision: str = "highest"

  @nn.compact
  def __call__(self, flow_BxNx3, corr_BxNxF):
    cor = nn.relu(dense(64, self.precision, name="conv_corr")(corr_BxNxF))
    flo = nn.relu(dense(64, self.precision, name="conv_flow")(flow_BxNx3))
    cat = jnp.concatenate([cor, flo], axis=-1)
    out = nn.relu(dense(self.features - 3, self.precision, name="conv")(cat))
    return jnp.concatenate([out, flow_BxNx3], axis=-1)


class SingleGateCell(nn.Module):
  """The paper's single-gate flow iterator (eq. 6): h = tanh(W [h, x])."""

  precision: str = "highest"

  @nn.compact
  def __call__(self, h_BxNxH, x_BxNxD):
    hx = jnp.concatenate([h_BxNxH, x_BxNxD], axis=-1)
    return jnp.tanh(dense(h_BxNxH.shape[-1], self.precision, name="convh")(hx))


class GRUCell(nn.Module):
  """PV-RAFT's point-wise ConvGRU."""

  precision: str = "highest"

  @nn.compact
  def __call__(self, h_BxNxH, x_BxNxD):
    hidden = h_BxNxH.shape[-1]
    gate = lambda name: dense(hidden, self.precision, name=name)
    hx = jnp.concatenate([h_BxNxH, x_BxNxD], axis=-1)
    z = nn.sigmoid(gate("convz")(hx))
    r = nn.sigmoid(gate("convr")(hx))
    q = jnp.tanh(gate("convq")(jnp.concatenate([r * h_BxNxH, x_BxNxD], axis=-1)))
    return (1.0 - z) * h_BxNxH + z * q


class FlowHead(nn.Module):
  """concat(SetConv(h -> 64) on pc1's graph, dense(h -> 64)) -> dense 64 -> ReLU -> dense 3."""

  precision: str = "highest"

  @nn.compact
  def __call__(self, h_BxNxH, xyz_BxNx3, nbr_BxNxK):
    a = dense(64, self.precision, name="conv1")(h_BxNxH)
    b = SetConv(64, self.precision, name="setconv")(h_BxNxH, xyz_BxNx3, nbr_BxNxK)
    x = nn.relu(dense(64, self.precision, name="out_conv0")(jnp.concatenate([b, a], axis=-1)))
    return dense(3, self.precision, name="out_conv2")(x)


class UpdateBlock(nn.Module):
  """One iteration's update: returns the new hidden state and the flow increment."""

  cell: str = "single_gate"
  precision: str = "highest"

  @nn.compact
  def __call__(self, h_BxNxH, context_BxNxD, corr_BxNxF, flow_BxNx3, xyz_BxNx3, nbr_BxNxK):
    motion = MotionEncoder(precision=self.precision, name="motion_encoder")(flow_BxNx3, corr_BxNxF)
    x = jnp.concatenate([context_BxNxD, motion], axis=-1)
    if self.cell == "gru":
      h = GRUCell(self.precision, name="gru")(h_BxNxH, x)
    elif self.cell == "single_gate":
      h = SingleGateCell(self.precision, name="single_gate")(h_BxNxH, x)
    else:
      raise ValueError(f"model.cell must be 'single_gate' or 'gru', got {self.cell!r}")
    return h, FlowHead(self.precision, name="flow_head")(h, xyz_BxNx3, nbr_BxNxK)
