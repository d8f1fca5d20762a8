"""Issue 66 (item 1): slow movers on real-like beams. A car creeping beside a parked one and a
person walking beside a hedge are each one group with a static thing seen from above, and move
too little to leave pc2 an empty place: their evidence is their faces, measured against the pair's
own noise (jaxflow.lidar.judge.Evidence) on the pieces of the group split without bridging."""

import dataclasses
import math

import numpy as np
import pytest

from jaxflow.data import synthetic as syn
from jaxflow.data.street import BACKGROUND, PEDESTRIAN, REGULAR_VEHICLE, person
from jaxflow.data.synthetic_sweep import Options, cast_pair
from jaxflow.lidar import sweep
from jaxflow.lidar.settings import DEFAULTS


def _street(seed: int, movers, driving: float = 0.0):
  """A road, two facades and `movers`, each (parts, position, motion, category), the ego stopped
  (`driving`: it drives this far forward a frame, past six kiosks that show how far); cast by a
  64-beam sensor 1.9 m above the road (the generator's beam model and range noise)."""
  rng = np.random.default_rng(seed)
  builder = syn.Builder(syn.IDENTITY, (0.0, 0.0, driving))
  cats, insts, grounds = [], [], []

  def add(parts, pos, motion=None, cat=BACKGROUND, is_ground=False):
    builder.add(parts, syn.IDENTITY, pos, None, motion)
    cats.extend([cat] * len(parts))
    insts.extend([max(insts, default=0) + 1 if cat != BACKGROUND else 0] * len(parts))
    grounds.extend([is_ground] * len(parts))

  height = 1.9
  add([(syn.BOX, syn.IDENTITY, syn.ZERO, (40.0, 0.05, 60.0), None)], (0, -height - 0.05, 0),
      is_ground=True)
  for side in (-1, 1):
    add([(syn.BOX, syn.IDENTITY, syn.ZERO, (2.0, 5.0, 60.0), None)], (side * 16.0, -height + 5, 0))
  if driving:  # the facades alone do not say how far the sensor went along them
    for x, z in ((-8, 12), (9, -10), (-10, -15), (7, 20), (12, 5), (-12, 3)):
      add([(syn.BOX, syn.IDENTITY, syn.ZERO, (1.5, 2.0, 1.5), None)], (x, -height + 2.0, z))
  for parts, pos, motion, cat in movers:
    add(parts, (pos[0], -height, pos[1]), motion, cat)
  built = (builder.scene(), np.array(cats, np.uint8), np.array(insts, np.int16),
           np.array(grounds), height)
  return cast_pair(rng, built, Options(beams=64), f"slow/{seed}")


# The step is on by default (benchmarks/REAL_SWEEPS.md, "Slow movers"); off: margins alone.
ON = DEFAULTS
OFF = dataclasses.replace(DEFAULTS, objects=dataclasses.replace(
  DEFAULTS.objects, judge=dataclasses.replace(DEFAULTS.objects.judge, evidence=0.0),
  part=dataclasses.replace(DEFAULTS.objects.part, split=False)))


def _errors(pair, settings):
  """Mean EPE over the points of each instance (1, 2, ...) and the count of the static world's
  points (instance 0) moved more than 5 cm (false alarms)."""
  flow, _ = sweep.raw_sweep_flow(None, pair.pc1, pair.pc2, settings=settings)
  epe = np.linalg.norm(flow - pair.flow, axis=1)
  static = np.linalg.norm(flow - pair.ego_flow, axis=1)[pair.instance == 0]
  return ([epe[pair.instance == k].mean() for k in range(1, pair.instance.max() + 1)],
          int((static > 0.05).sum()))


def _car(rng):
  return syn.car_parts(rng)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.xfail(
  strict=True, reason="issue 66, open: seed 1's street leaves the creeping car still (EPE 0.16 "
  "of 0.2; with a 0.5 m gap its unbridged piece held both cars)"))])
def test_a_car_creeping_beside_a_parked_one_is_moved(seed):
  """A car creeping 0.2 m a frame 5 m beside the sensor, 0.6 m ahead of a parked car (from above
  one group where the cells leave one empty cell between them, bridged): with the evidence it
  gets its motion (an EPE under a third of it) and the parked car and the street stand still;
  without it (margins and an empty place alone) it stood still (EPE = its speed). At 0.5 m the
  two touch at the cells for some samplings and the piece holding both stands still."""
  rng = np.random.default_rng(100 + seed)
  car, parked = _car(rng), _car(rng)
  length = max(p[3][2] for p in car) + max(p[3][2] for p in parked)
  pair = _street(seed, [(car, (-5.0, 2.0), (0, 0, 0.2), REGULAR_VEHICLE),
                        (parked, (-5.0, 2.0 - length - 0.6), None, REGULAR_VEHICLE)])
  moving = pair.instance == 1
  assert np.linalg.norm(pair.flow[moving] - pair.ego_flow[moving], axis=1).mean() == (
    pytest.approx(0.2, abs=0.01))
  (on, parked_on), static_on = _errors(pair, ON)
  (off, _), _ = _errors(pair, OFF)
  assert off > 0.15  # left still without the step
  assert on < 0.07 and parked_on < 0.01 and static_on == 0, (on, parked_on, static_on)


def test_a_person_walking_beside_a_hedge_is_moved():
  """A person walking 0.14 m a frame 18 m from the sensor, 0.1 m in front of a hedge 16 m long
  (one group with it, too large for an object: structure), ~70 points: moved with the step,
  still without; of the hedge and the street (110k points) at most 10 move (beside him)."""
  rng = np.random.default_rng(7)
  hedge = [(syn.BOX, syn.IDENTITY, (0, 0.6, 0), (0.4, 0.6, 8.0), None)]
  pair = _street(3, [(person(rng), (11.0, 14.0), (0, 0, 0.14), PEDESTRIAN),
                     (hedge, (11.7, 14.0), None, BACKGROUND)])
  walker = pair.instance == 1
  assert 40 <= walker.sum() <= 400
  (on,), static_on = _errors(pair, ON)
  (off,), _ = _errors(pair, OFF)
  assert off > 0.1  # left still without the step
  assert on < 0.06 and static_on <= 10, (on, static_on)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_parked_car_beside_a_driving_sensor_stays_still(seed):
  """A parked car 3 m beside a sensor driving 0.15 m a frame (PandaSet's track 99b5b04e on its
  driving run): the rings cross its flank as lines far apart, with points close along each, and
  residuals to planes fitted along one line favour a motion that keeps the car fixed to the
  rings (the sensor's motion). With points on no plane saying nothing it stands still; with
  every neighbourhood taken as a plane (the evidence as first built) it got 0.12 m."""
  rng = np.random.default_rng(200 + seed)
  pair = _street(seed, [(_car(rng), (3.0, 1.0), None, REGULAR_VEHICLE)], driving=0.15)
  car = pair.instance == 1
  lines = dataclasses.replace(ON, objects=dataclasses.replace(ON.objects, judge=dataclasses.replace(
    ON.objects.judge, surface=0.0, plane_points=10)))
  (on,), static_on = _errors(pair, ON)
  (as_built,), _ = _errors(pair, lines)
  assert as_built > 0.08  # ring lines taken as planes: moved with the sensor
  assert on < 0.01 and static_on == 0, (on, static_on)


@pytest.mark.slow
def test_the_step_on_pandasets_driving_run_moves_the_creeping_car(shared_dir):
  """PandaSet's driving run, its last pair (frames 40 -> 41), with the step on: a mover found from
  pc2 and offered back with the evidence (jaxflow.lidar.both_ways) once crashed there; the creeping
  car 20d13d1d (0.17 m a frame, 6 m away) gets at least half its labelled motion."""
  from jaxflow.data import open_dataset  # pylint: disable=import-outside-toplevel

  folder = shared_dir / "data" / "real_sweeps" / "pandaset"
  if not folder.is_dir():
    pytest.skip(f"{folder} not present")
  ds = open_dataset(f"opensf:{folder},region=sweep,lidar=ego", "val")
  i = max(k for k, (path, _, _) in enumerate(ds.pairs) if "30-41" in str(path))
  pair, (ids, table) = ds[i], ds.instances(i)
  flow, info = sweep.raw_sweep_flow(None, pair.pc1, pair.pc2, settings=ON)
  assert any(name.startswith("both ways") for *_, name in info.objects.moved)
  (track,) = [k + 1 for k, row in enumerate(table) if row[0].startswith("20d13d1d")]
  car = ids == track
  label = (pair.flow - pair.rigid_flow)[car].mean(0)
  ours = (flow - pair.rigid_flow)[car].mean(0)
  assert np.linalg.norm(label) > 0.1 and ours @ label >= 0.5 * label @ label, (ours, label)
