"""Scene flow of two raw LiDAR sweeps: the ground, the sensor's motion, the moving objects.

    flow_Nx3, info = raw_sweep_flow(None, pc1_Nx3, pc2_Mx3, up="z")
    print(info.note())

Raw sweeps (360 degrees, ground kept, independently sampled) are mostly static world, so the
sensor's own motion is most of the flow:
1. the ground of each sweep, if it has one: local planes per cell (jaxflow.lidar.ground);
   an up axis under which the sweep's largest plane stands upright near the origin is refused
   (`ground_limits=False` overrides), a ground that looks odd is noted; a sweep whose ground was
   removed upstream is a normal case;
2. the ego-motion: GICP of all the points from several starts, zero motion among the candidates,
   the one that explains the static world best kept (jaxflow.lidar.ego);
3. the ground again, fitted to both sweeps in pc1's frame, so the two agree;
4. moving objects: groups of points the ego-motion does not explain, one rigid motion each
   (jaxflow.lidar.objects), judged on what pc2's sensor saw from where it was (found from its rings,
   jaxflow.lidar.sensor: a vehicle frame's origin lies below it), sought in the whole sweep
   (`max_range` cuts only what flow_fn sees: the AV2 challenge scores a 70 x 70 m box, whose corners
   lie beyond a 35 m disc); every point on no moving object, ground included, gets the ego-motion
   flow.
`flow_fn(pc1_kept, pc2_kept)` (e.g. the network on the non-ground points within `max_range`) is
called only with `use_network=True` (or on a camera's view, where the farther points get the rigid
motion of its static part): its flow is then one more start for the ego-motion and for every object
(benchmarks/METHODS.md measures what it adds). Any up axis: the work is done z up.
The tuning is `settings` (jaxflow.lidar.settings.Sweep; `python -m jaxflow.predict --method lidar
--print_config` lists its fields with their units).
"""

import dataclasses

import numpy as np

from jaxflow.errors import ConfigError, DataError
from jaxflow.geometry import frames, rigid
from jaxflow.lidar import both_ways, ego, ground, objects, sensor
from jaxflow.lidar.settings import DEFAULTS, Sweep


@dataclasses.dataclass(frozen=True)
class SweepInfo:
  """What raw_sweep_flow did (counts are (pc1, pc2); `motion` in the input's axes)."""
  sensor_height: float | None  # metres above pc1's ground (None: no ground found)
  ground: tuple
  far: tuple  # non-ground points beyond max_range
  kept: tuple  # non-ground points within max_range (what flow_fn sees)
  motion: rigid.Motion  # the ego-motion
  ego: ego.EgoMotion
  objects: objects.Found
  max_range: float | None
  used_network: bool
  notes: tuple = ()  # fits that failed or look wrong
  ground_masks: tuple = ()  # (pc1 N, pc2 M) bool: the points taken as ground (the pictures)
  settings: Sweep = DEFAULTS  # the settings used
  sensor2: tuple = (0.0, 0.0, 0.0)  # where pc2's sensor was found in its frame (input's axes)

  def note(self) -> str:
    moved = sum(m[0] for m in self.objects.moved)
    settings = self.settings
    cell = f"ground plane per {settings.ground.surface.cell:g} m cell"
    if self.ego.start == "flow_fn":  # a camera's view: the method's flow and its rigid part
      return (f"--lidar: {cell}; removed {self.ground[0]} ground and "
              f"{self.far[0]} far points of PC1; flow estimated on {self.kept[0]} points; the "
              f"removed PC1 points get the ego-motion flow of a rigid fit to its static part "
              f"({self.motion.angle_deg:.2f} deg, {np.linalg.norm(self.motion.translation):.2f} m)"
              + "".join(f"\nnote: {n}" for n in self.notes))
    ground_text = ("no ground found" if self.sensor_height is None else
                   f"{cell} (the origin {self.sensor_height:.2f} m above it)")
    return (f"--lidar: {ground_text}; removed {self.ground[0]} ground points of PC1 "
            f"({self.ground[1]} of PC2); ego-motion {self.ego.motion.angle_deg:.2f} deg, "
            f"{np.linalg.norm(self.motion.translation):.2f} m ({self.ego.start}, "
            f"{100 * self.ego.inlier_fraction:.0f}% of the points within "
            f"{100 * settings.ego.inlier:.0f} cm of PC2's surfaces); "
            f"{len(self.objects.moved)} of {self.objects.candidates} candidate objects move "
            f"({moved} points in them{self._sensor_text()}); the other "
            f"{self.kept[0] + self.far[0] + self.ground[0] - moved} PC1 points get the ego-motion "
            "flow"
            + ("; the method's flow was a start" if self.used_network else "")
            + "".join(f"\nnote: {n}" for n in self.notes))

  def _sensor_text(self) -> str:
    """Where pc2's sensor was found, when not at the frame's origin."""
    if not any(self.sensor2):
      return ""
    return ", judged from PC2's sensor found at (" + ", ".join(
      f"{v:.2f}" for v in self.sensor2) + ") m"


def settings_of(settings=None) -> Sweep:
  """`settings` (a jaxflow.lidar.settings.Sweep; None: the defaults); a ConfigError for anything
  else."""
  if settings is None:
    return DEFAULTS
  if not isinstance(settings, Sweep):
    raise ConfigError("the raw-sweep pipeline's settings are a jaxflow.lidar.settings.Sweep, got "
                      f"{type(settings).__name__}")
  return settings


def min_points(settings: Sweep | None = None) -> int:
  """The fewest points of a sweep the pipeline fits: ego.estimate's own (with fewer it fits no
  motion at all)."""
  return ego.min_points(settings_of(settings).ego)


def too_few(settings: Sweep | None = None) -> str:
  """Why a sweep needs `min_points`, for the error of a smaller one."""
  neighbours = settings_of(settings).ego.gicp.scales[-1][1]
  return (f"the raw-sweep pipeline (--lidar, method lidar) needs at least {min_points(settings)} "
          f"points a sweep: its ego-motion fit (GICP) takes {neighbours} neighbours a point in its "
          "finest pass, and three times as many points (--method.lidar.ego.gicp.scales)")


def _surface(points_Nx3, name, notes, settings):
  """(Surface or None, ground N): None with a note when no ground plane is found."""
  try:
    return ground.find_ground(points_Nx3, "z", name, settings)
  except DataError as e:
    notes.append(f"{e}; no point of {name} is taken as ground")
    return None, np.zeros(len(points_Nx3), bool)


def _z_up(pc1_Nx3, pc2_Mx3, up: str, names):
  """(pc1, pc2) float64 with z up, and the column order back to `up`'s; a ConfigError for a wrong
  axis name, a DataError for a cloud that is not N x 3."""
  order = frames.permutation(up, "z")  # a ConfigError for a wrong name
  for cloud, name in ((pc1_Nx3, names[0]), (pc2_Mx3, names[1])):
    if np.ndim(cloud) != 2 or np.shape(cloud)[1] != 3:
      raise DataError(name, f"raw_sweep_flow takes N x 3 points, got shape {np.shape(cloud)}")
  return (np.asarray(pc1_Nx3, np.float64)[:, order], np.asarray(pc2_Mx3, np.float64)[:, order],
          order, np.argsort(order))


def _ground_notes(clouds, surfaces, grounds, names, up: str, camera: bool, settings) -> list:
  """What looks wrong in each sweep's ground (check_ground), or its up axis (check_up_axis, not
  on a camera's view); either raises where the up axis is plainly wrong."""
  notes = []
  for raw, surf, g, name in zip(clouds, surfaces, grounds, names):
    problem = surf is not None and ground.check_ground(surf, g, name, up,
                                                       None if camera else raw, settings)
    note = not camera and ground.check_up_axis(raw, up, name, g.mean() if surf is not None
                                               else 0.0, settings=settings)
    notes.extend(n for n in (problem, note) if n)
  return notes


def _network_start(flow_fn, pc1_Nx3, pc2_Mx3, pc1, keep1, keep2, order, settings):
  """({"network": the rigid motion of the static part of flow_fn's flow}, that flow N x 3 z up,
  NaN where flow_fn did not see the point): one more start for the ego-motion and the objects."""
  kept_flow = np.asarray(flow_fn(np.asarray(pc1_Nx3, np.float32)[keep1],
                                 np.asarray(pc2_Mx3, np.float32)[keep2]), np.float64)
  start_flow = np.full_like(pc1, np.nan)
  start_flow[keep1] = kept_flow[:, order]
  return ({"network": rigid.fit_static_motion(pc1[keep1], start_flow[keep1],
                                              settings.static_threshold)}, start_flow)


def _joint_ground(pc1, pc2, motion, surf1, surf2, g1, g2, name, settings):
  """(surface, g1, g2): one ground fitted to both sweeps in pc1's frame, so that the two agree
  (pc1's own surface and both masks as they are when either sweep has no ground)."""
  if surf1 is None or surf2 is None:
    return surf1, g1, g2
  inverse = motion.inverse()
  both = np.concatenate([pc1, inverse.apply(pc2)])
  surface = ground.fit_surface(both, "z", None, name, settings=settings)
  return surface, surface.ground(pc1), surface.ground(inverse.apply(pc2))


def raw_sweep_flow(flow_fn, pc1_Nx3, pc2_Mx3, up: str = "z", max_range: float | None = None,
                   names=("pc1", "pc2"), use_network: bool = False, ground_limits: bool = True,
                   moving_objects: bool = True, seed: int = 0,
                   settings: Sweep | None = None
                   ) -> tuple[np.ndarray, SweepInfo]:
  """Flow N x 3 (float32) of EVERY point of pc1 and a SweepInfo (module docstring);
  moving_objects=False: the ego-motion flow for every point (what the objects step adds).
  `settings`: a jaxflow.lidar.settings.Sweep (None: the defaults);
  `max_range` (m; 0: every point): default settings.max_range."""
  settings = settings_of(settings)
  max_range = settings.max_range if max_range is None else max_range
  pc1, pc2, order, back = _z_up(pc1_Nx3, pc2_Mx3, up, names)
  notes = []
  surf1, g1 = _surface(pc1, names[0], notes, settings.ground)
  surf2, g2 = _surface(pc2, names[1], notes, settings.ground)
  view = azimuth_coverage(pc1)
  camera = view < settings.min_azimuth  # a camera facing a wall sees mostly wall: no sign of up
  if ground_limits:
    notes.extend(_ground_notes((pc1_Nx3, pc2_Mx3), (surf1, surf2), (g1, g2), names, up, camera,
                               settings.ground))
  near1, near2 = ground.within_range(pc1, "z", max_range), ground.within_range(pc2, "z", max_range)
  keep1, keep2 = ~g1 & near1, ~g2 & near2
  flow_fn_can = flow_fn is not None and keep1.sum() >= 3 and keep2.sum() >= 3
  if camera and flow_fn_can:
    return _camera_view(flow_fn, pc1_Nx3, pc2_Mx3, keep1, keep2, g1, g2, near1, near2, up,
                        surf1, max_range, settings, notes + [
                          f"{names[0]} covers {360 * view:.0f} of 360 degrees of azimuth: a "
                          "camera's view, not a sweep; the flow of its non-ground points within "
                          "max_range is the method's, the rest gets the rigid motion of their "
                          "static part"])
  if camera:
    notes.append(f"{names[0]} covers {360 * view:.0f} of 360 degrees of azimuth: a camera's view, "
                 "not a sweep; the sweep's ego-motion fit may be wrong there")
  starts, start_flow = {}, None
  if use_network and flow_fn_can:
    starts, start_flow = _network_start(flow_fn, pc1_Nx3, pc2_Mx3, pc1, keep1, keep2, order,
                                        settings)
  rate = settings.frame_rate_hz
  fit = ego.estimate(pc1, pc2, g1, g2, starts, seed, settings=settings.ego, frame_rate_hz=rate,
                     refit_search=True)
  if fit.note:
    notes.append(fit.note)
  surface, g1, g2 = _joint_ground(pc1, pc2, fit.motion, surf1, surf2, g1, g2, names[0],
                                  settings.ground)
  sensor2 = np.zeros(3)
  if moving_objects:
    # Not the ground: seen from the road's own height the whole road lies at one elevation.
    sensor2, _ = sensor.sensor_position(pc2[~g2], settings.sensor, seed)
    sensor1 = (sensor.sensor_position(pc1[~g1], settings.sensor, seed)[0]
               if settings.objects.both_ways else None)
    flow, found = both_ways.object_flow(pc1, pc2, g1, g2, fit.motion, surface, start_flow, seed,
                                        settings.objects, settings.ego, rate, (sensor1, sensor2))
  else:
    flow, found = fit.motion.flow(pc1), objects.Found(0, 0, [])
  if not np.isfinite(flow).all():  # never reached by construction; never returned either
    raise FloatingPointError("raw_sweep_flow: a non-finite flow")
  motion = fit.motion.in_frame(frames.rotation("z", up))  # back in the input's frame
  info = _info(surf1, g1, g2, near1, near2, motion, fit, found, max_range,
               start_flow is not None, notes, settings, sensor2[back])
  return np.ascontiguousarray(flow[:, back], np.float32), info


def _info(surf1, g1, g2, near1, near2, motion, fit, found, max_range, used_network, notes,
          settings, sensor2=np.zeros(3)):
  """The SweepInfo of a pair: `motion` in the input's frame, `fit` in the z-up frame."""
  return SweepInfo(
    sensor_height=None if surf1 is None else surf1.sensor_height,
    ground=(int(g1.sum()), int(g2.sum())),
    far=(int((~g1 & ~near1).sum()), int((~g2 & ~near2).sum())),
    kept=(int((~g1 & near1).sum()), int((~g2 & near2).sum())), motion=motion, ego=fit,
    objects=found, max_range=max_range, used_network=used_network, notes=tuple(notes),
    ground_masks=(g1, g2), settings=settings, sensor2=tuple(map(float, sensor2)))


def azimuth_coverage(points_Nx3) -> float:
  """Share of 36 azimuth sectors (z up) holding at least 0.1% of the points."""
  azimuth = np.arctan2(points_Nx3[:, 1], points_Nx3[:, 0])
  counts = np.histogram(azimuth, 36, (-np.pi, np.pi))[0]
  return float((counts >= max(1, 1e-3 * len(points_Nx3))).mean())


def _camera_view(flow_fn, pc1_Nx3, pc2_Mx3, keep1, keep2, g1, g2, near1, near2, up, surf1,
                 max_range, settings, notes):
  """A camera-frame pair (e.g. KITTI's stereo frames): flow_fn on the kept points, the removed
  ones the rigid motion of the static part of that flow (jaxflow.geometry.rigid)."""
  pc1 = np.asarray(pc1_Nx3, np.float32)
  kept_flow = np.asarray(flow_fn(pc1[keep1], np.asarray(pc2_Mx3, np.float32)[keep2]), np.float32)
  motion = rigid.fit_static_motion(pc1[keep1], kept_flow, settings.static_threshold)
  flow = motion.flow(pc1)
  flow[keep1] = kept_flow
  z_up = motion.in_frame(frames.rotation(up, "z"))
  fit = ego.EgoMotion(z_up, float(motion.inliers.mean()), float("nan"), "flow_fn", {})
  info = _info(surf1, g1, g2, near1, near2, motion, fit, objects.Found(0, 0, []), max_range, True,
               notes, settings)
  return flow, info
