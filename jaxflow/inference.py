"""Flow of two point clouds by a method of jaxflow.methods.registry: the library side of jaxflow.predict.

    flow_Nx3 = predict_flow(pc1_Nx3, pc2_Mx3)                    # optimise, as the command
    flow_Nx3 = predict_flow(pc1_Nx3, pc2_Mx3, method="network")  # the network alone
    flow_Nx3 = predict_flow(pc1_Nx3, pc2_Mx3, method="lidar")    # raw sweeps (lidar=True, below)
    predictor = load_predictor(checkpoint, method="nsfp", objective="grid")
    prediction = predictor.predict(pc1_Nx3, pc2_Mx3)   # .flow, .notes, .used, .sweep

Every method is reached through the registry (jaxflow.methods.registry), by its properties
(jaxflow.methods.interface.Method): the frame it works in, whether it needs a network, whether it
refines the network's flow at every point, whether it reads raw sweeps.

Cloud size. A cloud with at most `max_points` points (8192, the paper's test size; 0 or None: whole
clouds) is used whole, without resampling. A larger one is sampled to `max_points` points without
replacement, seeded (`seed`: the same call gives the same flow); pc1 and pc2 are sampled
independently. The flow is then mapped back to EVERY point of pc1: an unsampled pc1 point takes the
flow of its nearest sampled pc1 point (Euclidean; a sampled point keeps its own). A method that
refines the network's flow (`optimise`) then refines that mapped network flow at every point against
every pc2 point. `full=True` runs the model on the whole clouds instead, with the correlation and
kNN built config.model.corr_chunk pc1 rows at a time (0: by the clouds' sizes; the model's config is
that setting's one home: `--corr_chunk` or `--config.model.corr_chunk` on the command line).

Raw sweeps (the `lidar` method; `lidar=True` runs it with the predictor's method as the one it may
run): jaxflow.lidar.sweep.raw_sweep_flow, the ground, the sensor's ego-motion and one rigid motion
per moving object; every pc1 point gets a row. The method of its settings (`method.lidar.method`,
jaxflow.methods.lidar.Lidar) runs only on a camera's view (under half the azimuth: the
non-ground points within `max_range`), or as one more start of the fits with `start`; its checkpoint
is loaded then, not before.
"""

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from jaxflow.data.pointfiles import read_points
from jaxflow.data.sampling import sample_indices
from jaxflow.errors import ConfigError, DataError
from jaxflow.geometry import frames, neighbours
from jaxflow.lidar import sweep
from jaxflow.methods import lidar as lidar_method
from jaxflow.methods import registry
from jaxflow.network import checkpointing
from jaxflow.refine import progress
from jaxflow.runtime import configfile

DEFAULT_METHOD = "optimise"  # the API's and predict's: the network's flow refined per pair
DEFAULT_MAX_POINTS = 8192  # the paper's evaluation size
DEFAULT_ITERS = 32  # the paper's flow iterations at test time
SIZE_RATIO_WARNING = 100  # one cloud with this many times the other's points: a warning
# Said after the note of a cloud read with another up axis than the models' (z up: a sweep's).
LIDAR_HINT = ("; for a raw 360-degree LiDAR sweep (ground kept, before any cut) use --lidar "
              "(lidar=True in Python): the ground, the sensor's ego-motion and the moving objects, "
              "jaxflow.lidar.sweep")
_NO_MODEL = ml_collections.ConfigDict({"model": {"knn": 1}})  # a method without a network


@dataclasses.dataclass(frozen=True)
class Prediction:
  """One call's flow and what the user should know about it."""

  flow: np.ndarray  # N x 3 float32, a row per point of pc1 in its order
  notes: tuple = ()  # non-convergence of an optimisation, a lopsided pair
  used: tuple = ()  # (pc1, pc2) points the method was given (after the lidar cut)
  sweep: object = None  # sweep.SweepInfo of a raw-sweep method
  up: str = frames.MODEL_UP  # the up axis of the clouds (jaxflow.geometry.frames): the flow is in their frame


def lopsided(n1: int, n2: int) -> str | None:
  """A warning when one cloud has SIZE_RATIO_WARNING times the other's points (None otherwise)."""
  ratio = max(n1, n2) / max(min(n1, n2), 1)
  if ratio <= SIZE_RATIO_WARNING:
    return None
  return (f"PC1 has {n1} points and PC2 {n2} ({ratio:.0f}x) as the method saw them: the model "
          "expects two scans of one scene at a similar density; this flow is unlikely to mean much")


class _Deferred:
  """() -> a Predictor loaded at its first call (the lidar method's: a 360-degree sweep never
  loads it)."""

  def __init__(self, load):
    self._load, self.value = load, None

  def __call__(self):
    if self.value is None:
      self.value = self._load()
    return self.value


@dataclasses.dataclass
class Predictor:
  """A method with its network (None for nsfp, lidar): `predictor.predict(pc1_Nx3, pc2_Mx3)` ->
  Prediction; `predictor(pc1_Nx3, pc2_Mx3)` -> its flow alone."""

  model: object
  params: object
  config: ml_collections.ConfigDict | None  # the checkpoint's config (the model it was built from)
  refine: bool  # the refined flow (stage 2) or the last iteration's
  name: str = ""  # checkpoint path and step, for messages
  method: str = DEFAULT_METHOD  # its name in jaxflow.methods.registry
  method_settings: object = None  # None: the method's defaults
  # A raw-sweep method's: () -> the Predictor of the method its settings run (loaded at first use).
  nested: object = None
  _fns: dict = dataclasses.field(default_factory=dict, repr=False)  # compiled, by shapes' settings

  def __post_init__(self):
    if self.method_settings is None:
      self.method_settings = registry.settings(self.method)
    if self.config is None:
      self.config = _NO_MODEL
    if registry.get(self.method).raw_sweeps:
      self.method_settings = lidar_method.settings_of(self.method_settings)

  @property
  def min_points(self) -> int:
    """Fewer points than the model's neighbourhood (config.model.knn) are refused."""
    return int(self.config.model.knn)

  @property
  def source(self) -> str:
    """What gave the flow, for messages: the checkpoint (or the method without one)."""
    if not registry.get(self.method).raw_sweeps:
      return self.name
    return self.nested.value.source if self.nested and self.nested.value else "no checkpoint loaded"

  def _fn(self, num_iters: int):
    """jit (params, pc1, pc2) -> (flow, info) of the method."""
    if num_iters not in self._fns:
      self._fns[num_iters] = registry.model_predict_fn(self.model, num_iters, self.refine,
                                                       self.method, self.method_settings,
                                                       with_info=True)
    return self._fns[num_iters]

  def __call__(self, pc1_Nx3, pc2_Mx3, **kwargs) -> np.ndarray:
    """The flow N x 3 of every point of pc1 (`predict`'s arguments)."""
    return self.predict(pc1_Nx3, pc2_Mx3, **kwargs).flow

  def as_lidar(self, fields: dict | None = None) -> "Predictor":
    """The lidar method that runs this predictor's method (its settings with `fields`, {dotted
    field: value}, changed); itself with `fields` for a raw-sweep method."""
    if registry.get(self.method).raw_sweeps:
      return dataclasses.replace(self, method_settings=configfile.replace_settings(
        self.method_settings, fields, f"method.{self.method}"), _fns={}) if fields else self
    name = lidar_method.METHOD.name
    nested = _Deferred(lambda: self)
    return Predictor(None, None, None, False, method=name, nested=nested,
                     method_settings=registry.settings(name, fields={"method": self.method,
                                                                     **(fields or {})}))

  def predict(self, pc1_Nx3, pc2_Mx3, num_iters: int = DEFAULT_ITERS,
              max_points: int | None = DEFAULT_MAX_POINTS, full: bool = False, seed: int = 0,
              names=("pc1", "pc2"), lidar: bool = False, up: str | None = None,
              ground_limits: bool = True) -> Prediction:
    """The Prediction of every point of pc1 (the module docstring: sampling, full, raw sweeps;
    progress shown, jaxflow.refine.progress). `up`: the clouds' up axis (default: the method's, z
    for raw sweeps, else y, the models' frame; jaxflow.geometry.frames): the clouds are rotated into
    the method's frame and the flow back. `lidar`: the lidar method running this one (as_lidar)."""
    with progress.Working(f"flow of {names[0]} ({'lidar' if lidar else self.method})"):
      return self._predict_pair(pc1_Nx3, pc2_Mx3, num_iters, max_points, full, seed, names, lidar,
                                up, ground_limits)

  def _predict_pair(self, pc1_Nx3, pc2_Mx3, num_iters, max_points, full, seed, names, lidar, up,
                    ground_limits) -> Prediction:  # predict's, shown
    if lidar:
      return self.as_lidar().predict(pc1_Nx3, pc2_Mx3, num_iters, max_points, full, seed, names,
                                     up=up, ground_limits=ground_limits)
    sampling = dict(num_iters=num_iters, max_points=max_points, full=full, seed=seed)
    method = registry.get(self.method)
    if method.raw_sweeps:
      return self._sweeps(pc1_Nx3, pc2_Mx3, names, up, ground_limits, sampling)
    pc1 = as_cloud(pc1_Nx3, names[0], self.min_points)
    up, note = frames.resolve_up(pc1, up, method.up, names[0], ground_limits)
    note = note and note + LIDAR_HINT  # a cloud read with another up is likely a sweep
    inner = []  # the Prediction of the method, in its frame
    flow = lidar_method.in_frame(_estimate(lambda: self, names, sampling, inner), up, method.up)(
      pc1, as_cloud(pc2_Mx3, names[1], self.min_points))
    return dataclasses.replace(inner[0], flow=flow, up=up,
                               notes=(note, *inner[0].notes) if note else inner[0].notes)

  def _sweeps(self, pc1_Nx3, pc2_Mx3, names, up, ground_limits, sampling) -> Prediction:
    """A raw-sweep method's Prediction (jaxflow.methods.lidar; any method of it on kept points)."""
    settings = self.method_settings
    least = sweep.min_points(settings)  # the pipeline's own, whether or not a method runs
    clouds = [as_cloud(c, n, least, sweep.too_few(settings))
              for c, n in zip((pc1_Nx3, pc2_Mx3), names)]
    up, up_note = frames.resolve_up(clouds[0], up, registry.get(self.method).up, names[0],
                                    ground_limits)
    kept_names = tuple(f"{n} (after ground removal and the {settings.max_range} m cut)"
                       for n in names)
    inner = []  # the Prediction of the kept points
    flow_fn = None if self.nested is None else lidar_method.in_frame(
      _estimate(self.nested, kept_names, sampling, inner), up,
      registry.nested(settings.method).up)
    flow, info = lidar_method.pair_flow(flow_fn, *clouds, settings, up, names, ground_limits,
                                        sampling["seed"])
    notes = inner[-1].notes if inner else tuple(n for n in [lopsided(*info.kept)] if n)
    notes = (up_note, *notes) if up_note else notes
    return Prediction(np.asarray(flow, np.float32), notes, info.kept, info, up)

  def _predict(self, pc1_Nx3, pc2_Mx3, num_iters, max_points, full, seed):
    """The Prediction of clouds in the method's frame."""
    if num_iters < 1:
      raise ConfigError(f"num_iters must be >= 1, got {num_iters}")
    if max_points is not None and max_points < 0:
      raise ConfigError(f"max_points must be >= 0, got {max_points}")
    used = (len(pc1_Nx3), len(pc2_Mx3))
    notes = [lopsided(*used)]
    if full or not max_points:
      flow, info = self._fn(num_iters)(self.params, pc1_Nx3[None], pc2_Mx3[None])
      return self._prediction(flow[0], info, notes, used)
    if max_points < self.min_points:
      raise ConfigError(f"max_points={max_points} is below the model's neighbourhood "
                        f"(config.model.knn={self.min_points})")
    rng = np.random.default_rng(seed)
    idx1 = sample_indices(len(pc1_Nx3), max_points, rng)[0] if len(pc1_Nx3) > max_points else None
    idx2 = sample_indices(len(pc2_Mx3), max_points, rng)[0] if len(pc2_Mx3) > max_points else None
    sub1 = pc1_Nx3 if idx1 is None else pc1_Nx3[idx1]
    sub2 = pc2_Mx3 if idx2 is None else pc2_Mx3[idx2]
    # A method refining the network's flow: the network sees the samples, the method every point.
    every_point = registry.get(self.method).refines_start
    progress.stage("network")  # (what a log's progress line names; compiled at a first call)
    flow_Sx3, info = (self._start(num_iters) if every_point else self._fn(num_iters))(
      self.params, sub1[None], sub2[None])
    flow_Sx3 = np.asarray(flow_Sx3[0])
    flow_Nx3 = flow_Sx3 if idx1 is None else spread_flow(pc1_Nx3, sub1, flow_Sx3)
    if idx1 is not None:
      flow_Nx3[idx1] = flow_Sx3  # a sampled point keeps its own flow, even at ties
    if every_point:
      flow, info = _from_start(self.method, self.method_settings)(flow_Nx3[None], pc1_Nx3[None],
                                                                  pc2_Mx3[None])
      flow_Nx3 = flow[0]
    return self._prediction(flow_Nx3, info, notes, used)

  def _start(self, num_iters: int):
    """jit (params, pc1, pc2) -> (the network's flow the method starts from, None)."""
    iters, candidates = registry.network_asked(self.method, self.method_settings)
    key = ("start", candidates, iters or num_iters)
    if key not in self._fns:
      network = registry.network_for(self.model, num_iters, self.refine)(iters, candidates)
      self._fns[key] = jax.jit(lambda *args: (network(*args), None))
    return self._fns[key]

  def _prediction(self, flow_Nx3, info, notes, used) -> Prediction:
    notes = [*notes, registry.convergence_note(self.method, jax.device_get(info))]
    return Prediction(np.asarray(flow_Nx3, np.float32), tuple(n for n in notes if n), used)


def _estimate(get_predictor, names, sampling: dict, inner: list):
  """(pc1, pc2) -> the flow of `get_predictor()`'s method (called at the first flow: a raw-sweep
  method's is loaded then), in its frame; each Prediction appended to `inner`."""

  def estimate(pc1_Nx3, pc2_Mx3):
    predictor = get_predictor()
    inner.append(predictor._predict(  # pylint: disable=protected-access
      as_cloud(pc1_Nx3, names[0], predictor.min_points),
      as_cloud(pc2_Mx3, names[1], predictor.min_points), **sampling))
    return inner[-1].flow

  return estimate


@functools.lru_cache(maxsize=8)
def _from_start(method: str, chosen):
  """jit (start flow, pc1, pc2) -> (flow, info) of a method that refines the network's flow, from a
  given starting flow (the network's flow of the samples spread to every point)."""
  return registry.flow_fn(method, lambda start, pc1, pc2: start, chosen, with_info=True)


def spread_flow(points_Nx3, sampled_Sx3, flow_Sx3, chunk: int = 4096) -> np.ndarray:
  """Flow N x 3 for every point: the flow of its nearest sampled point (chunked: memory ~ chunk x S)."""
  return np.array(_spread(jnp.asarray(points_Nx3), jnp.asarray(sampled_Sx3),
                           jnp.asarray(flow_Sx3), chunk))


@functools.partial(jax.jit, static_argnums=3)
def _spread(points_Nx3, sampled_Sx3, flow_Sx3, chunk):
  nearest_N = neighbours.matmul_knn(points_Nx3[None], sampled_Sx3[None], 1, chunk)[0, :, 0]
  return flow_Sx3[nearest_N]


def as_cloud(points, name, min_points: int, needs: str | None = None) -> np.ndarray:
  """An N x 3 float32 array, finite, with at least `min_points` points; else DataError(name).
  `needs`: what asks for `min_points`, in the error (default: the model's neighbourhood)."""
  a = np.asarray(points)
  if a.dtype.kind not in "iuf":
    raise DataError(name, f"points have dtype {a.dtype}, expected numbers")
  if a.ndim != 2 or a.shape[1] != 3:
    raise DataError(name, f"points have shape {a.shape}, expected N x 3")
  a = a.astype(np.float32)
  if not np.isfinite(a).all():
    raise DataError(name, "non-finite coordinates (read_points drops such rows)")
  if len(a) < min_points:
    raise DataError(name, f"only {len(a)} points; " + (needs or (
      f"the model needs at least {min_points} (its neighbourhood size, config.model.knn)")))
  return a


def load_predictor(checkpoint=None, config: ml_collections.ConfigDict | None = None,
                   model_fields=(), method: str = DEFAULT_METHOD, steps: int | None = None,
                   objective: str | None = None, iters: int | None = None,
                   method_fields: dict | None = None, method_settings=None,
                   nested_settings=None) -> Predictor:
  """The Predictor of `method` (jaxflow.methods.registry; `steps` caps its optimiser, `objective` is
  NSFP's, `iters` sets optimise's starting flow's iterations, `method_fields` sets any of its
  settings, {"bodies.inlier": 0.1}; `method_settings`: the settings themselves instead) with the
  model of a checkpoint (workdir, checkpoints folder or step folder; None: the shipped one; a method
  without a network loads none). A raw-sweep method (lidar) runs the method its settings name
  (`method.lidar.method`) with `nested_settings` (default: its defaults with `steps`, `objective`,
  `iters`), loaded at its first use. `model_fields`: checkpointing.load_for_inference."""
  chosen_method = registry.get(method)
  if chosen_method.raw_sweeps:
    chosen = method_settings or registry.settings(method, fields=method_fields)
    nested = lidar_method.settings_of(chosen).method
    if nested is not None:  # its settings' errors now, its checkpoint when it runs
      registry.nested(nested)
      settings = nested_settings or registry.settings(nested, steps, iters, objective)
      nested = _Deferred(functools.partial(load_predictor, checkpoint, config, model_fields,
                                           nested, method_settings=settings))
    return Predictor(None, None, None, False, method=method, method_settings=chosen, nested=nested)
  chosen = method_settings or registry.settings(method, steps, iters, objective, method_fields)
  if not chosen_method.needs_network:
    return Predictor(None, None, None, False, name=f"{method}, no network", method=method,
                     method_settings=chosen)
  model, params, saved, step, refine = checkpointing.load_for_inference(checkpoint, config,
                                                                        model_fields)
  return Predictor(model, params, saved, refine, method=method, method_settings=chosen,
                   name=f"{checkpoint or checkpointing.SHIPPED_CHECKPOINT} (step {step})")


def fresh_predictor(config: ml_collections.ConfigDict, seed: int = 0,
                    method: str = DEFAULT_METHOD) -> Predictor:
  """An untrained model of `config.model` (random parameters): for trying the API without weights."""
  from jaxflow.network import train_state  # pylint: disable=import-outside-toplevel
  from jaxflow.network.model import build_model  # pylint: disable=import-outside-toplevel

  model = build_model(config.model)
  params = train_state.init_params(model, config, jax.random.key(seed))
  return Predictor(model, params, config, refine=False, name="fresh (untrained)", method=method)


@functools.lru_cache(maxsize=4)
def _cached_predictor(checkpoint: str | None, method: str, steps, objective,
                      method_fields: tuple) -> Predictor:
  return load_predictor(checkpoint, method=method, steps=steps, objective=objective,
                        method_fields=dict(method_fields))


def predict_flow(pc1_Nx3, pc2_Mx3, method: str | None = None, checkpoint=None,
                 steps: int | None = None, objective: str | None = None,
                 num_iters: int = DEFAULT_ITERS, max_points: int | None = DEFAULT_MAX_POINTS,
                 full: bool = False, seed: int = 0, predictor: Predictor | None = None,
                 lidar: bool = False, up: str | None = None, max_range: float | None = None,
                 ground_limits: bool = True, method_fields: dict | None = None) -> np.ndarray:
  """Flow N x 3 (float32) of every point of pc1 towards pc2 by `method` (default DEFAULT_METHOD,
  `optimise`, as `python -m jaxflow.predict`) with `method_fields` of its settings changed
  (load_predictor); the checkpoint (None: the shipped one) is loaded once and kept. `predictor`
  (load_predictor / fresh_predictor) replaces checkpoint and method. The Prediction's notes
  (non-convergence, a lopsided pair) are issued as warnings. `lidar=True` (predict's --lidar): the
  lidar method running `method` (the module docstring); `max_range`: its setting (m)."""
  if predictor is None:
    predictor = _cached_predictor(None if checkpoint is None else str(checkpoint),
                                  method or DEFAULT_METHOD, steps, objective,
                                  tuple(sorted((method_fields or {}).items())))
  elif method is not None and method != predictor.method:
    raise ConfigError(f"method={method!r} but the predictor given runs {predictor.method!r}")
  if lidar or registry.get(predictor.method).raw_sweeps:
    predictor = predictor.as_lidar(None if max_range is None else {"max_range": max_range})
  elif max_range is not None:
    raise ConfigError("max_range is the lidar method's setting: give lidar=True")
  prediction = predictor.predict(pc1_Nx3, pc2_Mx3, num_iters=num_iters, max_points=max_points,
                                 full=full, seed=seed, up=up, ground_limits=ground_limits)
  for note in prediction.notes:
    warnings.warn(note, stacklevel=2)
  return prediction.flow


def read_cloud(path, columns: int | None = None) -> tuple[np.ndarray, str | None, np.ndarray]:
  """read_points(path, columns), a note when non-finite rows were dropped (None otherwise) and
  which of the file's rows the points are (N bool: False for a dropped row)."""
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    points, rows = read_points(path, columns, rows=True)
  notes = [str(w.message) for w in caught if "non-finite" in str(w.message)]
  for w in caught:
    if "non-finite" not in str(w.message):
      warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
  return points, (notes[0] if notes else None), rows


def file_rows(flow_Nx3, rows_R) -> np.ndarray:
  """A flow of the kept points as one row per row of the file (R x 3, float32): NaN where the
  file's point was dropped (non-finite), so row i is always the flow of the file's i-th point."""
  out = np.full((len(rows_R), 3), np.nan, np.float32)
  out[rows_R] = flow_Nx3
  return out
