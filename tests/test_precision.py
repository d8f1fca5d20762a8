"""model.precision reaches every matmul of the network, its gradient and its kNN; every program a
method of jaxflow.methods.registry compiles has every matmul at its configured precision and no host
callback; the table of model fields (jaxflow.network.model_fields) covers the model and gives old
checkpoints the defaults."""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow.configs import default
from jaxflow.methods import registry
from jaxflow.network import checkpointing, model_fields
from jaxflow.network.model import SceneFlowNet, build_model
from jaxflow.training import losses

DOT = re.compile(r"stablehlo\.(dot_general|dot|convolution)\b")
PRECISION = re.compile(r"precision = \[(\w+), (\w+)\]")


def tiny_model_config(**overrides):
  m = default.model_config()
  m.widths, m.knn, m.truncate_k, m.corr_knn = (16, 16, 16, 32), 8, 16, 8
  m.refine_widths = (32, 16, 16)
  for k, v in overrides.items():
    m[k] = v
  return m


def dot_precisions(text: str) -> list[str]:
  """The precision of every dot / dot_general / convolution of a lowered program's text; "none"
  for one that states none (the backend's default)."""
  found = []
  for line in text.splitlines():
    if DOT.search(line) and "=" in line:
      m = PRECISION.search(line)
      found.append(f"{m.group(1)},{m.group(2)}" if m else "none")
  return found


def pair(n=40, seed=0):
  rng = np.random.default_rng(seed)
  pc1 = rng.uniform(-3, 3, (2, n, 3)).astype(np.float32)
  return jnp.asarray(pc1), jnp.asarray(pc1 + rng.normal(0, 0.1, pc1.shape).astype(np.float32))


@pytest.mark.parametrize("precision,want", [("highest", "HIGHEST"), ("default", "DEFAULT")])
@pytest.mark.parametrize("variant", ["paper", "pvraft"])
def test_every_dot_of_the_training_gradient_carries_the_precision(precision, want, variant):
  """Lowered, not run: the gradient of both losses (sequence loss over 3 iterations + refinement
  loss), i.e. the forward (kNN, encoders, correlation, update, refinement) and every matmul of its
  backward, custom gradients included, states the configured precision on every dot, so a GPU
  computes what the CPU tests check."""
  overrides = dict(precision=precision)
  if variant == "pvraft":  # SetConv encoder, GRU and SetConv refinement
    overrides.update(encoder="setconv", widths=(16, 16, 32), residual=False, cell="gru",
                     refine="setconv")
  model = build_model(tiny_model_config(**overrides))
  pc1, pc2 = pair()
  params = jax.eval_shape(lambda: model.init(jax.random.key(0), pc1, pc2, num_iters=1))["params"]

  def loss(p):
    out = model.apply({"params": p}, pc1, pc2, num_iters=3)
    return losses.total_loss(out["flows"], out["refined"], pc2 - pc1)

  found = dot_precisions(jax.jit(jax.value_and_grad(loss)).lower(params).as_text())
  assert len(found) >= 40, len(found)  # the program holds the network's forward and backward
  wrong = sorted({p for p in found if p != f"{want},{want}"})
  assert not wrong, f"{len(found)} dots, some at {wrong} instead of {want}"


def test_precision_reaches_the_knn_and_the_correlation():
  """The kNN distance matmul and the all-pairs correlation alone (no network dots) follow it."""
  from jaxflow.geometry import neighbours
  from jaxflow.network.correlation import truncated_correlation
  pc1, pc2 = pair()
  for precision, want in (("highest", "HIGHEST"), ("tensorfloat32", "HIGH"),
                          ("bfloat16", "DEFAULT")):
    knn = jax.jit(lambda a: neighbours.matmul_knn(a, a, 8, precision=precision)).lower(pc1).as_text()
    corr = jax.jit(lambda a, b: truncated_correlation(a, b, b, 8, precision=precision))
    for text in (knn, corr.lower(pc1, pc2).as_text()):
      assert dot_precisions(text) == [f"{want},{want}"]


def test_precision_default_is_exact_float32_and_a_bad_name_is_refused():
  assert SceneFlowNet().precision == "highest" == default.get_config().model.precision
  model = build_model(tiny_model_config(precision="fp16"))
  pc1, pc2 = pair()
  with pytest.raises(ValueError, match="model.precision must be one of highest, float32, high"):
    model.init(jax.random.key(0), pc1, pc2, num_iters=1)


def test_the_field_table_covers_the_model_and_the_configs():
  fields = set(SceneFlowNet.__dataclass_fields__) - {"parent", "name"}
  assert set(model_fields.MODEL_FIELDS) == fields | {"infer_truncate_k"}  # build_model pops it
  assert set(default.get_config().model) == set(model_fields.MODEL_FIELDS)
  kinds = {f.kind for f in model_fields.MODEL_FIELDS.values()}
  assert kinds == {"architecture", "parameter_free", "runtime"}
  assert set(model_fields.RUNTIME_MODEL_FIELDS) < set(model_fields.PARAMETER_FREE_FIELDS)
  # Every added field's value for old checkpoints is the model's own default.
  for name, value in model_fields.ADDED_MODEL_FIELDS.items():
    if name != "infer_truncate_k":
      assert getattr(SceneFlowNet(), name) == value, name
  assert set(model_fields.REFINE_FIELDS) <= {
    k for k, f in model_fields.MODEL_FIELDS.items() if f.kind == "architecture"}


def test_a_checkpoint_config_without_the_new_fields_reads_as_their_defaults():
  """A config stored before precision / voxel_cells existed: same model, built with defaults."""
  new = default.get_config()
  old = default.get_config()
  with old.unlocked():
    for name in ("precision", "voxel_cells", "remat_iterations", "infer_truncate_k"):
      del old.model[name]
  assert checkpointing.model_differences(old, new) == []
  model = build_model(old.model)
  assert (model.precision, model.voxel_cells) == ("highest", "auto")
  new.model.precision = "default"
  assert checkpointing.model_differences(old, new) == ["precision: 'highest' != 'default'"]
  assert "precision" in model_fields.RUNTIME_MODEL_FIELDS  # evaluation takes it from the user


def test_voxel_cells_setting_reaches_the_model_and_is_decided_per_platform():
  """model.voxel_cells picks the voxel branch's form in the whole model (its forward holds no other
  scatter); "auto" is the CPU's scatter when lowered for the CPU and the comparison when lowered
  for a GPU, from the same trace (tests/test_ops.py holds the forms to the same values)."""
  pc1, pc2 = pair()
  scatters = {}
  for form in ("scatter", "compare", "auto"):
    model = build_model(tiny_model_config(voxel_cells=form))
    params = jax.eval_shape(lambda: model.init(jax.random.key(0), pc1, pc2, num_iters=1))
    traced = jax.jit(lambda v, a, b: model.apply(v, a, b, num_iters=2)).trace(params, pc1, pc2)
    for platform in ("cpu", "cuda"):
      text = traced.lower(lowering_platforms=(platform,)).as_text()
      scatters[form, platform] = "stablehlo.scatter" in text
  assert scatters == {("scatter", "cpu"): True, ("scatter", "cuda"): True,
                      ("compare", "cpu"): False, ("compare", "cuda"): False,
                      ("auto", "cpu"): True, ("auto", "cuda"): False}
  with pytest.raises(ValueError, match="model.voxel_cells must be one of auto, scatter, compare"):
    build_model(tiny_model_config(voxel_cells="loop")).init(jax.random.key(0), pc1, pc2)


# Every method of jaxflow.methods.registry (a method added later is covered without a change here).


def configured(chosen, **fields):
  """A method's settings with every field named in `fields` (precision, search) replaced, in
  every settings dataclass nested inside (the optimise method's stages, its clusters)."""
  if not dataclasses.is_dataclass(chosen):
    return chosen
  changes = {}
  for f in dataclasses.fields(chosen):
    value = getattr(chosen, f.name)
    if f.name in fields:
      changes[f.name] = fields[f.name]
    elif dataclasses.is_dataclass(value):
      changes[f.name] = configured(value, **fields)
  return dataclasses.replace(chosen, **changes)


def lowered_by_method(tmp_path, method, precision=None, **fields):
  """The text of every program `method` lowers when it runs on a toy pair (jax_dump_ir_to), the
  network at `precision` (None: defaults). The methods are driven from Python between compiled
  stages (jaxflow.methods.registry.flow_fn): what they compile is what they lowered."""
  pc1, pc2 = pair(n=64)
  model = build_model(tiny_model_config(**({} if precision is None else {"precision": precision})))
  init = lambda: model.init(jax.random.key(0), pc1, pc2, num_iters=1)["params"]
  # The network runs only in optimise (its start); eager init is slow: traced once, compiled.
  params = jax.jit(init)() if method == "optimise" else jax.eval_shape(init)
  network = lambda p, a, b: model.apply({"params": p}, a, b, num_iters=2)["flows"][:, -1]
  chosen = registry.settings(method, steps=20)
  if precision is not None:
    fields["precision"] = precision
  chosen = configured(chosen, **fields)
  if method == "network":  # one jitted program: lowered, not run
    return [registry.flow_fn(method, network, chosen).lower(params, pc1, pc2).as_text()]
  folder = tmp_path / f"{method}-{precision}-{len(fields)}"
  jax.clear_caches()  # every stage lowered again, in this folder
  before = jax.config.read("jax_dump_ir_to")
  jax.config.update("jax_dump_ir_to", str(folder))
  try:
    jax.block_until_ready(registry.flow_fn(method, network, chosen)(params, pc1, pc2))
  finally:
    jax.config.update("jax_dump_ir_to", before)
  texts = [f.read_text() for f in sorted(folder.glob("*.mlir"))]
  assert texts, f"nothing lowered into {folder}"
  return texts


def callbacks(text: str) -> list[str]:
  return [line for line in text.splitlines() if "custom_call" in line and "callback" in line]


@pytest.mark.slow
@pytest.mark.parametrize("method", [m for m in registry.METHODS if registry.get(m).compiles])
def test_every_program_of_a_method_carries_the_precision_and_no_callback(method, tmp_path):
  """Every program a method compiles (the network, NSFP's MLPs and their gradients, the optimise
  stages' Kabsch, Rodrigues and rigid flows) states HIGHEST on every dot by default and the
  configured precision when one is set; none holds a host callback, with the searches on the host
  (the CPU's "auto") or on the device (an accelerator's): the k-d tree searches, the distance grids
  and the rigid-bodies stage run between compiled stages. JAX's persistent compilation cache keeps
  only such programs (jaxflow.runtime.compile_cache), and a GPU program never waits on the host."""
  runs = {"HIGHEST": lowered_by_method(tmp_path, method),
          "DEFAULT": lowered_by_method(tmp_path, method, "default",
                                       **({} if method == "network" else {"search": "device"}))}
  for want, texts in runs.items():
    found = [p for text in texts for p in dot_precisions(text)]
    assert len(found) >= 40, len(found)  # the network alone holds 50, NSFP's two MLPs 89
    assert set(found) == {f"{want},{want}"}, sorted(set(found))
    assert [c for text in texts for c in callbacks(text)] == [], want


def test_the_callback_check_can_fail():
  """The jitted optimiser with its searches inside does call back to the host on the CPU."""
  from jaxflow.refine import optimiser  # pylint: disable=import-outside-toplevel
  pc1, pc2 = pair(n=64)
  assert callbacks(optimiser.optimise.lower(jnp.zeros_like(pc1), pc1, pc2,
                                            optimiser.NSFP).as_text())


def test_a_bad_precision_or_search_is_refused():
  from jaxflow.refine import optimiser, rigid_clusters
  with pytest.raises(ValueError, match="optimiser precision must be one of highest"):
    optimiser.Settings(precision="fp16")
  with pytest.raises(ValueError, match="optimiser search must be one of auto, host, device"):
    optimiser.Settings(search="gpu")
  with pytest.raises(ValueError, match="rigid search must be one of auto, host, device"):
    rigid_clusters.Settings(search="tree")
