r"""The raw-sweep pipeline's settings (the `lidar` method: ground, ego-motion, moving objects), one
frozen dataclass a block, as every method's settings (jaxflow.methods.registry); a block's
families are blocks of their own (ground: surface, up_check; ego: gicp, search; objects: judge,
part, search, icp, person, along). Each block checks its own fields (__post_init__: a ValueError
naming the setting, `lidar objects.person.radius`).

    python -m jaxflow.predict a.npy b.npy --lidar --out f.npy --method.lidar.objects.cell=0.25
    python -m jaxflow.predict a.npy b.npy --lidar --method.lidar.objects.person.radius=0.6
    python -m jaxflow.predict a.npy b.npy --lidar --method.lidar.ground.surface.cell=1.0
    python -m jaxflow.predict --method lidar --print_config      # every field, with its unit
    flow, info = raw_sweep_flow(None, pc1, pc2, settings=Sweep(max_range=50.0))   # from Python
    dataclasses.replace(s, objects=dataclasses.replace(s.objects, cell=0.25))     # one field

Motion limits are per second and divided by `frame_rate_hz` (10 Hz, the sweep rate of Velodyne,
Argoverse 2 and Waymo sensors), so a 20 Hz sensor searches half as far a frame. A grid search is
(lowest, highest, step), both ends included. The values are those measured in
benchmarks/REAL_SWEEPS.md and benchmarks/sweeps.py.
"""

import dataclasses
import math


def _finite(value) -> bool:
  return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _sizes(value, length=None) -> bool:
  """A non-empty tuple of numbers >= 0 (of `length` of them where given)."""
  return (isinstance(value, tuple) and len(value) > 0 and (length is None or len(value) == length)
          and all(_finite(x) and x >= 0 for x in value))


# (what a value must be, its test): the kinds of the settings below.
_NUMBER = "a finite number >= 0", lambda v: _finite(v) and v >= 0
_SIGNED = "a finite number", _finite
_COUNT = "an integer >= 0", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0
_FLAG = "True or False", lambda v: isinstance(v, bool)
_SIZES = "a non-empty tuple of numbers >= 0", _sizes
_GRID = ("(lowest, highest, step) of finite numbers",
         lambda v: isinstance(v, tuple) and len(v) == 3 and all(map(_finite, v)))
_PASSES = ("a non-empty tuple of (voxel, neighbours, largest match), numbers >= 0",
           lambda v: isinstance(v, tuple) and len(v) > 0 and all(_sizes(p, 3) for p in v))


def _block(cls):
  return f"a {cls.__name__}", lambda v: type(v) is cls


def _need(block, path: str, kind, *names):
  """A ValueError naming the setting (`path` + NAME) of the first of `names` not of `kind`."""
  must, ok = kind
  for name in names:
    value = getattr(block, name)
    if not ok(value):
      raise ValueError(f"{path}{name} must be {must}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class GroundSurface:
  """The local ground (jaxflow.lidar.ground.fit_surface): a height map of cells, each one's plane
  fitted in windows around it, reweighted round by round."""
  cell: float = 2.0  # m: cells of the local ground's height map
  windows: tuple = (5, 11, 23)  # cells: windows of a cell's plane, smallest first
  above: float = 0.2  # m: a cell's lowest point this far above: no ground (object)
  near: float = 0.08  # m: points this near the surface refine its height
  rounds: int = 24  # reweighting rounds (the ground grows a window a round)
  extent: float = 110.0  # m: the height map's half width (edge cells beyond)

  def __post_init__(self):
    _need(self, "lidar ground.surface.", _NUMBER, "cell", "above", "near", "extent")
    _need(self, "lidar ground.surface.", _COUNT, "rounds")
    _need(self, "lidar ground.surface.", _SIZES, "windows")


@dataclasses.dataclass(frozen=True)
class UpCheck:
  """The up-axis check (jaxflow.lidar.ground.check_up_axis): a plane of random triples of a sample
  that holds more of the sweep than its ground, standing upright, refutes --up."""
  points: int = 4000  # the up-axis check's sample of a sweep (seeded)
  planes: int = 300  # its random planes (triples of the sample)
  share: float = 1 / 3  # share of the sample the largest plane must hold
  over_ground: float = 1.2  # ... and this many times the share taken as ground
  tilt_deg: float = 45.0  # deg: a plane tilted more from --up stands upright

  def __post_init__(self):
    _need(self, "lidar ground.up_check.", _COUNT, "points", "planes")
    _need(self, "lidar ground.up_check.", _NUMBER, "share", "over_ground", "tilt_deg")


@dataclasses.dataclass(frozen=True)
class Ground:
  """The ground (jaxflow.lidar.ground): RANSAC planes, the local surface, the up-axis check."""
  margin: float = 0.25  # m above the ground still ground (KITTI: y < -1.4, road -1.65)
  plane_range: float = 20.0  # m: the RANSAC plane's points, within this of the sensor
  cell: float = 2.0  # m: RANSAC candidates are the lowest points of cells of this size
  lowest: float = 0.3  # m above a cell's lowest point: a RANSAC candidate
  inlier: float = 0.1  # m: RANSAC inlier distance to a plane
  max_tilt_deg: float = 20.0  # deg: a ground plane's normal is within this of the up axis
  iterations: int = 200  # RANSAC's random triples
  max_sensor_height: float = 5.0  # m: a ground farther below the origin: a note
  # Not 0: vehicle (ego) frames, Argoverse 2's and Waymo's, put the origin near the ground.
  min_sensor_height: float = -1.0  # m: a ground higher above the origin: a note
  max_ground_fraction: float = 0.85  # a "ground" holding more of a sweep: a note
  surface: GroundSurface = GroundSurface()
  up_check: UpCheck = UpCheck()

  def __post_init__(self):
    _need(self, "lidar ground.", _NUMBER, "margin", "plane_range", "cell", "lowest", "inlier",
          "max_tilt_deg", "max_sensor_height", "max_ground_fraction")
    _need(self, "lidar ground.", _SIGNED, "min_sensor_height")
    _need(self, "lidar ground.", _COUNT, "iterations")
    _need(self, "lidar ground.", _block(GroundSurface), "surface")
    _need(self, "lidar ground.", _block(UpCheck), "up_check")


@dataclasses.dataclass(frozen=True)
class Gicp:
  """small_gicp's GICP passes, coarse to fine, and their refit on the points the fit explains."""
  # Coarse to fine: (voxel m, neighbours of a covariance, largest match m) of each GICP pass.
  scales: tuple = ((1.0, 20, 3.0), (0.5, 20, 1.0), (0.25, 30, 0.5))
  iterations: int = 30  # GICP iterations a pass
  trim_rounds: int = 2  # GICP again on the points the fit explains

  def __post_init__(self):
    _need(self, "lidar ego.gicp.", _PASSES, "scales")
    _need(self, "lidar ego.gicp.", _COUNT, "iterations", "trim_rounds")


@dataclasses.dataclass(frozen=True)
class EgoSearch:
  """The coarse grid search seen from above, GICP's start (jaxflow.lidar.ego.search), on pc2's
  bird's-eye lines (ego.Target, which the objects' residuals use too)."""
  sample: int = 600  # points of the coarse grid search
  neighbours: int = 8  # bird's-eye neighbours of a pc2 point for its line
  bev_cell: float = 0.1  # m: pc2's points above the ground merged per cell seen from above
  max_match: float = 1.5  # m: a bird's-eye match farther than this is no match
  line: float = 0.15  # minor / major spread below which a neighbourhood is a line
  blob: float = 0.15  # m: spread below which in every direction a neighbourhood is a pole
  yaw_deg_per_s: tuple = (-60.0, 60.0, 10.0)  # deg/s: the coarse search's yaws
  x_per_s: tuple = (-40.0, 40.0, 5.0)  # m/s: the coarse search's forward motions
  y_per_s: tuple = (-15.0, 15.0, 5.0)  # m/s: the coarse search's sideways motions

  def __post_init__(self):
    _need(self, "lidar ego.search.", _COUNT, "sample", "neighbours")
    _need(self, "lidar ego.search.", _NUMBER, "bev_cell", "max_match", "line", "blob")
    _need(self, "lidar ego.search.", _GRID, "yaw_deg_per_s", "x_per_s", "y_per_s")


@dataclasses.dataclass(frozen=True)
class Ego:
  """The sensor's motion (jaxflow.lidar.ego): GICP coarse to fine from the grid search's start and
  others, the fits scored by their static residual."""
  residual_voxel: float = 0.5  # m: voxels of the static residual's clouds
  residual_neighbours: int = 20  # points of the static residual's local planes
  truncate: float = 0.3  # m: a point's static residual is at most this
  inlier: float = 0.1  # m: a point this near pc2's local plane is explained
  plausible_inliers: float = 0.5  # share explained below which the fit is a note
  gicp: Gicp = Gicp()
  search: EgoSearch = EgoSearch()

  def __post_init__(self):
    _need(self, "lidar ego.", _NUMBER, "residual_voxel", "truncate", "inlier", "plausible_inliers")
    _need(self, "lidar ego.", _COUNT, "residual_neighbours")
    _need(self, "lidar ego.", _block(Gicp), "gicp")
    _need(self, "lidar ego.", _block(EgoSearch), "search")


@dataclasses.dataclass(frozen=True)
class Sensor:
  """Where pc2's sensor is in its frame (jaxflow.lidar.sensor): whence its rings look sharpest."""
  find: bool = True  # False: at the frame's origin (a sensor's own frame, KITTI's)
  fine_bin_deg: float = 0.03  # deg: the elevation histogram's fine bins
  coarse: int = 8  # fine bins in a coarse one
  min_range: float = 3.0  # m: nearer points (the vehicle's own body) left out
  least_points: int = 500  # fewer points than this: at the origin
  sample: int = 10000  # points the search looks at (a seeded sample)
  search_x: tuple = (-3.0, 3.0, 0.5)  # m: the grid's forward positions
  search_z: tuple = (-1.0, 3.0, 0.25)  # m: the grid's heights
  search_y: tuple = (-1.0, 1.0, 0.1)  # m: then sideways, at the grid's best
  refine_steps: tuple = (0.1, 0.02)  # m: the axis-by-axis refinement's steps
  # Smear saved over the origin below which the origin is kept: the best of the grid's
  # positions saves up to ~0.02 by chance on a cloud without rings, a sweep's sensor 0.2-2.
  min_gain: float = 0.05

  def __post_init__(self):
    _need(self, "lidar sensor.", _FLAG, "find")
    _need(self, "lidar sensor.", _NUMBER, "fine_bin_deg", "min_range", "min_gain")
    _need(self, "lidar sensor.", _COUNT, "coarse", "least_points", "sample")
    _need(self, "lidar sensor.", _GRID, "search_x", "search_z", "search_y")
    _need(self, "lidar sensor.", _SIZES, "refine_steps")


@dataclasses.dataclass(frozen=True)
class Part:
  """A group kept still may join a mover to what stands beside it: its unexplained points' own
  groups (parts) are fitted, and a part's motion is kept where it lands on `novelty` new points,
  leaves a place whose cost is `vacated` and is `size` wide."""
  cell: float = 0.15  # m: a moved object's parts, connected cells (no bridging)
  share: float = 0.9  # a part holding more of its group is the group again: not fitted
  vacated: float = 0.6  # a part's least mean cost standing still (pc2 shows its place empty)
  size: float = 1.0  # m: a part's least width seen from above
  # A group kept still is also split at `cell` of the objects without bridging (a car creeping
  # beside a parked one is one group bridged, two apart), each piece fitted as a part; a part that
  # does not leave its place (a slow mover) is kept on the judge's evidence instead (Judge.evidence)
  split: bool = True
  # m from ego-compensated pc2 (from above): with the evidence, the seeds of a kept-still group's
  # parts (a person walking 0.1-0.15 m a frame leaves few points beyond `unexplained`)
  seeds: float = 0.08

  def __post_init__(self):
    _need(self, "lidar objects.part.", _NUMBER, "cell", "share", "vacated", "size", "seeds")
    _need(self, "lidar objects.part.", _FLAG, "split")


@dataclasses.dataclass(frozen=True)
class Search:
  """An object's translation search (coarse, then fine) on a sample of its points."""
  per_s: float = 35.0  # m/s: an object's translation search, +- this
  step: float = 0.25  # m: the translation search's fine step (twice that first)
  coarse_step: float = 0.5  # m: its coarse step (the fine one searches +- this)
  points: int = 150  # points at most a motion is searched on (half judge it)
  keep: int = 3  # coarse shifts whose neighbourhoods the fine step searches
  agree: float = 0.3  # m: the judged half's own search finds the searched half's shift this near
  slack: float = 0.5  # m: a refined motion may reach this beyond the search

  def __post_init__(self):
    _need(self, "lidar objects.search.", _NUMBER, "per_s", "step", "coarse_step", "slack",
          "agree")
    _need(self, "lidar objects.search.", _COUNT, "points", "keep")


@dataclasses.dataclass(frozen=True)
class Icp:
  """An object's bird's-eye ICP (yaw and horizontal translation, robust)."""
  rounds: int = 15  # iterations of an object's bird's-eye ICP
  scales: tuple = (0.3, 0.15, 0.08, 0.05)  # m: its robust scales, 4 rounds each
  gate: float = 3.0  # scales (plus gate_margin): its rows farther are left out
  gate_margin: float = 0.2  # m

  def __post_init__(self):
    _need(self, "lidar objects.icp.", _COUNT, "rounds")
    _need(self, "lidar objects.icp.", _SIZES, "scales")
    _need(self, "lidar objects.icp.", _NUMBER, "gate", "gate_margin")


@dataclasses.dataclass(frozen=True)
class Person:
  """A walking person moves 5-17 cm a frame, under `unexplained`: an upright person-sized group
  gets the shift of the centroid of pc2's points around it, kept when it beats standing still."""
  size: float = 1.2  # m: a person's group is at most this wide seen from above
  top: tuple = (1.0, 2.3)  # m above the ground: where a person's highest point lies
  upright: float = 0.9  # m: a person's points span at least this height
  radius: float = 0.8  # m: pc2's points this near the moved centre (from above) are his
  rounds: int = 3  # centroid shifts, each from the last
  least_matches: int = 5  # pc2's points there at least (fewer: no shift) ...
  matched_share: float = 1 / 3  # ... and at least this share of the group's count
  min_shift: float = 0.05  # m: a smaller shift is standing still

  def __post_init__(self):
    _need(self, "lidar objects.person.", _NUMBER, "size", "upright", "radius", "matched_share",
          "min_shift")
    _need(self, "lidar objects.person.", _COUNT, "rounds", "least_matches")
    _need(self, "lidar objects.person.", ("(lowest, highest), numbers >= 0",
                                          lambda v: _sizes(v, 2)), "top")


@dataclasses.dataclass(frozen=True)
class Along:
  """A long object sliding along its own flat side (a car passing beside the sensor) is fixed along
  its length by its ends: the cells it occupies along its axis vote for its shift
  (jaxflow.lidar.along), which makes it a candidate and starts its fit, kept where the costs do
  not clearly refute it."""
  min_length: float = 2.5  # m: a group at least this long (seen from above) gets the vote
  bin: float = 0.025  # m: the vote's cells along the axis (and its shifts' step)
  band: float = 0.3  # m: ... and their height
  # m: cells between two returns of a band this near are occupied too, so that the ends decide
  # the vote, not the returns' spacing (a ring's on a car's side: centimetres near, more far)
  gap: float = 0.3
  cross: float = 0.5  # m: pc2's points this far beyond the group's band across the axis vote
  support: float = 0.5  # share of the group's cells the vote's shift must match
  # Mean squared along-axis part of the normals of a long object's lines (from above) below which
  # it shows a flat side only (a car beside the sensor: 0.01-0.03; seen from its end: 0.5-0.9):
  # only then it gets the vote, and its fit keeps the vote's shift; else its end face fixes it.
  faces: float = 0.1

  def __post_init__(self):
    _need(self, "lidar objects.along.", _NUMBER, "min_length", "bin", "band", "gap", "cross",
          "support", "faces")


@dataclasses.dataclass(frozen=True)
class Judge:
  """How an object's placement is judged against pc2 (jaxflow.lidar.judge): each point's cost, what
  pc2 can see (its range image), and how clearly a motion must beat standing still."""
  # A point's cost is its 3-D distance to pc2 truncated at `spacings` of the object's point
  # spacings, within truncate .. max_truncate, in units of that truncation (0 .. 1).
  truncate: float = 0.3  # m: the least truncation of a point's cost (the search's)
  spacings: float = 3.0  # point spacings of an object: the truncation of its costs
  max_truncate: float = 1.5  # m: the largest truncation of a point's cost
  # A motion replaces standing still when its mean cost is lower by all of these:
  margin: float = 0.05  # of the truncation: a motion's least gain over standing still
  relative_margin: float = 0.1  # share of standing still's cost: the least gain too
  significance: float = 3.0  # standard errors of the per-point gain: the least gain too
  azimuth_bins: int = 1200  # columns of the visibility image (0.3 deg)
  elevation_bins: int = 360  # rows of the visibility image (0.5 deg)
  hidden: float = 0.5  # m behind pc2's return in its direction: hidden
  hidden_fit: float = 0.45  # mean cost a motion must reach where pc2 hides still's place
  min_seen: float = 0.3  # share visible in pc2 below which a motion is refused
  # Evidence that grows with the points (jaxflow.lidar.judge.Evidence): a motion also replaces
  # standing still where the point-to-plane residuals it saves, in units of the pair's own noise
  # (measured on its static world), add up to `evidence` (2 x the log-likelihood ratio of Gaussian
  # noise; each point's residual capped at `noise_cap` noises) at `significance` standard errors:
  # a car creeping 0.2 m a frame with 1,000 points is then overwhelming, 5 points are not.
  # 0: margins alone (benchmarks/REAL_SWEEPS.md, "Slow movers": PandaSet's creeping cars move).
  evidence: float = 150.0
  noise_cap: float = 3.0  # noises: a point's point-to-plane residual is capped at this
  noise_floor: float = 0.01  # m: the noise is at least this
  noise_points: int = 4000  # static points (explained from above) the noise is measured on
  # pc2's local plane at a point: from its `plane_points` nearest, a plane where their second
  # spread is `surface` of their first or more: a ring across a car's flank close beside the
  # sensor is a line, no plane; residuals to it favour holding the car to the sensor's rings.
  plane_points: int = 30
  surface: float = 0.1  # the second spread's least share of the first (variances): a plane
  # m: the evidence decides only motions of an object's centre this short, which leave no empty
  # place (a faster mover's old place is empty: the margins see it)
  slow: float = 0.5

  def __post_init__(self):
    _need(self, "lidar objects.judge.", _NUMBER, "truncate", "spacings", "max_truncate", "margin",
          "relative_margin", "significance", "hidden", "hidden_fit", "min_seen", "evidence",
          "noise_cap", "noise_floor", "slow", "surface")
    _need(self, "lidar objects.judge.", _COUNT, "azimuth_bins", "elevation_bins", "noise_points",
          "plane_points")
    if self.plane_points < 3:
      raise ValueError(f"lidar objects.judge.plane_points must be 3 or more (a plane), got "
                       f"{self.plane_points!r}")


@dataclasses.dataclass(frozen=True)
class Objects:
  """Moving objects (jaxflow.lidar.objects): groups from above, their motions, the judge."""
  cell: float = 0.3  # m: objects are connected cells from above (a cell's gap bridged)
  object_top: float = 2.6  # m above the ground: higher points join no object
  min_points: int = 12  # points of an object (and of a part kept still)
  # Share of the pc2 points a motion lands on that pc1 did not see there (asked of a part, and of
  # any object moved farther than its own width: a mover that far has left its own place).
  novelty: float = 0.7
  max_high: float = 0.25  # share above object_top beyond which a group is structure
  max_size: float = 14.0  # m: a larger group is structure (a facade), never moved
  # m from ego-compensated pc2 (from above): unexplained (a group's parts fitted on their own are
  # its unexplained points; a long object's ends vote on what pc1 does not explain)
  unexplained: float = 0.15
  max_yaw_deg_per_s: float = 100.0  # deg/s: an object turning faster is refused
  low_ground: float = 0.05  # m: "ground" this high in a moving object's cells moves too
  # pc2's groups fitted against pc1 too, each mover found offered to pc1's points where it stood
  # (jaxflow.lidar.both_ways); False: pc1's groups alone
  both_ways: bool = True
  judge: Judge = Judge()
  part: Part = Part()
  search: Search = Search()
  icp: Icp = Icp()
  person: Person = Person()
  along: Along = Along()

  def __post_init__(self):
    _need(self, "lidar objects.", _NUMBER, "cell", "object_top", "novelty", "max_high",
          "max_size", "unexplained", "max_yaw_deg_per_s", "low_ground")
    _need(self, "lidar objects.", _COUNT, "min_points")
    _need(self, "lidar objects.", _FLAG, "both_ways")
    for name, cls in (("judge", Judge), ("part", Part), ("search", Search), ("icp", Icp),
                      ("person", Person), ("along", Along)):
      _need(self, "lidar objects.", _block(cls), name)


@dataclasses.dataclass(frozen=True)
class Sweep:
  """The raw-sweep pipeline (jaxflow.lidar.sweep.raw_sweep_flow): its blocks and limits."""
  # m: the non-ground points within this horizontal distance are what a method sees (0: all);
  # moving objects are sought in the whole sweep (jaxflow.lidar.sweep).
  max_range: float = 35.0
  min_azimuth: float = 0.5  # share of 360 deg a sweep covers at least (a camera's view: less)
  frame_rate_hz: float = 10.0  # sweeps a second: the per-second limits are divided by it
  static_threshold: float = 0.1  # m: within this of a rigid fit of a method's flow: static
  ground: Ground = Ground()
  ego: Ego = Ego()
  sensor: Sensor = Sensor()
  objects: Objects = Objects()

  def __post_init__(self):
    _need(self, "lidar ", _NUMBER, "max_range", "min_azimuth", "static_threshold")
    if not (_finite(self.frame_rate_hz) and self.frame_rate_hz > 0):
      raise ValueError(f"lidar frame_rate_hz must be > 0, got {self.frame_rate_hz!r}")
    for name, cls in (("ground", Ground), ("ego", Ego), ("sensor", Sensor), ("objects", Objects)):
      _need(self, "lidar ", _block(cls), name)


DEFAULTS = Sweep()  # the settings of a call given none
