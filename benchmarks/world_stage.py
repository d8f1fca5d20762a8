r"""How optimise's last stage, the world (jaxflow.methods.optimise.World), was chosen: optimise
without it once a pair and seed, then every setting of the grid below applied to that same flow
(the stage reads only the flow it is given, pc1 and pc2). Prints each setting's mean EPE per seed.

    python benchmarks/world_stage.py --set lidar_val --seeds 0-4 [--json OUT.json]

Sets as benchmarks/stability.py's (`lidar_val`: the generator's LiDAR val split, 8 pairs, where the
settings were chosen; `lidar`, `kitti`, `ft3d` to see what the choice does elsewhere), 8192
points a cloud sampled with each seed. The network is the shipped checkpoint.
"""

import argparse
import dataclasses
import itertools
import json
import pathlib

import jax
import numpy as np

import stability
from jaxflow.methods import optimise, registry
from jaxflow.network import checkpointing
from jaxflow.refine import rigid_clusters

GRID = {"tie": (0.005, 0.01), "min_change": (0.0, 0.03, 0.05, 0.1),
        "veto": (0.03, 0.05, 0.1, float("inf"))}  # veto inf: no cluster vetoes


def variants(batch, flow, chosen):
  """{setting name: EPE} of every World in GRID applied to `flow` (GICP registered once)."""
  labels = rigid_clusters.clusters(batch["pc1"], flow, chosen.clusters)
  by_world = optimise.registered_world(batch["pc1"], batch["pc2"])
  guarded = optimise.Guarded(batch["pc1"], batch["pc2"], chosen.guard)
  out = {"off": stability.epe(batch, flow)}
  for values in itertools.product(*GRID.values()):
    world = optimise.World(**dict(zip(GRID, values)))
    taken, to = optimise.world_flow(batch["pc1"], batch["pc2"], flow, labels, by_world, world)
    name = " ".join(f"{k} {v:g}" for k, v in zip(GRID, values))
    out[name] = stability.epe(batch, guarded(np.where(taken, 0, -1), to, flow))
  return out


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--set", default="lidar_val", choices=sorted(stability.SETS))
  parser.add_argument("--seeds", default="0-4")
  parser.add_argument("--json", default=None)
  args = parser.parse_args()
  seeds = stability.seeds_of(args.seeds)
  model, params, _, _, refine = checkpointing.load_for_inference(None)
  chosen = registry.settings("optimise")
  without = dataclasses.replace(chosen, world=None)
  network = jax.jit(registry.network_for(model, 32, refine)(chosen.start_iters,
                                                            chosen.start_candidates))
  epe = {}  # setting -> seed -> [EPE of each pair]
  for seed in seeds:
    for batch in stability.pairs(args.set, seed, 8192):
      init = np.asarray(network(params, batch["pc1"], batch["pc2"]))
      flow = np.asarray(optimise.optimise_flow(init, batch["pc1"], batch["pc2"], without)[0])
      for name, value in variants(batch, flow, chosen).items():
        epe.setdefault(name, {}).setdefault(seed, []).append(value)
      print(f"seed {seed} {batch['names'][0]}: off {epe['off'][seed][-1]:.4f}", flush=True)
  print(f"\n| world ({args.set}) | " + " | ".join(f"seed {s}" for s in seeds) + " | mean |")
  print("|---" * (len(seeds) + 2) + "|")
  for name, by_seed in epe.items():
    means = [float(np.mean(by_seed[s])) for s in seeds]
    print(f"| {name} | " + " | ".join(f"{m:.4f}" for m in means) + f" | {np.mean(means):.4f} |")
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps({"set": args.set, "seeds": seeds, "epe": epe},
                                                  indent=1) + "\n")


if __name__ == "__main__":
  main()
