r"""Pairs per second of BatchLoader (batch 2, 8192 points) and synthetic-vs-real statistics.

    python benchmarks/data_throughput.py                 # throughput table (markdown)
    python benchmarks/data_throughput.py --stats         # synthetic vs real FT3D / KITTI statistics

Sources: synthetic_things, synthetic_lidar, h5 (converted here from synthetic_things) and ft3d from
../shared/data when present. Each row is the best of --repeats runs (the CPU may be shared).
"""

import argparse
import pathlib
import tempfile
import time
import warnings

import numpy as np

from jaxflow.data import BatchLoader, open_dataset, sample_pair
from jaxflow.data.convert import convert

SHARED = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pairs_per_second(dataset, steps: int, prefetch: int, workers: int = 0, batch_size: int = 2,
                     num_points: int = 8192) -> tuple[float, float]:
  """(pairs per second of wall time, CPU milliseconds of this process per pair)."""
  loader = BatchLoader(dataset, batch_size, num_points, seed=0, prefetch=prefetch, workers=workers)
  it = loader.iterate()
  for _ in range(max(1, workers)):  # warm-up: threads or processes start, first files open
    next(it)
  start, cpu = time.perf_counter(), time.process_time()
  for _ in range(steps):
    next(it)
  elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
  it.close()
  pairs = steps * batch_size
  return pairs / elapsed, 1000 * cpu / pairs


def throughput(args):
  sources = [("synthetic_things", "synthetic_things:100000"),
             ("synthetic_lidar", "synthetic_lidar:100000")]
  with tempfile.TemporaryDirectory() as tmp:
    h5 = pathlib.Path(tmp) / "things.h5"
    convert("synthetic_things:200", "train", h5, progress=False)
    sources.append(("h5 (200 synthetic_things)", f"h5:{h5}"))
    ft3d = SHARED / "FlyingThings3D_subset_processed_35m"
    if ft3d.is_dir():
      sources.append(("ft3d (3 real pairs, page-cached)", f"ft3d:{ft3d}"))
    print(f"| source | prefetch 0 (synchronous) | CPU per pair, synchronous | prefetch {args.prefetch} "
          f"(threads, default) | workers {args.workers} (processes) |")
    print("|---|---|---|---|---|")
    for label, spec in sources:
      dataset = open_dataset(spec, "train")
      runs = {(p, w): [pairs_per_second(dataset, args.steps, p, w) for _ in range(args.repeats)]
              for p, w in ((0, 0), (args.prefetch, 0), (args.prefetch, args.workers))}
      best = {key: max(r[0] for r in rows) for key, rows in runs.items()}
      cpu = min(r[1] for r in runs[(0, 0)])
      print(f"| {label} | {best[(0, 0)]:.0f} pairs/s | {cpu:.1f} ms | {best[(args.prefetch, 0)]:.0f} pairs/s "
            f"| {best[(args.prefetch, args.workers)]:.0f} pairs/s |", flush=True)


def pair_stats(pair, rng, spatial) -> dict:
  flow = np.linalg.norm(pair.flow, axis=1)
  stats = {"points": len(pair.pc1), "mean_flow": flow.mean(), "std_flow": flow.std(),
           "z": np.percentile(pair.pc1[:, 2], [5, 50, 95]), "x": np.percentile(pair.pc1[:, 0], [5, 95]),
           "y": np.percentile(pair.pc1[:, 1], [5, 95])}
  if spatial is not None:
    sampled, _ = sample_pair(pair, 8192, rng)
    stats["spacing"] = np.median(spatial.cKDTree(sampled.pc1).query(sampled.pc1, k=2)[0][:, 1])
  return stats


def statistics(args):
  try:
    from scipy import spatial  # pylint: disable=import-outside-toplevel
  except ImportError:
    spatial = None
  rows = []
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    for label, spec, split, count in [
        ("real FT3D (train samples)", f"ft3d:{SHARED / 'FlyingThings3D_subset_processed_35m'}",
         "train_all", None),
        ("synthetic_things", f"synthetic_things:{args.pairs}", "val", None),
        ("real KITTI 000002", f"kitti:{SHARED / 'KITTI_processed_occ_final'}", None, None),
        ("synthetic_lidar", f"synthetic_lidar:{args.pairs}", "val", None)]:
      try:
        dataset = open_dataset(spec, split)
      except Exception as e:  # pylint: disable=broad-except
        print(f"skipping {label}: {e}")
        continue
      stats = [pair_stats(dataset[i], np.random.default_rng(i), spatial)
               for i in range(count or len(dataset))]
      rows.append((label, stats))
  print("| data | pairs | points/pair after cuts | per-pair mean abs flow (m): mean, p10-p90 "
        "[min, max] | std of abs flow | depth z (m) p5 / p50 / p95 | x p5..p95 | y p5..p95 | "
        "NN spacing at 8192 (m) |")
  print("|---|---|---|---|---|---|---|---|---|")
  for label, stats in rows:
    mean = lambda k: np.mean([s[k] for s in stats], axis=0)
    mf = [s["mean_flow"] for s in stats]
    spacing = f"{mean('spacing'):.3f}" if "spacing" in stats[0] else "-"
    z, x, y = mean("z"), mean("x"), mean("y")
    p10, p90 = np.percentile(mf, [10, 90])
    print(f"| {label} | {len(stats)} | {mean('points'):.0f} | {np.mean(mf):.2f}, {p10:.2f}-{p90:.2f} "
          f"[{min(mf):.2f}, {max(mf):.2f}] | "
          f"{mean('std_flow'):.2f} | {z[0]:.1f} / {z[1]:.1f} / {z[2]:.1f} | {x[0]:.1f}..{x[1]:.1f} | "
          f"{y[0]:.1f}..{y[1]:.1f} | {spacing} |")


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--stats", action="store_true", help="print synthetic-vs-real statistics instead")
  parser.add_argument("--steps", type=int, default=50, help="batches timed per run")
  parser.add_argument("--repeats", type=int, default=3, help="runs per row; the best is reported")
  parser.add_argument("--prefetch", type=int, default=2)
  parser.add_argument("--workers", type=int, default=2, help="processes for the third column")
  parser.add_argument("--pairs", type=int, default=100, help="synthetic pairs for --stats")
  args = parser.parse_args()
  statistics(args) if args.stats else throughput(args)


if __name__ == "__main__":
  main()
