r"""The raw-sweep pipeline's settings (the `lidar` method: ground, ego-motion, moving objects), one
frozen dataclass a block, as every method's settings (jaxflow.methods.registry).

    python -m jaxflow.predict a.npy b.npy --lidar --out f.npy --method.lidar.objects.cell=0.25
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

# Fields that may be negative: a height below the origin, the grid searches' lower ends.
_SIGNED = {"min_sensor_height", "search_yaw_deg_per_s", "search_x_per_s", "search_y_per_s",
           "search_x", "search_y", "search_z"}
# Tuples whose length is the user's: the passes and windows of a coarse-to-fine search.
_VARIABLE_LENGTH = {"scales", "surface_windows", "icp_scales", "refine_steps"}


def _check(block):
  """A ValueError naming the field for a value of another kind than its default's, or a negative
  or non-finite number where the field is not signed."""
  name = type(block).__name__.lower()
  for f in dataclasses.fields(block):
    value, default = getattr(block, f.name), f.default
    if dataclasses.is_dataclass(default):
      ok = type(value) is type(default)
    elif isinstance(default, bool):
      ok = isinstance(value, bool)
    elif isinstance(default, int):
      ok = isinstance(value, int) and not isinstance(value, bool) and value >= 0
    elif isinstance(default, float):
      ok = (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            and (value >= 0 or f.name in _SIGNED))
    else:  # a tuple: of numbers (or of tuples of them), as long as its default when that is fixed
      flat = [x for v in value for x in (v if isinstance(v, tuple) else (v,))] if isinstance(
        value, tuple) else None
      ok = (flat is not None and all(isinstance(x, (int, float)) and math.isfinite(x)
                                     and (x >= 0 or f.name in _SIGNED) for x in flat)
            and (len(value) == len(default) or f.name in _VARIABLE_LENGTH) and len(value) > 0)
    if not ok:
      raise ValueError(f"lidar {name}.{f.name}: {value!r} is not a valid value (default "
                       f"{default!r})")


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
  surface_cell: float = 2.0  # m: cells of the local ground's height map
  surface_windows: tuple = (5, 11, 23)  # cells: windows of a cell's plane, smallest first
  surface_above: float = 0.2  # m: a cell's lowest point this far above: no ground (object)
  surface_near: float = 0.08  # m: points this near the surface refine its height
  surface_rounds: int = 24  # reweighting rounds (the ground grows a window a round)
  surface_extent: float = 110.0  # m: the height map's half width (edge cells beyond)
  max_sensor_height: float = 5.0  # m: a ground farther below the origin: a note
  # Not 0: vehicle (ego) frames, Argoverse 2's and Waymo's, put the origin near the ground.
  min_sensor_height: float = -1.0  # m: a ground higher above the origin: a note
  max_ground_fraction: float = 0.85  # a "ground" holding more of a sweep: a note
  up_check_points: int = 4000  # the up-axis check's sample of a sweep (seeded)
  up_check_planes: int = 300  # its random planes (triples of the sample)
  up_check_share: float = 1 / 3  # share of the sample the largest plane must hold
  up_check_over_ground: float = 1.2  # ... and this many times the share taken as ground
  up_check_tilt_deg: float = 45.0  # deg: a plane tilted more from --up stands upright

  def __post_init__(self):
    _check(self)


@dataclasses.dataclass(frozen=True)
class Ego:
  """The sensor's motion (jaxflow.lidar.ego): GICP coarse to fine and the grid search."""
  # Coarse to fine: (voxel m, neighbours of a covariance, largest match m) of each GICP pass.
  scales: tuple = ((1.0, 20, 3.0), (0.5, 20, 1.0), (0.25, 30, 0.5))
  gicp_iterations: int = 30  # GICP iterations a pass
  trim_rounds: int = 2  # GICP again on the points the fit explains
  residual_voxel: float = 0.5  # m: voxels of the static residual's clouds
  residual_neighbours: int = 20  # points of the static residual's local planes
  truncate: float = 0.3  # m: a point's static residual is at most this
  inlier: float = 0.1  # m: a point this near pc2's local plane is explained
  plausible_inliers: float = 0.5  # share explained below which the fit is a note
  search_sample: int = 600  # points of the coarse grid search
  neighbours: int = 8  # bird's-eye neighbours of a pc2 point for its line
  bev_cell: float = 0.1  # m: pc2's points above the ground merged per cell seen from above
  max_match: float = 1.5  # m: a bird's-eye match farther than this is no match
  line: float = 0.15  # minor / major spread below which a neighbourhood is a line
  blob: float = 0.15  # m: spread below which in every direction a neighbourhood is a pole
  search_yaw_deg_per_s: tuple = (-60.0, 60.0, 10.0)  # deg/s: the coarse search's yaws
  search_x_per_s: tuple = (-40.0, 40.0, 5.0)  # m/s: the coarse search's forward motions
  search_y_per_s: tuple = (-15.0, 15.0, 5.0)  # m/s: the coarse search's sideways motions

  def __post_init__(self):
    _check(self)


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
    _check(self)


@dataclasses.dataclass(frozen=True)
class Objects:
  """Moving objects (jaxflow.lidar.objects): groups from above, their motions, the judge."""
  cell: float = 0.3  # m: objects are connected cells from above (a cell's gap bridged)
  part_cell: float = 0.15  # m: a moved object's parts, connected cells (no bridging)
  object_top: float = 2.6  # m above the ground: higher points join no object
  min_points: int = 12  # points of an object (and of a part kept still)
  # A group kept still may join a mover to what stands beside it: its unexplained points' own
  # groups (parts) are fitted, and a part's motion is kept where it lands on `novelty` new
  # points, leaves a place whose cost is `vacated` and is `part_size` wide.
  part_share: float = 0.9  # a part holding more of its group is the group again: not fitted
  # Share of the pc2 points a motion lands on that pc1 did not see there (asked too of any
  # object moved farther than its own width: a mover that far has left its own place).
  novelty: float = 0.7
  vacated: float = 0.6  # a part's least mean cost standing still (pc2 shows its place empty)
  part_size: float = 1.0  # m: a part's least width seen from above
  max_high: float = 0.25  # share above object_top beyond which a group is structure
  max_size: float = 14.0  # m: a larger group is structure (a facade), never moved
  unexplained: float = 0.15  # m from ego-compensated pc2 (from above): unexplained
  min_unexplained: float = 0.15  # share of unexplained points below which it stands still
  # ... unless it has this many: a car beside the sensor, sliding along its own side, is explained
  # but at its ends.
  many_unexplained: int = 100  # unexplained points that make any object a candidate
  search_per_s: float = 35.0  # m/s: an object's translation search, +- this
  search_step: float = 0.25  # m: the translation search's fine step (twice that first)
  search_coarse_step: float = 0.5  # m: its coarse step (the fine one searches +- this)
  search_points: int = 150  # points at most a motion is searched on (half judge it)
  search_slack: float = 0.5  # m: a refined motion may reach this beyond the search
  # A point's cost is its 3-D distance to pc2 truncated at `spacings` of the object's point
  # spacings, within truncate .. max_truncate, in units of that truncation (0 .. 1).
  truncate: float = 0.3  # m: the least truncation of a point's cost (the search's)
  spacings: float = 3.0  # point spacings of an object: the truncation of its costs
  max_truncate: float = 1.5  # m: the largest truncation of a point's cost
  # A motion replaces standing still when its mean cost is lower by all of these:
  margin: float = 0.05  # of the truncation: a motion's least gain over standing still
  relative_margin: float = 0.1  # share of standing still's cost: the least gain too
  significance: float = 3.0  # standard errors of the per-point gain: the least gain too
  max_yaw_deg_per_s: float = 100.0  # deg/s: an object turning faster is refused
  low_ground: float = 0.05  # m: "ground" this high in a moving object's cells moves too
  rounds: int = 15  # iterations of an object's bird's-eye ICP
  icp_scales: tuple = (0.3, 0.15, 0.08, 0.05)  # m: its robust scales, 4 rounds each
  icp_gate: float = 3.0  # scales (plus icp_gate_margin): its rows farther are left out
  icp_gate_margin: float = 0.2  # m
  azimuth_bins: int = 1200  # columns of the visibility image (0.3 deg)
  elevation_bins: int = 360  # rows of the visibility image (0.5 deg)
  hidden: float = 0.5  # m behind pc2's return in its direction: hidden
  hidden_fit: float = 0.45  # mean cost a motion must reach where pc2 hides still's place
  min_seen: float = 0.3  # share visible in pc2 below which a motion is refused
  # A walking person moves 5-17 cm a frame, under `unexplained`: an upright person-sized group
  # gets the shift of the centroid of pc2's points around it, kept when it beats standing still.
  person_size: float = 1.2  # m: a person's group is at most this wide seen from above
  person_top: tuple = (1.0, 2.3)  # m above the ground: where a person's highest point lies
  person_upright: float = 0.9  # m: a person's points span at least this height
  person_radius: float = 0.8  # m: pc2's points this near the moved centre (from above) are his
  person_rounds: int = 3  # centroid shifts, each from the last
  person_least_matches: int = 5  # pc2's points there at least (fewer: no shift) ...
  person_matched_share: float = 1 / 3  # ... and at least this share of the group's count
  person_min_shift: float = 0.05  # m: a smaller shift is standing still
  # A long object sliding along its own flat side (a car passing beside the sensor) is fixed along
  # its length by its ends: the cells it occupies along its axis vote for its shift
  # (jaxflow.lidar.along), which makes it a candidate and starts its fit, kept where the costs do
  # not clearly refute it.
  along_min_length: float = 2.5  # m: a group at least this long (seen from above) gets the vote
  along_bin: float = 0.025  # m: the vote's cells along the axis (and its shifts' step)
  along_band: float = 0.3  # m: ... and their height
  # m: cells between two returns of a band this near are occupied too, so that the ends decide
  # the vote, not the returns' spacing (a ring's on a car's side: centimetres near, more far)
  along_gap: float = 0.3
  along_cross: float = 0.5  # m: pc2's points this far beyond the group's band across the axis vote
  along_support: float = 0.5  # share of the group's cells the vote's shift must match
  # Mean squared along-axis part of the normals of a long object's lines (from above) below which
  # it shows a flat side only (a car beside the sensor: 0.01-0.03; seen from its end: 0.5-0.9):
  # only then it gets the vote, and its fit keeps the vote's shift; else its end face fixes it.
  along_faces: float = 0.1

  def __post_init__(self):
    _check(self)


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
    _check(self)
    if not self.frame_rate_hz > 0:
      raise ValueError(f"lidar sweep.frame_rate_hz must be > 0, got {self.frame_rate_hz!r}")


DEFAULTS = Sweep()  # the settings of a call given none
