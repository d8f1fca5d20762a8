r"""Issue 69: optimise's changes since 9d35694, each switched by a setting, on the pairs they were
not chosen on. One line of JSON a pair, seed and variant appended to --out:

    python benchmarks/optimise_changes.py --set report --seeds 0-4 --variants head,no_world \
      --out results.jsonl [--starts DIR: the network's starts, kept]
    PYTHONPATH=/tmp/old_9d35694 python benchmarks/optimise_changes.py --code old ...   # 9d35694

Sets: `choose` and `report` (benchmarks/methods.FT3D_CHOOSE / FT3D_REPORT, the 21 shared FT3D
pairs' halves), `av2` (the shared labelled Argoverse 2 pair cut to NSFP's layout:
methods.av2_cut). 8192 points a cloud sampled with np.random.default_rng((seed, i)), i the pair's
index in its split (evaluate.py's sampling). The network's start (8 iterations, 64 candidates,
optimise's) is computed once a pair and seed and kept under --starts, so every variant refines the
same start. Variants: `head` (the defaults), `no_guard`, `draws_each`, `refit_always`, `old`
(these and world=None switched back: 9d35694's stages) and the stage prefixes `s1` (descent), `s2`
(+ rigid clusters), `s3` (+ polish), `s4` (+ bodies: world=None); a variant naming a field the
code lacks (9d35694's) leaves it. Where the code can (optimise_flow's `resume`), a variant resumes
after the stages it shares with one run before it (VARIANTS), and each row holds the EPE after
every stage run (`stages`; world=None is a run's "rigid bodies"). Results: benchmarks/METHODS.md.
"""

import argparse
import dataclasses
import importlib.util
import inspect
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

# benchmarks/methods.py of this tree whatever jaxflow PYTHONPATH gives (9d35694's worktree)
_spec = importlib.util.spec_from_file_location("methods_bench",
                                               pathlib.Path(__file__).with_name("methods.py"))
methods_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(methods_bench)

# name: (changes to the defaults, (a variant run before, the stage this one resumes after) or None)
VARIANTS = {
  "head": ({}, None),
  "no_guard": ({"guard": None}, ("head", "descent")),
  "draws_each": ({"bodies.draws": "each"}, ("head", "polish")),
  "refit_always": ({"bodies.world_refit": "always"}, ("head", "polish")),
  "old": ({"world": None, "guard": None, "bodies.draws": "each", "bodies.world_refit": "always"},
          ("no_guard", "polish")),
  "s1": ({"rigid_steps": 0, "polish.steps": 0, "bodies": None, "world": None}, None),
  "s2": ({"polish.steps": 0, "bodies": None, "world": None}, None),
  "s3": ({"bodies": None, "world": None}, None),
  "s4": ({"world": None}, None),
}


def variant(chosen, changes: dict):
  """`chosen` with `changes` ("field" or "block.field": value) where its fields exist."""
  for key, value in changes.items():
    block, _, field = key.rpartition(".")
    fields = {f.name for f in dataclasses.fields(chosen)}
    if not block:
      if key in fields:
        chosen = dataclasses.replace(chosen, **{key: value})
      continue
    inner = getattr(chosen, block)
    if inner is None or field not in {f.name for f in dataclasses.fields(inner)}:
      continue
    chosen = dataclasses.replace(chosen, **{block: dataclasses.replace(inner, **{field: value})})
  return chosen


def pairs(name: str):
  """(pair name, index in its split, pc1, pc2, flow, mask) of a set."""
  from jaxflow.data import open_dataset  # pylint: disable=import-outside-toplevel
  if name == "av2":
    pc1, pc2, flow, mask = methods_bench.av2_cut()
    yield "av2_labelled_nsfp", 0, pc1, pc2, flow, mask
    return
  names = {"choose": methods_bench.FT3D_CHOOSE, "report": methods_bench.FT3D_REPORT}[name]
  for split in ("train_all", "val"):
    ds = open_dataset(f"ft3d:{methods_bench.DATA / 'FlyingThings3D_subset_processed_35m'}", split)
    for i in range(len(ds)):
      pair = ds[i]
      short = pathlib.Path(pair.name).name
      if short in names:
        yield short, i, pair.pc1, pair.pc2, pair.flow, pair.mask


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--set", required=True, choices=("choose", "report", "av2"))
  parser.add_argument("--seeds", default="0-4")
  parser.add_argument("--variants", default="head")
  parser.add_argument("--code", default="head", help="a label for the code run (head, old)")
  parser.add_argument("--out", required=True)
  parser.add_argument("--starts",
                      default=str(pathlib.Path(tempfile.gettempdir()) / "jaxflow-optimise-starts"))
  args = parser.parse_args()
  import jax  # pylint: disable=import-outside-toplevel
  from jaxflow.data.sampling import sample_indices  # pylint: disable=import-outside-toplevel
  from jaxflow.methods import optimise, registry  # pylint: disable=import-outside-toplevel
  from jaxflow.network import checkpointing  # pylint: disable=import-outside-toplevel
  lo, _, hi = args.seeds.partition("-")
  seeds = range(int(lo), int(hi or lo) + 1)
  names = args.variants.split(",")
  for v in names:
    if v not in VARIANTS:
      sys.exit(f"error: --variants: unknown {v!r} (one of {', '.join(VARIANTS)})")
  defaults = registry.settings("optimise")
  starts = pathlib.Path(args.starts)
  starts.mkdir(parents=True, exist_ok=True)
  network = None
  chosen_pairs = list(pairs(args.set))
  for seed in seeds:  # every pair at a seed before the next seed
    for pair_name, index, pc1_all, pc2_all, flow_all, mask_all in chosen_pairs:
      rng = np.random.default_rng((seed, index))
      i1, _ = sample_indices(len(pc1_all), 8192, rng)
      i2, _ = sample_indices(len(pc2_all), 8192, rng)
      pc1, pc2 = pc1_all[i1][None].astype(np.float32), pc2_all[i2][None].astype(np.float32)
      flow, mask = flow_all[i1], mask_all[i1] > 0
      cached = starts / f"{args.code}_{pair_name}_{seed}.npy"
      if cached.exists():
        start = np.load(cached)
      else:
        if network is None:
          model, params, _, _, refine = checkpointing.load_for_inference(None)
          network = jax.jit(registry.network_for(model, 32, refine)(defaults.start_iters,
                                                                    defaults.start_candidates))
        start = np.asarray(network(params, pc1, pc2))
        np.save(cached, start)
      runs = {}  # variant: its flows by stage
      for v in names:
        changes, resume = VARIANTS[v]
        chosen = variant(defaults, changes)
        flows, extra = {}, {}
        if "flows" in inspect.signature(optimise.optimise_flow).parameters:
          extra["flows"] = flows
          if resume is not None and resume[0] in runs:
            extra["resume"] = (resume[1], runs[resume[0]][resume[1]])
        began = time.perf_counter()
        out = np.asarray(optimise.optimise_flow(start, pc1, pc2, chosen, **extra)[0])[0]
        seconds = time.perf_counter() - began
        before = runs[resume[0]] if "resume" in extra else {}
        kept = optimise.STAGES[:optimise.STAGES.index(resume[1]) + 1] if before else ()
        runs[v] = {**{k: f for k, f in before.items() if k in kept}, **flows}
        error = lambda f: float(np.linalg.norm(np.asarray(f)[0] - flow, axis=1)[mask].mean())
        row = dict(code=args.code, set=args.set, variant=v, pair=pair_name, seed=seed,
                   epe=error(out[None]), seconds=round(seconds, 2),
                   stages={k: error(f) for k, f in runs[v].items()})
        print(json.dumps(row), flush=True)
        with open(args.out, "a", encoding="utf-8") as f:
          f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
  main()
