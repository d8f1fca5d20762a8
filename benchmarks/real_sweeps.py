r"""`--lidar`'s steps on real sweeps and on the generator, own code and the field's libraries side by
side: the ground, the ego-motion, the flow. Prints markdown tables, writes JSON.

    PYTHONPATH=. python benchmarks/real_sweeps.py [--pairs 6] [--split test] [--json OUT.json]

Samples: the real sweeps of ../shared/data/real_sweeps by name (the labelled Argoverse 2 pair with
pc1 moved by a known ego-motion, 2 deg yaw and (1.0, 0.1, 0.02) m, as ../shared/tools/
real_sweeps_check.py does, and the same pair backwards, its labels derived from the forward
ones (`backwards`); the unlabelled AV2 pair; KITTI's Velodyne scan split into two disjoint
halves, the second moved by the same motion) and `--pairs` pairs of the generator's split in three
forms: as generated (a roof sensor at the origin), a dense city seen from Argoverse 2's ego frame
(origin 0.33 m above the road, two stacked 32-beam sensors), and with the ground removed.
- ground: share of pc1 taken as ground, and precision / recall where the truth is known (the
  generator), for jaxflow.lidar.ground.fit_surface and Patchwork++ (pypatchworkpp, if installed) at
  its default sensor height (1.73 m) and at the height jaxflow's fit finds;
- ego-motion: translation (cm) and rotation (deg) error against the known motion, for
jaxflow.lidar.ego
  (GICP from several starts, the residual's choice), small_gicp's GICP and VGICP at their untuned
  defaults (0.25 m voxels, 10 neighbours, 1 m matches) and KISS-ICP (kiss-icp, if installed; two
  frames, its default config);
- flow (`jaxflow.lidar.sweep.raw_sweep_flow`, what `predict --lidar` runs): FD / FS / BS and
three-way
  (av2's classes: dynamic = |flow - ego flow| >= 0.05 m; labelled points with |x|, |y| <= 50 m,
  the generator's ground left out; three-way = the mean of the three, per pair, then over pairs),
  the unlabelled pair's median nearest-neighbour distance of pc1 + flow to pc2 (zero flow's beside
  it), KITTI's mean error; seconds of the pipeline in this process.
"""

import argparse
import importlib.util
import json
import warnings
import pathlib
import platform
import time

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from jaxflow.data import synthetic_sweep as ss
from jaxflow.evaluation import metrics
from jaxflow.geometry import groups, rigid
from jaxflow.lidar import ego, ground, sweep

REAL = pathlib.Path(__file__).resolve().parents[2] / "shared/data/real_sweeps"
MOTION = rigid.Motion(Rotation.from_euler("z", 2.0, degrees=True).as_matrix(),
                      np.array([1.0, 0.1, 0.02]))
FORMS = {"generated": ss.FORMS["generated"],
         "city (dense, AV2 ego frame, stacked)": ss.FORMS["city"],
         "ground removed": ss.FORMS["noground"]}


def backwards(raw1, pc2, truth, valid, category):
  """The labelled pair taken backwards (pc2 -> pc1), its labels derived from the forward ones:
  each forward mover (0.5 m cells of its dynamic points, 20 or more) moves rigidly (a Kabsch fit
  of its labelled flow), and pc2's points within 0.3 m of its moved points get that motion's
  inverse; the rest the ego-motion's inverse. A pc2 point's class: that of pc1's nearest point
  moved by its labelled flow, within 0.3 m (background beyond)."""
  dynamic = valid & (np.linalg.norm(truth - MOTION.flow(raw1), axis=1) >= 0.05)
  inverse = MOTION.inverse()
  flow = inverse.flow(pc2)
  tree = cKDTree(pc2)
  for _, idx in groups.cell_components(raw1, dynamic, 0.5, bridge=True).members():
    idx = idx[dynamic[idx]]
    if len(idx) >= 20:
      mover = rigid.kabsch(raw1[idx], raw1[idx] + truth[idx])
      near = np.unique(np.concatenate(tree.query_ball_point(mover.apply(raw1[idx]), 0.3)))
      near = near.astype(np.int64)
      flow[near] = mover.inverse().flow(pc2[near])
  d, j = cKDTree((raw1 + truth)[valid]).query(pc2, distance_upper_bound=0.3)
  seen = np.isfinite(d)
  foreground = np.zeros(len(pc2), bool)
  foreground[seen] = category[valid][j[seen]] >= 0
  return dict(motion=inverse, flow=flow, ego_flow=inverse.flow(pc2), foreground=foreground,
              mask=np.all(np.abs(pc2[:, :2]) <= 50, axis=1))


def samples(pairs: int, split: str):
  """(name, pc1, pc2, truth dict) of every sample: motion, and flow / classes / ground if known."""
  if REAL.is_dir():
    z = np.load(REAL / "av2_pair_flow_labelled.npz")
    pc1 = z["pc1"].astype(np.float64)
    raw1 = (pc1 - MOTION.translation) @ MOTION.rotation
    truth = np.nan_to_num(pc1 + z["flow"]) - raw1
    box = z["flow_valid"] & np.all(np.abs(raw1[:, :2]) <= 50, axis=1)
    yield "AV2 labelled (moved)", raw1, z["pc2"].astype(np.float64), dict(
      motion=MOTION, flow=truth, ego_flow=MOTION.flow(raw1), foreground=z["category"] >= 0,
      mask=box)
    pc2 = z["pc2"].astype(np.float64)
    yield "AV2 labelled, backwards", pc2, raw1, backwards(raw1, pc2, truth, z["flow_valid"],
                                                          z["category"])
    yield "AV2 unlabelled", *(np.load(REAL / f"av2_pair_unlabelled_pc{i}.npy")[:, :3].astype(
      np.float64) for i in (1, 2)), {}
    k = np.fromfile(REAL / "kitti_velodyne_000002.bin", np.float32).reshape(-1, 4)[:, :3]
    half = np.random.default_rng(0).random(len(k)) < 0.5
    k1 = k[half].astype(np.float64)
    yield "KITTI scan (two halves)", k1, MOTION.apply(k[~half]), dict(motion=MOTION,
                                                                       flow=MOTION.flow(k1))
  for form, options in FORMS.items():
    for i in range(pairs):
      s = ss.sweep_pair(split, i, options)
      yield f"{form} {split} {i}", s.pc1.astype(np.float64), s.pc2.astype(np.float64), dict(
        motion=rigid.Motion(s.ego_rotation, s.ego_translation), flow=s.flow,
        ego_flow=s.ego_flow, foreground=s.foreground, mask=s.eval_mask, ground=s.ground)


def patchwork(points, height):
  import pypatchworkpp  # pylint: disable=import-outside-toplevel
  params = pypatchworkpp.Parameters()
  params.sensor_height, params.verbose = float(height), False
  pp = pypatchworkpp.patchworkpp(params)
  pp.estimateGround(np.c_[points, np.zeros(len(points))])
  out = np.zeros(len(points), bool)
  out[np.asarray(pp.getGroundIndices(), int)] = True
  return out


def ground_rows(pc1, truth):
  """{method: (share, precision, recall, seconds)}."""
  rows = {}
  start = time.perf_counter()
  try:
    surface = ground.fit_surface(pc1, "z")
    own, height = surface.ground(pc1), surface.sensor_height
  except Exception:  # pylint: disable=broad-except  (no plane: no ground)
    own, height = np.zeros(len(pc1), bool), 1.73
  rows["jaxflow.lidar.ground"] = own, time.perf_counter() - start
  try:
    for name, h in (("Patchwork++ (1.73 m)", 1.73), ("Patchwork++ (jaxflow's height)", height)):
      start = time.perf_counter()
      rows[name] = patchwork(pc1, h), time.perf_counter() - start
  except ImportError:
    pass
  out = {}
  for name, (mask, seconds) in rows.items():
    p = r = float("nan")
    if "ground" in truth:
      p = float(truth["ground"][mask].mean()) if mask.any() else float("nan")
      r = float(mask[truth["ground"]].mean()) if truth["ground"].any() else float("nan")
    out[name] = (float(mask.mean()), p, r, seconds)
  return out


def kiss(pc1, pc2):
  from kiss_icp.config import load_config  # pylint: disable=import-outside-toplevel
  from kiss_icp.kiss_icp import KissICP  # pylint: disable=import-outside-toplevel
  config = load_config(None)
  config.data.deskew = False
  odometry = KissICP(config)
  odometry.register_frame(pc1, np.zeros(0))
  odometry.register_frame(pc2, np.zeros(0))
  t = np.linalg.inv(odometry.last_pose)  # frame-1 coordinates -> frame-2 coordinates
  return rigid.Motion(t[:3, :3], t[:3, 3])


def small_gicp_default(pc1, pc2, kind):
  import small_gicp  # pylint: disable=import-outside-toplevel
  t = small_gicp.align(pc2, pc1, registration_type=kind, num_threads=ego.GICP_THREADS)
  return rigid.Motion(t.T_target_source[:3, :3], t.T_target_source[:3, 3])


def ego_rows(pc1, pc2, truth):
  """{method: (translation error cm, rotation error deg, seconds)}."""
  methods = {"jaxflow.lidar.ego": lambda: ego.estimate(pc1, pc2).motion,
             "small_gicp GICP (defaults)": lambda: small_gicp_default(pc1, pc2, "GICP"),
             "small_gicp VGICP (defaults)": lambda: small_gicp_default(pc1, pc2, "VGICP")}
  if importlib.util.find_spec("kiss_icp"):  # optional: measured where installed
    methods["KISS-ICP (two frames)"] = lambda: kiss(pc1, pc2)
  out = {}
  for name, fn in methods.items():
    start = time.perf_counter()
    m = fn()
    seconds = time.perf_counter() - start
    if "motion" not in truth:
      out[name] = (float("nan"), float("nan"), seconds)
      continue
    d = m.rotation @ truth["motion"].rotation.T
    angle = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1)))
    out[name] = (100 * float(np.linalg.norm(m.translation - truth["motion"].translation)),
                 float(angle), seconds)
  return out


def flow_row(pc1, pc2, truth):
  start = time.perf_counter()
  flow, _ = sweep.raw_sweep_flow(None, pc1, pc2)
  row = {"seconds": time.perf_counter() - start}
  if "foreground" in truth:
    row.update(metrics.three_way_epe(flow, truth["flow"], truth["ego_flow"], truth["foreground"],
                                     truth["mask"]))
  elif "flow" in truth:
    row["mean error"] = float(np.linalg.norm(flow - truth["flow"], axis=1).mean())
  else:
    tree = cKDTree(pc2)
    row["median NN"] = float(np.median(tree.query(pc1 + flow)[0]))
    row["median NN, zero flow"] = float(np.median(tree.query(pc1)[0]))
  return row


def fmt(x, digits=4):
  return "-" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{x:.{digits}f}"


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--pairs", type=int, default=6)
  parser.add_argument("--split", default="test")
  parser.add_argument("--json", default=None)
  args = parser.parse_args()
  warnings.filterwarnings("ignore", "Mean of empty slice")  # a sample without a class: "-"
  results = []
  for name, pc1, pc2, truth in samples(args.pairs, args.split):
    results.append(dict(name=name, ground=ground_rows(pc1, truth), ego=ego_rows(pc1, pc2, truth),
                        flow=flow_row(pc1, pc2, truth)))
    print(name, json.dumps(results[-1]["flow"]), flush=True)
  real = [r for r in results if not any(r["name"].startswith(f) for f in FORMS)]
  # (label, its results): each real sample alone, then each generator form's pairs together
  labelled = [(r["name"], [r]) for r in real] + [
    (f, [r for r in results if r["name"].startswith(f)]) for f in FORMS]

  def table(title, key, cell):
    """One markdown table: a column per method of results[i][key], cell(values of the rows)."""
    print(f"\n## {title}\n")
    names = list(results[0][key])
    print("| sample | pairs | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for label, rows in labelled:
      cells = [cell(np.array([r[key][n] for r in rows], float)) for n in names]
      print(f"| {label} | {len(rows)} | " + " | ".join(cells) + " |")

  def ground_cell(v):
    v = np.nanmean(v, axis=0)
    return (f"{v[0]:.3f}" + ("" if np.isnan(v[1]) else f" ({v[1]:.3f} / {v[2]:.3f})")
            + f", {v[3]:.2f} s")

  def ego_cell(v):
    if np.isnan(v[:, 0]).all():
      return f"-, {v[:, 2].mean():.2f} s"
    if len(v) == 1:
      return f"{v[0, 0]:.1f} / {v[0, 1]:.3f}, {v[0, 2]:.2f} s"
    return (f"{v[:, 0].mean():.1f} ({v[:, 0].max():.1f}) / {v[:, 1].mean():.3f} "
            f"({v[:, 1].max():.3f}), {v[:, 2].mean():.2f} s")

  table("Ground: share of pc1 taken as ground (precision / recall where known), seconds",
        "ground", ground_cell)
  table("Ego-motion: error, cm / deg (mean, max over pairs), seconds", "ego", ego_cell)
  print("\n## Flow (`predict --lidar`'s pipeline)\n")
  print("| sample | pairs | FD | FS | BS | three-way | other | s / pair |")
  print("|---|---|---|---|---|---|---|---|")
  for label, rows in labelled:
    f = [r["flow"] for r in rows]
    mean = lambda k: float(np.nanmean([x.get(k, np.nan) for x in f]))
    other = ""
    if "mean error" in f[0]:
      other = f"mean error {mean('mean error'):.4f} m"
    if "median NN" in f[0]:
      other = f"median NN {mean('median NN'):.4f} m (zero flow {mean('median NN, zero flow'):.4f})"
    print(f"| {label} | {len(rows)} | {fmt(mean('fd'))} | {fmt(mean('fs'))} | {fmt(mean('bs'))} "
          f"| {fmt(mean('mean'))} | {other} | {mean('seconds'):.1f} |")
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(dict(
      machine=f"{platform.machine()} {platform.processor()}, {platform.system()}", split=args.split,
      pairs=args.pairs, results=results), indent=1))


if __name__ == "__main__":
  main()
