"""The network's GPU programs measured without a GPU: exact, load-independent figures of XLA.

    python -m benchmarks.yardstick                       # 8192 points, both configs, a table
    python -m benchmarks.yardstick --points 256 --json out.json

For each config (PV-RAFT's, the paper's full model): inference (B=1, 32 iterations) and a
training step (B=2, 8 iterations, sequence loss, Adam), compiled on whatever device JAX finds
with the selection a GPU runs (model.selection="blockwise"; the forms decided by the device
it is compiled for, the voxel cells' and the GCL's cosines, are the CPU's) and the training
memory's recipe (model.remat_iterations). Printed:
XLA's temporary bytes (memory_analysis), bytes accessed and flops (cost_analysis), and the sorts
and top-k calls of the optimised HLO (how many, and the longest row one of them orders: a GPU
sorts a top-k row whole). None of these depends on the
machine's load; on the CPU the temporaries track a GPU's peak memory (benchmarks/NETWORK_GPU.md).
"""

import argparse
import json
import re

from benchmarks.model_speed import device_line
from benchmarks.network_gpu import programs

# The GPU's selection. The voxel branch keeps the CPU's form (a scatter, the same values): its
# GPU form compares every candidate with every cell, which a GPU fuses and the CPU stores
# (B x N x K x 27 of them), so it would swamp the figures with what no GPU holds.
GPU_FORMS = {"selection": "blockwise", "remat_iterations": True}


def selections(hlo_text: str) -> tuple[int, int]:
  """(number of sorts and top-k calls, longest row one of them orders) in an optimised HLO
  module's text. The CPU keeps lax.top_k as a TopK call; a GPU sorts its rows whole (k > 16)."""
  shapes = {m.group(1): [int(d) for d in m.group(2).split(",") if d]
            for m in re.finditer(r"%([\w.\-]+) = \(?\w+\[([\d,]*)\]", hlo_text)}
  count, longest = 0, 0
  for line in hlo_text.splitlines():
    if sort := re.search(r"= \(?\w+\[([\d,]*)\][^=]*? sort\(.*dimensions=\{(\d+)\}", line):
      dims = [int(d) for d in sort.group(1).split(",") if d]
      row = dims[int(sort.group(2))] if dims else 1
    elif topk := re.search(r"custom-call\(%([\w.\-]+)\).*custom_call_target=\"TopK\"", line):
      row = (shapes.get(topk.group(1)) or [0])[-1]
    else:
      continue
    count, longest = count + 1, max(longest, row)
  return count, longest


def figures(compiled) -> dict:
  """The yardstick of one compiled program."""
  cost = compiled.cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) else cost
  count, longest = selections(compiled.as_text())
  return {"temp_mib": compiled.memory_analysis().temp_size_in_bytes / 2**20,
          "gbytes_accessed": float(cost.get("bytes accessed", float("nan"))) / 1e9,
          "gflops": float(cost.get("flops", float("nan"))) / 1e9,
          "selections": count, "longest_row": longest}


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--points", type=int, default=8192)
  parser.add_argument("--iters", type=int, default=32)
  parser.add_argument("--train_iters", type=int, default=8)
  parser.add_argument("--configs", default="pvraft,default_full")
  parser.add_argument("--json", default="", help="also write the figures to this file")
  args = parser.parse_args()
  print(device_line())
  print("| program | XLA temporaries (MiB) | bytes accessed (GB) | GFLOP | sorts and top-k (longest row) |")
  print("|---|---|---|---|---|")
  rows = []
  for name in args.configs.split(","):
    for label, (fn, fn_args) in zip(("inference B=1", "train step B=2"), programs(
        name, args.points, args.iters, args.train_iters, GPU_FORMS)):
      f = figures(fn.lower(*fn_args).compile())
      rows.append({"config": name, "program": label, "points": args.points, **f})
      print(f"| {name}, {label} | {f['temp_mib']:,.0f} | {f['gbytes_accessed']:.1f} | "
            f"{f['gflops']:.1f} | {f['selections']} ({f['longest_row']}) |", flush=True)
  if args.json:
    with open(args.json, "w") as out:
      json.dump({"device": device_line(), "forms": GPU_FORMS, "rows": rows}, out, indent=1)


if __name__ == "__main__":
  main()
