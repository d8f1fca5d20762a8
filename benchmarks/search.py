"""Cost of one exact nearest-point search (jaxflow.geometry.neighbours.knn, k = 1) on each path.

    python -m benchmarks.search --sizes 8192,100000 [--repeats 5] [--json FILE]

At each size N, a LiDAR-like pair of N points (tests/test_search.py's sweep) is searched
warped -> pc2, as the exact objective does at every refresh: "host" with pc2's k-d tree built for
the search (an empty cache) and found in the cache (pc2 searched before: every step of an
optimisation after its first), "device" (the brute force, on whatever device jax finds); and the
k-d tree's two parts alone (scipy, no jax): building pc2's tree, querying it. Times are the fastest
and the median of --repeats compiled runs, in ms (on a loaded machine the fastest is the steadier);
the device, jax version and core count go with them.
"""

import argparse
import json
import os
import time

import jax
import numpy as np
from scipy import spatial

from benchmarks.model_speed import device_line
from jaxflow.geometry import neighbours
from tests.test_search import sweep_like


def times_ms(fn, repeats: int, before=lambda: None) -> dict:
  times = []
  for _ in range(repeats):
    before()
    start = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - start)
  return {"min": round(1e3 * min(times), 2), "median": round(1e3 * float(np.median(times)), 2)}


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--sizes", default="8192,100000")
  parser.add_argument("--repeats", type=int, default=5)
  parser.add_argument("--device-repeats", type=int, default=None, help="default --repeats")
  parser.add_argument("--paths", default="host,device")
  parser.add_argument("--json", default=None)
  args = parser.parse_args()
  print(device_line(), f"cores {os.cpu_count()}")
  rows = []
  for n in (int(s) for s in args.sizes.split(",")):
    pc1, pc2 = sweep_like(n, seed=0)
    q, p = jax.device_put(pc1[None] + np.float32([0.7, 0, 0])), jax.device_put(pc2[None])
    row = {"points": n}
    p64 = pc2.astype(np.float64)
    tree = spatial.cKDTree(p64)
    row["scipy_build_ms"] = times_ms(lambda: spatial.cKDTree(p64), args.repeats)
    row["scipy_query_ms"] = times_ms(lambda: tree.query(np.asarray(q[0], np.float64), k=[1],
                                                        workers=-1), args.repeats)
    for path in args.paths.split(","):
      fn = jax.jit(lambda a, b, path=path: neighbours.knn(a, b, 1, path))
      jax.block_until_ready(fn(q, p))  # compile (and fill the cache)
      if path == "host":
        row["host_cached_ms"] = times_ms(lambda: fn(q, p), args.repeats)
        row["host_cold_ms"] = times_ms(lambda: fn(q, p), args.repeats, neighbours.clear_tree_cache)
      else:
        row["device_ms"] = times_ms(lambda: fn(q, p), args.device_repeats or args.repeats)
      print(json.dumps(row), flush=True)
    rows.append(row)
  if args.json:
    with open(args.json, "w") as f:
      json.dump({"device": device_line(), "cores": os.cpu_count(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
  main()
