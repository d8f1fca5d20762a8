"""Training end to end on the smoke config: a step, a run, stage 2, non-finite stop, broken data,
data parallelism."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import traverse_util

from conftest import CACHE, xla_flags
from jaxflow.configs import default, stage2_synthetic
from jaxflow.data import BatchLoader, open_dataset
from jaxflow.errors import CheckpointError, ConfigError, DataError, NonFiniteError
from jaxflow.evaluation import evaluator
from jaxflow.network import checkpointing, train_state
from jaxflow.network.model import build_model
from jaxflow.training import events, trainer

STEPS = 24  # the last step of configs/default.py:smoke

REPO = Path(__file__).absolute().parent.parent
# Compiled programs are shared by the tests (and their subprocesses) through jax's persistent cache.
jax.config.update("jax_compilation_cache_dir", CACHE)


def smoke(overrides=None, get_config=default.get_config):
  config = get_config("smoke")
  for key, value in (overrides or {}).items():
    *path, last = key.split(".")
    node = config
    for p in path:
      node = node[p]
    node[last] = value
  return config


def flat(params):
  return traverse_util.flatten_dict(jax.device_get(params), sep="/")


@pytest.fixture(scope="module")
def stage1(tmp_path_factory):
  workdir = tmp_path_factory.mktemp("stage1")
  state = trainer.train_and_evaluate(smoke({"eval.every": 12}), workdir)
  return workdir, state


def test_one_train_step():
  config = smoke()
  model = build_model(config.model)
  tx = train_state.make_optimizer(config, config.train.num_steps)
  mesh = trainer.make_mesh()
  state = train_state.create_train_state(
    train_state.init_params(model, config, jax.random.key(0)), tx)
  before = flat(state.params)
  loader = BatchLoader(open_dataset(config.data.dataset), config.train.batch_size,
                       config.data.num_points, seed=0)
  step = trainer.jit_train_step(model, tx, config, mesh)
  state, metrics = step(state, trainer.device_batch(loader.batch(0), mesh))
  metrics = jax.device_get(metrics)
  assert set(metrics) == {"loss", "grad_norm", "param_norm"}
  assert all(np.isfinite(v) and v > 0 for v in metrics.values())
  assert int(state.step) == 1
  after = flat(state.params)
  changed = [k for k in before if not np.array_equal(before[k], after[k])]
  assert changed and all(not k.startswith("refine/") for k in changed)  # stage 1 leaves refine


def test_smoke_run_writes_checkpoints_metrics_curve_and_eval(stage1):
  workdir, state = stage1
  config = smoke()
  assert int(state.step) == config.train.num_steps
  steps = sorted(int(p.name) for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())
  every, total = config.train.checkpoint_every, config.train.num_steps
  assert steps == list(range(every, total + 1, every))[-config.train.max_to_keep:]
  records = [json.loads(l) for l in (workdir / "metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in records] == list(range(config.train.log_every, total + 1,
                                                     config.train.log_every))
  assert set(records[0]) == {"step", "loss", "grad_norm", "param_norm", "pairs_per_s", "lr",
                             "stage", "time"}
  assert (workdir / "learning_curve.png").stat().st_size > 1000
  assert json.loads((workdir / "config.json").read_text())["model"]["knn"] == config.model.knn
  results = json.loads((workdir / "eval.json").read_text())
  for name in ("model", "zero_flow"):
    assert results[name]["pairs"] == 4
    assert set(results[name]) >= {"epe", "acc_strict", "acc_relax", "outliers", "angle",
                                  "ms_per_pair"}
  # The restored checkpoint is the returned state.
  restored, saved_config, step = checkpointing.restore_checkpoint(workdir)
  assert step == total and saved_config.train.stage == 1
  a, b = flat(restored.params), flat(state.params)
  assert all(np.array_equal(a[k], b[k]) for k in a)


def test_heldout_evaluation_during_training_matches_evaluating_the_checkpoint(stage1):
  workdir, _ = stage1
  config = smoke()
  records = [json.loads(l) for l in (workdir / "eval_metrics.jsonl").read_text().splitlines()]
  assert [r["step"] for r in records] == [12, 24]
  ds = open_dataset(config.eval.dataset, split=config.eval.split)
  model = build_model(config.model)
  for record in records:  # the checkpoints of those steps, evaluated afresh on the same pairs
    state, _, _ = checkpointing.restore_checkpoint(workdir, step=record["step"])
    fresh = evaluator.evaluate(model, state.params, ds, num_points=config.eval.num_points,
                                batch_size=config.eval.batch_size, num_iters=config.eval.num_iters)
    assert record["pairs"] == fresh["pairs"] == 4
    for k in ("epe", "acc_strict", "acc_relax", "outliers", "angle"):
      assert np.isclose(record[k], fresh[k], rtol=1e-5, atol=1e-7), k
  assert records[0]["epe"] != records[1]["epe"]
  # The end-of-run evaluation is the same as the last held-out one (reused, not run again).
  final = json.loads((workdir / "eval.json").read_text())["model"]
  assert final["epe"] == records[-1]["epe"] and final["output"] == "coarse"


def test_heldout_evaluation_keeps_the_test_time_candidates(stage1):
  # The run's held-out check evaluates as evaluate.py does: with model.infer_truncate_k candidates.
  _, state = stage1
  config = smoke({"model.infer_truncate_k": 4})  # the smoke model trains with 16
  ds = open_dataset(config.eval.dataset, split=config.eval.split)
  settings = dict(num_points=config.eval.num_points, batch_size=config.eval.batch_size,
                  num_iters=config.eval.num_iters)
  heldout = trainer.evaluate_run(state.params, config)["model"]
  four, sixteen = (evaluator.evaluate(build_model(smoke({"model.truncate_k": k}).model),
                                       state.params, ds, **settings) for k in (4, 16))
  assert four["epe"] != sixteen["epe"]
  for k in ("epe", "acc_strict", "acc_relax", "outliers", "angle"):
    assert np.isclose(heldout[k], four[k], rtol=1e-5, atol=1e-7), k


def test_evaluator_reuses_results_only_for_the_same_parameter_arrays(stage1):
  workdir, state = stage1
  config = smoke()
  ds = open_dataset(config.eval.dataset, split=config.eval.split)
  evaluate_params = evaluator.Evaluator(build_model(config.model), ds, num_points=config.eval.num_points,
                                         batch_size=config.eval.batch_size, num_iters=config.eval.num_iters)
  first = evaluate_params(state.params)
  assert evaluate_params(state.params) == first
  scaled = jax.tree.map(lambda x: x * 0.5, state.params)  # new arrays: evaluated afresh
  assert evaluate_params(scaled)["epe"] != first["epe"]
  restored, _, _ = checkpointing.restore_checkpoint(workdir)  # equal values, other arrays
  again = evaluate_params(restored.params)
  assert again["epe"] == first["epe"] and again is not first
  # Zero flow on the kept pairs is the baseline evaluate_zero_flow samples afresh.
  fresh = evaluator.evaluate_zero_flow(ds, num_points=config.eval.num_points,
                                        batch_size=config.eval.batch_size)
  assert evaluate_params.zero_flow()["epe"] == fresh["epe"] > 0


def test_heldout_evaluation_needs_a_dataset(tmp_path):
  for overrides in ({"eval.every": 5, "eval.dataset": ""}, {"eval.every": -1}):
    with pytest.raises(ConfigError, match="config.eval.every"):
      trainer.train_and_evaluate(smoke(overrides), tmp_path)
  assert not (tmp_path / "checkpoints").exists()


def test_stage2_freezes_backbone_bitwise_and_trains_refinement(stage1, tmp_path):
  stage1_dir, stage1_state = stage1
  config = smoke({"train.init_from": str(stage1_dir), "train.num_steps": 4,
                  "eval.dataset": ""}, get_config=stage2_synthetic.get_config)
  state = trainer.train_and_evaluate(config, tmp_path)
  before, after = flat(stage1_state.params), flat(state.params)
  assert before.keys() == after.keys()
  backbone = [k for k in before if not k.startswith("refine/")]
  refine = [k for k in before if k.startswith("refine/")]
  assert backbone and refine
  for k in backbone:
    assert after[k].tobytes() == before[k].tobytes(), k
  # Stage 1 never trains the refinement, so its values there are the (shared) initial ones.
  assert any(not np.array_equal(after[k], before[k]) for k in refine)
  # The optimiser holds state for the refinement only.
  n_refine = sum(before[k].size for k in refine)
  n_opt = sum(x.size for x in jax.tree.leaves(state.opt_state) if x.ndim > 0)
  assert n_opt == 2 * n_refine  # Adam's mu and nu


@pytest.mark.slow
def test_stage1_init_from_warm_starts_every_parameter(stage1, tmp_path):
  stage1_dir, stage1_state = stage1
  config = smoke({"train.init_from": str(stage1_dir), "train.num_steps": 1, "eval.dataset": ""})
  model = build_model(config.model)
  fresh = flat(train_state.init_params(model, config, jax.random.key(config.seed)))
  loaded = flat(trainer._load_init_params(train_state.init_params(model, config,
                                                                 jax.random.key(config.seed)),
                                            config))
  before = flat(stage1_state.params)
  assert all(np.array_equal(loaded[k], before[k]) for k in before)
  assert any(not np.array_equal(loaded[k], fresh[k]) for k in fresh)
  # One step of the new round starts from those parameters with a fresh optimiser.
  state = trainer.train_and_evaluate(config, tmp_path)
  assert int(state.step) == 1
  after = flat(state.params)
  assert all(np.allclose(after[k], before[k], atol=2 * config.train.lr) for k in before)
  assert any(not np.array_equal(after[k], before[k]) for k in before)
  with pytest.raises(CheckpointError, match="model differs"):
    trainer._load_init_params({}, smoke({"train.init_from": str(stage1_dir), "model.knn": 4}))
  # Fields no parameter depends on may change between rounds (e.g. candidates for larger windows).
  wider = smoke({"train.init_from": str(stage1_dir), "model.truncate_k": 32,
                 "model.infer_truncate_k": 64})
  loaded = flat(trainer._load_init_params({}, wider))
  assert all(np.array_equal(loaded[k], before[k]) for k in before)


def test_save_params_writes_a_workdir_that_loads(tmp_path):
  config = smoke()
  params = train_state.init_params(build_model(config.model), config, jax.random.key(3))
  path = checkpointing.save_params(tmp_path / "imported", jax.device_get(params), config,
                                   note="imported from nowhere")
  state, saved, step = checkpointing.restore_checkpoint(path)
  assert step == 0 and not checkpointing.model_differences(saved, config)
  a, b = flat(state.params), flat(params)
  assert all(np.array_equal(a[k], b[k]) for k in a)
  assert (path / "NOTE.txt").read_text() == "imported from nowhere\n"
  with pytest.raises(CheckpointError, match="already holds checkpoints"):
    checkpointing.save_params(path, params, config)
  del params["refine"]
  with pytest.raises(CheckpointError, match="do not match config.model"):
    checkpointing.save_params(tmp_path / "other", params, config)


class NaNAt(BatchLoader):
  """A loader whose batch at index `bad` has a NaN ground truth."""

  bad = 8

  def batch(self, step):
    b = super().batch(step)
    if step == self.bad:
      b["flow"] = np.full_like(b["flow"], np.nan)
    return b


def test_nonfinite_loss_stops_naming_the_step_and_keeps_last_good_checkpoint(tmp_path,
                                                                            monkeypatch):
  monkeypatch.setattr(trainer, "BatchLoader", NaNAt)
  config = smoke({"eval.dataset": ""})  # checkpoints at 6, 12, ...; batch 8 is update step 9
  assert config.train.checkpoint_every == 6 and config.train.log_every == 2
  with pytest.raises(NonFiniteError, match=r"step 9\b") as info:
    trainer.train_and_evaluate(config, tmp_path)
  assert "checkpoints/6" in str(info.value)
  steps = sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir() if p.name.isdigit())
  assert steps == [6]
  state, _, step = checkpointing.restore_checkpoint(tmp_path)
  assert step == 6 and int(state.step) == 6
  assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(jax.device_get(state.params)))


def _ft3d_folder(root: Path, n: int, broken: int) -> Path:
  rng = np.random.default_rng(0)
  for i in range(n):
    d = root / "val" / f"{i:07d}"
    d.mkdir(parents=True)
    pc1 = rng.uniform(-5, 5, (200, 3)).astype(np.float32)
    pc1[:, 2] = -rng.uniform(2, 20, 200)  # HPLFlowNet stores z < 0
    np.save(d / "pc1.npy", pc1)
    np.save(d / "pc2.npy", pc1 + np.float32([0.1, 0.0, -0.2]))
  (root / "val" / f"{broken:07d}" / "pc1.npy").write_bytes(b"\x93NUMPY truncated")
  return root


@pytest.mark.slow
def test_broken_data_stops_or_is_skipped_and_reported(tmp_path, capsys):
  root = _ft3d_folder(tmp_path / "ft3d", n=6, broken=2)
  broken = str(root / "val" / "0000002")
  config = smoke({"data.dataset": f"ft3d:{root}", "data.split": "test", "eval.dataset": ""})
  with pytest.raises(DataError, match="0000002"):
    trainer.train_and_evaluate(config, tmp_path / "stop")
  config.data.skip_broken = True
  with pytest.warns(UserWarning, match="0000002"):
    state = trainer.train_and_evaluate(config, tmp_path / "skip")
  assert int(state.step) == config.train.num_steps
  err = capsys.readouterr().err
  assert "skipped 1 unreadable sample(s)" in err and broken in err


DATA_PARALLEL = textwrap.dedent("""
  import sys
  import jax, numpy as np
  from jaxflow.configs import default
  from jaxflow.network import train_state
  from jaxflow.training import trainer
  from jaxflow.data import BatchLoader, open_dataset
  from jaxflow.network.model import build_model
  assert jax.device_count() == 2, jax.devices()
  config = default.get_config("smoke")
  model = build_model(config.model)
  tx = train_state.make_optimizer(config, config.train.num_steps)
  loader = BatchLoader(open_dataset(config.data.dataset), 2, config.data.num_points, seed=0)
  mesh = trainer.make_mesh()
  state = train_state.create_train_state(
    train_state.init_params(model, config, jax.random.key(0)), tx)
  step = trainer.jit_train_step(model, tx, config, mesh)
  state, metrics = step(state, trainer.device_batch(loader.batch(0), mesh))
  assert len(state.params["update"]["flow_head"]["out_conv2"]["bias"].sharding.device_set) == 2
  metrics, params = jax.device_get((metrics, state.params))
  np.savez(sys.argv[1], loss=metrics["loss"], grad_norm=metrics["grad_norm"],
           **{str(i): p for i, p in enumerate(jax.tree.leaves(params))})
""")


@pytest.mark.slow
def test_data_parallel_over_two_devices_matches_one_device(tmp_path):
  """One step with the batch split over 2 (forced host) devices gives the 1-device step."""
  config = smoke()
  model = build_model(config.model)
  tx = train_state.make_optimizer(config, config.train.num_steps)
  loader = BatchLoader(open_dataset(config.data.dataset), 2, config.data.num_points, seed=0)
  mesh = trainer.make_mesh(jax.local_devices()[:1])
  state = train_state.create_train_state(
    train_state.init_params(model, config, jax.random.key(0)), tx)
  step = trainer.jit_train_step(model, tx, config, mesh)
  state, metrics = jax.device_get(step(state, trainer.device_batch(loader.batch(0), mesh)))

  env = dict(os.environ, XLA_FLAGS=xla_flags("--xla_force_host_platform_device_count=2"),
             JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  out = tmp_path / "two.npz"
  proc = subprocess.run([sys.executable, "-c", DATA_PARALLEL, str(out)], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=1200)
  assert proc.returncode == 0, proc.stderr[-3000:]
  two = np.load(out)
  np.testing.assert_allclose(two["loss"], metrics["loss"], rtol=1e-5)
  np.testing.assert_allclose(two["grad_norm"], metrics["grad_norm"], rtol=1e-4)
  leaves = jax.tree.leaves(state.params)
  # Adam's first update is ~lr * sign(gradient): allow a fraction of lr where a gradient is ~0.
  for i, leaf in enumerate(leaves):
    np.testing.assert_allclose(two[str(i)], leaf, rtol=0, atol=0.1 * config.train.lr)


def test_tensorboard_events_hold_the_logged_metrics_and_pictures(stage1):
  """The event files beside metrics.jsonl, read back from their records: every logged step's
  losses, learning rate and pairs a second, the held-out metrics, and PNG views of val pairs."""
  workdir, _ = stage1
  found = events.read_events(workdir)
  logged = [json.loads(l) for l in (workdir / "metrics.jsonl").read_text().splitlines()]
  for name in ("loss", "grad_norm", "lr", "pairs_per_s"):
    got = found[f"train/{name}"]
    assert [s for s, _ in got] == [r["step"] for r in logged], name
    np.testing.assert_allclose([v for _, v in got], [r[name] for r in logged], rtol=1e-6)
  held = [json.loads(l) for l in (workdir / "eval_metrics.jsonl").read_text().splitlines()]
  final = json.loads((workdir / "eval.json").read_text())["model"]
  epe = found["eval/epe"]
  assert [s for s, _ in epe] == [r["step"] for r in held] + [STEPS]
  np.testing.assert_allclose([v for _, v in epe], [r["epe"] for r in held] + [final["epe"]],
                             rtol=1e-6)
  assert "eval_zero_flow/epe" in found
  for tag in ("eval/pair_0", "eval/pair_1"):
    pictures = found[tag]
    assert [s for s, _ in pictures] == [r["step"] for r in held] + [STEPS]
    assert all(png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 1000 for _, png in pictures)
