r"""Raw sweep vs the loader's cut on the shared KITTI frame: EPE, points and times.

    PYTHONPATH=. python benchmarks/lidar_raw_sweep.py [FRAME_FOLDER]   # default: the shared 000002

The frame's pc1.npy / pc2.npy hold the whole frame, ground included, rows corresponding (flow = pc2
- pc1). "cut": predict on the pair the KITTI loader gives (ground y < -1.4 and z >= 35 removed).
"raw": predict on the whole frame as it is. "raw --lidar": predict with the ground plane fit and the
35 m range cut (camera frame: up = y). EPE of each on the points the loader keeps (the same points
in the three rows), and of --lidar on the points it kept itself and on those it filled with the
ego-motion flow. The shipped checkpoint, default settings (8192 points, 32 iterations); every time
is after a warm-up call of the same shapes, one process.
"""

import pathlib
import sys
import time

import numpy as np

from jaxflow import inference
from jaxflow.data.readers import kitti_keep
from jaxflow.geometry import rigid
from jaxflow.lidar import ground

FRAME = pathlib.Path(__file__).resolve().parents[2] / "shared/data/KITTI_processed_occ_final/000002"


def main(frame=FRAME, seeds=3):
  frame = pathlib.Path(frame)
  raw1, raw2 = np.load(frame / "pc1.npy"), np.load(frame / "pc2.npy")
  gt = raw2 - raw1
  loader = kitti_keep(raw1, raw2)
  predictor = inference.load_predictor(method="network")
  epe = lambda f, m: float(np.linalg.norm(f[m] - gt[m], axis=1).mean())
  def cut(s):
    flow = np.zeros_like(gt)
    flow[loader] = predictor(raw1[loader], raw2[loader], seed=s)
    return flow

  cases = {"cut (loader)": cut, "raw as is": lambda s: predictor(raw1, raw2, seed=s),
           "raw --lidar": lambda s: predictor(raw1, raw2, seed=s, lidar=True, up="y")}
  for fn in cases.values():
    fn(0)  # compile
  results = {k: ([], []) for k in cases}
  for s in range(seeds):  # interleaved, so load on the machine hits the cases alike
    for name, fn in cases.items():
      start = time.perf_counter()
      flow = fn(s)
      results[name][1].append(time.perf_counter() - start)
      results[name][0].append(epe(flow, loader))
  start = time.perf_counter()
  surface, ground1 = ground.find_ground(raw1, "y")
  keep1 = ~ground1 & ground.within_range(raw1, "y", 35.0)
  t_ground = time.perf_counter() - start
  prediction = predictor.predict(raw1, raw2, lidar=True, up="y")
  lidar, info = prediction.flow, prediction.sweep
  start = time.perf_counter()
  rigid.fit_static_motion(raw1[keep1], lidar[keep1])
  t_rigid = time.perf_counter() - start
  rule = raw1[:, 1] < -1.4
  print(f"frame {frame}: {len(raw1)} points; seeds 0..{seeds - 1} (sampling to 8192)")
  print(f"ground of pc1 (a plane per cell): the sensor {surface.sensor_height:.3f} m above it; "
        f"removed {ground1.sum()} (y < -1.4 rule: {rule.sum()}; "
        f"both {(ground1 & rule).sum()}, plane only {(ground1 & ~rule).sum()}, rule only "
        f"{(rule & ~ground1).sum()}); fit {t_ground:.2f} s, rigid fit {t_rigid:.2f} s")
  print(info.note())
  points = {"cut (loader)": int(loader.sum()), "raw as is": len(raw1), "raw --lidar": info.kept[0]}
  print("| input | EPE on the loader's points (m), mean of seeds | per seed | points to the model "
        "| time (s), median |")
  print("|---|---|---|---|---|")
  for name, (epes, times) in results.items():
    print(f"| {name} | {np.mean(epes):.4f} | {', '.join(f'{e:.4f}' for e in epes)} | "
          f"{points[name]} | {np.median(times):.2f} |")
  cut_epe = np.mean(results["cut (loader)"][0])
  print(f"raw --lidar / cut: {np.mean(results['raw --lidar'][0]) / cut_epe:.3f} (goal <= 1.1); "
        f"raw as is / cut: {np.mean(results['raw as is'][0]) / cut_epe:.3f}")
  print(f"--lidar (seed 0) EPE on its own kept points {epe(lidar, keep1):.4f} ({keep1.sum()}), on "
        f"the ground {epe(lidar, ground1):.4f} ({ground1.sum()}), beyond 35 m "
        f"{epe(lidar, ~keep1 & ~ground1):.4f} ({(~keep1 & ~ground1).sum()}); the ego-motion flow "
        f"alone on the loader's points: {epe(info.motion.flow(raw1), loader):.4f}")


if __name__ == "__main__":
  main(*sys.argv[1:])
