"""Tiny labelled Argoverse 2 logs in OpenSceneFlow's h5 layout, written from the documented layout
(OpenSceneFlow's dataprocess/extract_av2.py; jaxflow.data.opensf states it), never by jaxflow.

A scene is built in the ego frame of sweep 0 (x forward, y left, z up; ground at z = 0): ground,
static structures, and objects of av2 categories, some moving. `flow` is where each point is at
sweep 1, in sweep 1's ego frame (it includes the ego-motion), as extract_av2.py computes it.
lidar_frame="sensor" stores `lidar` in the up_lidar frame (extract_av2.py since commit 2bd9036),
"ego" in the ego frame (older files); the sensor's extrinsic goes to
AV2_DIR/<log>/calibration/egovehicle_SE3_sensor.feather as AV2 ships it.
"""

import h5py
import numpy as np

# av2 CATEGORY_TO_INDEX: NONE 0, REGULAR_VEHICLE 19, PEDESTRIAN 17, BICYCLIST 4, BUS 7, SIGN 21,
# DOG 10 (the last two are outside the bucketed meta-classes).
OBJECTS = [  # (category, centre xy, size, motion per frame in the ego-0 frame (dx, dy), yaw deg)
  (19, (8, 3), (4.5, 1.9, 1.5), (1.2, 0.1), 1.0),   # a car driving
  (19, (-12, 6), (4.5, 1.9, 1.5), (0.0, 0.0), 0.0),  # a parked car
  (17, (5, -7), (0.6, 0.6, 1.7), (0.1, 0.05), 0.0),  # a pedestrian walking
  (4, (20, -2), (1.8, 0.6, 1.7), (0.5, 0.0), 0.0),   # a cyclist
  (7, (-30, -10), (12, 2.6, 3.2), (0.8, 0.0), 0.5),  # a bus
  (21, (15, 9), (0.3, 0.3, 2.0), (0.0, 0.0), 0.0),   # a sign
  (10, (-3, -4), (0.8, 0.3, 0.6), (0.3, -0.1), 0.0),  # a dog
  (19, (38, 20), (4.5, 1.9, 1.5), (0.9, 0.0), 0.0),  # a far car (beyond the Close box)
]
UP_LIDAR = ((0.99999, 0.001, -0.002, 0.004), (1.35, 0.02, 1.64))  # (qw qx qy qz), t: ego <- sensor


def se3(yaw_deg=0.0, t=(0.0, 0.0, 0.0)):
  a = np.radians(yaw_deg)
  m = np.eye(4)
  m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
  m[:3, 3] = t
  return m


def quat_to_matrix(w, x, y, z):
  n = np.sqrt(w * w + x * x + y * y + z * z)
  w, x, y, z = w / n, x / n, y / n, z / n
  return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def ego_from_sensor():
  m = np.eye(4)
  m[:3, :3] = quat_to_matrix(*UP_LIDAR[0])
  m[:3, 3] = UP_LIDAR[1]
  return m


def apply(m, p):
  return p @ m[:3, :3].T + m[:3, 3]


def scene(rng, ego_motion):
  """One sweep in its ego frame: dict of ego-frame xyz, ground, category, flow (including the
  ego-motion), valid; every array N long."""
  parts = [("ground", rng.uniform(-60, 60, (160, 3)) * [1, 1, 0] + [0, 0, 0.02], 0, se3()),
           ("static", np.c_[rng.uniform(-58, 58, (260, 2)), rng.uniform(0.3, 5, 260)], 0, se3())]
  for cat, (cx, cy), size, (dx, dy), yaw in OBJECTS:
    local = rng.uniform(-0.5, 0.5, (40, 3)) * size + [0, 0, size[2] / 2]
    parts.append(("object", local + [cx, cy, 0.0], cat,
                  se3(0, (cx + dx, cy + dy, 0)) @ se3(yaw) @ se3(0, (-cx, -cy, 0))))
  xyz = np.concatenate([p for _, p, _, _ in parts]).astype(np.float32)
  flow = np.concatenate([apply(ego_motion @ m, p.astype(np.float32)) - p.astype(np.float32)
                         for _, p, _, m in parts]).astype(np.float32)
  return {"xyz": xyz, "flow": flow,
          "ground": np.concatenate([[k == "ground"] * len(p) for k, p, _, _ in parts]),
          "category": np.concatenate([[c] * len(p) for _, p, c, _ in parts]).astype(np.uint8),
          "valid": rng.uniform(size=len(xyz)) > 0.05}


def write_log(path, rng, stamps, lidar_frame="ego", eval_every=None, ego_motion=None):
  """<path> = DIR/<log_id>.h5 with one group per timestamp; every frame but the last labelled.
  eval_every k: frames 0, k, 2k ... get the challenge's `eval_mask` (N x 1: non-ground, |x|, |y|
  <= 50 m). Returns {timestamp: scene} (the ego-frame truth of each labelled frame)."""
  motion = se3(1.5, (1.0, 0.1, 0.0)) if ego_motion is None else ego_motion
  to_sensor = np.linalg.inv(ego_from_sensor())
  truth, pose = {}, se3(30.0, (2000.0, -500.0, 10.0))
  with h5py.File(path, "w") as f:
    for k, stamp in enumerate(stamps):
      s = scene(rng, motion)
      stored = s["xyz"] if lidar_frame == "ego" else apply(to_sensor, s["xyz"]).astype(np.float32)
      g = f.create_group(str(stamp))
      g.create_dataset("lidar", data=stored)
      g.create_dataset("ground_mask", data=s["ground"])
      g.create_dataset("pose", data=pose.astype(np.float32))
      g.create_dataset("lidar_id", data=np.ones(len(stored), np.uint8))
      g.create_dataset("lidar_dt", data=np.zeros(len(stored), np.float32))
      if k < len(stamps) - 1:
        g.create_dataset("flow", data=s["flow"])
        g.create_dataset("flow_is_valid", data=s["valid"])
        g.create_dataset("flow_category_indices", data=s["category"])
        g.create_dataset("flow_instance_id", data=s["category"].astype(np.int16))
        g.create_dataset("ego_motion", data=motion.astype(np.float32))
        if eval_every and k % eval_every == 0:
          mask = ~s["ground"] & (np.abs(s["xyz"][:, :2]) <= 50).all(1)
          g.create_dataset("eval_mask", data=mask[:, None])
        truth[stamp] = s
      pose = pose @ np.linalg.inv(motion)  # ego_motion = inv(pose1) @ pose0
  return truth


def write_calibration(av2_dir, log_id):
  """AV2_DIR/<log_id>/calibration/egovehicle_SE3_sensor.feather (up_lidar and down_lidar rows)."""
  import pyarrow  # pylint: disable=import-outside-toplevel
  import pyarrow.feather  # pylint: disable=import-outside-toplevel

  folder = av2_dir / log_id / "calibration"
  folder.mkdir(parents=True, exist_ok=True)
  (qw, qx, qy, qz), (tx, ty, tz) = UP_LIDAR
  table = {"sensor_name": ["down_lidar", "up_lidar"], "qw": [0.0, qw], "qx": [1.0, qx],
           "qy": [0.0, qy], "qz": [0.0, qz], "tx_m": [1.3, tx], "ty_m": [0.0, ty],
           "tz_m": [1.5, tz]}
  pyarrow.feather.write_feather(pyarrow.table(table), str(folder / "egovehicle_SE3_sensor.feather"))


LOG_IDS = ("0c6e62d7-bdfa-3061-8d3d-03b13aa21f68", "7fab2350-7eaf-3b7e-a39d-6937a4c1bede")
STAMPS = ((315966265659927216, 315966265759927216, 315966265859927216, 315966265959927216),
          (315968867659956000, 315968867759956000, 315968867859956000))


def write_split(root, lidar_frame="ego", eval_every=None, seed=0):
  """ROOT/val/<log>.h5 for both logs (3 + 2 labelled pairs); ROOT/av2 holds the calibration.
  Returns {(log_id, timestamp): scene}."""
  rng = np.random.default_rng(seed)
  (root / "val").mkdir(parents=True, exist_ok=True)
  truth = {}
  for log_id, stamps in zip(LOG_IDS, STAMPS):
    for stamp, s in write_log(root / "val" / f"{log_id}.h5", rng, stamps, lidar_frame,
                              eval_every).items():
      truth[log_id, stamp] = s
    write_calibration(root / "av2", log_id)
  return truth
