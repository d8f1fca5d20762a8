r"""Is `optimise` a function of its input? Its EPE on each pair over sampling seeds, and with its
starting flow perturbed by a few micrometres (issue 56's goals).

    python benchmarks/stability.py --sets lidar,ft3d,kitti --seeds 0-9 --perturb 1e-5 \
        --json benchmarks/stability.json

Sets: `lidar` the generator's synthetic_lidar test split (8 pairs; `lidar_val` its val split, where
optimise.World was chosen), `ft3d` the 21 real FT3D pairs and `kitti` the real KITTI frame of
../shared/data (skipped when absent), 8192 points a cloud sampled with each seed (evaluate.py's
--seed). Per pair: its EPE at each seed, the median and the worst; a pair is stable when its
worst seed is within max(1.5 x median, median + 2 cm). Per seed: the mean EPE of each set.
`--perturb S`: the start (the network's flow at seed 0) plus Gaussian noise of S m per
coordinate, `--draws` draws, each held to the same bound against the seed-0 median. The network
is the shipped checkpoint; its start is computed once a pair and seed.
"""

import argparse
import json
import os
import pathlib
import platform
import time

import jax
import numpy as np

from jaxflow.data import eval_batches, open_dataset
from jaxflow.methods import optimise, registry
from jaxflow.network import checkpointing

DATA = pathlib.Path(__file__).absolute().parent.parent.parent / "shared" / "data"
SETS = {  # name: (dataset spec, splits)
  "lidar": ("synthetic_lidar:8", ("test",)),
  "lidar_val": ("synthetic_lidar:8", ("val",)),  # where optimise.World was chosen
  "ft3d": (f"ft3d:{DATA / 'FlyingThings3D_subset_processed_35m'}", ("train_all", "val")),
  "kitti": (f"kitti:{DATA / 'KITTI_processed_occ_final'}", ("test",)),
}


def stable(worst: float, median: float) -> bool:
  """Issue 56's bound: the worst within 1.5 x the median, or 2 cm above it."""
  return worst <= max(1.5 * median, median + 0.02)


def seeds_of(text: str) -> list[int]:
  if "-" in text:
    lo, hi = map(int, text.split("-"))
    return list(range(lo, hi + 1))
  return [int(s) for s in text.split(",")]


def pairs(name: str, seed: int, num_points: int):
  spec, splits = SETS[name]
  if not name.startswith("lidar") and not pathlib.Path(spec.split(":", 1)[1]).is_dir():
    return
  for split in splits:
    yield from eval_batches(open_dataset(spec, split), 1, num_points, seed=seed)


def epe(batch, flow) -> float:
  error = np.linalg.norm(np.asarray(flow)[0] - batch["flow"][0], axis=-1)
  return float(np.mean(error, where=batch["mask"][0] > 0))


def run_set(name, seeds, perturb, draws, num_points, start, chosen):
  """{pair: {"seeds": {seed: EPE}, "perturbed": [EPE]}} of one set."""
  out = {}
  for seed in seeds:
    for batch in pairs(name, seed, num_points):
      began = time.perf_counter()
      init = np.asarray(start(batch["pc1"], batch["pc2"]))
      pair = out.setdefault(batch["names"][0], {"seeds": {}, "perturbed": []})
      pair["seeds"][seed] = epe(batch, optimise.optimise_flow(init, batch["pc1"], batch["pc2"],
                                                              chosen)[0])
      if seed == seeds[0] and perturb:
        rng = np.random.default_rng(1)
        for _ in range(draws):
          noisy = init + rng.normal(0.0, perturb, init.shape).astype(np.float32)
          pair["perturbed"].append(epe(batch, optimise.optimise_flow(
            noisy, batch["pc1"], batch["pc2"], chosen)[0]))
      print(f"{name} seed {seed} {batch['names'][0]}: {pair['seeds'][seed]:.4f} "
            f"perturbed {[round(e, 4) for e in pair['perturbed']] if seed == seeds[0] else ''} "
            f"({time.perf_counter() - began:.1f} s)", flush=True)
  return out


def from_json(path) -> tuple[dict, list[int]]:
  """A --json file's results (seeds as integers again) and seeds."""
  data = json.loads(pathlib.Path(path).read_text())
  return ({name: {pair: {"seeds": {int(s): v for s, v in r["seeds"].items()},
                         "perturbed": r["perturbed"]} for pair, r in result.items()}
           for name, result in data["results"].items()}, data["seeds"])


def summary(name, result, seeds):
  """Markdown lines: per pair median / worst / perturbed worst / stable, then per seed means."""
  lines = [f"\n### {name} ({len(result)} pairs, seeds {seeds[0]}-{seeds[-1]})\n",
           "| pair | median | worst (seed) | perturbed worst | stable |", "|---|---|---|---|---|"]
  unstable = 0
  for pair, r in result.items():
    values = np.array(list(r["seeds"].values()))
    median, worst = float(np.median(values)), float(values.max())
    worst_seed = list(r["seeds"])[int(values.argmax())]
    shaken = max(r["perturbed"]) if r["perturbed"] else float("nan")
    ok = stable(worst, median) and (not r["perturbed"] or stable(shaken, median))
    unstable += not ok
    lines.append(f"| {pair} | {median:.4f} | {worst:.4f} ({worst_seed}) | {shaken:.4f} | "
                 f"{'yes' if ok else '**no**'} |")
  means = [np.mean([r["seeds"][s] for r in result.values()]) for s in seeds]
  lines += ["", "| seed | " + " | ".join(map(str, seeds)) + " |",
            "|---" * (len(seeds) + 1) + "|",
            "| mean EPE | " + " | ".join(f"{m:.4f}" for m in means) + " |",
            f"\n{unstable} of {len(result)} pairs outside the bound; set mean over seeds: median "
            f"{np.median(means):.4f}, worst {max(means):.4f}"]
  return lines


def _numbers(result, seeds) -> dict:
  """A set's figures: each seed's mean EPE, their median and worst, the pairs outside the bound."""
  means = [float(np.mean([r["seeds"][s] for r in result.values()])) for s in seeds]
  outside = [pair for pair, r in result.items()
             if not all(stable(v, float(np.median(list(r["seeds"].values()))))
                        for v in [*r["seeds"].values(), *r["perturbed"]])]
  return {"seed_means": means, "median": float(np.median(means)), "worst": max(means),
          "pairs": len(result), "outside_bound": outside}


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--sets", default="lidar,ft3d,kitti")
  parser.add_argument("--seeds", default="0-9", help="e.g. 0-9 or 0,3,5")
  parser.add_argument("--perturb", type=float, default=1e-5, help="m; 0: none")
  parser.add_argument("--draws", type=int, default=2, help="perturbed starts a pair (seed 0)")
  parser.add_argument("--num-points", type=int, default=8192)
  parser.add_argument("--json", default=None)
  args = parser.parse_args()
  seeds = seeds_of(args.seeds)
  model, params, _, _, refine = checkpointing.load_for_inference(None)
  chosen = registry.settings("optimise")
  network = jax.jit(registry.network_for(model, 32, refine)(chosen.start_iters,
                                                            chosen.start_candidates))
  start = lambda pc1, pc2: network(params, pc1, pc2)
  results, lines = {}, []
  for name in args.sets.split(","):
    results[name] = run_set(name, seeds, args.perturb, args.draws, args.num_points, start, chosen)
    if results[name]:
      lines += summary(name, results[name], seeds)
  print("\n".join(lines))
  summary_of = {name: _numbers(r, seeds) for name, r in results.items() if r}
  if args.json:
    machine = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
               "processor": platform.processor(), "jax": jax.__version__}
    pathlib.Path(args.json).write_text(json.dumps(
      {"machine": machine, "seeds": seeds, "perturb": args.perturb, "summary": summary_of,
       "results": results},
      indent=1) + "\n")


if __name__ == "__main__":
  main()
