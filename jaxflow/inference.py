"""Flow of two point clouds by a method of jaxflow.methods.registry: the library side of jaxflow.predict.

    flow_Nx3 = predict_flow(pc1_Nx3, pc2_Mx3)                    # optimise, as the command
    flow_Nx3 = predict_flow(pc1_Nx3, pc2_Mx3, method="network")  # the network alone
    predictor = load_predictor(checkpoint, method="nsfp", objective="grid")
    prediction = predictor.predict(pc1_Nx3, pc2_Mx3)   # .flow, .notes, .used, .sweep

Cloud size. A cloud with at most `max_points` points (8192, the paper's test size; 0 or None: whole
clouds) is used whole, without resampling. A larger one is sampled to `max_points` points without
replacement, seeded (`seed`: the same call gives the same flow); pc1 and pc2 are sampled
independently. The flow is then mapped back to EVERY point of pc1: an unsampled pc1 point takes the
flow of its nearest sampled pc1 point (Euclidean; a sampled point keeps its own). With the
`optimise` method that mapped network flow is then optimised at every point against every pc2 point.
`full=True` runs the model on the whole clouds instead, with the correlation and kNN built
`corr_chunk` pc1 rows at a time (memory linear in the points; time grows as N x M).

Raw sweeps (`lidar=True`): jaxflow.lidar.sweep.raw_sweep_flow, the ground, the sensor's ego-motion
and one rigid motion per moving object; every pc1 point gets a row. The method itself runs only on a
camera's view (under half the azimuth: the non-ground points within `max_range`), or as one more
start for the fits with `use_network=True` (predict --lidar with an explicit --method);
`DeferredPredictor` loads the checkpoint only then. `sweep_settings`: the pipeline's settings
(a jaxflow.lidar.settings.Sweep; None: its defaults); `max_range` None: theirs.
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
from jaxflow.geometry import frames, ops
from jaxflow.lidar import sweep
from jaxflow.methods import registry
from jaxflow.network import checkpointing

DEFAULT_METHOD = "optimise"  # the API's and predict's: the network's flow refined per pair
DEFAULT_MAX_POINTS = 8192  # the paper's evaluation size
DEFAULT_ITERS = 32  # the paper's flow iterations at test time
DEFAULT_CORR_CHUNK = 2048  # full=True: pc1 rows of the correlation / kNN built at a time
SIZE_RATIO_WARNING = 100  # one cloud with this many times the other's points: a warning
# Said after the note of a cloud read with another up axis than the models' (z up: a sweep's).
LIDAR_HINT = ("; for a raw 360-degree LiDAR sweep (ground kept, before any cut) use --lidar "
              "(lidar=True in Python): the ground, the sensor's ego-motion and the moving objects, "
              "jaxflow.lidar.sweep")


@dataclasses.dataclass(frozen=True)
class Prediction:
  """One call's flow and what the user should know about it."""

  flow: np.ndarray  # N x 3 float32, a row per point of pc1 in its order
  notes: tuple = ()  # non-convergence of an optimisation, a lopsided pair
  used: tuple = ()  # (pc1, pc2) points the method was given (after the lidar cut)
  sweep: object = None  # sweep.SweepInfo with lidar=True
  up: str = frames.MODEL_UP  # the up axis of the clouds (jaxflow.geometry.frames): the flow is in their frame


def lopsided(n1: int, n2: int) -> str | None:
  """A warning when one cloud has SIZE_RATIO_WARNING times the other's points (None otherwise)."""
  ratio = max(n1, n2) / max(min(n1, n2), 1)
  if ratio <= SIZE_RATIO_WARNING:
    return None
  return (f"PC1 has {n1} points and PC2 {n2} ({ratio:.0f}x) as the method saw them: the model "
          "expects two scans of one scene at a similar density; this flow is unlikely to mean much")


@dataclasses.dataclass
class Predictor:
  """A method with its network (None for nsfp): `predictor.predict(pc1_Nx3, pc2_Mx3)` ->
  Prediction; `predictor(pc1_Nx3, pc2_Mx3)` -> its flow alone."""

  model: object
  params: object
  config: ml_collections.ConfigDict  # the checkpoint's config (the model it was built from)
  refine: bool  # the refined flow (stage 2) or the last iteration's
  name: str = ""  # checkpoint path and step, for messages
  method: str = DEFAULT_METHOD  # jaxflow.methods.registry: network, nsfp (model None) or optimise
  method_settings: object = None  # None: the method's defaults
  _fns: dict = dataclasses.field(default_factory=dict, repr=False)  # compiled, by shapes' settings

  @property
  def min_points(self) -> int:
    """Fewer points than the model's neighbourhood (config.model.knn) are refused."""
    return int(self.config.model.knn)

  def _fn(self, num_iters: int, corr_chunk: int, method: str):
    """jit (params, pc1, pc2) -> (flow, info) of `method` (this predictor's or `network`)."""
    key = (num_iters, corr_chunk, method)
    if key not in self._fns:
      model = self.model if self.model is None or corr_chunk == self.model.corr_chunk else (
        self.model.clone(corr_chunk=corr_chunk))
      chosen = self.method_settings if method == self.method else None
      self._fns[key] = registry.model_predict_fn(model, num_iters, self.refine, method, chosen,
                                                   with_info=True)
    return self._fns[key]

  def __call__(self, pc1_Nx3, pc2_Mx3, **kwargs) -> np.ndarray:
    """The flow N x 3 of every point of pc1 (`predict`'s arguments)."""
    return self.predict(pc1_Nx3, pc2_Mx3, **kwargs).flow

  def predict(self, pc1_Nx3, pc2_Mx3, num_iters: int = DEFAULT_ITERS,
              max_points: int | None = DEFAULT_MAX_POINTS, full: bool = False,
              corr_chunk: int | None = DEFAULT_CORR_CHUNK, seed: int = 0, names=("pc1", "pc2"),
              lidar: bool = False, up: str | None = None, max_range: float | None = None,
              ground_limits: bool = True, use_network: bool = False,
              sweep_settings=None) -> Prediction:
    """The Prediction of every point of pc1 (the module docstring: sampling, full, lidar). `up`:
    the clouds' up axis (default z with lidar, else y, the models' frame; jaxflow.geometry.frames):
    the clouds are rotated into the models' frame for the method and the flow back. `corr_chunk`
    None: the model's own."""
    kwargs = dict(num_iters=num_iters, max_points=max_points, full=full, corr_chunk=corr_chunk,
                  seed=seed)
    if self.method == "lidar":  # the lidar method alone: no network, not even for a camera's view
      settings = self.method_settings if sweep_settings is None else sweep_settings
      return sweep_prediction(None, pc1_Nx3, pc2_Mx3, names, up, max_range, ground_limits,
                              use_network, settings, **kwargs)
    if lidar:
      return sweep_prediction(lambda: self, pc1_Nx3, pc2_Mx3, names, up, max_range, ground_limits,
                              use_network, sweep_settings, **kwargs)
    pc1 = as_cloud(pc1_Nx3, names[0], self.min_points)
    up, note = frames.resolve_up(pc1, up, frames.MODEL_UP, names[0], ground_limits)
    note = note and note + LIDAR_HINT  # a cloud read with another up is likely a sweep
    inner = self._predict(frames.to_model(pc1, up),
                          frames.to_model(as_cloud(pc2_Mx3, names[1], self.min_points), up),
                          **kwargs)
    return dataclasses.replace(inner, flow=frames.from_model(inner.flow, up), up=up,
                               notes=(note, *inner.notes) if note else inner.notes)

  def _predict(self, pc1_Nx3, pc2_Mx3, num_iters, max_points, full, corr_chunk, seed):
    corr_chunk = getattr(self.model, "corr_chunk", 0) if corr_chunk is None else corr_chunk
    if num_iters < 1:
      raise ConfigError(f"num_iters must be >= 1, got {num_iters}")
    if corr_chunk < 0:
      raise ConfigError(f"corr_chunk must be >= 0, got {corr_chunk}")
    if max_points is not None and max_points < 0:
      raise ConfigError(f"max_points must be >= 0, got {max_points}")
    used = (len(pc1_Nx3), len(pc2_Mx3))
    notes = [lopsided(*used)]
    if full or not max_points:
      flow, info = self._fn(num_iters, corr_chunk, self.method)(
        self.params, pc1_Nx3[None], pc2_Mx3[None])
      return self._prediction(flow[0], info, notes, used)
    if max_points < self.min_points:
      raise ConfigError(f"max_points={max_points} is below the model's neighbourhood "
                        f"(config.model.knn={self.min_points})")
    rng = np.random.default_rng(seed)
    idx1 = sample_indices(len(pc1_Nx3), max_points, rng)[0] if len(pc1_Nx3) > max_points else None
    idx2 = sample_indices(len(pc2_Mx3), max_points, rng)[0] if len(pc2_Mx3) > max_points else None
    sub1 = pc1_Nx3 if idx1 is None else pc1_Nx3[idx1]
    sub2 = pc2_Mx3 if idx2 is None else pc2_Mx3[idx2]
    every_point = self.method == "optimise"  # the network sees samples, the optimiser every point
    if every_point:  # the network's flow of the samples starts optimise: the method's settings
      chosen = self.method_settings
      key = ("start", chosen.start_candidates, chosen.start_iters or num_iters)
      if key not in self._fns:
        network = registry.network_for(self.model, num_iters, self.refine)(
          chosen.start_iters, chosen.start_candidates)
        self._fns[key] = jax.jit(lambda *args: (network(*args), None))
      fn = self._fns[key]
    else:
      fn = self._fn(num_iters, getattr(self.model, "corr_chunk", 0), self.method)
    flow_Sx3, info = fn(self.params, sub1[None], sub2[None])
    flow_Sx3 = np.asarray(flow_Sx3[0])
    flow_Nx3 = flow_Sx3 if idx1 is None else spread_flow(pc1_Nx3, sub1, flow_Sx3)
    if idx1 is not None:
      flow_Nx3[idx1] = flow_Sx3  # a sampled point keeps its own flow, even at ties
    if every_point:
      flow, info = _from_start(self.method_settings)(flow_Nx3[None], pc1_Nx3[None], pc2_Mx3[None])
      flow_Nx3 = flow[0]
    return self._prediction(flow_Nx3, info, notes, used)

  def _prediction(self, flow_Nx3, info, notes, used) -> Prediction:
    notes = [*notes, registry.convergence_note(self.method, jax.device_get(info))]
    return Prediction(np.asarray(flow_Nx3, np.float32), tuple(n for n in notes if n), used)


def sweep_prediction(get_predictor, pc1_Nx3, pc2_Mx3, names=("pc1", "pc2"), up: str | None = None,
                     max_range: float | None = None, ground_limits: bool = True,
                     use_network: bool = False,
                     sweep_settings=None,
                     **kwargs) -> Prediction:
  """The Prediction of raw sweeps (jaxflow.lidar.sweep); `get_predictor()` gives the method's
  Predictor, called only when the method runs (a camera's view, or `use_network`): a 360-degree
  sweep loads no network (None: no method runs, the `lidar` method alone). `sweep_settings`:
  raw_sweep_flow's `settings`; `kwargs`: Predictor.predict's sampling arguments."""
  sweep_settings = sweep.settings_of(sweep_settings)
  least = sweep.min_points(sweep_settings)  # the pipeline's own, whether or not a method runs
  clouds = [as_cloud(c, n, least, sweep.too_few(sweep_settings))
            for c, n in zip((pc1_Nx3, pc2_Mx3), names)]
  up, up_note = frames.resolve_up(clouds[0], up, "z", names[0], ground_limits)
  max_range = sweep_settings.max_range if max_range is None else max_range
  kwargs = {**dict(num_iters=DEFAULT_ITERS, max_points=DEFAULT_MAX_POINTS, full=False,
                   corr_chunk=DEFAULT_CORR_CHUNK, seed=0), **kwargs}
  kept_names = tuple(f"{n} (after ground removal and the {max_range} m cut)" for n in names)
  inner = []  # the Prediction of the kept points (this call's own)

  def estimate(kept1, kept2):  # in the models' frame (frames.in_model_frame)
    predictor = get_predictor()
    inner.append(predictor._predict(  # pylint: disable=protected-access
      as_cloud(kept1, kept_names[0], predictor.min_points),
      as_cloud(kept2, kept_names[1], predictor.min_points), **kwargs))
    return inner[-1].flow

  flow_fn = None if get_predictor is None else frames.in_model_frame(estimate, up)
  flow, info = sweep.raw_sweep_flow(flow_fn, *clouds, up=up,
                                    max_range=max_range, names=names,
                                    ground_limits=ground_limits, use_network=use_network,
                                    settings=sweep_settings)
  notes = inner[-1].notes if inner else tuple(n for n in [lopsided(*info.kept)] if n)
  notes = (up_note, *notes) if up_note else notes
  return Prediction(np.asarray(flow, np.float32), notes, info.kept, info, up)


class DeferredPredictor:
  """load_predictor(*args), loaded at its first use: `predict(..., lidar=True)` of a 360-degree
  sweep never uses it (predict --lidar loads no checkpoint unless the method runs)."""

  def __init__(self, *load_args):
    self._load_args, self._loaded = load_args, None

  @property
  def loaded(self) -> bool:
    return self._loaded is not None

  def get(self) -> Predictor:
    if self._loaded is None:
      self._loaded = load_predictor(*self._load_args)
    return self._loaded

  def predict(self, pc1_Nx3, pc2_Mx3, lidar: bool = False, names=("pc1", "pc2"),
              up: str | None = None, max_range: float | None = None,
              ground_limits: bool = True, use_network: bool = False,
              sweep_settings=None, **kwargs) -> Prediction:
    if not lidar:
      return self.get().predict(pc1_Nx3, pc2_Mx3, names=names, up=up,
                                ground_limits=ground_limits, **kwargs)
    return sweep_prediction(self.get, pc1_Nx3, pc2_Mx3, names, up, max_range, ground_limits,
                            use_network, sweep_settings, **kwargs)

  def __getattr__(self, name):  # name, method, method_settings, model, ...: the loaded one's
    if name.startswith("_"):
      raise AttributeError(name)
    return getattr(self.get(), name)


@functools.lru_cache(maxsize=8)
def _from_start(chosen):
  """jit (start flow, pc1, pc2) -> (flow, info) of `optimise` from a given starting flow (the
  network's flow of the samples spread to every point)."""
  return registry.flow_fn("optimise", lambda start, pc1, pc2: start, chosen, with_info=True)


def spread_flow(points_Nx3, sampled_Sx3, flow_Sx3, chunk: int = 4096) -> np.ndarray:
  """Flow N x 3 for every point: the flow of its nearest sampled point (chunked: memory ~ chunk x S)."""
  return np.array(_spread(jnp.asarray(points_Nx3), jnp.asarray(sampled_Sx3),
                           jnp.asarray(flow_Sx3), chunk))


@functools.partial(jax.jit, static_argnums=3)
def _spread(points_Nx3, sampled_Sx3, flow_Sx3, chunk):
  nearest_N = ops.knn(points_Nx3[None], sampled_Sx3[None], 1, chunk)[0, :, 0]
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
                   method_fields: dict | None = None) -> Predictor:
  """The Predictor of `method` (jaxflow.methods.registry; `steps` caps its optimiser, `objective` is
  NSFP's, `iters` sets optimise's starting flow's iterations, `method_fields` sets any of its
  settings, {"bodies.inlier": 0.1}) with the model of a checkpoint (workdir, checkpoints folder or
  step folder; None: the shipped one; nsfp loads none). `model_fields`:
  checkpointing.load_for_inference."""
  chosen = registry.settings(method, steps, iters, objective, method_fields)
  if method not in registry.NEEDS_NETWORK:
    return Predictor(None, None, ml_collections.ConfigDict({"model": {"knn": 1}}), False,
                     name=f"{method}, no network", method=method, method_settings=chosen)
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
  return Predictor(model, params, config, refine=False, name="fresh (untrained)", method=method,
                   method_settings=registry.settings(method))


@functools.lru_cache(maxsize=4)
def _cached_predictor(checkpoint: str | None, method: str, steps, objective,
                      method_fields: tuple) -> Predictor:
  return load_predictor(checkpoint, method=method, steps=steps, objective=objective,
                        method_fields=dict(method_fields))


def predict_flow(pc1_Nx3, pc2_Mx3, method: str | None = None, checkpoint=None,
                 steps: int | None = None, objective: str | None = None,
                 num_iters: int = DEFAULT_ITERS, max_points: int | None = DEFAULT_MAX_POINTS,
                 full: bool = False, corr_chunk: int = DEFAULT_CORR_CHUNK, seed: int = 0,
                 predictor: Predictor | None = None, lidar: bool = False, up: str | None = None,
                 max_range: float | None = None, ground_limits: bool = True,
                 sweep_settings=None,
                 method_fields: dict | None = None) -> np.ndarray:
  """Flow N x 3 (float32) of every point of pc1 towards pc2 by `method` (default DEFAULT_METHOD,
  `optimise`, as `python -m jaxflow.predict`) with `method_fields` of its settings changed
  (load_predictor); the checkpoint (None: the shipped one) is loaded once and kept. `predictor`
  (load_predictor / fresh_predictor) replaces checkpoint and method. The Prediction's notes
  (non-convergence, a lopsided pair) are issued as warnings. `lidar=True`: raw sweeps (the module
  docstring), tuned by `sweep_settings`."""
  if predictor is None:
    predictor = _cached_predictor(None if checkpoint is None else str(checkpoint),
                                  method or DEFAULT_METHOD, steps, objective,
                                  tuple(sorted((method_fields or {}).items())))
  elif method is not None and method != predictor.method:
    raise ConfigError(f"method={method!r} but the predictor given runs {predictor.method!r}")
  prediction = predictor.predict(pc1_Nx3, pc2_Mx3, num_iters=num_iters, max_points=max_points,
                                 full=full, corr_chunk=corr_chunk, seed=seed, lidar=lidar, up=up,
                                 max_range=max_range, ground_limits=ground_limits,
                                 sweep_settings=sweep_settings)
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
