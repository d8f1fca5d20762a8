"""What a generated street holds (jaxflow.data.synthetic_sweep's scenes): the road and its ground,
facades, poles and trees, parked cars, traffic, walkers and cyclists, each mover where no other
stands, in the ray caster's frame (x across the road, y up, z along it; the sensor at the origin).

    scene = Labelled(syn.Builder(sensor_rotation, sensor_position))
    street = Street(rng, sensor_height, dense)
    facades(rng, scene, street, side, dense); traffic(rng, scene, street, dense)
    built = scene.built(sensor_height)

Each function draws from `rng` in a fixed order (a scene's identity is its draws' order).
"""

import math

import numpy as np

from jaxflow.data import synthetic as syn

BACKGROUND, BICYCLIST, PEDESTRIAN, REGULAR_VEHICLE = 0, 4, 17, 19  # av2 CATEGORY_TO_INDEX


class Street:
  """The ground's height field (caster frame: x across the road, z along it) and its planes."""

  def __init__(self, rng, sensor_height: float, dense: bool = False):
    self.g = -sensor_height
    # half width: parking, a cycle lane, two lanes, the ego's (a dense city: parking and two
    # lanes, 11-13 m between the kerbs)
    self.road = rng.uniform(9.0, 12.0) if not dense else rng.uniform(5.5, 6.5)
    # Lane centres from the parking strips (+z on the left, -z on the right; a dense city's two
    # lanes 3.2 m apart, a car in them 1-2 m from a parked one).
    self.inner = 0.8 if not dense else (self.road - 3.2) / 2
    # The road's centre line across the sensor (x): the ego drives on the crown of a wide road,
    # in its own (right) lane of a dense city's, the oncoming lane 3.2 m beside it.
    self.centre = 0.0 if not dense else self.road / 2 - self.inner
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
    x = x - self.centre
    across = self.crown * max(0.0, 1 - abs(x) / self.road) if abs(x) < self.road else self.kerb
    return self.along(z) + across

  def lanes(self) -> tuple:
    """(x of the lane's centre across the sensor, heading) of the two lanes."""
    return tuple((self.centre + lane, 0.0 if lane < 0 else math.pi)
                 for lane in (self.inner - self.road / 2, self.road / 2 - self.inner))

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
        pos = (self.centre + side * self.road / 2, self.along(zc) + self.crown / 2, zc)
        out.append((syn.PLANE, pitch @ roll, pos, (self.road / 2, 0, half_z)))
        walk, depth = 55.0, 0.6  # a slab: its top is the sidewalk, its side the kerb
        pos = (self.centre + side * (self.road + walk), self.along(zc) + self.kerb - depth / 2,
               zc)
        out.append((syn.BOX, pitch, pos, (walk, depth / 2, half_z)))
    return out


def person(rng):
  return [(syn.CYLINDER, syn.IDENTITY, (0, 0.8, 0), (rng.uniform(0.18, 0.26), 0.8, 0), None),
          (syn.ELLIPSOID, syn.IDENTITY, (0, 1.8, 0), (0.13,) * 3, None)]


def cyclist(rng):
  return [(syn.BOX, syn.IDENTITY, (0, 0.45, 0), (0.08, 0.35, 0.85), None),
          (syn.CYLINDER, syn.IDENTITY, (0, 1.25, 0), (0.2, 0.45, 0), None)]


class Labelled:
  """A scene's builder, the labels of its primitives as build_scene adds them, and where each
  mover and parked car stands at either time (seen from above), so that an added mover clears
  them."""

  def __init__(self, builder: syn.Builder):
    self.builder, self.cats, self.insts, self.grounds = builder, [], [], []
    # (x, z at time 1, x, z at time 2, half width across x, half length along z) of each
    # footprint; the ego car's first (about its sensor).
    ego = builder.sensor_pos
    self.footprints = [(0.0, 0.0, ego[0], ego[2], 1.1, 2.6)]

  def add(self, parts, rot, pos, cat=BACKGROUND, motion_rot=None, motion_pos=None,
          is_ground=False, half=None):
    """One object (its primitives share its label; an instance number unless background);
    `half`: its (across, along) half size from above, recorded as a footprint."""
    inst = len(set(self.insts)) + 1 if cat != BACKGROUND else 0
    self.builder.add(parts, rot, pos, motion_rot, motion_pos)
    self.cats.extend([cat] * len(parts))
    self.insts.extend([inst] * len(parts))
    self.grounds.extend([is_ground] * len(parts))
    if half is not None:
      self.footprints.append(_footprint(pos, motion_pos, half))

  def clear(self, pos, motion_pos, half) -> bool:
    """Whether an object there (half size from above) overlaps no footprint at either time."""
    x1, z1, x2, z2, w, l = _footprint(pos, motion_pos, half)
    return not any((abs(x1 - a1) < w + fw and abs(z1 - b1) < l + fl)
                   or (abs(x2 - a2) < w + fw and abs(z2 - b2) < l + fl)
                   for a1, b1, a2, b2, fw, fl in self.footprints)

  def built(self, sensor_height: float):
    """build_scene's tuple."""
    return (self.builder.scene(), np.array(self.cats, np.uint8), np.array(self.insts, np.int16),
            np.array(self.grounds), sensor_height)


CAR, PERSON, BIKE = (1.0, 2.5), (0.4, 0.4), (0.35, 1.0)  # half sizes from above (across, along)


def _footprint(pos, motion_pos, half):
  shift = np.zeros(3) if motion_pos is None else np.asarray(motion_pos, float)
  return (pos[0], pos[2], pos[0] + shift[0], pos[2] + shift[2], *half)


def _vehicle_speed(u: float, dense: bool) -> float:
  """A moving vehicle's speed (m a frame) from a uniform draw in [0, 1): log-uniform from 0.05
  (creeping, stopping, starting, queueing) to 3 (a dense city: 1.5), so a slow car is as common
  as a fast one (the bucketed metric divides by speed: slow movers weigh most)."""
  top = 1.5 if dense else 3.0
  return 0.05 * (top / 0.05) ** u


def facades(rng, scene: Labelled, street: Street, side: int, dense: bool):
  """A row of buildings along one side, with gaps (a dense city: at the sidewalk, tall)."""
  road, centre = street.road, street.centre
  z = rng.uniform(-100, -80)
  while z < 100:
    length = rng.uniform(6, 30)
    if rng.random() < 0.75 or dense:
      x = centre + side * (road + (rng.uniform(3, 9) if not dense else rng.uniform(1.0, 2.0)))
      height = rng.uniform(3, 18) if not dense else rng.uniform(12, 30)
      base = street.height(x, z + length / 2) - 2
      scene.add([(syn.BOX, syn.IDENTITY, syn.ZERO, (4, height / 2 + 1, length / 2), None)],
                syn.rotation((0, 1, 0), rng.uniform(-0.06, 0.06)),
                (x + side * 4, base + height / 2 + 1, z + length / 2))
    z += length + (rng.uniform(0, 8) if not dense else rng.uniform(0, 1))


def roadside(rng, scene: Labelled, street: Street, side: int, dense: bool):
  """Poles and trees on one sidewalk, and the cars parked along it."""
  road, centre = street.road, street.centre
  for _ in range(rng.integers(3, 10)):
    x = centre + side * (road + rng.uniform(0.4, 2.0))
    z, h = rng.uniform(-60, 60), rng.uniform(3, 8)
    parts = [(syn.CYLINDER, syn.IDENTITY, (0, h / 2, 0), (rng.uniform(0.08, 0.25), h / 2, 0), None)]
    if rng.random() < 0.5:
      crown = rng.uniform(1.0, 2.5)
      parts.append((syn.ELLIPSOID, syn.IDENTITY, (0, h + crown * 0.6, 0),
                    (crown, crown * 0.8, crown), syn.random_bump(rng, 0.12)))
    scene.add(parts, syn.IDENTITY, (x, street.height(x, z) - 0.05, z))
  for _ in range(rng.integers(1, 7) if not dense else rng.integers(6, 12)):
    x, z = centre + side * (road - 1.1), rng.uniform(-50, 50)
    heading = rng.uniform(-0.08, 0.08) + (side < 0) * math.pi
    scene.add(syn.car_parts(rng), syn.rotation((0, 1, 0), heading), (x, street.height(x, z), z),
              REGULAR_VEHICLE, half=CAR)


def _walking(u: float) -> float:
  """A walker's speed along the sidewalk (m a frame, signed) from a uniform draw in [-1, 1]: 0.06
  to 0.18 (2-6.5 km/h) either way."""
  return math.copysign(0.06 + 0.12 * abs(u), u)


def vulnerable(rng, scene: Labelled, street: Street, side: int, dense: bool):
  """Pedestrians on one sidewalk (most walking) and perhaps a cyclist near its kerb, riding with
  the traffic of its side (where no other mover stands)."""
  road, centre = street.road, street.centre
  for _ in range(rng.integers(0, 4)):
    # (a dense city's facades stand 1-2 m beyond the kerb: its walkers between)
    x = centre + side * (road + (rng.uniform(0.6, 2.5) if not dense else rng.uniform(0.35, 0.75)))
    z = rng.uniform(-30, 30)
    walking = rng.random() < 0.7
    scene.add(person(rng), syn.IDENTITY, (x, street.height(x, z), z), PEDESTRIAN,
              syn.rotation((0, 1, 0), rng.uniform(-0.1, 0.1)) if walking else None,
              (rng.uniform(-0.05, 0.05), 0, _walking(rng.uniform(-1, 1))) if walking else None,
              half=PERSON)
  if rng.random() < 0.5:
    x, z = centre + side * (road - 3.2), rng.uniform(-30, 30)
    heading = 0.0 if side < 0 else math.pi
    pos, motion = (x, street.height(x, z), z), (0, 0, rng.uniform(0.3, 0.8) * math.cos(heading))
    if scene.clear(pos, motion, BIKE):  # (a dense city's cycle lane is the ego's lane)
      scene.add(cyclist(rng), syn.rotation((0, 1, 0), heading), pos, BICYCLIST, syn.IDENTITY,
                motion, half=BIKE)


def traffic(rng, scene: Labelled, street: Street, dense: bool):
  """Cars in the two lanes (+z on the left, -z on the right), a quarter of them stopped."""
  for lane, heading in street.lanes():
    z = rng.uniform(-60, -40)
    while z < 60:
      if abs(z) > 6 or lane > 2.2:  # the ego car drives at x = 0 (2 m wide): no car on it
        v = 0.0 if rng.random() < 0.25 else _vehicle_speed(rng.random(), dense)
        turn = np.deg2rad(rng.uniform(-2, 2)) * (v > 0)
        d = np.array([math.sin(heading + turn / 2), 0, math.cos(heading + turn / 2)])
        x = lane + rng.uniform(-0.2, 0.2)
        scene.add(syn.car_parts(rng), syn.rotation((0, 1, 0), heading + rng.uniform(-0.04, 0.04)),
                  (x, street.height(x, z), z), REGULAR_VEHICLE,
                  syn.rotation((0, 1, 0), turn) if v else None, v * d if v else None, half=CAR)
      z += rng.uniform(10, 30)


def _placed(scene: Labelled, draw, tries: int = 12):
  """The first of `tries` placements `draw()` makes ((pos, motion_pos, half) or None) that clears
  every footprint, or None."""
  for _ in range(tries):
    placement = draw()
    if placement is not None and scene.clear(*placement):
      return placement
  return None


def more_movers(rng, scene: Labelled, street: Street, dense: bool):
  """The movers a street shows beyond its traffic's spacing: a car passing beside the sensor (in
  a lane more than 2.2 m to its side, beside it midway between the frames), slow vehicles
  (0.05-0.3 m a frame: stopping, starting, queueing; a dense city has more) and walkers 10-25 m
  away, crossing the road or walking along it. Each where no other mover stands at either time
  (else left out)."""
  ego = scene.builder.sensor_pos[2]
  beside = [(x, h) for x, h in street.lanes() if abs(x) > 2.2]

  def passing():
    x, heading = beside[rng.integers(len(beside))]
    direction, v = math.cos(heading), rng.uniform(0.3, 2.5)
    z = (ego - direction * v) / 2 + rng.uniform(-1.5, 1.5)
    return (x + rng.uniform(-0.2, 0.2), street.height(x, z), z), (0, 0, direction * v), CAR

  def slow():
    x, heading = street.lanes()[rng.integers(2)]
    z, v = rng.choice([-1, 1]) * rng.uniform(8, 35), 0.05 * 6 ** rng.random()
    return (x + rng.uniform(-0.2, 0.2), street.height(x, z), z), (0, 0, math.cos(heading) * v), CAR

  def walker():
    reach, v = rng.uniform(10, 25), _walking(rng.uniform(-1, 1))
    if rng.random() < 0.5:  # crossing the road
      x = street.centre + rng.uniform(-1, 1) * (street.road - 1.5)
      motion = (v, 0, rng.uniform(-0.03, 0.03))
    else:  # along a sidewalk
      x = street.centre + rng.choice([-1, 1]) * (street.road + (
        rng.uniform(0.6, 2.5) if not dense else rng.uniform(0.35, 0.75)))
      motion = (rng.uniform(-0.03, 0.03), 0, v)
    if abs(x) >= reach:
      return None
    z = rng.choice([-1, 1]) * math.sqrt(reach * reach - x * x)
    return (x, street.height(x, z), z), motion, PERSON

  kinds = ([(passing, REGULAR_VEHICLE)] if beside and rng.random() < 0.6 else []) + [
    (slow, REGULAR_VEHICLE)] * rng.integers(1, 3 if not dense else 5) + [
    (walker, PEDESTRIAN)] * rng.integers(1, 3 if not dense else 4)
  for draw, cat in kinds:
    placement = _placed(scene, draw)
    if placement is None:
      continue
    pos, motion, half = placement
    parts = syn.car_parts(rng) if cat == REGULAR_VEHICLE else person(rng)
    heading = math.atan2(motion[0], motion[2]) if cat == REGULAR_VEHICLE else 0.0
    scene.add(parts, syn.rotation((0, 1, 0), heading), pos, cat, None, motion, half=half)
