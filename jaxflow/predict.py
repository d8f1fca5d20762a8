r"""Scene flow of your own point files with a trained checkpoint.

    python -m jaxflow.predict SWEEP1 SWEEP2 --lidar [--up z] [--max-range 35] --out FLOW.npy
    python -m jaxflow.predict PC1 PC2 --out FLOW.npy [--checkpoint PATH] [--config CONFIG]
        [--iters 32] [--max-points 8192 | --full [--corr-chunk 2048]] [--seed 0] [--render OUT.png]
        [--save-flows DIR]

    flow_Nx3 = predict_flow(pc1_Nx3, pc2_Mx3)            # from Python (a notebook)

PC1 and PC2 are any file `jaxflow.data.read_points` reads (.npy, .ply, .pcd, KITTI .bin, .xyz/.txt),
in metres, in one frame: x right, y up, z forward works best (the conventions of the FT3D and KITTI
readers the models are trained in). The output is float32 N x 3 (.npy; --out FLOW.txt or FLOW.csv
writes the same rows as text), one row per point of PC1, in file order: row i is the flow of the
i-th point of PC1 that read_points keeps. read_points drops rows with
a non-finite coordinate; when it does, the count is printed on stderr and those rows have no output
row (the output aligns with the finite rows of PC1, in their order).

Cloud size. A cloud with at most `max_points` points (config.eval.num_points: 8192, the paper's test
size, in the default configs/default.py:eval; 0 means whole clouds; --max-points overrides it) is used
whole, without resampling. A larger one is sampled to `max_points` points without replacement,
seeded (`--seed`, default 0: the same call gives the same flow); pc1 and pc2 are sampled independently.
The flow is then mapped back to EVERY point of PC1: an unsampled pc1 point takes the flow of its
nearest sampled pc1 point (Euclidean; a sampled point keeps its own). With --method optimise that
mapped network flow is then optimised at every point against every PC2 point. With --full the
model runs on the whole clouds instead, with the correlation and kNN built `corr_chunk` pc1 rows at
a time, so memory stays linear in the number of points (time grows as N x M).

Raw sweeps (--lidar; `lidar=True, up=..., max_range=...` in Python). The models are trained on
clouds without ground and within 35 m, as the benchmark loaders cut them. --lidar does that cut on
raw sweeps (jaxflow.ground): a RANSAC plane under the lowest points along --up (z, the LiDAR
convention; y for a camera frame such as KITTI's) removes each cloud's ground, the points beyond
--max-range (35 m, horizontal distance) go too, and the model estimates the flow of the rest. Every
point of PC1 still gets a row: a removed one gets the ego-motion flow of a rigid fit (Kabsch) to the
static part of the estimated flow (jaxflow.rigid), and a note on stderr says how many and what was
fitted. --save-flows DIR also writes the flow as DIR/NAME.npy, NAME made from "PC1,PC2" as
evaluate.py --save-flows names its pairs (jaxflow.export).

Model. The checkpoint (default: the shipped `jaxflow/checkpoints/jaxflow_synthetic/` of this repository, found
from the package, not the working directory) carries its config: the model is built from it. As in
evaluate.py, --config (default configs/default.py:eval) only sets evaluation settings
(config.eval.num_points, config.eval.num_iters: 32); a model field of an explicit --config file that
contradicts the checkpoint is an error, except corr_chunk and infer_truncate_k (the correlation
candidates kept at test time), which stay the checkpoint's unless given as --config.model.FIELD=N
(e.g. --config.model.infer_truncate_k=64: faster with --full). A stage-2 checkpoint gives the
refined flow, a stage-1 one the last iteration's. --config.eval.test_time.steps=N (0, off, by default)
then optimises that flow for N steps against the clouds the model saw, with no ground truth
(jaxflow.test_time: Chamfer distance to PC2 plus smoothness); the mapping back to every PC1 point
comes after it.

Method (--method, jaxflow.methods, docs/methods.md): `optimise` (the command's default) refines the
network's flow against the whole clouds (distance-grid Chamfer, one rigid motion per cluster of
points, an exact Chamfer polish); `network` is the network alone (the Python API's default, the
paper's protocol); `nsfp` is the NSFP baseline (no checkpoint). --steps N caps the optimisation
steps. An optimisation that did not converge says so in a note on stderr.

Broken input (a missing or unreadable file, a wrong number of columns, no finite point, fewer points
than the model's neighbourhood config.model.knn) prints one line naming the file and the problem and
exits with code 2.
"""

import dataclasses
import functools
import pathlib
import sys
import warnings

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from jaxflow import evaluation, export, geometry, ground, methods, test_time
from jaxflow.data import read_points
from jaxflow.data.sampling import sample_indices
from jaxflow.errors import ConfigError, DataError
from jaxflow.export import write_ply  # noqa: F401  (predict.write_ply, as the docs use it)
from jaxflow.model import build_model

DEFAULT_MAX_POINTS = 8192  # the paper's evaluation size
DEFAULT_ITERS = 32  # the paper's test-time iterations
DEFAULT_CORR_CHUNK = 2048  # --full: pc1 rows of the correlation / kNN built at a time
SHIPPED_CHECKPOINT = evaluation.SHIPPED_CHECKPOINT


@dataclasses.dataclass
class Predictor:
  """A model with its parameters: `predictor(pc1_Nx3, pc2_Mx3) -> flow N x 3` (numpy)."""

  model: object
  params: object
  config: ml_collections.ConfigDict  # the checkpoint's config (the model it was built from)
  refine: bool  # the refined flow (stage 2) or the last iteration's
  name: str = ""  # checkpoint path and step, for messages
  method: str = "network"  # jaxflow.methods: network, nsfp (model None) or optimise
  method_settings: object = None  # None: the method's defaults
  notes: list = dataclasses.field(default_factory=list)  # non-convergence notes of the last call
  _fns: dict = dataclasses.field(default_factory=dict, repr=False)

  @property
  def min_points(self) -> int:
    """Fewer points than the model's neighbourhood (config.model.knn) are refused."""
    return int(self.config.model.knn)

  def _fn(self, num_iters: int, corr_chunk: int, optimise: test_time.Settings, method=None):
    method = method or self.method
    key = (num_iters, corr_chunk, optimise, method)
    if key not in self._fns:
      model = self.model if self.model is None or corr_chunk == self.model.corr_chunk else (
        self.model.clone(corr_chunk=corr_chunk))
      fn = evaluation.model_predict_fn(model, num_iters, self.refine, optimise, method,
                                       self.method_settings if method == self.method else None,
                                       with_info=True)
      self._fns[key] = lambda *args: self._noted(*fn(*args))
    return self._fns[key]

  def _noted(self, flow, info):
    note = methods.convergence_note(self.method, info)
    self.notes = [note] if note else []
    return flow

  def __call__(self, pc1_Nx3, pc2_Mx3, num_iters: int = DEFAULT_ITERS,
               max_points: int | None = DEFAULT_MAX_POINTS, full: bool = False,
               corr_chunk: int = DEFAULT_CORR_CHUNK, seed: int = 0, names=("pc1", "pc2"),
               optimise: test_time.Settings = test_time.Settings(), lidar: bool = False,
               up: str = "z", max_range: float | None = ground.DEFAULT_MAX_RANGE):
    """Flow N x 3 of every point of pc1 (see the module docstring for sampling and --full); with
    `optimise.steps` > 0 the flow of the clouds the model saw is then optimised (jaxflow.test_time);
    lidar=True: raw sweeps, see `lidar`."""
    kwargs = dict(num_iters=num_iters, max_points=max_points, full=full, corr_chunk=corr_chunk,
                  seed=seed, names=names, optimise=optimise)
    if lidar:
      return self.lidar(pc1_Nx3, pc2_Mx3, up=up, max_range=max_range, **kwargs)[0]
    pc1_Nx3 = _cloud(pc1_Nx3, names[0], self.min_points)
    pc2_Mx3 = _cloud(pc2_Mx3, names[1], self.min_points)
    if num_iters < 1:
      raise ConfigError(f"num_iters must be >= 1, got {num_iters}")
    if full or not max_points:
      if corr_chunk < 0:
        raise ConfigError(f"corr_chunk must be >= 0, got {corr_chunk}")
      fn = self._fn(num_iters, corr_chunk, optimise)
      return np.asarray(fn(self.params, pc1_Nx3[None], pc2_Mx3[None])[0])
    if max_points < self.min_points:
      raise ConfigError(f"max_points={max_points} is below the model's neighbourhood "
                        f"(config.model.knn={self.min_points})")
    rng = np.random.default_rng(seed)
    idx1 = sample_indices(len(pc1_Nx3), max_points, rng)[0] if len(pc1_Nx3) > max_points else None
    idx2 = sample_indices(len(pc2_Mx3), max_points, rng)[0] if len(pc2_Mx3) > max_points else None
    sub1 = pc1_Nx3 if idx1 is None else pc1_Nx3[idx1]
    sub2 = pc2_Mx3 if idx2 is None else pc2_Mx3[idx2]
    every_point = self.method == "optimise"  # the network sees samples, the optimiser every point
    fn = self._fn(num_iters, getattr(self.model, "corr_chunk", 0), optimise,
                  "network" if every_point else None)
    flow_Sx3 = np.asarray(fn(self.params, sub1[None], sub2[None])[0])
    flow_Nx3 = flow_Sx3 if idx1 is None else spread_flow(pc1_Nx3, sub1, flow_Sx3)
    if idx1 is not None:
      flow_Nx3[idx1] = flow_Sx3  # a sampled point keeps its own flow, even at ties
    if every_point:
      chosen = self.method_settings or methods.settings("optimise")
      flow, info = _optimise_flow(flow_Nx3[None], pc1_Nx3[None], pc2_Mx3[None], chosen)
      return np.asarray(self._noted(flow, info)[0])
    return flow_Nx3


  def lidar(self, pc1_Nx3, pc2_Mx3, up: str = "z",
            max_range: float | None = ground.DEFAULT_MAX_RANGE, names=("pc1", "pc2"), **kwargs):
    """(flow N x 3 of every pc1 point, ground.SweepInfo) of two raw sweeps: ground removed and
    the range cut (jaxflow.ground) before the model; removed points get the ego-motion flow."""
    kept_names = tuple(f"{n} (after ground removal and the {max_range} m cut)" for n in names)
    clouds = [_cloud(c, n, 3) for c, n in zip((pc1_Nx3, pc2_Mx3), names)]
    return ground.raw_sweep_flow(lambda a, b: self(a, b, names=kept_names, **kwargs), *clouds,
                                 up=up, max_range=max_range, names=names)


_optimise_flow = jax.jit(methods.optimise_flow, static_argnums=3)


def spread_flow(points_Nx3, sampled_Sx3, flow_Sx3, chunk: int = 4096) -> np.ndarray:
  """Flow N x 3 for every point: the flow of its nearest sampled point (chunked: memory ~ chunk x S)."""
  return np.array(_spread(jnp.asarray(points_Nx3), jnp.asarray(sampled_Sx3),
                           jnp.asarray(flow_Sx3), chunk))


@functools.partial(jax.jit, static_argnums=3)
def _spread(points_Nx3, sampled_Sx3, flow_Sx3, chunk):
  nearest_N = geometry.knn(points_Nx3[None], sampled_Sx3[None], 1, chunk)[0, :, 0]
  return flow_Sx3[nearest_N]


def _cloud(points, name, min_points: int) -> np.ndarray:
  """An N x 3 float32 array, finite, with at least `min_points` points; else DataError(name)."""
  a = np.asarray(points)
  if a.dtype.kind not in "iuf":
    raise DataError(name, f"points have dtype {a.dtype}, expected numbers")
  if a.ndim != 2 or a.shape[1] != 3:
    raise DataError(name, f"points have shape {a.shape}, expected N x 3")
  a = a.astype(np.float32)
  if not np.isfinite(a).all():
    raise DataError(name, "non-finite coordinates (read_points drops such rows)")
  if len(a) < min_points:
    raise DataError(name, f"only {len(a)} points; the model needs at least {min_points} "
                    "(its neighbourhood size, config.model.knn)")
  return a


def load_predictor(checkpoint=None, config: ml_collections.ConfigDict | None = None,
                   model_fields=(), method: str = "network", steps: int | None = None) -> Predictor:
  """The model of a checkpoint (workdir, checkpoints folder or step folder; None: the shipped one).

  `model_fields` names fields of `config.model` the user asked for; as in evaluate.py one that
  contradicts the checkpoint is a CheckpointError, except the runtime fields (corr_chunk,
  infer_truncate_k), which are taken from `config`. `method` (jaxflow.methods; `steps` caps its
  optimiser): nsfp loads no checkpoint.
  """
  chosen = methods.settings(method, steps)
  if method not in methods.NEEDS_NETWORK:
    return Predictor(None, None, ml_collections.ConfigDict({"model": {"knn": 1}}), False,
                     name="NSFP, no network", method=method, method_settings=chosen)
  model, params, saved, step, refine = evaluation.load_model(checkpoint, config, model_fields)
  return Predictor(model, params, saved, refine, method=method, method_settings=chosen,
                   name=f"{checkpoint or SHIPPED_CHECKPOINT} (step {step})")


def fresh_predictor(config: ml_collections.ConfigDict, seed: int = 0) -> Predictor:
  """An untrained model of `config.model` (random parameters): for trying the API without weights."""
  from jaxflow import training  # pylint: disable=import-outside-toplevel

  model = build_model(config.model)
  params = training.init_params(model, config, jax.random.key(seed))
  return Predictor(model, params, config, refine=False, name="fresh (untrained)")


@functools.lru_cache(maxsize=4)
def _cached_predictor(checkpoint: str | None) -> Predictor:
  return load_predictor(checkpoint)


def predict_flow(pc1_Nx3, pc2_Mx3, checkpoint=None, num_iters: int = DEFAULT_ITERS,
                 max_points: int | None = DEFAULT_MAX_POINTS, full: bool = False,
                 corr_chunk: int = DEFAULT_CORR_CHUNK, seed: int = 0,
                 predictor: Predictor | None = None,
                 optimise: test_time.Settings = test_time.Settings(), lidar: bool = False,
                 up: str = "z", max_range: float | None = ground.DEFAULT_MAX_RANGE) -> np.ndarray:
  """Flow N x 3 (float32) of every point of pc1 towards pc2; the checkpoint is loaded once and kept.

  checkpoint None is the shipped one; `predictor` (from load_predictor / fresh_predictor) replaces it.
  lidar=True: raw sweeps (ground removed along `up`, `max_range` m kept; see the module docstring).
  """
  if predictor is None:
    predictor = _cached_predictor(None if checkpoint is None else str(checkpoint))
  return predictor(pc1_Nx3, pc2_Mx3, num_iters=num_iters, max_points=max_points, full=full,
                   corr_chunk=corr_chunk, seed=seed, optimise=optimise, lidar=lidar, up=up,
                   max_range=max_range)


def read_cloud(path, columns: int | None = None) -> tuple[np.ndarray, str | None]:
  """read_points(path, columns) and a note when non-finite rows were dropped (None otherwise)."""
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    points = read_points(path, columns)
  notes = [str(w.message) for w in caught if "non-finite" in str(w.message)]
  for w in caught:
    if "non-finite" not in str(w.message):
      warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
  return points, (notes[0] if notes else None)


# The command line.

SIZE_RATIO_WARNING = 100  # predict warns when one cloud has this many times the other's points
def _used(name: str, n: int, max_points: int | None, whole: bool) -> str:
  """How a cloud of n points went into the model, for the closing message."""
  if whole or n <= max_points:
    return f"{name}: all {n} points used"
  return (f"{name}: sampled to {max_points} of {n} points"
          + (", flow mapped back to every point" if name == "PC1" else ""))


def _define_flags():
  from absl import flags  # pylint: disable=import-outside-toplevel
  from ml_collections import config_flags  # pylint: disable=import-outside-toplevel

  config_flags.DEFINE_config_file(
    "config", evaluation.EVAL_CONFIG, "Evaluation settings (config.eval.num_points, "
    "config.eval.num_iters); the model comes from the checkpoint.", lock_config=True)
  flags.DEFINE_string("checkpoint", None, "Workdir, checkpoints folder or step folder (default: the "
                      "shipped jaxflow/checkpoints/jaxflow_synthetic/).")
  flags.DEFINE_string("out", None, "Write the flow here, one row per point of PC1: .npy "
                      "(float32) or text, .txt (x y z per line) or .csv.")
  flags.DEFINE_integer("iters", None, "Flow iterations (default: config.eval.num_iters, 32).")
  flags.DEFINE_integer("max-points", None, "Clouds above this size are sampled to it and the flow is "
                       "mapped back to every PC1 point by nearest sampled neighbour (default: "
                       "config.eval.num_points, 8192; 0: whole clouds).")
  flags.DEFINE_bool("full", False, "Run on the whole clouds, the correlation and kNN built in chunks "
                    "of --corr-chunk rows (memory linear in the points).")
  flags.DEFINE_integer("corr-chunk", DEFAULT_CORR_CHUNK, "Rows per chunk with --full.")
  flags.DEFINE_integer("seed", 0, "Seed of the sampling of larger clouds.")
  flags.DEFINE_integer("columns", None, ".bin files: float32 values a point (default 4, KITTI's x y "
                       "z intensity; 5: nuScenes' x y z intensity ring; 3: x y z).")
  flags.DEFINE_string("render", None, "Also save the Fig. 2 view (pc1 blue, pc2 red, pc1 + flow "
                      "green) as this PNG.")
  flags.DEFINE_bool("lidar", False, "Raw sweeps: remove the ground (plane fit along --up) and the "
                    "points beyond --max-range before the model; those get the ego-motion flow.")
  flags.DEFINE_enum("up", "z", ["x", "y", "z"], "--lidar: the up axis (z: LiDAR; y: camera frame).")
  flags.DEFINE_float("max-range", ground.DEFAULT_MAX_RANGE, "--lidar: keep the points within this "
                     "horizontal distance (m) of the sensor; 0: all.")
  flags.DEFINE_string("save-flows", None, "Also write the flow into this folder as NAME.npy, NAME "
                      "made from PC1,PC2 (jaxflow.export; the naming of evaluate.py --save-flows).")
  flags.DEFINE_enum("method", "optimise", list(methods.METHODS), "optimise (default): the network's "
                    "flow refined per pair; network: the network alone; nsfp: the NSFP baseline, no "
                    "checkpoint (docs/methods.md).")
  flags.DEFINE_integer("steps", None, "Cap the optimisation steps of nsfp / optimise.")
  return flags.FLAGS


def main(argv):
  from absl import flags  # pylint: disable=import-outside-toplevel
  from absl import logging as absl_logging  # pylint: disable=import-outside-toplevel

  from jaxflow import cli  # pylint: disable=import-outside-toplevel

  FLAGS = flags.FLAGS
  if not FLAGS["verbosity"].present:  # orbax warns that a read-only checkpoint is read-only
    absl_logging.set_verbosity(absl_logging.ERROR)
  if len(argv) != 3:
    cli.fail(f"expected two point files PC1 PC2, got {len(argv) - 1} argument(s): "
             f"{' '.join(argv[1:]) or '(none)'}")
  pc1_path, pc2_path = argv[1:]
  config = FLAGS.config
  max_points, num_iters = config.eval.num_points, config.eval.num_iters
  model_fields = evaluation.requested_model_fields(FLAGS["config"])
  if FLAGS["max-points"].value is not None:
    max_points = FLAGS["max-points"].value
  if FLAGS.iters is not None:
    num_iters = FLAGS.iters
  if max_points is not None and max_points < 0:
    raise ConfigError(f"--max-points must be >= 0, got {max_points}")
  if not FLAGS.out and not FLAGS["save-flows"].value:
    raise ConfigError("give --out FLOW.npy or --save-flows DIR (or both)")
  out = pathlib.Path(FLAGS.out or "")
  if FLAGS.out:
    export.check_flow_path(out)

  pc1, note1 = read_cloud(pc1_path, FLAGS.columns)
  pc2, note2 = read_cloud(pc2_path, FLAGS.columns)
  optimise = test_time.settings_from_config(config.eval)
  predictor = load_predictor(FLAGS.checkpoint, config, model_fields, FLAGS.method, FLAGS.steps)
  kwargs = dict(num_iters=num_iters, max_points=max_points, full=FLAGS.full,
                corr_chunk=FLAGS["corr-chunk"].value, seed=FLAGS.seed, names=(pc1_path, pc2_path),
                optimise=optimise)
  if FLAGS.lidar:
    flow_Nx3, sweep = predictor.lidar(pc1, pc2, up=FLAGS.up, max_range=FLAGS["max-range"].value,
                                      **kwargs)
    print(f"note: {sweep.note()}", file=sys.stderr)
  else:
    flow_Nx3 = predictor(pc1, pc2, **kwargs)
  flow_Nx3 = flow_Nx3.astype(np.float32)
  written = []
  if FLAGS.out:
    export.save_flow(out, flow_Nx3)
    written.append(out)
  if FLAGS["save-flows"].value:
    written.append(export.FlowSaver(FLAGS["save-flows"].value).save(f"{pc1_path},{pc2_path}",
                                                                     flow_Nx3))
  if note1:
    print(f"note: {note1}; {written[0]} has one row per remaining PC1 row, in file order",
          file=sys.stderr)
  if note2:
    print(f"note: {note2}", file=sys.stderr)
  for note in predictor.notes:
    print(f"note: {note}", file=sys.stderr)
  whole = FLAGS.full or not max_points
  sizes = sweep.kept if FLAGS.lidar else (len(pc1), len(pc2))
  how = ("ground and far points removed; " if FLAGS.lidar else "")
  how += "; ".join(_used(name, n, max_points, whole) for name, n in zip(("PC1", "PC2"), sizes))
  how += (f"; {num_iters} iterations" if FLAGS.method in methods.NEEDS_NETWORK else "") + (
    f", then {optimise.steps} test-time steps" if optimise.steps else "")
  how += f"; method {FLAGS.method}" + (" at every point" if FLAGS.method == "optimise" else "")
  print(f"{', '.join(map(str, written))}: flow of {len(pc1)} points ({how}; {predictor.name})",
        file=sys.stderr)
  ratio = max(len(pc1), len(pc2)) / min(len(pc1), len(pc2))
  if ratio > SIZE_RATIO_WARNING:
    print(f"warning: PC1 has {len(pc1)} points and PC2 {len(pc2)} ({ratio:.0f}x): the model expects "
          "two scans of one scene at a similar density; this flow is unlikely to mean much",
          file=sys.stderr)
  if FLAGS.render:
    from jaxflow import viz  # pylint: disable=import-outside-toplevel
    viz.render_pair(pc1, pc2, flow_Nx3, FLAGS.render,
                    title=f"{pathlib.Path(pc1_path).name} -> {pathlib.Path(pc2_path).name}")
    print(f"{FLAGS.render}: Fig. 2 view", file=sys.stderr)


def run():
  """The console script `jaxflow-predict`."""
  from jaxflow import cli  # pylint: disable=import-outside-toplevel

  cli.run(main, _define_flags, {"config": evaluation.EVAL_CONFIG})


if __name__ == "__main__":
  run()
