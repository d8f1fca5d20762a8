"""Exact top-k of long rows without sorting them whole.

XLA lowers `lax.top_k` on a GPU to a full sort of every row: for a kNN graph of 8192 points that
is a sort of 8192 x 8192 entries, 5.5 ms on an H200 (benchmarks/NETWORK_GPU.md). `top_k` here
returns exactly what `lax.top_k` returns, values and indices in the same order, ties to the lower
index, by taking the top k of each block of `block` entries and then the top k of those survivors:
sorts of short rows, which a GPU does in on-chip memory (3.0 ms for the same graph).

Forms (model.selection): "sort" is lax.top_k; "blockwise" the above; "auto" the blockwise form
where the program is compiled for a GPU or TPU and lax.top_k on the CPU, whose top-k is no full
sort and where the blocks cost more than they save (decided when XLA lowers the program for its
device, jax.lax.platform_dependent).
"""

import functools

import jax
import jax.numpy as jnp

FORMS = ("auto", "sort", "blockwise")


def block_for(k: int, m: int) -> int:
  """The block length the blockwise form uses for the top k of m (0: too short to gain).

  Measured on an H200 (benchmarks/NETWORK_GPU.md): 256 for k = 32 of 8192, 2048 for 512 of
  8192; a row under four blocks is sorted whole.
  """
  block = max(256, 4 * k)
  return block if m >= 4 * block else 0


def blockwise_top_k(x, k: int, block: int):
  """lax.top_k(x, k) along the last axis, in blocks of `block` entries (module docstring)."""
  m = x.shape[-1]
  if block <= 0 or block < k or block >= m:
    return tuple(jax.lax.top_k(x, k))
  blocks = -(-m // block)
  pad = blocks * block - m
  if pad:  # the padding sorts last among equal values: it has the largest indices
    x = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, pad)], constant_values=-jnp.inf)
  lead = x.shape[:-1]
  values, index = jax.lax.top_k(x.reshape(*lead, blocks, block), k)
  index = index + (jnp.arange(blocks, dtype=index.dtype) * block)[:, None]
  # Survivors in block order, each block's sorted: among equal values, position order is index
  # order, so the top k of the survivors breaks ties as lax.top_k does on the whole row.
  values, index = values.reshape(*lead, blocks * k), index.reshape(*lead, blocks * k)
  values, at = top_k(values, k, "blockwise")
  return values, jnp.take_along_axis(index, at, axis=-1)


def top_k(x, k: int, form: str = "auto"):
  """(values, indices) of the k largest entries of the last axis, exactly as lax.top_k."""
  if form not in FORMS:
    raise ValueError(f"model.selection must be one of {', '.join(FORMS)}, got {form!r}")
  block = block_for(k, x.shape[-1])
  if form == "sort" or not block:
    return tuple(jax.lax.top_k(x, k))
  if form == "blockwise":
    return blockwise_top_k(x, k, block)
  return jax.lax.platform_dependent(
    x, cpu=lambda v: tuple(jax.lax.top_k(v, k)),
    default=functools.partial(blockwise_top_k, k=k, block=block))
