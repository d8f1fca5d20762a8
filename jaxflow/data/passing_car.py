"""One car passing beside the sensor: the case where a flat side slides along itself.

    sweep = pair(seed=2, lateral=5.0, speed=0.8, options=Options(beams=32))   # a SweepPair
    sweep = pair(oncoming=True)                                               # coming the other way

A street of facades, poles and parked cars (synthetic_sweep's street) and one car driving past
the sensor at a given lateral distance and speed, beside it midway between the two frames, so
that most of its returns are its long flat side. The pair is cast and labelled as
`synthetic_sweep.sweep_pair` casts (z up; the car is the instance with the largest label).
"""

import math

import numpy as np

from jaxflow.data import synthetic as syn
from jaxflow.data.street import BACKGROUND, REGULAR_VEHICLE, Street
from jaxflow.data.synthetic_sweep import Options, SweepPair, cast_pair


def scene(rng, lateral: float = 5.0, speed: float = 0.8, ego_speed: float = 0.3,
          oncoming: bool = False, opt: Options = Options()):
  """build_scene's tuple for one car passing `lateral` m beside the sensor (left of it; negative:
  right) at `speed` m a frame along the street, beside the sensor midway between the two frames
  (the ego drives `ego_speed` m a frame; the car overtakes it, or comes the other way), in a street
  of facades, poles and a few parked cars (`opt`: ground, dense)."""
  builder = syn.Builder(syn.IDENTITY, (0.0, 0.0, ego_speed))
  street = Street(rng, rng.uniform(1.7, 2.1), opt.dense)
  street.road = max(street.road, abs(lateral) + 2.5)  # the passing car's lane is road
  cats, insts, grounds = [], [], []

  def add(parts, rot, pos, cat=BACKGROUND, motion_pos=None, is_ground=False):
    builder.add(parts, rot, pos, None, motion_pos)
    cats.extend([cat] * len(parts))
    insts.extend([max(insts, default=0) + 1 if cat != BACKGROUND else 0] * len(parts))
    grounds.extend([is_ground] * len(parts))

  if opt.ground:
    for kind, rot, pos, size in street.planes():
      add([(kind, syn.IDENTITY, syn.ZERO, size, None)], rot, pos, is_ground=True)
  for side in (-1, 1):
    z = rng.uniform(-80, -60)
    while z < 80:
      length = rng.uniform(6, 30)
      x = side * (street.road + rng.uniform(2, 6))
      height = rng.uniform(4, 18)
      add([(syn.BOX, syn.IDENTITY, syn.ZERO, (4, height / 2 + 1, length / 2), None)], syn.IDENTITY,
          (x + side * 4, street.height(x, z + length / 2) - 2 + height / 2 + 1, z + length / 2))
      z += length + rng.uniform(0, 6)
    for _ in range(4):  # poles, and parked cars away from the passing one
      x, z = side * (street.road + rng.uniform(0.4, 2.0)), rng.uniform(-40, 40)
      h = rng.uniform(3, 8)
      add([(syn.CYLINDER, syn.IDENTITY, (0, h / 2, 0), (0.15, h / 2, 0), None)], syn.IDENTITY,
          (x, street.height(x, z) - 0.05, z))
      x, z = side * (street.road - 1.1), rng.choice([-1, 1]) * rng.uniform(12, 45)
      add(syn.car_parts(rng), syn.rotation((0, 1, 0), (side < 0) * math.pi), (x, street.height(x, z),
                                                                              z), REGULAR_VEHICLE)
  direction = -1.0 if oncoming else 1.0
  z = (ego_speed - direction * speed) / 2  # beside the sensor midway between the frames
  add(syn.car_parts(rng), syn.rotation((0, 1, 0), 0.0 if direction > 0 else math.pi),
      (lateral, street.height(lateral, z), z), REGULAR_VEHICLE, (0, 0, direction * speed))
  return (builder.scene(), np.array(cats, np.uint8), np.array(insts, np.int16),
          np.array(grounds), -street.g)


def pair(seed: int = 0, lateral: float = 5.0, speed: float = 0.8, ego_speed: float = 0.3,
         oncoming: bool = False, options: Options = Options(beams=64)) -> SweepPair:
  """A pair of `scene` (its car: the instance of the largest `instance` label), cast as
  sweep_pair casts (`options`: beams, stacked, origin height, reverse); `seed` draws the street."""
  rng = np.random.default_rng(seed)
  built = scene(rng, lateral, speed, ego_speed, oncoming, options)
  name = f"synthetic_sweep/passing_car/{seed}" + ("/reverse" if options.reverse else "")
  return cast_pair(rng, built, options, name)
