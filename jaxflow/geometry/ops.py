"""Distances, chunked row maps and gathers on batched point clouds (the searches built on them:
jaxflow.geometry.neighbours).

Every function works on a batch: points `B x N x 3`, neighbour indices `B x N x K` (int32).
"""

import jax
import jax.numpy as jnp


def squared_distances(a_BxNx3: jax.Array, b_BxMx3: jax.Array,
                      precision: str = "highest") -> jax.Array:
  """|a_i - b_j|^2 as |a|^2 + |b|^2 - 2 a.b (one matmul; the reference's graph uses this form).

  `precision` (a jax.lax.Precision name) is the matmul's: below "highest" a GPU or TPU rounds a.b
  to ~1e-3 relative, enough to change which neighbours are nearest.
  """
  a2_BxNx1 = jnp.sum(a_BxNx3**2, axis=-1, keepdims=True)
  b2_Bx1xM = jnp.sum(b_BxMx3**2, axis=-1)[:, None, :]
  ab_BxNxM = jnp.einsum("bnc,bmc->bnm", a_BxNx3, b_BxMx3,
                        precision=jax.lax.Precision(precision))
  return a2_BxNx1 + b2_Bx1xM - 2.0 * ab_BxNxM


# model.corr_chunk 0 ("auto"): an N x M matrix (a kNN's distances, the correlation) is built in
# chunks of rows whose B x rows x M float32 take at most this, or a sixteenth of the device's
# memory where JAX reports it (GPUs; the CPU reports none): memory linear in N at any size.
CHUNK_BYTES = 64 << 20


def chunk_budget() -> int:
  """The bytes one chunk's matrix may take: CHUNK_BYTES, or a sixteenth of this process's first
  device's memory where JAX reports it and that is more. The device's size, not what is free at
  the moment: every process of a run must build the same program."""
  stats = jax.local_devices()[0].memory_stats() or {}
  return max(CHUNK_BYTES, stats.get("bytes_limit", 0) // 16)


def auto_chunk(b: int, n: int, m: int, chunk: int = 0, budget: int | None = None) -> int:
  """The rows of a B x N x M float32 matrix built at a time: `chunk` when > 0; otherwise 0 (all
  N) when it fits the budget (chunk_budget()), else the largest power of two rows that fit
  (at least 16)."""
  if chunk > 0:
    return chunk
  rows = (chunk_budget() if budget is None else budget) // (4 * b * m)
  return 0 if rows >= n else max(16, 1 << (max(rows, 1).bit_length() - 1))


def map_row_chunks(fn, xs, chunk: int):
  """Applies `fn` to row chunks of the arrays `xs` (each `B x N x ...`) and concatenates on axis 1.

  With chunk <= 0 or chunk >= N, `fn` sees the whole rows at once. Otherwise rows are padded to a
  multiple of `chunk` and processed with `lax.map`, so peak memory is that of one chunk.
  """
  n = xs[0].shape[1]
  if chunk <= 0 or chunk >= n:
    return fn(*xs)
  num = -(-n // chunk)
  pad = num * chunk - n

  def split(x):
    x = jnp.pad(x, [(0, 0), (0, pad)] + [(0, 0)] * (x.ndim - 2), mode="edge")
    x = x.reshape(x.shape[0], num, chunk, *x.shape[2:])
    return jnp.moveaxis(x, 1, 0)

  outs = jax.lax.map(lambda args: fn(*args), tuple(split(x) for x in xs))

  def merge(y):
    y = jnp.moveaxis(y, 0, 1)
    return y.reshape(y.shape[0], num * chunk, *y.shape[3:])[:, :n]

  return jax.tree_util.tree_map(merge, outs)


def gather(values_BxMxC: jax.Array, idx_BxNxK: jax.Array) -> jax.Array:
  """values[b, idx[b, n, k]] -> `B x N x K x C`."""
  return jax.vmap(lambda v, i: v[i])(values_BxMxC, idx_BxNxK)
