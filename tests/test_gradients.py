"""Gradient semantics: the estimate entering each iteration carries no gradient (RAFT's
detach), and stage 2's gradient reaches the refinement only."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from jaxflow.configs import default
from jaxflow.network import train_state
from jaxflow.network.model import build_model
from jaxflow.training import losses, trainer


def tiny_config():
  """The smallest program with every part: PV-RAFT's SetConv encoder (the encoders are not what
  these tests are about), the GRU, the graph refinement."""
  config = default.get_config("smoke")
  config.model.encoder, config.model.widths, config.model.cell = "setconv", (16, 16, 32), "gru"
  config.model.refine_widths = (32, 16, 16)
  return config


def pair(seed=0, n=32):
  rng = np.random.default_rng(seed)
  pc1 = rng.uniform(-2, 2, (1, n, 3)).astype(np.float32)
  flow = rng.normal(0, 0.2, pc1.shape).astype(np.float32)
  return jnp.asarray(pc1), jnp.asarray(pc1 + flow), jnp.asarray(flow)


def flat(tree):
  return traverse_util.flatten_dict(tree, sep="/")


@pytest.mark.slow
def test_the_estimate_entering_each_iteration_carries_no_gradient():
  """The gradient of the iterated part (the update block) equals that of the same model whose
  iterations are given the estimates entering them as constants (`entering`: the forward pass's
  values, no path back to earlier iterations; the hidden state still carries one). Checked by
  hand: with the model's stop_gradient deleted, this gradient differs, so the test fails."""
  config = tiny_config()
  model = build_model(config.model)
  pc1, pc2, gt = pair()
  params = train_state.init_params(model, config, jax.random.key(0))
  iters = 2  # the second iteration's input estimate is the first's output

  def update_grad(flows_fn):
    loss = lambda u: losses.sequence_loss(flows_fn({**params, "update": u}), gt)
    return flat(jax.jit(jax.grad(loss))(params["update"]))

  flows = model.apply({"params": params}, pc1, pc2, num_iters=iters, refine=False)["flows"]
  entering = jnp.moveaxis(jnp.concatenate([jnp.zeros_like(flows[:, :1]), flows[:, :-1]], 1), 1, 0)
  entering = jax.lax.stop_gradient(pc1[None] + entering)  # Z x B x N x 3, constants
  got = update_grad(lambda p: model.apply({"params": p}, pc1, pc2, num_iters=iters,
                                          refine=False)["flows"])
  want = update_grad(lambda p: model.apply({"params": p}, pc1, pc2, num_iters=iters,
                                           refine=False, entering=entering)["flows"])
  scale = max(float(jnp.max(jnp.abs(v))) for v in want.values())
  assert scale > 0
  for k in want:
    np.testing.assert_allclose(got[k], want[k], rtol=1e-4, atol=1e-6 * scale, err_msg=k)


@pytest.mark.slow
def test_stage2_gradient_reaches_the_refinement_only():
  """With freeze_backbone (stage 2) the refinement loss's gradient is exactly zero on every
  backbone parameter and non-zero on the refinement's (checked by hand: without the freeze's
  stop_gradient the backbone gets a gradient and this fails). The stage-2 train step
  differentiates the refinement alone: its gradient norm is the refinement's, and only the
  refinement moves."""
  config = tiny_config()
  model = build_model(config.model)
  pc1, pc2, gt = pair(1)
  params = train_state.init_params(model, config, jax.random.key(1))

  def loss(p):
    out = model.apply({"params": p}, pc1, pc2, num_iters=2, refine=True, freeze_backbone=True)
    return losses.refinement_loss(out["refined"], gt)

  frozen = flat(jax.jit(jax.grad(loss))(params))
  refine = [k for k in frozen if k.startswith("refine/")]
  backbone = [k for k in frozen if not k.startswith("refine/")]
  assert refine and backbone
  assert all(not np.any(frozen[k]) for k in backbone)  # exactly zero, every leaf
  assert all(np.any(frozen[k]) for k in refine if not k.endswith("bias"))

  config.train.stage, config.train.num_iters = 2, 2
  tx = train_state.make_optimizer(config, 10)
  batch = {"pc1": pc1, "pc2": pc2, "flow": gt, "mask": jnp.ones(pc1.shape[:2])}
  state, metrics = jax.jit(trainer.make_train_step(model, tx, config))(
    train_state.create_train_state(params, tx), batch)
  want = np.sqrt(sum(float(jnp.sum(frozen[k] ** 2)) for k in refine))
  np.testing.assert_allclose(float(metrics["grad_norm"]), want, rtol=1e-4)
  after = flat(state.params)
  assert all(np.array_equal(after[k], flat(params)[k]) for k in backbone)
  assert any(not np.array_equal(after[k], flat(params)[k]) for k in refine)
