r"""Raw sweep vs the loader's cut on the shared KITTI frame (issue 21): EPE, points and times.

    PYTHONPATH=. python benchmarks/lidar_raw_sweep.py [../shared/data/KITTI_processed_occ_final/000002]

The frame's pc1.npy / pc2.npy hold the whole frame, ground included, rows corresponding (flow = pc2 -
pc1). "cut": predict on the pair the KITTI loader gives (ground y < -1.4 and z >= 35 removed).
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

from jaxflow import ground, predict
from jaxflow.data.readers import kitti_keep

FRAME = pathlib.Path(__file__).resolve().parents[2] / "shared/data/KITTI_processed_occ_final/000002"


def main(frame=FRAME):
  frame = pathlib.Path(frame)
  raw1, raw2 = np.load(frame / "pc1.npy"), np.load(frame / "pc2.npy")
  gt = raw2 - raw1
  loader = kitti_keep(raw1, raw2)
  predictor = predict.load_predictor()
  epe = lambda f, m: float(np.linalg.norm(f[m] - gt[m], axis=1).mean())

  def timed(fn):
    fn()  # compile
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start

  cut, t_cut = timed(lambda: predictor(raw1[loader], raw2[loader]))
  raw, t_raw = timed(lambda: predictor(raw1, raw2))
  (lidar, info), t_lidar = timed(lambda: predictor.lidar(raw1, raw2, up="y"))
  keep1, ground1, plane = ground.lidar_keep(raw1, "y")
  rule = raw1[:, 1] < -1.4
  print(f"frame {frame}: {len(raw1)} points")
  print(f"ground plane of pc1: normal {np.round(plane.normal, 4)}, height {-plane.offset:.3f} m, "
        f"tilt {plane.tilt_deg:.2f} deg; removed {ground1.sum()} (y < -1.4 rule: {rule.sum()}, both "
        f"{(ground1 & rule).sum()}, plane only {(ground1 & ~rule).sum()}, rule only "
        f"{(rule & ~ground1).sum()})")
  print(info.note())
  cut_epe = float(np.linalg.norm(cut - gt[loader], axis=1).mean())
  rows = [("cut (loader)", cut_epe, int(loader.sum()), t_cut),
          ("raw as is", epe(raw, loader), len(raw1), t_raw),
          ("raw --lidar", epe(lidar, loader), info.kept[0], t_lidar)]
  print("| input | EPE on the loader's points (m) | points to the model | time (s) |")
  print("|---|---|---|---|")
  for name, e, n, t in rows:
    print(f"| {name} | {e:.4f} | {n} | {t:.2f} |")
  print(f"raw --lidar / cut: {rows[2][1] / cut_epe:.3f} (goal <= 1.1)")
  print(f"--lidar EPE on its own kept points {epe(lidar, keep1):.4f} ({keep1.sum()}), on the "
        f"ground {epe(lidar, ground1):.4f} ({ground1.sum()}), beyond 35 m "
        f"{epe(lidar, ~keep1 & ~ground1):.4f} ({(~keep1 & ~ground1).sum()}); ego-motion fill of "
        f"the loader's points instead of the model: {epe(info.motion.flow(raw1), loader):.4f}")


if __name__ == "__main__":
  main(*sys.argv[1:])
