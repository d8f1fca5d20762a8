"""jaxflow.geometry.select: the blocks return lax.top_k's values and indices, in its order."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow.geometry import select


def numpy_top_k(x, k):
  """The k largest of each row, ties to the lower index: a stable sort of -x."""
  order = np.argsort(-x, axis=-1, kind="stable")[..., :k]
  return np.take_along_axis(x, order, axis=-1), order


@pytest.mark.parametrize("shape,k,block", [
  ((2, 3, 2048), 32, 256),   # blocks, then the survivors' top k
  ((1, 5, 2000), 32, 256),   # a row that is no multiple of the block: padded
  ((1, 2, 9000), 16, 64),    # survivors still long: blockwise again
  ((3, 700), 512, 2048),     # a block longer than the row: lax.top_k itself
])
def test_blockwise_equals_a_stable_sort_with_many_ties(shape, k, block):
  rng = np.random.default_rng(0)
  x = rng.integers(-20, 20, shape).astype(np.float32)  # every value repeated: ties everywhere
  x[..., 5] = -np.inf
  values, index = jax.jit(lambda v: select.blockwise_top_k(v, k, block))(jnp.asarray(x))
  want_values, want_index = numpy_top_k(x, k)
  np.testing.assert_array_equal(np.asarray(index), want_index)
  np.testing.assert_array_equal(np.asarray(values), want_values)


def test_blocks_return_lax_top_k_on_gaussian_rows():
  rng = np.random.default_rng(1)
  x = jnp.asarray(rng.normal(size=(2, 4, 4096)).round(2), jnp.float32)  # a few ties
  for k in (32, 512):
    values, index = jax.jit(lambda v: select.top_k(v, k, "blockwise"))(x)
    want_values, want_index = jax.lax.top_k(x, k)
    np.testing.assert_array_equal(np.asarray(index), np.asarray(want_index))
    np.testing.assert_array_equal(np.asarray(values), np.asarray(want_values))


def test_auto_takes_blocks_where_the_program_is_lowered_for_a_gpu():
  # Lowered, not run: a CPU can lower for CUDA. The top-k calls' operands say which form it took.
  x = jnp.zeros((2, 4, 4096))
  operands = {}
  for platform in ("cpu", "cuda"):
    text = jax.jit(lambda v: select.top_k(v, 32, "auto")).trace(x).lower(
      lowering_platforms=(platform,)).as_text()
    operands[platform] = sorted(set(re.findall(r"top_k.*?tensor<([\dx]+)xf32>", text)))
  assert operands == {"cpu": ["2x4x4096"], "cuda": ["2x4x16x256", "2x4x512"]}


def test_block_lengths_measured_on_a_gpu():
  assert select.block_for(32, 8192) == 256 and select.block_for(512, 8192) == 2048
  assert select.block_for(32, 512) == 0  # the point branch's 512 candidates: sorted whole


def test_an_unknown_form_is_refused_by_name():
  with pytest.raises(ValueError, match="model.selection must be one of auto, sort, blockwise"):
    select.top_k(jnp.zeros((4, 8)), 2, "radix")
