"""jaxflow.geometry.frames: the models' frame and the rotations between frames; each reader's up axis
(`Dataset.up`) against the frame its clouds are really in.

Handedness: a scene turning left (counter-clockwise seen from above, a right-handed rotation about
up) is written in each reader's stored layout from the published definition of that layout, read
back, and must still turn left about the up axis jaxflow states for that reader; and predict --up z
hands the network a proper rotation of the sweep (y up) and returns the flow in the sweep's frame.
"""

import warnings

import h5py
import numpy as np
import pytest

from jaxflow.data import open_dataset
from jaxflow.errors import ConfigError, DataError
from jaxflow.geometry import frames
from jaxflow.lidar import ground

import zup_scene

SPIN_DEG = 10.0


def kabsch(a_Nx3, b_Nx3) -> np.ndarray:
  """The proper rotation R (det +1) that best maps the centred a onto the centred b (b ~ R a)."""
  a, b = a_Nx3 - a_Nx3.mean(0), b_Nx3 - b_Nx3.mean(0)
  u, _, vt = np.linalg.svd(b.T @ a)
  d = np.sign(np.linalg.det(u @ vt))
  return u @ np.diag([1.0, 1.0, d]) @ vt


def turn_about(rot_3x3, axis: int) -> float:
  """Degrees of a rotation about a coordinate axis, right-handed (its rotation vector's part)."""
  i, j = [(1, 2), (2, 0), (0, 1)][axis]
  return float(np.degrees(np.arctan2(rot_3x3[j, i] - rot_3x3[i, j],
                                     np.trace(rot_3x3) - rot_3x3[axis, axis])))


def opencv_scene(n=3000, seed=0):
  """A cloud in front of a camera in OpenCV's frame (x right, y down, z forward), and the same cloud
  turned left by SPIN_DEG about the camera's up (-y): a point ahead moves towards -x."""
  rng = np.random.default_rng(seed)
  pc1 = rng.uniform([-6, -1.0, 8], [6, 1.2, 20], (n, 3))  # above KITTI's ground cut (y up > -1.4)
  a = np.radians(SPIN_DEG)
  c, s = np.cos(a), np.sin(a)
  # Turning left about up = -y: z (forward) towards -x (left).
  r = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
  centre = np.array([0.0, 0.0, 14.0])
  pc2 = (pc1 - centre) @ r.T + centre
  return pc1, pc2


def test_rotations_are_proper_and_invert():
  for up in frames.UP_AXES:
    r = frames.rotation(up)
    assert np.isclose(np.linalg.det(r), 1.0), up  # never a mirror
    np.testing.assert_allclose(r @ r.T, np.eye(3))
    assert r[1, "xyz".index(up)] == 1.0  # the sensor's up becomes the model's y
    p = np.random.default_rng(0).normal(size=(5, 3))
    np.testing.assert_allclose(frames.to_model(p, up), p @ r.T)
    np.testing.assert_allclose(frames.from_model(frames.to_model(p, up), up), p)
  # z up (x forward, y left, z up) -> (x left, y up, z forward): opensf's frame=camera order.
  np.testing.assert_array_equal(frames.to_model(np.array([[1.0, 2, 3]]), "z"), [[2.0, 3, 1]])
  np.testing.assert_array_equal(frames.rotation("y"), np.eye(3))


def test_permutation_to_a_z_up_frame_and_the_up_index():
  """The sweeps' z-up frame (x forward, y left, z up) from each up axis, as written out by hand:
  y up (x left, y up, z forward) gives (z, x, y); x up (x up, y forward, z left) gives (y, z, x)."""
  assert frames.permutation("z", "z") == [0, 1, 2]
  assert frames.permutation("y", "z") == [2, 0, 1]
  assert frames.permutation("x", "z") == [1, 2, 0]
  assert frames.permutation("z") == [1, 2, 0]  # to the model frame: left, up, forward
  for up in frames.UP_AXES:  # to a frame and back: the identity
    there, back = frames.permutation(up, "z"), frames.permutation("z", up)
    assert [there[i] for i in back] == [0, 1, 2]
    assert np.linalg.det(np.eye(3)[there]) == 1.0  # a rotation, never a mirror
  assert [frames.up_index(u) for u in "xyz"] == [0, 1, 2]
  with pytest.raises(ConfigError, match="up must be one of x, y, z, got 'w'"):
    frames.up_index("w")


def _check_turns_left(pair, up_axis: int, where: str):
  rot = kabsch(pair.pc1.astype(np.float64), (pair.pc1 + pair.flow).astype(np.float64))
  assert turn_about(rot, up_axis) == pytest.approx(SPIN_DEG, abs=0.1), where


def test_ft3d_reader_keeps_a_left_turn(tmp_path):
  """HPLFlowNet's pixel2pc (f = -1050 in its call, FT3D's negative disparities): x = (u - cx) * -1 /
  d, y = (v - cy) / d, z = -f / d; the reader's output must turn left about its stated up (y)."""
  pc1, pc2 = opencv_scene()
  folder = tmp_path / "ft3d" / "val" / "0000000"
  folder.mkdir(parents=True)
  f, cx, cy = 1050.0, 479.5, 269.5
  for name, p in (("pc1", pc1), ("pc2", pc2)):
    u, v = f * p[:, 0] / p[:, 2] + cx, f * p[:, 1] / p[:, 2] + cy
    d = -f / p[:, 2]  # the subset's disparities are negative (its stored z < 0)
    stored = np.c_[(u - cx) * -1.0 / d, (v - cy) / d, -1.0 * -f / d]
    np.save(folder / f"{name}.npy", stored.astype(np.float32))
  ds = open_dataset(f"ft3d:{tmp_path / 'ft3d'}", "test")
  pair = ds[0]
  assert ds.up == "y"
  _check_turns_left(pair, 1, "ft3d")
  left = pc1[:, 0] < -1  # physically left of the camera: x > 0 in the model frame (x left)
  assert (pair.pc1[left, 0] > 0).all() and (pair.pc1[:, 2] > 0).all()


def test_kitti_reader_keeps_a_left_turn(tmp_path):
  """HPLFlowNet's KITTI files: the camera's x and y negated (y up, ground near y = -1.6)."""
  pc1, pc2 = opencv_scene()
  folder = tmp_path / "kitti" / "000002"
  folder.mkdir(parents=True)
  for name, p in (("pc1", pc1), ("pc2", pc2)):
    np.save(folder / f"{name}.npy", (p * [-1, -1, 1]).astype(np.float32))
  with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # 1 of the 142 benchmark frames
    ds = open_dataset(f"kitti:{tmp_path / 'kitti'}", "test")
  pair = ds[0]
  assert ds.up == "y"
  _check_turns_left(pair, 1, "kitti")
  left = pc1[:, 0] < -1
  assert (pair.pc1[left, 0] > 0).all() and (pair.pc1[:, 2] > 0).all()


def _write_opensf(root, pc1_ego, pc2_ego):
  (root / "val").mkdir(parents=True)
  n = len(pc1_ego)
  with h5py.File(root / "val" / "log.h5", "w") as f:
    for key, p in (("0", pc1_ego), ("1", pc2_ego)):
      g = f.create_group(key)
      g.create_dataset("lidar", data=p.astype(np.float32))
      g.create_dataset("ground_mask", data=np.zeros(n, bool))
      g.create_dataset("pose", data=np.eye(4))
    g = f["0"]
    g.create_dataset("flow", data=(pc2_ego - pc1_ego).astype(np.float32))
    g.create_dataset("flow_is_valid", data=np.ones(n, bool))
    g.create_dataset("flow_category_indices", data=np.zeros(n, np.uint8))
    g.create_dataset("ego_motion", data=np.eye(4))


@pytest.mark.parametrize("frame, up", [("ego", 2), ("camera", 1)])
def test_opensf_reader_keeps_a_left_turn(tmp_path, frame, up):
  """Argoverse 2's ego frame: x forward, y left, z up; a left turn is +SPIN_DEG about z."""
  pc1, pc2 = opencv_scene()
  to_ego = lambda p: np.c_[p[:, 2], -p[:, 0], -p[:, 1]]  # OpenCV (right, down, forward) -> ego
  _write_opensf(tmp_path / "av2", to_ego(pc1), to_ego(pc2))
  ds = open_dataset(f"opensf:{tmp_path / 'av2'},frame={frame},lidar=ego", "val")
  assert ds.up == "xyz"[up]
  _check_turns_left(ds[0], up, f"opensf frame={frame}")
  from jaxflow.data import convert  # pylint: disable=import-outside-toplevel
  convert.convert(f"opensf:{tmp_path / 'av2'},frame={frame},lidar=ego", "val",
                  tmp_path / "pairs.h5")
  converted = open_dataset(f"h5:{tmp_path / 'pairs.h5'}", "val")
  assert converted.up == "xyz"[up]  # the frame it was converted from
  _check_turns_left(converted[0], up, f"h5 of opensf frame={frame}")


def test_synthetic_lidar_is_in_the_model_frame():
  """The synthetic driving pairs: ground under the sensor along -y, the road ahead along +z."""
  pair = open_dataset("synthetic_lidar:1", "test")[0]
  assert open_dataset("synthetic_lidar:1", "test").up == "y"
  assert np.median(pair.pc1[:, 2]) > 5 and np.percentile(pair.pc1[:, 1], 2) < -1.0


def test_to_model_keeps_a_left_turn():
  """The z-up sweep's left turn (+SPIN_DEG about z) is one about y after to_model."""
  pc1 = np.random.default_rng(1).uniform(-10, 10, (500, 3))
  pc2 = pc1 @ zup_scene.yaw(SPIN_DEG).T
  rot = kabsch(frames.to_model(pc1, "z"), frames.to_model(pc2, "z"))
  assert turn_about(rot, 1) == pytest.approx(SPIN_DEG, abs=1e-6)


@pytest.fixture(scope="module")
def predictor():
  from jaxflow import inference  # pylint: disable=import-outside-toplevel
  return inference.load_predictor(method="network")


def test_predict_up_z_hands_the_network_a_y_up_sweep(predictor, monkeypatch):
  """predict --up z (the clouds cut as a benchmark loader would): the network sees them as (y, z, x)
  of the sweep (a proper rotation: y up); its flow comes back in the sweep's frame, turning the
  static world the way the sensor's yaw does, and it is better than the z-up clouds as they are."""
  from jaxflow import inference  # pylint: disable=import-outside-toplevel

  scene = zup_scene.sweep_pair(n_ground=3000, reach=40.0)  # 1 m forward, yaw +2 deg (left)
  # the ground and range cut, in the sweep
  kept1 = ~ground.find_ground(scene.pc1, "z")[1] & ground.within_range(scene.pc1, "z", 35.0)
  kept2 = ~ground.find_ground(scene.pc2, "z")[1] & ground.within_range(scene.pc2, "z", 35.0)
  pc1, pc2 = scene.pc1[kept1], scene.pc2[kept2]
  seen = []
  real = inference.Predictor._predict  # pylint: disable=protected-access

  def spy(self, a, b, *args, **kwargs):
    seen.append(np.array(a))
    return real(self, a, b, *args, **kwargs)

  monkeypatch.setattr(inference.Predictor, "_predict", spy)
  flow = predictor.predict(pc1, pc2, up="z", max_points=2048, num_iters=8).flow
  monkeypatch.undo()
  (a,) = seen
  assert len(a) == kept1.sum() > 0.9 * (~scene.ground1).sum() / 2
  np.testing.assert_allclose(a, pc1[:, [1, 2, 0]], atol=1e-5)  # (y, z, x): y up
  assert np.ptp(a[:, 1]) < 5 < np.ptp(a[:, 2])  # heights along y, the road along z
  static = ~scene.moving1[kept1]
  p = pc1.astype(np.float64)
  turn = turn_about(kabsch(p[static], p[static] + flow[static]), 2)
  truth = turn_about(scene.ego_rotation, 2)  # -2 deg: the world turns right, the sensor left
  assert truth == pytest.approx(-2.0) and turn == pytest.approx(truth, abs=1.5)
  as_is = predictor.predict(pc1, pc2, up="y", max_points=2048, num_iters=8,
                            ground_limits=False).flow
  epe = lambda f: np.linalg.norm(f - scene.flow[kept1], axis=1).mean()
  assert epe(flow) < 0.85 * epe(as_is)


@pytest.mark.slow
def test_evaluate_rotates_opensf_ego_clouds_for_the_model(tmp_path, predictor):
  """evaluate on opensf's ego frame (z up) gives the flow of its camera frame (the models'): the
  clouds are rotated before the network and the flow back (without it the network sees z up)."""
  from jaxflow.evaluation import evaluator  # pylint: disable=import-outside-toplevel

  pc1, pc2 = opencv_scene(n=1500)
  pc2 = pc2 + [0.3, 0.0, 0.5]  # and a drift, so that the flow is not a rotation alone
  to_ego = lambda p: np.c_[p[:, 2], -p[:, 0], -p[:, 1]]
  _write_opensf(tmp_path / "av2", to_ego(pc1), to_ego(pc2))
  results = {}
  for frame in ("ego", "camera"):
    ds = open_dataset(f"opensf:{tmp_path / 'av2'},frame={frame},lidar=ego", "val")
    results[frame] = evaluator.evaluate(predictor.model, predictor.params, ds, num_points=512,
                                         batch_size=1, num_iters=2)
  assert results["ego"]["epe"] == pytest.approx(results["camera"]["epe"], rel=1e-4)
  assert results["ego"]["angle"] == pytest.approx(results["camera"]["angle"], rel=1e-4)


def test_in_model_frame_rotates_the_clouds_in_and_the_flow_back():
  """A model that moves every point up by its own height (its y, the models' up) moves a z-up
  cloud along z, by its z: the clouds went in y up and the flow came back z up; numpy and jax."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel

  rng = np.random.default_rng(0)
  pc1, pc2 = rng.normal(size=(50, 3)), rng.normal(size=(40, 3))
  lift = lambda a, b: a * np.array([0.0, 1.0, 0.0])  # in the model frame: (0, y, 0)
  flow = frames.in_model_frame(lift, "z")(pc1, pc2)
  np.testing.assert_allclose(flow, pc1 * [0.0, 0.0, 1.0])  # sensor frame: (0, 0, z)
  assert frames.in_model_frame(lift, "y") is lift
  lift_jax = lambda params, a, b: (a * jnp.array([0.0, 1.0, 0.0]), {"steps": params})
  for jitted in (True, False):
    out, info = frames.in_frame(lift_jax, "z", jitted=jitted)(3, pc1[None], pc2[None])
    np.testing.assert_allclose(np.asarray(out)[0], pc1 * [0.0, 0.0, 1.0], rtol=1e-6)
    assert int(info["steps"]) == 3
  # A method working z up (the lidar method) on y-up clouds: its z is their y.
  rise = lambda params, a, b: a * jnp.array([0.0, 0.0, 1.0])
  out = frames.in_frame(rise, "y", "z")(None, pc1[None], pc2[None])
  np.testing.assert_allclose(np.asarray(out)[0], pc1 * [0.0, 1.0, 0.0], rtol=1e-6)
  assert frames.in_frame(rise, "z", "z") is rise


def test_a_cloud_flat_along_another_axis_is_read_with_it_up_or_refused():
  """A z-up sweep given without --up is read z up (a note says so), with --up y refused naming
  the flat axis, unless the check is off; FlyingThings3D-like clouds (no flat axis) keep y."""
  scene = zup_scene.sweep_pair(n_ground=3000, reach=40.0)
  assert frames.flat_axis(scene.pc1)[0] == "z"
  assert frames.flat_axis(scene.pc1[:, [1, 2, 0]])[0] == "y"  # the same sweep, y up
  up, note = frames.resolve_up(scene.pc1, None, "y", "a.npy")
  assert up == "z" and "a.npy is flat along z" in note and "--up y" in note
  with pytest.raises(DataError, match=r"a\.npy.*flat along z.*--up y.*give --up z"):
    frames.resolve_up(scene.pc1, "y", "y", "a.npy")
  assert frames.resolve_up(scene.pc1, "y", "y", "a.npy", check=False) == ("y", None)
  assert frames.resolve_up(scene.pc1, "z", "y", "a.npy") == ("z", None)
  cube = np.random.default_rng(0).uniform(-10, 10, (500, 3)) * [1.5, 0.9, 2.0]  # spreads 30/18/40
  assert frames.flat_axis(cube)[0] is None
  assert frames.resolve_up(cube, None, "y", "a.npy") == ("y", None)


def test_rotation_between_any_two_up_axes_is_proper_and_inverts():
  """rotation(up, to) takes the up axis to the up axis, is a rotation (det +1), and
  rotation(to, up) is its inverse; the default target is the models' frame."""
  for up in frames.UP_AXES:
    for to in frames.UP_AXES:
      r = frames.rotation(up, to)
      np.testing.assert_array_equal(r @ np.eye(3)[frames.up_index(up)], np.eye(3)[frames.up_index(to)])
      assert np.linalg.det(r) == pytest.approx(1.0)
      np.testing.assert_array_equal(frames.rotation(to, up) @ r, np.eye(3))
    np.testing.assert_array_equal(frames.rotation(up), frames.rotation(up, frames.MODEL_UP))
