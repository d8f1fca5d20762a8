"""The network's three kinds of top-k, each way: lax.top_k, select.top_k's blocks, and top-16 twice.

    python -m benchmarks.selection                   # 8192 points
    python -m benchmarks.selection --points 1024     # any CPU

Rows: a kNN graph (32 of N, of a distance matrix), the correlation's candidates (512 of N) and
the point branch (32 of 512, every iteration), at B = 1 and 2. "top-16 twice" takes the top 16,
masks them and takes the next 16: XLA's GPUs have a kernel of their own for k <= 16 on rows of
1024 and more (no sort). Every way must return lax.top_k's indices (checked; "DIFFERS" if not).
Medians of --repeats calls after compilation.
"""

import argparse
import functools

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.model_speed import device_line, timed
from jaxflow.geometry import select


def top16_twice(x, k):
  """lax.top_k(x, 32) as two top-16s: the second after masking what the first took."""
  if k != 32:
    return jax.lax.top_k(x, k)
  v1, i1 = jax.lax.top_k(x, 16)
  # Taken: above the 16th value, or equal to it at an index not after its own (ties go low).
  iota = jax.lax.broadcasted_iota(jnp.int32, x.shape, x.ndim - 1)
  taken = (x > v1[..., -1:]) | ((x == v1[..., -1:]) & (iota <= i1[..., -1:]))
  v2, i2 = jax.lax.top_k(jnp.where(taken, -jnp.inf, x), 16)
  return jnp.concatenate([v1, v2], -1), jnp.concatenate([i1, i2], -1)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--points", type=int, default=8192)
  parser.add_argument("--repeats", type=int, default=10)
  args = parser.parse_args()
  n = args.points
  print(device_line())
  print("| selection | B | lax.top_k (ms) | blocks (ms) | top-16 twice (ms) |")
  print("|---|---|---|---|---|")
  rng = np.random.default_rng(0)
  for b in (1, 2):
    pts = jnp.asarray(rng.uniform(-10, 10, (b, n, 3)), jnp.float32)
    dist = jax.jit(lambda p: jnp.sum((p[:, :, None] - p[:, None]) ** 2, -1))(pts)
    cand = jnp.asarray(rng.normal(size=(b, n, 512)), jnp.float32)
    for label, x, k in ((f"kNN, 32 of {n}", -dist, 32), (f"candidates, 512 of {n}", -dist, 512),
                        ("point branch, 32 of 512", cand, 32)):
      want = np.asarray(jax.lax.top_k(x, k)[1])
      cells = []
      for fn in (jax.lax.top_k, functools.partial(select.top_k, form="blockwise"), top16_twice):
        f = jax.jit(lambda v, fn=fn: fn(v, k))
        same = np.array_equal(np.asarray(f(x)[1]), want)
        cells.append(f"{1e3 * timed(f, x, repeats=args.repeats):.3f}" + ("" if same else " DIFFERS"))
      print(f"| {label} | {b} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
  main()
