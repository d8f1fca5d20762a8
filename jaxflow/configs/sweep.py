r"""The raw-sweep pipeline's settings (jaxflow.lidar: ground, ego-motion, moving objects).

    python -m jaxflow.predict a.npy b.npy --lidar --out f.npy --sweep.objects.max_yaw_deg_per_s=50
    python -m jaxflow.predict --print_config          # every field, with its unit
    flow, info = raw_sweep_flow(None, pc1, pc2, settings=config)   # from Python

Motion limits are per second and divided by `frame_rate_hz` (10 Hz, the sweep rate of Velodyne,
Argoverse 2 and Waymo sensors), so a 20 Hz sensor searches half as far a frame. A grid search is
(lowest, highest, step), both ends included.
"""

import functools

import ml_collections


def get_config() -> ml_collections.ConfigDict:
  """The settings of jaxflow.lidar.sweep.raw_sweep_flow (the values measured in
  benchmarks/REAL_SWEEPS.md and benchmarks/sweeps.py)."""
  config = ml_collections.ConfigDict()
  config.max_range = 35.0  # m: the points within this horizontal distance are kept (0: all)
  config.min_azimuth = 0.5  # share of 360 deg a sweep covers at least (a camera's view: less)
  config.frame_rate_hz = 10.0  # sweeps a second: the per-second limits are divided by it
  config.static_threshold = 0.1  # m: within this of a rigid fit of a method's flow: static

  config.ground = ml_collections.ConfigDict()
  config.ground.margin = 0.25  # m above the ground still ground (KITTI: y < -1.4, road -1.65)
  config.ground.plane_range = 20.0  # m: the RANSAC plane's points, within this of the sensor
  config.ground.cell = 2.0  # m: RANSAC candidates are the lowest points of cells of this size
  config.ground.lowest = 0.3  # m above a cell's lowest point: a RANSAC candidate
  config.ground.inlier = 0.1  # m: RANSAC inlier distance to a plane
  config.ground.max_tilt_deg = 20.0  # deg: a ground plane's normal is within this of the up axis
  config.ground.iterations = 200  # RANSAC's random triples
  config.ground.surface_cell = 2.0  # m: cells of the local ground's height map
  config.ground.surface_windows = (5, 11, 23)  # cells: windows of a cell's plane, smallest first
  config.ground.surface_above = 0.2  # m: a cell's lowest point this far above: no ground (object)
  config.ground.surface_near = 0.08  # m: points this near the surface refine its height
  config.ground.surface_rounds = 24  # reweighting rounds (the ground grows a window a round)
  config.ground.surface_extent = 110.0  # m: the height map's half width (edge cells beyond)
  config.ground.max_sensor_height = 5.0  # m: a ground farther below the origin: a note
  # Not 0: vehicle (ego) frames, Argoverse 2's and Waymo's, put the origin near the ground.
  config.ground.min_sensor_height = -1.0  # m: a ground higher above the origin: a note
  config.ground.max_ground_fraction = 0.85  # a "ground" holding more of a sweep: a note
  config.ground.up_check_points = 4000  # the up-axis check's sample of a sweep (seeded)
  config.ground.up_check_planes = 300  # its random planes (triples of the sample)
  config.ground.up_check_share = 1 / 3  # share of the sample the largest plane must hold
  config.ground.up_check_over_ground = 1.2  # ... and this many times the share taken as ground
  config.ground.up_check_tilt_deg = 45.0  # deg: a plane tilted more from --up stands upright

  config.ego = ml_collections.ConfigDict()
  # Coarse to fine: (voxel m, neighbours of a covariance, largest match m) of each GICP pass.
  config.ego.scales = ((1.0, 20, 3.0), (0.5, 20, 1.0),  # (voxel m, neighbours, match m) a pass
                       (0.25, 30, 0.5))
  config.ego.gicp_iterations = 30  # GICP iterations a pass
  config.ego.trim_rounds = 2  # GICP again on the points the fit explains
  config.ego.residual_voxel = 0.5  # m: voxels of the static residual's clouds
  config.ego.residual_neighbours = 20  # points of the static residual's local planes
  config.ego.truncate = 0.3  # m: a point's static residual is at most this
  config.ego.inlier = 0.1  # m: a point this near pc2's local plane is explained
  config.ego.plausible_inliers = 0.5  # share explained below which the fit is a note
  config.ego.search_sample = 600  # points of the coarse grid search
  config.ego.neighbours = 8  # bird's-eye neighbours of a pc2 point for its line
  config.ego.bev_cell = 0.1  # m: pc2's points above the ground merged per cell seen from above
  config.ego.max_match = 1.5  # m: a bird's-eye match farther than this is no match
  config.ego.line = 0.15  # minor / major spread below which a neighbourhood is a line
  config.ego.blob = 0.15  # m: spread below which in every direction a neighbourhood is a pole
  config.ego.search_yaw_deg_per_s = (-60.0, 60.0, 10.0)  # deg/s: the coarse search's yaws
  config.ego.search_x_per_s = (-40.0, 40.0, 5.0)  # m/s: the coarse search's forward motions
  config.ego.search_y_per_s = (-15.0, 15.0, 5.0)  # m/s: the coarse search's sideways motions

  config.objects = ml_collections.ConfigDict()
  config.objects.cell = 0.3  # m: objects are connected cells from above (a cell's gap bridged)
  config.objects.part_cell = 0.15  # m: a moved object's parts, connected cells (no bridging)
  config.objects.object_top = 2.6  # m above the ground: higher points join no object
  config.objects.min_points = 12  # points of an object (and of a part kept still)
  config.objects.max_high = 0.25  # share above object_top beyond which a group is structure
  config.objects.max_size = 14.0  # m: a larger group is structure (a facade), never moved
  config.objects.unexplained = 0.15  # m from ego-compensated pc2 (from above): unexplained
  config.objects.min_unexplained = 0.15  # share of unexplained points below which it stands still
  # ... unless it has this many: a car beside the sensor, sliding along its own side, is explained
  # but at its ends.
  config.objects.many_unexplained = 100  # unexplained points that make any object a candidate
  config.objects.search_per_s = 35.0  # m/s: an object's translation search, +- this
  config.objects.search_step = 0.25  # m: the translation search's fine step (twice that first)
  config.objects.search_coarse_step = 0.5  # m: its coarse step (the fine one searches +- this)
  config.objects.search_points = 150  # points at most a motion is searched on (half judge it)
  config.objects.search_slack = 0.5  # m: a refined motion may reach this beyond the search
  # A point's cost is its 3-D distance to pc2 truncated at `spacings` of the object's point
  # spacings, within truncate .. max_truncate, in units of that truncation (0 .. 1).
  config.objects.truncate = 0.3  # m: the least truncation of a point's cost (the search's)
  config.objects.spacings = 3.0  # point spacings of an object: the truncation of its costs
  config.objects.max_truncate = 1.5  # m: the largest truncation of a point's cost
  # A motion replaces standing still when its mean cost is lower by all of these:
  config.objects.margin = 0.05  # of the truncation: a motion's least gain over standing still
  config.objects.relative_margin = 0.1  # share of standing still's cost: the least gain too
  config.objects.significance = 3.0  # standard errors of the per-point gain: the least gain too
  config.objects.max_yaw_deg_per_s = 100.0  # deg/s: an object turning faster is refused
  config.objects.low_ground = 0.05  # m: "ground" this high in a moving object's cells moves too
  config.objects.rounds = 15  # iterations of an object's bird's-eye ICP
  config.objects.icp_scales = (0.3, 0.15, 0.08, 0.05)  # m: its robust scales, 4 rounds each
  config.objects.icp_gate = 3.0  # scales (plus icp_gate_margin): its rows farther are left out
  config.objects.icp_gate_margin = 0.2  # m
  config.objects.azimuth_bins = 1200  # columns of the visibility image (0.3 deg)
  config.objects.elevation_bins = 360  # rows of the visibility image (0.5 deg)
  config.objects.hidden = 0.5  # m behind pc2's return in its direction: hidden
  config.objects.hidden_fit = 0.45  # mean cost a motion must reach where pc2 hides still's place
  config.objects.min_seen = 0.3  # share visible in pc2 below which a motion is refused
  return config


@functools.lru_cache(maxsize=None)
def block(name: str, given=None):
  """The `name` block (ground, ego, objects): `given`, else the defaults' (a call given none)."""
  return getattr(defaults(), name) if given is None else given


def defaults() -> ml_collections.FrozenConfigDict:
  """get_config(), frozen and built once: the settings of a call given none."""
  return ml_collections.FrozenConfigDict(get_config())

