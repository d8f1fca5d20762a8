"""Raw 360-degree LiDAR sweep pairs, as a driving car's roof sensor records them.

    sweep = sweep_pair("val", 3)          # a SweepPair: pc1, pc2, flow, ego flow, labels, ground
    ds = open_dataset("synthetic_sweep:20", "test")   # as jaxflow Pairs (evaluate.py)
    ds = open_dataset("synthetic_sweep:8,form=city", "val")   # a dense city (FORMS)
    ds = open_dataset("synthetic_sweep:8,reverse=1", "val")   # each pair backwards

Unlike `synthetic_lidar` (the KITTI loader's cut: no ground, 35 m, the camera's field of view, y up)
these pairs are what a raw sweep is: z up (x forward, y left), the full azimuth, 32, 64 or 128
beams from -25 to +15 degrees, ranges to 100 m, the ground KEPT (a crowned road with raised
sidewalks and, in some scenes, a slope that starts ahead or behind), the ego car moving 0-3 m a
frame with a yaw rate, buildings, poles, trees, parked cars and what moves at the world's speeds:
cars at every speed from 0.05 to 3 m a frame (log-uniform, so creeping, stopping and queueing cars
are as common as fast ones; a dense city's to 1.5 and more slow ones), often one passing beside
the sensor, pedestrians walking 0.06-0.18 m a frame (on the sidewalks, and 10-25 m away crossing
the road or walking along it) and cyclists.
The two sweeps are ray-cast independently from the sensor's two poses (their own azimuth phase and
range noise): no point of pc2 is a moved pc1 point, as in real sweeps.

Per point of pc1: `flow` (where the surface point is in frame 2, in frame 2's sensor coordinates:
ego-motion included, the OpenSceneFlow convention), `ego_flow` (the flow the point would have if
static: the sensor's motion alone), `category` (av2's CATEGORY_TO_INDEX: 0 background, 19
REGULAR_VEHICLE, 17 PEDESTRIAN, 4 BICYCLIST), `instance` (0 for the background), `ground` (bool).
`eval_mask`: the AV2 challenge's points (non-ground, |x|, |y| <= 50 m).

Splits are seed ranges: val (for choosing settings) and test (for reporting only) never share a
scene; each pair is determined by (split, index). Scenes are built in `jaxflow.data.synthetic`'s
internal frame (y up, z forward) with its ray caster, then turned to z up by a cyclic permutation
of the axes (a proper rotation, so rigid motions stay rigid).
"""

import dataclasses
import math

import numpy as np

from jaxflow.data import street as streets, synthetic as syn
# (the av2 categories of the labels, for the callers: ss.PEDESTRIAN)
from jaxflow.data.street import (BACKGROUND, BICYCLIST, PEDESTRIAN,  # noqa: F401
                                 REGULAR_VEHICLE, Street)
from jaxflow.data.registry import Dataset, Pair, register
from jaxflow.errors import DataError
from jaxflow.geometry import frames

SPLITS = ("val", "test")
SEED_BASE = {"val": 1_000_000, "test": 2_000_000}  # seeds: base + index (disjoint ranges)
DEFAULT_COUNT = {"val": 50, "test": 50}
BEAMS = (32, 64, 128)
ELEVATION_DEG = (-25.0, 15.0)
RAYS = 120_000  # rays a sweep at scale 1 (about 80-100k returns)
MAX_RANGE = 100.0
RANGE_NOISE = 0.01  # metres, one sigma along the ray
EVAL_BOX = 50.0  # |x|, |y| <= this: the AV2 challenge's evaluated points


@dataclasses.dataclass(frozen=True)
class SweepPair:
  """Two raw sweeps (float32, z up) and pc1's labels; ego_motion maps frame-1 to frame-2 sensor
  coordinates (x -> R x + t, the flow of a static point is R x + t - x)."""
  pc1: np.ndarray  # N x 3
  pc2: np.ndarray  # M x 3
  flow: np.ndarray  # N x 3, ego-motion included
  ego_flow: np.ndarray  # N x 3
  category: np.ndarray  # N uint8
  instance: np.ndarray  # N int16
  ground: np.ndarray  # N bool
  ground2: np.ndarray  # M bool
  ego_rotation: np.ndarray  # 3 x 3
  ego_translation: np.ndarray  # 3
  name: str

  @property
  def eval_mask(self) -> np.ndarray:
    return ~self.ground & (np.abs(self.pc1[:, :2]) <= EVAL_BOX).all(1)

  @property
  def foreground(self) -> np.ndarray:
    return self.category != BACKGROUND

  def to_pair(self) -> Pair:
    """As a jaxflow Pair: mask = eval_mask, rigid_flow = ego_flow, the av2 categories and the
    points' x, y (the sensor's frame stands for the ego frame: the official breakdown)."""
    return Pair(self.pc1, self.pc2, self.flow, self.eval_mask, self.name, rigid_flow=self.ego_flow,
                foreground=self.foreground, category=self.category.astype(np.uint8),
                ego_xy=np.ascontiguousarray(self.pc1[:, :2], np.float32))


@dataclasses.dataclass(frozen=True)
class Options:
  """What a scene may hold (the defaults: everything drawn at random)."""
  ground: bool = True
  speed: tuple | None = None  # (lo, hi) m a frame; None: 0-3 with parked and slow scenes
  movers: bool = True  # moving cars, pedestrians and cyclists
  scale: float = 1.0  # rays x scale (0.05: ~5k points, for tests)
  beams: int | None = None
  # What real sweeps vary in beyond the scene (the defaults: a roof sensor at the origin):
  origin_height: float | None = None  # metres above the road of the frame's origin (None: the
  # sensor's, 1.7-2.1 m; Argoverse 2's ego frame 0.33, Waymo's vehicle frame 0)
  dense: bool = False  # a dense city: a narrow street walled by facades (the road ~20-30% of
  # the points within 20 m instead of ~55-70%)
  stacked: bool = False  # two 32-beam sensors stacked (Argoverse 2): two ring patterns a sweep
  reverse: bool = False  # the pair taken backwards: pc1 the later sweep, its flow to the earlier


# z up (x forward, y left) <- the caster's frame (x, y up, z forward): a cyclic permutation.
_TO_Z_UP = frames.rotation("y", "z")


def _grid(rng, beams: int, columns: int, offset_deg: float = 0.0) -> syn.Grid:
  el = np.deg2rad(np.linspace(*ELEVATION_DEG, beams) + offset_deg)
  step = 2 * math.pi / columns
  az = -math.pi + (np.arange(columns) + rng.random()) * step
  ce, se, ca, sa = np.cos(el)[:, None], np.sin(el)[:, None], np.cos(az), np.sin(az)
  dirs = np.stack([ce * sa, np.broadcast_to(se, (beams, columns)), ce * ca])
  return syn.Grid(dirs, el, el, az - step / 2, az + step / 2, pinhole=False)


def _sensor_motion(rng, opt: Options):
  """(rotation, position) of the sensor in frame 2: 0-3 m a frame forward (or opt.speed's), a yaw
  rate, a little pitch and roll when moving."""
  speed = rng.uniform(*opt.speed) if opt.speed else (
    0.0 if rng.random() < 0.1 else rng.uniform(0.1, 1.0) if rng.random() < 0.4
    else rng.uniform(1.0, 3.0))
  yaw = np.deg2rad(rng.uniform(-3, 3)) * (0.3 if speed > 2 else 1.0) * (speed > 0)
  tilt = syn.rotation((1, 0, 0), np.deg2rad(rng.normal(0, 0.15))) @ syn.rotation(
    (0, 0, 1), np.deg2rad(rng.normal(0, 0.1))) if speed > 0 else syn.IDENTITY
  return (syn.rotation((0, 1, 0), yaw) @ tilt,
          (math.sin(yaw / 2) * speed, 0.0, math.cos(yaw / 2) * speed))


def build_scene(rng, opt: Options = Options()):
  """(Scene in the caster's frame, category per primitive, instance per primitive, ground prims,
  the sensor's height above the road)."""
  # The draws' order is the scenes' identity: (split, index) pairs stay the same scenes. The
  # movers added last draw from their own stream (spawned: `rng`'s draws are not moved by them).
  more = rng.spawn(1)[0]
  scene = streets.Labelled(syn.Builder(*_sensor_motion(rng, opt)))
  street = Street(rng, rng.uniform(1.7, 2.1), opt.dense)
  if opt.ground:
    for kind, rot, pos, size in street.planes():
      scene.add([(kind, syn.IDENTITY, syn.ZERO, size, None)], rot, pos, is_ground=True)
  for side in (-1, 1):
    streets.facades(rng, scene, street, side, opt.dense)
    streets.roadside(rng, scene, street, side, opt.dense)
    if opt.movers:
      streets.vulnerable(rng, scene, street, side, opt.dense)
  if opt.movers:
    streets.traffic(rng, scene, street, opt.dense)
    streets.more_movers(more, scene, street, opt.dense)
  return scene.built(-street.g)


def _cast(scene, frame, rng, opt: Options, beams: int):
  columns = max(16, round(RAYS * opt.scale / beams))
  if opt.stacked:  # two 32-beam sensors, each with its own azimuth phase, rings interleaved
    grids = [_grid(rng, 32, columns * beams // 64), _grid(rng, 32, columns * beams // 64, 0.6)]
  else:
    grids = [_grid(rng, beams, columns)]
  casts = [syn.render(scene, frame, g, max_depth=MAX_RANGE) for g in grids]
  points = np.concatenate([c[0] for c in casts], 1)
  prim = np.concatenate([c[1] for c in casts])
  rng_ = np.sqrt((points * points).sum(0))
  keep = np.flatnonzero(rng_ <= MAX_RANGE)
  points, prim, rng_ = points.take(keep, axis=1), prim[keep], rng_[keep]
  noise = points * (rng.normal(0, RANGE_NOISE, len(rng_)) / np.maximum(rng_, 1e-6))
  return points, prim, noise


def sweep_pair(split: str, index: int, options: Options = Options()) -> SweepPair:
  """Pair `index` of `split` (val or test): see the module docstring."""
  if split not in SPLITS:
    raise DataError(f"synthetic_sweep/{split}", f"unknown split; expected one of {SPLITS}")
  rng = np.random.default_rng(SEED_BASE[split] + index)
  built = build_scene(rng, options)
  name = f"synthetic_sweep/{split}/{index}" + ("/reverse" if options.reverse else "")
  return cast_pair(rng, built, options, name)


def cast_pair(rng, built, options: Options, name: str) -> SweepPair:
  """The two sweeps of a built scene (build_scene's tuple), cast with `rng`, and pc1's labels."""
  scene, cat_P, inst_P, ground_P, sensor_height = built
  beams = options.beams or int(rng.choice(BEAMS))
  p1, prim1, noise1 = _cast(scene, 0, rng, options, beams)
  p2, prim2, noise2 = _cast(scene, 1, rng, options, beams)
  p1, p2 = p1 + noise1, p2 + noise2  # the measured point moves with its object
  static = dataclasses.replace(scene, obj_P=np.zeros_like(scene.obj_P))
  a, b = scene.a_Kx3x3[0], scene.b_Kx3[0]  # the static world's (the sensor's) motion
  if options.reverse:  # frame 2 -> frame 1: each object's inverse motion
    p1, p2, prim1, prim2 = p2, p1, prim2, prim1
    a, b = a.T, -a.T @ b
  moved = syn.warp(scene, p1, prim1, inverse=options.reverse)  # the same points in the other frame
  ego = syn.warp(static, p1, prim1, inverse=options.reverse)
  # The frame's origin below the sensor (a vehicle frame): every point higher by `lift`, the
  # frame's motion x -> R x + t becomes x -> R x + t + lift - R lift.
  lift = np.zeros(3)
  if options.origin_height is not None:
    lift[2] = sensor_height - options.origin_height
  z_up = lambda a_3xN: np.ascontiguousarray((_TO_Z_UP @ a_3xN).T, np.float32)
  rotation = _TO_Z_UP @ a @ _TO_Z_UP.T
  return SweepPair(
    pc1=z_up(p1) + lift.astype(np.float32), pc2=z_up(p2) + lift.astype(np.float32),
    flow=z_up(moved - p1), ego_flow=z_up(ego - p1),
    category=cat_P[prim1], instance=inst_P[prim1], ground=ground_P[prim1], ground2=ground_P[prim2],
    ego_rotation=rotation, ego_translation=_TO_Z_UP @ b + lift - rotation @ lift,
    name=name)


# The forms a spec may ask for ("synthetic_sweep:COUNT,form=NAME"): what the benchmarks score.
FORMS = {"generated": Options(),
         "city": Options(dense=True, origin_height=0.33, stacked=True),  # Argoverse 2-like
         "noground": Options(ground=False)}  # the ground removed upstream


class SyntheticSweep(Dataset):
  """`count` raw sweep pairs of one split and form, generated on demand."""
  up = "z"  # x forward, y left, z up: the sensor at the origin

  def __init__(self, split: str, count: int, form: str = "generated", reverse: bool = False):
    self.split, self.count, self.form, self.reverse = split, count, form, reverse
    self.name = (f"synthetic_sweep:{count}" + (f",form={form}" if form != "generated" else "")
                 + (",reverse=1" if reverse else ""))

  def __len__(self):
    return self.count

  def load(self, i):
    options = dataclasses.replace(FORMS[self.form], reverse=self.reverse)
    return sweep_pair(self.split, i, options).to_pair()

  def describe(self):
    return (f"{self.name} split={self.split}: {self.count} raw 360-degree sweep pairs "
            f"({self.form}{', backwards' if self.reverse else ''}), z up")


def open_sweeps(arg: str, split: str | None) -> SyntheticSweep:
  """"COUNT[,form=generated|city|noground][,reverse=1]" (module docstring; FORMS; reverse: each
  pair taken backwards)."""
  spec = f"synthetic_sweep:{arg}"
  count, *options = arg.split(",")
  split = split or "val"
  if split not in SPLITS:
    raise DataError(spec, f"unknown split {split!r}; synthetic_sweep's splits are {SPLITS}")
  if count and (not count.isdigit() or int(count) < 1):
    raise DataError(spec, f"COUNT must be a positive integer, got {count!r}")
  form, reverse = "generated", False
  for option in options:
    key, eq, value = option.partition("=")
    if key == "reverse" and value in ("0", "1"):
      reverse = value == "1"
    elif key != "form" or not eq or value not in FORMS:
      raise DataError(spec, f"bad option {option!r}; expected form=one of {', '.join(FORMS)} or "
                      "reverse=0|1")
    else:
      form = value
  return SyntheticSweep(split, int(count) if count else DEFAULT_COUNT[split], form, reverse)


register("synthetic_sweep", open_sweeps)
