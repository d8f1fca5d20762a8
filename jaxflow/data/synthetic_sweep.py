"""Raw 360-degree LiDAR sweep pairs, as a driving car's roof sensor records them.

    sweep = sweep_pair("val", 3)          # a SweepPair: pc1, pc2, flow, ego flow, labels, ground
    ds = open_dataset("synthetic_sweep:20", "test")   # as jaxflow Pairs (evaluate.py)
    ds = open_dataset("synthetic_sweep:8,form=city", "val")   # a dense city (FORMS)
    ds = open_dataset("synthetic_sweep:8,reverse=1", "val")   # each pair backwards

Unlike `synthetic_lidar` (the KITTI loader's cut: no ground, 35 m, the camera's field of view, y up)
these pairs are what a raw sweep is: z up (x forward, y left), the full azimuth, 32, 64 or 128
beams from -25 to +15 degrees, ranges to 100 m, the ground KEPT (a crowned road with raised
sidewalks and, in some scenes, a slope that starts ahead or behind), the ego car moving 0-3 m a
frame with a yaw rate, parked and moving cars, pedestrians, cyclists, buildings, poles and trees.
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

from jaxflow.data import synthetic as syn
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
BACKGROUND, BICYCLIST, PEDESTRIAN, REGULAR_VEHICLE = 0, 4, 17, 19  # av2 CATEGORY_TO_INDEX


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


class Street:
  """The ground's height field (caster frame: x across the road, z along it) and its planes."""

  def __init__(self, rng, sensor_height: float, dense: bool = False):
    self.g = -sensor_height
    # half width: parking, a cycle lane, two lanes, the ego's (a dense city: two lanes, parking)
    self.road = rng.uniform(9.0, 12.0) if not dense else rng.uniform(4.5, 5.5)
    self.crown = rng.uniform(0.0, 0.15)  # road centre above its edges
    self.kerb = rng.uniform(0.08, 0.18)
    hill = rng.random()
    self.ahead = (rng.uniform(8, 30), rng.uniform(-0.07, 0.07)) if hill < 0.4 else None
    self.behind = (rng.uniform(-30, -8), rng.uniform(-0.07, 0.07)) if 0.25 < hill < 0.55 else None

  def along(self, z):
    """Height of the road's edge line at z (the slope part)."""
    h = self.g
    if self.ahead and z > self.ahead[0]:
      h += (z - self.ahead[0]) * self.ahead[1]
    if self.behind and z < self.behind[0]:
      h += (z - self.behind[0]) * self.behind[1]
    return h

  def height(self, x, z):
    across = self.crown * max(0.0, 1 - abs(x) / self.road) if abs(x) < self.road else self.kerb
    return self.along(z) + across

  def planes(self):
    """[(kind, rot, pos, size)] of the ground: road halves (crowned planes) and sidewalks (slabs)
    per segment of the slope."""
    cuts = [-110.0] + ([self.behind[0]] if self.behind else []) + (
      [self.ahead[0]] if self.ahead else []) + [110.0]
    out = []
    for z0, z1 in zip(cuts[:-1], cuts[1:]):
      zc = (z0 + z1) / 2
      grade = (self.along(z1) - self.along(z0)) / (z1 - z0)
      pitch = syn.rotation((1, 0, 0), -math.atan(grade))
      half_z = (z1 - z0) / 2 * math.sqrt(1 + grade * grade)
      for side in (-1, 1):
        roll = syn.rotation((0, 0, 1), -side * math.atan(self.crown / self.road))
        pos = (side * self.road / 2, self.along(zc) + self.crown / 2, zc)
        out.append((syn.PLANE, pitch @ roll, pos, (self.road / 2, 0, half_z)))
        walk, depth = 55.0, 0.6  # a slab: its top is the sidewalk, its side the kerb
        pos = (side * (self.road + walk), self.along(zc) + self.kerb - depth / 2, zc)
        out.append((syn.BOX, pitch, pos, (walk, depth / 2, half_z)))
    return out


def _person(rng):
  return [(syn.CYLINDER, syn.IDENTITY, (0, 0.8, 0), (rng.uniform(0.18, 0.26), 0.8, 0), None),
          (syn.ELLIPSOID, syn.IDENTITY, (0, 1.8, 0), (0.13,) * 3, None)]


def _cyclist(rng):
  return [(syn.BOX, syn.IDENTITY, (0, 0.45, 0), (0.08, 0.35, 0.85), None),
          (syn.CYLINDER, syn.IDENTITY, (0, 1.25, 0), (0.2, 0.45, 0), None)]


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


class _Labelled:
  """A scene's builder and the labels of its primitives, as build_scene adds them."""

  def __init__(self, builder: syn.Builder):
    self.builder, self.cats, self.insts, self.grounds = builder, [], [], []

  def add(self, parts, rot, pos, cat=BACKGROUND, motion_rot=None, motion_pos=None,
          is_ground=False):
    """One object (its primitives share its label; an instance number unless background)."""
    inst = len(set(self.insts)) + 1 if cat != BACKGROUND else 0
    self.builder.add(parts, rot, pos, motion_rot, motion_pos)
    self.cats.extend([cat] * len(parts))
    self.insts.extend([inst] * len(parts))
    self.grounds.extend([is_ground] * len(parts))

  def built(self, sensor_height: float):
    """build_scene's tuple."""
    return (self.builder.scene(), np.array(self.cats, np.uint8), np.array(self.insts, np.int16),
            np.array(self.grounds), sensor_height)


def _facades(rng, scene: _Labelled, street: Street, side: int, dense: bool):
  """A row of buildings along one side, with gaps (a dense city: at the sidewalk, tall)."""
  road = street.road
  z = rng.uniform(-100, -80)
  while z < 100:
    length = rng.uniform(6, 30)
    if rng.random() < 0.75 or dense:
      x = side * (road + (rng.uniform(3, 9) if not dense else rng.uniform(1.0, 2.0)))
      height = rng.uniform(3, 18) if not dense else rng.uniform(12, 30)
      base = street.height(x, z + length / 2) - 2
      scene.add([(syn.BOX, syn.IDENTITY, syn.ZERO, (4, height / 2 + 1, length / 2), None)],
                syn.rotation((0, 1, 0), rng.uniform(-0.06, 0.06)),
                (x + side * 4, base + height / 2 + 1, z + length / 2))
    z += length + (rng.uniform(0, 8) if not dense else rng.uniform(0, 1))


def _roadside(rng, scene: _Labelled, street: Street, side: int, dense: bool):
  """Poles and trees on one sidewalk, and the cars parked along it."""
  road = street.road
  for _ in range(rng.integers(3, 10)):
    x, z, h = side * (road + rng.uniform(0.4, 2.0)), rng.uniform(-60, 60), rng.uniform(3, 8)
    parts = [(syn.CYLINDER, syn.IDENTITY, (0, h / 2, 0), (rng.uniform(0.08, 0.25), h / 2, 0), None)]
    if rng.random() < 0.5:
      crown = rng.uniform(1.0, 2.5)
      parts.append((syn.ELLIPSOID, syn.IDENTITY, (0, h + crown * 0.6, 0), (crown, crown * 0.8, crown),
                    syn.random_bump(rng, 0.12)))
    scene.add(parts, syn.IDENTITY, (x, street.height(x, z) - 0.05, z))
  for _ in range(rng.integers(1, 7) if not dense else rng.integers(6, 12)):
    x, z = side * (road - 1.1), rng.uniform(-50, 50)
    heading = rng.uniform(-0.08, 0.08) + (side < 0) * math.pi
    scene.add(syn.car_parts(rng), syn.rotation((0, 1, 0), heading), (x, street.height(x, z), z),
              REGULAR_VEHICLE)


def _vulnerable(rng, scene: _Labelled, street: Street, side: int):
  """Pedestrians on one sidewalk (most walking) and perhaps a cyclist near its kerb, riding with
  the traffic of its side."""
  road = street.road
  for _ in range(rng.integers(0, 4)):
    x, z = side * (road + rng.uniform(0.6, 2.5)), rng.uniform(-30, 30)
    walking = rng.random() < 0.7
    scene.add(_person(rng), syn.IDENTITY, (x, street.height(x, z), z), PEDESTRIAN,
              syn.rotation((0, 1, 0), rng.uniform(-0.1, 0.1)) if walking else None,
              (rng.uniform(-0.05, 0.05), 0, rng.uniform(-0.18, 0.18)) if walking else None)
  if rng.random() < 0.5:
    x, z = side * (road - 3.2), rng.uniform(-30, 30)
    heading = 0.0 if side < 0 else math.pi
    v = rng.uniform(0.3, 0.8)
    scene.add(_cyclist(rng), syn.rotation((0, 1, 0), heading), (x, street.height(x, z), z),
              BICYCLIST, syn.IDENTITY, (0, 0, v * math.cos(heading)))


def _traffic(rng, scene: _Labelled, street: Street, dense: bool):
  """Cars in the two lanes (+z on the left, -z on the right), a quarter of them stopped."""
  road = street.road
  inner = 0.8 if not dense else 1.3  # lane centre from the parking strip (dense: 0.6-1.1 m
  # between a passing car and a parked one)
  for lane in (inner - road / 2, road / 2 - inner):
    heading = 0.0 if lane < 0 else math.pi
    z = rng.uniform(-60, -40)
    while z < 60:
      if abs(z) > 6 or lane > 2.2:  # the ego car drives at x = 0 (2 m wide): no car on it
        v = 0.0 if rng.random() < 0.25 else rng.uniform(0.3, 3.0)
        turn = np.deg2rad(rng.uniform(-2, 2)) * (v > 0)
        d = np.array([math.sin(heading + turn / 2), 0, math.cos(heading + turn / 2)])
        x = lane + rng.uniform(-0.2, 0.2)
        scene.add(syn.car_parts(rng), syn.rotation((0, 1, 0), heading + rng.uniform(-0.04, 0.04)),
                  (x, street.height(x, z), z), REGULAR_VEHICLE,
                  syn.rotation((0, 1, 0), turn) if v else None, v * d if v else None)
      z += rng.uniform(10, 30)


def build_scene(rng, opt: Options = Options()):
  """(Scene in the caster's frame, category per primitive, instance per primitive, ground prims,
  the sensor's height above the road)."""
  # The draws' order is the scenes' identity: (split, index) pairs stay the same scenes.
  scene = _Labelled(syn.Builder(*_sensor_motion(rng, opt)))
  street = Street(rng, rng.uniform(1.7, 2.1), opt.dense)
  if opt.ground:
    for kind, rot, pos, size in street.planes():
      scene.add([(kind, syn.IDENTITY, syn.ZERO, size, None)], rot, pos, is_ground=True)
  for side in (-1, 1):
    _facades(rng, scene, street, side, opt.dense)
    _roadside(rng, scene, street, side, opt.dense)
    if opt.movers:
      _vulnerable(rng, scene, street, side)
  if opt.movers:
    _traffic(rng, scene, street, opt.dense)
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
