"""The update block run at every iteration: motion encoder, recurrent cell and flow head."""

import flax.linen as nn
import jax.numpy as jnp

from jaxflow.layers import SetConv


class MotionEncoder(nn.Module):
  """relu(dense(J)) and relu(dense(flow)) -> relu(dense(. -> features - 3)), then the raw flow."""

  features: int = 64

  @nn.compact
  def __call__(self, flow_BxNx3, corr_BxNxF):
    cor = nn.relu(nn.Dense(64, name="conv_corr")(corr_BxNxF))
    flo = nn.relu(nn.Dense(64, name="conv_flow")(flow_BxNx3))
    out = nn.relu(nn.Dense(self.features - 3, name="conv")(jnp.concatenate([cor, flo], axis=-1)))
    return jnp.concatenate([out, flow_BxNx3], axis=-1)


class SingleGateCell(nn.Module):
  """The paper's single-gate flow iterator (eq. 6): h = tanh(W [h, x])."""

  @nn.compact
  def __call__(self, h_BxNxH, x_BxNxD):
    hx = jnp.concatenate([h_BxNxH, x_BxNxD], axis=-1)
    return jnp.tanh(nn.Dense(h_BxNxH.shape[-1], name="convh")(hx))


class GRUCell(nn.Module):
  """PV-RAFT's point-wise ConvGRU."""

  @nn.compact
  def __call__(self, h_BxNxH, x_BxNxD):
    hidden = h_BxNxH.shape[-1]
    hx = jnp.concatenate([h_BxNxH, x_BxNxD], axis=-1)
    z = nn.sigmoid(nn.Dense(hidden, name="convz")(hx))
    r = nn.sigmoid(nn.Dense(hidden, name="convr")(hx))
    q = jnp.tanh(nn.Dense(hidden, name="convq")(jnp.concatenate([r * h_BxNxH, x_BxNxD], axis=-1)))
    return (1.0 - z) * h_BxNxH + z * q


class FlowHead(nn.Module):
  """concat(SetConv(h -> 64) on pc1's graph, dense(h -> 64)) -> dense 64 -> ReLU -> dense 3."""

  @nn.compact
  def __call__(self, h_BxNxH, xyz_BxNx3, nbr_BxNxK):
    a = nn.Dense(64, name="conv1")(h_BxNxH)
    b = SetConv(64, name="setconv")(h_BxNxH, xyz_BxNx3, nbr_BxNxK)
    x = nn.relu(nn.Dense(64, name="out_conv0")(jnp.concatenate([b, a], axis=-1)))
    return nn.Dense(3, name="out_conv2")(x)


class UpdateBlock(nn.Module):
  """One iteration's update: returns the new hidden state and the flow increment."""

  cell: str = "single_gate"

  @nn.compact
  def __call__(self, h_BxNxH, context_BxNxD, corr_BxNxF, flow_BxNx3, xyz_BxNx3, nbr_BxNxK):
    motion = MotionEncoder(name="motion_encoder")(flow_BxNx3, corr_BxNxF)
    x = jnp.concatenate([context_BxNxD, motion], axis=-1)
    if self.cell == "gru":
      h = GRUCell(name="gru")(h_BxNxH, x)
    elif self.cell == "single_gate":
      h = SingleGateCell(name="single_gate")(h_BxNxH, x)
    else:
      raise ValueError(f"model.cell must be 'single_gate' or 'gru', got {self.cell!r}")
    return h, FlowHead(name="flow_head")(h, xyz_BxNx3, nbr_BxNxK)
