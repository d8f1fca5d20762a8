"""jaxflow.predict (the command line on user files: broken ones -> exit 2, one line) and
jaxflow.inference (the API)."""

import os

import jax
import numpy as np
import pytest

from jaxflow import inference, predict
from jaxflow.configs import default
from jaxflow.data import open_dataset, read_points
from jaxflow.data.sampling import sample_pair
from jaxflow.errors import DataError
from jaxflow.evaluation import export
from jaxflow.network import checkpointing, train_state
from jaxflow.network.model import build_model

import commands

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
N1, N2 = 150, 140  # points of the test pair (the smoke model's knn is 8)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
  """A stage-2 checkpoint of the smoke-sized model (random weights: the tests check plumbing)."""
  config = default.get_config("smoke")
  config.train.stage = 2
  model = build_model(config.model)
  tx = train_state.make_optimizer(config, 1)
  state = train_state.create_train_state(train_state.init_params(model, config, jax.random.key(0)),
                                         tx)
  path = tmp_path_factory.mktemp("ckpt")
  ckpts = checkpointing.Checkpoints(path / "checkpoints")
  ckpts.save(1, state, config)
  ckpts.close()
  return path


@pytest.fixture(scope="module")
def pair():
  p = open_dataset("synthetic_things:1", split="test")[0]
  p, _ = sample_pair(p, max(N1, N2), np.random.default_rng(0))
  return p.pc1[:N1], p.pc2[:N2], p.flow[:N1]


@pytest.fixture(scope="module")
def files(tmp_path_factory, pair):
  """Point files, good and broken."""
  d = tmp_path_factory.mktemp("points")
  pc1, pc2, _ = pair
  np.save(d / "pc1.npy", pc1)
  np.save(d / "pc2.npy", pc2)
  export.write_ply(d / "pc1.ply", pc1)
  export.write_ply(d / "pc2.ply", pc2)
  with_nan = pc1.copy()
  with_nan[[3, 10]] = np.nan
  np.save(d / "nan.npy", with_nan)
  big = np.concatenate([pc1, pc1[:, :] + np.float32(0.01)])  # 2 N1 points, above --max-points
  np.save(d / "big.npy", big)
  (d / "corrupt.npy").write_bytes(b"\x93NUMPY garbage")
  np.save(d / "two_columns.npy", pc1[:, :2])
  np.save(d / "all_nan.npy", np.full((20, 3), np.nan, np.float32))
  np.save(d / "few.npy", pc1[:5])  # fewer than the model's knn (8)
  (d / "notes.txt").write_text("1 2\n3 4\n")
  raw1, raw2 = raw_sweeps()
  np.save(d / "raw1.npy", raw1)
  np.save(d / "raw2.npy", raw2)
  return d


def raw_sweeps(seed=0):
  """Two LiDAR-like raw sweeps (z up): ground at z = -1.7, boxes, points beyond 35 m; the second
  is the first moved by an ego-motion (a 2 degree yaw and 1 m) with fresh ground and far points."""
  rng = np.random.default_rng(seed)

  def sweep():
    ground = np.c_[rng.uniform(-25, 25, (250, 2)), rng.normal(-1.7, 0.02, 250)]
    far = rng.uniform(-1, 1, (20, 3)) + [40, 5, 0]
    return ground, far

  boxes = np.concatenate([rng.uniform(0, 1, (60, 3)) * [3, 2, 1.6] + [x, y, -1.7]
                          for x, y in ((6, 2), (-8, 4), (3, -9))])
  a = np.radians(2.0)
  rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
  g1, f1 = sweep()
  g2, f2 = sweep()
  raw1 = np.concatenate([g1, boxes, f1])
  raw2 = np.concatenate([g2, boxes @ rot.T + [1.0, 0, 0], f2])
  return raw1.astype(np.float32), raw2.astype(np.float32)


def _cli(*args):
  return list(args)  # predict's arguments, run in this process (commands.run)


@pytest.fixture(scope="module")
def predictor(workdir):
  return inference.load_predictor(workdir, method="network")


@pytest.fixture(scope="module")
def runs(files, workdir):
  """Every command-line case, run in this process one after another (jaxflow.cli.call: one jax
  import, the compiled programs shared), as `python -m jaxflow.predict` would run it."""
  ck = ["--checkpoint", workdir]
  net = ck + ["--method", "network"]  # the API's default (the command's is optimise)
  d = files
  cases = {
    "missing": _cli(d / "nope.npy", d / "pc2.npy", "--out", d / "o1.npy", *ck),
    "corrupt": _cli(d / "corrupt.npy", d / "pc2.npy", "--out", d / "o2.npy", *ck),
    "two_columns": _cli(d / "pc1.npy", d / "two_columns.npy", "--out", d / "o3.npy", *ck),
    "text_two_columns": _cli(d / "notes.txt", d / "pc2.npy", "--out", d / "o4.npy", *ck),
    "all_nan": _cli(d / "all_nan.npy", d / "pc2.npy", "--out", d / "o5.npy", *ck),
    "few": _cli(d / "pc1.npy", d / "few.npy", "--out", d / "o6.npy", *ck),
    "bad_checkpoint": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "o7.npy", "--checkpoint",
                           d / "nothing_here"),
    "config_contradicts": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "o8.npy", *ck,
                               "--config", os.path.join(ROOT, "configs", "default.py")),
    "npy": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "flow_npy.npy", *net, "--iters", 4,
                "--render", d / "view.png"),
    "ply": _cli(d / "pc1.ply", d / "pc2.ply", "--out", d / "flow_ply.npy", *net, "--iters", 4),
    "nan": _cli(d / "nan.npy", d / "pc2.npy", "--out", d / "flow_nan.npy", *net, "--iters", 4,
                "--max_points", 100),
    "candidates": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "flow_k4.npy", *net, "--iters", 4,
                       "--config.model.infer_truncate_k=4"),  # without a --config file
    "test_time": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "o9.npy", *ck,
                      "--config.eval.test_time.steps=20"),  # removed: names its replacement
    "nsfp_grid": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "flow_nsfp.npy", "--method",
                      "nsfp", "--objective", "grid", "--steps", 10),
    "objective_not_nsfp": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "o12.npy", *net,
                               "--objective", "grid"),
    "nsfp_fields": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "flow_nsfp_fields.npy",
                        "--method", "nsfp", "--method.nsfp.objective=grid",
                        "--method.nsfp.steps=10"),  # nsfp_grid's settings, field by field
    "field_typo": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "o13.npy", *ck,
                       "--method.optimise.bodies.inlir=0.1"),
    "field_other_method": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "o14.npy", *net,
                               "--method.nsfp.steps=3"),
    "hyphenated": _cli(d / "pc1.npy", d / "pc2.npy", "--out", d / "o11.npy", *ck,
                       "--max-points", "100"),
    "lidar": _cli(d / "raw1.npy", d / "raw2.npy", "--out", d / "flow_lidar.npy", *net, "--lidar",
                  "--iters", 2, "--save_flows", d / "flows", "--ego_out", d / "ego.txt"),
    "method_lidar": _cli(d / "raw1.npy", d / "raw2.npy", "--out", d / "flow_method_lidar.npy",
                         *ck, "--method", "lidar"),  # the same as --lidar, no network start
    "bad_up": _cli(d / "raw1.npy", d / "raw2.npy", "--out", d / "o10.npy", *ck, "--lidar",
                   "--up", "x"),  # the sweep is flat along z
    "bad_up_ground": _cli(d / "raw1.npy", d / "raw2.npy", "--out", d / "o15.npy", *ck, "--lidar",
                          "--up", "x", "--noground_limits"),  # taken as given: no sweep check
    "zup_plain": _cli(d / "raw1.npy", d / "raw2.npy", "--out", d / "flow_zup.npy", *net,
                      "--iters", 1, "--max_points", 64),  # no --up, no --lidar: read z up
    "config_smoke": _cli(d / "big.npy", d / "pc2.npy", "--out", d / "flow_cfg.npy", *net,
                         "--config", os.path.join(ROOT, "configs", "default.py") + ":smoke"),
  }
  out = {}
  for k, args in cases.items():
    done = commands.run(predict.run, *args, cwd=d)
    out[k] = (done.returncode, done.stdout, done.stderr)
  return out


@pytest.mark.slow
@pytest.mark.parametrize("case, words", [
  ("missing", ["nope.npy", "missing file"]),
  ("corrupt", ["corrupt.npy", "corrupt"]),
  ("two_columns", ["two_columns.npy", "shape (150, 2)"]),
  ("text_two_columns", ["notes.txt", "expected at least 3"]),
  ("all_nan", ["all_nan.npy", "only 0 point"]),
  ("few", ["few.npy", "only 5 points", "config.model.knn"]),
  ("bad_checkpoint", ["nothing_here"]),
  ("config_contradicts", ["contradicts the checkpoint"]),
  ("test_time", ["--config.eval.test_time.steps", "--method optimise"]),
  ("hyphenated", ["--max-points is now --max_points"]),
  ("objective_not_nsfp", ["--objective", "--method nsfp", "network"]),
  ("field_typo", ["method.optimise.bodies.inlir", "no field 'inlir'", "inlier"]),
  ("field_other_method", ["--method.nsfp.*", "the method is network"]),
  ("bad_up", ["raw1.npy", "flat along z", "--up x", "give --up z"]),
])
def test_broken_input_is_one_line_and_exit_2(runs, case, words):
  rc, stdout, stderr = runs[case]
  assert rc == 2, stderr
  lines = stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("error: "), stderr
  assert "Traceback" not in stderr and stdout == ""
  for w in words:
    assert w in lines[0]


@pytest.mark.slow
def test_round_trip_npy_and_ply(runs, files, predictor, pair):
  for case in ("npy", "ply"):
    assert runs[case][0] == 0, runs[case][2]
  flow_npy = np.load(files / "flow_npy.npy")
  flow_ply = np.load(files / "flow_ply.npy")
  assert flow_npy.shape == (N1, 3) and flow_npy.dtype == np.float32
  assert np.isfinite(flow_npy).all()
  np.testing.assert_array_equal(read_points(files / "pc1.ply"), pair[0])  # the writer round-trips
  np.testing.assert_allclose(flow_ply, flow_npy, atol=1e-5)
  api = inference.predict_flow(pair[0], pair[1], num_iters=4, predictor=predictor)  # the CLI's
  np.testing.assert_allclose(api, flow_npy, atol=1e-4)
  png = (files / "view.png").read_bytes()
  assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 1000


@pytest.mark.slow
def test_cli_sets_the_test_time_candidates(runs, files, predictor, pair):
  rc, _, stderr = runs["candidates"]
  assert rc == 0, stderr
  config = predictor.config.copy_and_resolve_references()
  config.model.truncate_k = 4  # the smoke checkpoint keeps 16; a model built with 4 directly
  four = inference.Predictor(build_model(config.model), predictor.params, config, refine=True,
                             method="network")
  flow = np.load(files / "flow_k4.npy")
  np.testing.assert_allclose(flow, four(pair[0], pair[1], num_iters=4), atol=1e-4)
  assert not np.allclose(flow, np.load(files / "flow_npy.npy"), atol=1e-3)


@pytest.mark.slow
def test_larger_cloud_gives_one_row_per_input_point(runs, files):
  rc, _, stderr = runs["config_smoke"]  # config.eval.num_points = 64 < 300 points: sampled
  assert rc == 0, stderr
  assert "sampled to 64" in stderr and np.load(files / "flow_cfg.npy").shape == (2 * N1, 3)
  rc, _, stderr = runs["nan"]  # --max_points 100 < 148 points
  assert rc == 0, stderr
  assert "sampled to 100" in stderr


@pytest.mark.slow
def test_dropped_rows_are_reported_and_output_aligns(runs, files):
  rc, _, stderr = runs["nan"]
  assert rc == 0, stderr
  assert "dropped 2 of 150" in stderr and "NaN where the point was dropped" in stderr
  flow = np.load(files / "flow_nan.npy")
  dropped = ~np.isfinite(np.load(files / "nan.npy")).all(1)
  assert flow.shape == (N1, 3) and dropped.sum() == 2  # one row per row of the file
  assert np.isnan(flow[dropped]).all() and np.isfinite(flow[~dropped]).all()


def test_sampling_maps_flow_to_nearest_sampled_point(predictor, files, pair):
  big, pc2 = np.load(files / "big.npy"), pair[1]
  flow = predictor(big, pc2, num_iters=4, max_points=N1, seed=3)  # the model sees N1 points
  np.testing.assert_array_equal(flow, predictor(big, pc2, num_iters=4, max_points=N1, seed=3))
  idx = np.random.default_rng(3).choice(len(big), N1, replace=False)  # the documented sampling
  d = np.linalg.norm(big[:, None] - big[idx][None], axis=-1)
  np.testing.assert_allclose(flow, flow[idx][np.argmin(d, axis=1)], atol=1e-6)
  assert flow.shape == (2 * N1, 3) and len(np.unique(flow, axis=0)) <= N1


@pytest.mark.slow
def test_optimise_refines_every_point_of_a_sampled_cloud(workdir, files):
  big = np.load(files / "big.npy")
  move = np.float32([0.3, 0.0, -0.2])
  optimiser = inference.load_predictor(workdir, method="optimise", steps=40)
  flow = optimiser(big, big + move, num_iters=4, max_points=N1, seed=3)  # the network sees N1
  network = inference.load_predictor(workdir, method="network")(big, big + move, num_iters=4, max_points=N1, seed=3)
  assert flow.shape == (2 * N1, 3) and np.isfinite(flow).all()
  # Not the sampled points' flows copied (as for the network): every point was optimised.
  assert len(np.unique(network, axis=0)) <= N1 < len(np.unique(flow, axis=0))
  error = lambda f: np.mean(np.linalg.norm(f - move, axis=1))
  assert error(flow) < 0.5 * error(network)


def test_full_clouds_with_chunks_match_unchunked(predictor, pair):
  pc1, pc2, _ = pair
  assert predictor.model.corr_chunk == 0  # the checkpoint's: rows by the clouds' sizes
  whole = predictor(pc1, pc2, num_iters=4, full=True)
  # config.model.corr_chunk is the setting's one home (predict's --corr_chunk sets it).
  chunked = inference.Predictor(predictor.model.clone(corr_chunk=32), predictor.params,
                                predictor.config, predictor.refine, method=predictor.method)(
    pc1, pc2, num_iters=4, full=True)
  np.testing.assert_allclose(chunked, whole, atol=1e-4)
  # Clouds within max_points are used whole, without resampling.
  np.testing.assert_array_equal(predictor(pc1, pc2, num_iters=4, max_points=N1), whole)


def test_api_rejects_small_or_malformed_clouds(predictor, pair):
  with pytest.raises(DataError, match="pc2: only 4 points"):
    predictor(pair[0], pair[1][:4])
  with pytest.raises(DataError, match="expected N x 3"):
    predictor(pair[0][:, :2], pair[1])


def test_default_checkpoint_is_the_shipped_one(pair):
  """No checkpoint given: the shipped one's flow, not an untrained model's of the same config."""
  if not checkpointing.SHIPPED_CHECKPOINT.exists():
    pytest.skip("no shipped checkpoint in this tree")
  pc1, pc2 = pair[0][:64], pair[1][:64]
  flow = inference.predict_flow(pc1, pc2, method="network", num_iters=2)
  shipped = inference.load_predictor(checkpointing.SHIPPED_CHECKPOINT, method="network")
  np.testing.assert_array_equal(flow, shipped(pc1, pc2, num_iters=2))
  untrained = inference.fresh_predictor(shipped.config, method="network")(pc1, pc2, num_iters=2)
  assert np.abs(flow - untrained).max() > 1e-3


@pytest.mark.slow
def test_lidar_gives_every_raw_point_a_flow_and_saves_it(runs, files, predictor):
  rc, _, stderr = runs["lidar"]
  assert rc == 0, stderr
  raw1, raw2 = np.load(files / "raw1.npy"), np.load(files / "raw2.npy")
  flow = np.load(files / "flow_lidar.npy")
  assert flow.shape == raw1.shape and np.isfinite(flow).all()  # one row per input point
  assert "--lidar: ground plane" in stderr and "get the ego-motion flow" in stderr
  stem = export.flow_stem(f"{files / 'raw1.npy'},{files / 'raw2.npy'}")
  saved = files / "flows" / f"{stem}.npy"
  np.testing.assert_array_equal(np.load(saved), flow)
  # The flow itself is checked against a sweep's true ego-motion in tests/test_sweep.py.
  api = inference.predict_flow(raw1, raw2, num_iters=2, predictor=predictor, lidar=True, up="z")
  np.testing.assert_allclose(api, flow, atol=1e-4)
  # --ego_out: the sensor's motion as a 4 x 4 matrix; every point no moving object claims (most of
  # them here) has exactly its flow, R x + t - x.
  ego = np.loadtxt(files / "ego.txt")
  assert ego.shape == (4, 4) and np.allclose(ego[3], [0, 0, 0, 1])
  np.testing.assert_allclose(ego[:3, :3] @ ego[:3, :3].T, np.eye(3), atol=1e-6)
  static = np.linalg.norm(raw1 @ ego[:3, :3].T + ego[:3, 3] - raw1 - flow, axis=1) < 1e-4
  assert static.mean() > 0.8, static.mean()
  # --method lidar is --lidar without a method's start: the API's lidar method, the same flow.
  rc, _, stderr = runs["method_lidar"]
  assert rc == 0 and "no method run" in stderr and "no checkpoint loaded" in stderr, stderr
  np.testing.assert_allclose(np.load(files / "flow_method_lidar.npy"),
                             inference.predict_flow(raw1, raw2, method="lidar"), atol=1e-5)


@pytest.mark.slow  # it reads the `runs` fixture (every command line at once)
def test_nsfp_is_a_method_of_predict_with_its_objective(runs, files, pair):
  rc, _, stderr = runs["nsfp_grid"]
  assert rc == 0, stderr
  assert "method nsfp (grid objective)" in stderr and "did not fire within 10 steps" in stderr
  api = inference.predict_flow(pair[0], pair[1], method="nsfp", objective="grid", steps=10)
  np.testing.assert_allclose(np.load(files / "flow_nsfp.npy"), api, atol=1e-5)
  # The same settings given field by field, on the command line and through the API.
  assert runs["nsfp_fields"][0] == 0, runs["nsfp_fields"][2]
  np.testing.assert_allclose(np.load(files / "flow_nsfp_fields.npy"), api, atol=1e-5)
  by_fields = inference.predict_flow(pair[0], pair[1], method="nsfp",
                                     method_fields={"objective": "grid", "steps": 10})
  np.testing.assert_allclose(by_fields, api, atol=1e-5)


def test_notes_come_with_the_flow_and_as_warnings(pair):
  predictor = inference.load_predictor(method="nsfp", steps=5)
  first = predictor.predict(pair[0], pair[1])
  assert any("did not fire within 5 steps" in n for n in first.notes)
  assert first.used == (N1, N2) and first.sweep is None
  assert not hasattr(predictor, "notes")  # nothing of a call is kept on the (cached) predictor
  with pytest.warns(UserWarning, match="did not fire within 5 steps"):
    inference.predict_flow(pair[0], pair[1], predictor=predictor)


def _lopsided_after_the_cut(seed=1):
  """Raw sweeps of similar sizes whose clouds after the --lidar cut are not: pc1 keeps 1600 box
  points, pc2 12 (the rest of pc2 is ground)."""
  rng = np.random.default_rng(seed)
  ground = lambda n: np.c_[rng.uniform(-25, 25, (n, 2)), rng.normal(-1.7, 0.02, n)]
  box = lambda n: rng.uniform(0, 1, (n, 3)) * [3, 2, 1.6] + [6, 2, -1.2]
  raw1 = np.concatenate([ground(400), box(1600)])
  raw2 = np.concatenate([ground(1990), box(12)])
  return raw1.astype(np.float32), raw2.astype(np.float32)


def test_size_warning_compares_the_clouds_after_the_lidar_cut(predictor):
  raw1, raw2 = _lopsided_after_the_cut()
  assert inference.lopsided(len(raw1), len(raw2)) is None  # the raw clouds are alike
  got = predictor.predict(raw1, raw2, num_iters=2, lidar=True, ground_limits=False)
  assert got.used == got.sweep.kept and got.used[0] > 100 * got.used[1], got.used
  assert any(n.startswith(f"PC1 has {got.used[0]} points and PC2 {got.used[1]}")
             for n in got.notes), got.notes
  # The other way round: lopsided raw clouds whose kept parts are alike give no warning.
  rng = np.random.default_rng(2)
  extra = np.c_[rng.uniform(-25, 25, (30000, 2)), rng.normal(-1.7, 0.02, 30000)].astype(np.float32)
  alike = predictor.predict(np.concatenate([raw1, extra]), raw1[400:], num_iters=2, lidar=True,
                            max_points=256, ground_limits=False)
  assert not any(n.startswith("PC1 has") for n in alike.notes), alike.notes


@pytest.mark.slow
def test_a_z_up_sweep_is_read_z_up_without_up_and_a_wrong_up_is_refused(runs, files):
  """Without --up (and without --lidar) the z-up sweep is read z up and a note says so; --lidar
  --up x is refused naming the flat axis (above); with --noground_limits it is taken as given."""
  rc, _, stderr = runs["zup_plain"]
  assert rc == 0, stderr
  assert "raw1.npy is flat along z" in stderr and "read with z up" in stderr
  assert np.load(files / "flow_zup.npy").shape == (len(np.load(files / "raw1.npy")), 3)
  rc, _, stderr = runs["bad_up_ground"]  # runs; the pipeline notes that no ground is across x
  assert rc == 0 and "flat along" not in stderr and "is the up axis right?" in stderr, stderr
