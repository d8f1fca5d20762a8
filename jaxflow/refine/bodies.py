"""The rigid bodies of a scene, found from a flow and fitted to pc2: a stage of `optimise`.

    flow_Nx3, found = rigid_bodies(pc1_Nx3, pc2_Mx3, flow_Nx3)   # NumPy + SciPy, on the host

A scene of FT3D or a street is a few rigid bodies (the static world seen from a moving sensor is
one): this stage serves pairs without ground or ego-motion structure. From a flow that is
right on most of each body (the optimiser's):
1. hypotheses: sequential RANSAC on the flow's correspondences p -> p + flow, each sample drawn
   among a point's nearest neighbours (a body is local), inliers removed, until too few remain
   (the random draws made once for every point: a micrometre does not redraw them all);
2. each hypothesis refined against pc2 by a robust ICP of its inliers (point-to-plane with a
   small point-to-point part, so a plane cannot slide along itself; jaxflow.geometry.registration),
   the unrefined motion kept beside it; a refinement that moves its points by more than
   `max_shift` on average is refused;
3. each point takes the motion whose moved neighbourhood lies nearest pc2's surfaces (distances to
   pc2's local planes, truncated, averaged over the point's neighbours in pc1), among the motions
   its neighbours hold (a body is contiguous), pulled a little towards its starting flow and towards
   the largest body (the world) so that ties (a plane sliding along itself) do not jump; motions are
   refitted to the points they won (the world's refit kept only where pc2 supports it better) and
   the points reassigned (`em_rounds`); a body whose points the
   world's motion fits as well (on the points pc2 would see: jaxflow.geometry.visibility) joins the
   world; so does one the world's motion takes out of pc2's view when its own motion is a slide of
   the world's along its surfaces (a facade leaving a camera's view, dragged along itself onto what
   pc2 still sees: nothing refutes the world's motion there);
4. per-point freedom where no rigid motion fits: a point whose best motion fits worse than its
   starting flow by more than `free_margin` keeps the starting flow, unless its best motion takes
   it out of pc2's view (there a starting flow that fits is a point dragged onto what pc2 saw).
Seeded: the same input gives the same flow. Settings were chosen on 7 of the 21 shared FT3D
pairs, the KITTI sample and 4 val pairs each of synthetic_lidar and synthetic_things
(benchmarks/METHODS.md).
"""

import dataclasses

import numpy as np

from jaxflow.geometry import groups, neighbours, registration, rigid
from jaxflow.geometry.visibility import OUTSIDE, SEEN, View


@dataclasses.dataclass(frozen=True)
class Settings:
  inlier: float = 0.08  # metres: a correspondence this near a hypothesis supports it
  trials: int = 150  # RANSAC samples a hypothesis
  local: int = 32  # a sample's three points come from one point's this many nearest neighbours
  min_support: int = 30  # points: a smaller hypothesis ends the search
  max_bodies: int = 25
  sample: int = 8192  # points at most that the hypotheses are searched on (seeded sample)
  icp_rounds: int = 20
  icp_points: int = 4000  # points at most an ICP fits (seeded sample)
  icp_scales: tuple = (0.2, 0.1, 0.05, 0.03)  # metres: the ICP's robust scales, coarse to fine
  point_weight: float = 0.1  # of the point-to-point rows beside the point-to-plane ones
  max_shift: float = 0.5  # metres: a refinement moving its points more than this is refused
  neighbours: int = 32  # a point's cost is the mean over this many neighbours in pc1
  truncate: float = 0.3  # metres
  pull: float = 0.03  # per metre of (neighbourhood mean) departure from the starting flow
  stick: float = 0.05  # metres of cost: a motion that departs from a point's flow must fit better
  world: float = 0.02  # metres of cost: any body but the largest (the world) must fit better
  em_rounds: int = 6
  free_margin: float = 0.05  # metres: a point keeps its starting flow when rigid fits this worse
  merge: float = 0.02  # metres of cost: a body the world's motion fits this well joins the world
  min_seen: float = 0.3  # ... judged on the points pc2 would see moved so; fewer seen: no judging
  slide: float = 0.1  # a body off pc2's view under the world's motion joins it when its own motion
  # departs from the world's along its surfaces (|normal part| / departure below this: a slide)
  hidden: float = 0.5  # metres: a point this far behind pc2's nearest return in its direction
  view_bin_deg: float = 1.0  # degrees: pc2's directions binned (its nearest return per bin)
  seed: int = 0
  # The RANSAC draws: "once" for every point (a micrometre of change redraws few samples), or
  # "each" hypothesis anew (9d35694's); the world's refit each EM round: "guarded" (kept only
  # where pc2 supports it better) or "always" (9d35694's). Issue 69 measures both on held-out
  # pairs (benchmarks/METHODS.md).
  draws: str = "once"
  world_refit: str = "guarded"

  def __post_init__(self):
    for name, choices in (("draws", ("once", "each")), ("world_refit", ("guarded", "always"))):
      if getattr(self, name) not in choices:
        raise ValueError(f"bodies {name} must be one of {choices}, got {getattr(self, name)!r}")
    for name in ("trials", "local", "min_support", "max_bodies", "sample", "icp_points",
                 "neighbours"):
      if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
        raise ValueError(f"bodies {name} must be an integer >= 1, got {getattr(self, name)!r}")
    if self.local < 3:
      raise ValueError(f"bodies local must be >= 3 (a sample is 3 points), got {self.local}")
    for name in ("inlier", "truncate", "max_shift", "hidden", "view_bin_deg"):
      if not getattr(self, name) > 0:
        raise ValueError(f"bodies {name} must be > 0, got {getattr(self, name)!r}")


@dataclasses.dataclass(frozen=True)
class BodiesFit:
  """What rigid_bodies did: hypotheses found, points that kept their starting flow, and each
  point's motion (-1: it kept its starting flow; None when no motion was fitted)."""
  bodies: int
  free_points: int
  note: str | None = None
  motion_of: np.ndarray | None = None


def _slides(points_Kx3, normals_Kx3, motion, world, most: float) -> bool:
  """Whether `motion` departs from `world` along the points' surfaces (a plane sliding along
  itself, which pc2 cannot tell from standing on it): the median |normal part| / departure is
  below `most`."""
  departure = motion.apply(points_Kx3) - world.apply(points_Kx3)
  across = np.abs(np.sum(departure * normals_Kx3, 1))
  return bool(np.median(across / np.maximum(np.linalg.norm(departure, axis=1), 1e-9)) < most)


def _join_world(best_N, motions, body_of, pc1, normals_Nx3, target, view, settings):
  """best_N with every body moved to the world (motion 0) that the world's motion explains as well
  as its own (jaxflow.geometry.groups.beats: its own must beat the world's by `merge`), judged on
  the points pc2 would see under the world's motion when `min_seen` of them are; when it takes
  most of them out of pc2's view, the body joins if its own motion is a slide of the world's. A
  body mostly hidden under the world's motion keeps its own. `body_of`: each motion's body."""
  world = motions[0]
  moved = world.apply(pc1)
  state = view.state(moved)
  seen_N = state == SEEN
  world_cost = np.where(seen_N, target.plane_distance(moved, settings.truncate), np.nan)
  rule = groups.Rule(margin=settings.merge, min_seen=settings.min_seen)
  out = best_N.copy()
  for h, pts in groups.Groups(best_N, len(motions)).members():
    if body_of[h] == 0 or not len(pts):
      continue
    seen = seen_N[pts]
    own = np.full(len(pts), np.nan)
    own[seen] = target.plane_distance(motions[h].apply(pc1[pts[seen]]), settings.truncate)
    stays = groups.beats(world_cost[pts], own, rule)
    if stays is None:  # out of pc2's view under the world's motion
      stays = not ((state[pts] == OUTSIDE).mean() >= 0.5 and _slides(
        pc1[pts], normals_Nx3[pts], motions[h], world, settings.slide))
    if not stays:
      out[pts] = 0
  return out


def _icp(target: registration.PlaneTarget, src_Kx3, motion, rounds: int, scales,
         settings: Settings):
  """`motion` (a rigid.Motion) refined by the robust point-to-plane (+ point-to-point) fit of src
  to pc2, `scales` spread over `rounds` rounds; refused (the start returned) when it moves the
  points by more than `max_shift` on average."""
  per_round = [scales[min(i * len(scales) // rounds, len(scales) - 1)] for i in range(rounds)]
  fitted = registration.robust_fit(src_Kx3, motion, target.plane_rows, per_round,
                                   point_weight=settings.point_weight, min_weight=6)
  shift = np.linalg.norm(fitted.apply(src_Kx3) - motion.apply(src_Kx3), axis=1).mean()
  if shift > settings.max_shift or not np.all(np.isfinite(fitted.rotation)):
    return motion
  return fitted


def _refit(target, evidence: groups.Evidence, pc1, pts, motion, world: bool, settings: Settings,
           rng):
  """`motion` refitted to its points `pts` (a fine ICP). The world's refit is kept only when pc2
  supports it better on them: every point may take the world's motion, so the points no motion
  explains gather there, and refitted on them each round it drifted (carried 1.4 m down, out of
  pc2's view, where nothing refutes it, in 6 rounds); another body's points are its neighbours'."""
  if len(pts) < 10:
    return motion
  fitted = _icp(target, pc1[_subset(pts, settings.icp_points, rng)], motion, 10, (0.05, 0.03),
                settings)
  if not world or settings.world_refit == "always":
    return fitted
  rule = groups.Rule(margin=0.0, min_seen=settings.min_seen)
  better = groups.beats(evidence.costs(motion.apply(pc1[pts])),
                        evidence.costs(fitted.apply(pc1[pts])), rule)
  return fitted if better else motion


def _sample_fits(src_Nx3, dst_Nx3, picks_Tx3):
  """The Kabsch motions (R T x 3 x 3, t T x 3) of T samples of three correspondences each."""
  a, b = src_Nx3[picks_Tx3], dst_Nx3[picks_Tx3]
  mu_a, mu_b = a.mean(1), b.mean(1)
  cov = np.einsum("tki,tkj->tij", a - mu_a[:, None], b - mu_b[:, None])
  rot = rigid.kabsch_rotation(cov)
  return rot, mu_b - np.einsum("tij,tj->ti", rot, mu_a)


def hypotheses(pc1_Nx3, flow_Nx3, settings: Settings, rng, nbr_NxK=None):
  """(groups.Groups, [rigid.Motion]): sequential local RANSAC on p -> p + flow, group k the inliers
  of motion k (-1: no motion's). `nbr_NxK`: each point's `settings.local` nearest (searched when
  not given). A hypothesis's `trials` samples are drawn and scored at once."""
  target = pc1_Nx3 + flow_Nx3
  if nbr_NxK is None:
    nbr_NxK = neighbours.knn_graph(pc1_Nx3, settings.local)
  remaining, found = np.arange(len(pc1_Nx3)), []
  # The draws are made once, for every point: a sample is the next `trials` points of one random
  # order still left, each with three of its neighbours still left (the smallest of keys drawn
  # for all). A few points' support flipping by a micrometre then changes a few samples, not
  # every later draw (a pair's EPE went from 0.08 to 0.16 under 2e-5 m of change in its flow).
  once = settings.draws == "once"
  if once:
    anchors, keys_NxK, cursor = rng.permutation(len(pc1_Nx3)), rng.random(nbr_NxK.shape), 0
  while len(remaining) >= settings.min_support and len(found) < settings.max_bodies:
    left = np.zeros(len(pc1_Nx3), bool)
    left[remaining] = True
    if once:
      ahead = np.roll(anchors, -cursor)
      ahead = ahead[left[ahead]][:settings.trials]
      cursor = (cursor + settings.trials) % len(anchors)
    else:
      ahead = rng.choice(remaining, settings.trials)
    near_TxK = nbr_NxK[ahead]
    usable_TxK = left[near_TxK]
    # Three distinct neighbours still left, uniformly: the three smallest random keys.
    keys = np.where(usable_TxK, keys_NxK[ahead] if once else rng.random(near_TxK.shape), np.inf)
    order = np.argsort(keys, axis=1)[:, :3]
    ok = usable_TxK.sum(1) >= 3
    if not ok.any():
      break
    picks = np.take_along_axis(near_TxK, order, 1)[ok]
    rot, trans = _sample_fits(pc1_Nx3, target, picks)
    moved = pc1_Nx3[remaining] @ rot.transpose(0, 2, 1) + trans[:, None]  # T x N x 3 (BLAS)
    counts = (np.sum((moved - target[remaining]) ** 2, -1) < settings.inlier**2).sum(1)
    best = int(np.argmax(counts))  # the first of the most supported
    if counts[best] < settings.min_support:
      break
    best = rigid.Motion(rot[best], trans[best])
    for _ in range(3):  # refit to the inliers
      inliers = remaining[np.linalg.norm(best.apply(pc1_Nx3[remaining]) - target[remaining],
                                         axis=1) < settings.inlier]
      if len(inliers) < 3:
        break
      best = rigid.kabsch(pc1_Nx3[inliers], target[inliers])
    found.append((best, inliers))
    remaining = np.setdiff1d(remaining, inliers)
  label = np.full(len(pc1_Nx3), -1)
  for k, (_, inliers) in enumerate(found):
    label[inliers] = k
  return groups.Groups(label, len(found)), [motion for motion, _ in found]


def _subset(indices, most: int, rng):
  return indices if len(indices) <= most else np.sort(rng.choice(indices, most, replace=False))


def _costs(motions, body_of, pc1, flow, label_N, nbr_NxK, target, settings):
  """(cost N x H, choice N x H) of each point under each motion H: the mean over its neighbours of
  their distances to pc2's planes (inf where the motion may not be taken: a body is contiguous, a
  point takes only a motion whose body a neighbour holds, or any where a neighbour holds none),
  and the cost plus what ties are broken by (departing from the starting flow, not the world)."""
  n, bodies_found = len(pc1), body_of.max() + 1
  every = np.arange(n)
  held = np.zeros((n, bodies_found + 1), bool)
  held[every[:, None], label_N[nbr_NxK]] = True
  allowed = held[:, body_of] | held[:, -1:]
  cost_NxH = np.full((n, len(motions)), np.inf)
  choice_NxH = np.full_like(cost_NxH, np.inf)
  cost_N, departure_N = np.empty(n), np.empty(n)
  for h, motion in enumerate(motions):
    # Costs only where the motion may be taken (the world's: everywhere, bodies join it), each
    # the mean over the point's neighbours: those are the points whose cost is needed.
    rows = every if body_of[h] == 0 else np.flatnonzero(allowed[:, h])
    if not len(rows):
      continue
    need = every if len(rows) == n else np.unique(nbr_NxK[rows])
    moved = motion.apply(pc1[need])
    cost_N[need] = target.plane_distance(moved, settings.truncate)
    departure_N[need] = np.minimum(np.linalg.norm(moved - pc1[need] - flow[need], axis=1), 1.0)
    cost_NxH[rows, h] = cost_N[nbr_NxK[rows]].mean(1)
    choice_NxH[rows, h] = (cost_NxH[rows, h] + settings.pull * departure_N[nbr_NxK[rows]].mean(1)
                           + settings.stick * (departure_N[rows] > settings.inlier)
                           + settings.world * (body_of[h] != 0))
  return cost_NxH, choice_NxH


def rigid_bodies(pc1_Nx3, pc2_Mx3, flow_Nx3, settings: Settings = Settings()):
  """(flow N x 3 float32, BodiesFit): `flow_Nx3` made piecewise rigid where rigid motions fit pc2
  (module docstring). A flow that is not finite, or too few points, is returned unchanged with a
  note."""
  pc1, pc2 = np.asarray(pc1_Nx3, np.float64), np.asarray(pc2_Mx3, np.float64)
  flow = np.asarray(flow_Nx3, np.float64)
  if not np.all(np.isfinite(flow)) or not np.all(np.isfinite(pc1)) or \
      not np.all(np.isfinite(pc2)):
    return flow.astype(np.float32), BodiesFit(0, len(pc1), "bodies: a non-finite input; the flow "
                                                          "is returned unchanged")
  if min(len(pc1), len(pc2)) < max(settings.min_support, 10):
    return flow.astype(np.float32), BodiesFit(0, len(pc1), f"bodies: {len(pc1)} and {len(pc2)} "
                                              "points are too few for rigid bodies; the flow is "
                                              "returned unchanged")
  rng = np.random.default_rng(settings.seed)
  sample = _subset(np.arange(len(pc1)), settings.sample, rng)
  tree1 = neighbours.Tree(pc1)
  nbr_NxK = tree1.knn(pc1, settings.neighbours)
  whole = len(sample) == len(pc1) and settings.local == settings.neighbours  # one search serves
  support, found = hypotheses(pc1[sample], flow[sample], settings, rng,
                              nbr_NxK if whole else None)
  if not found:
    return flow.astype(np.float32), BodiesFit(0, len(pc1), "bodies: no rigid motion has support; "
                                                          "the flow is returned unchanged")
  target = registration.PlaneTarget(pc2)
  bins = round(360 / settings.view_bin_deg), round(180 / settings.view_bin_deg)
  view = View(pc2, "y", *bins, settings.hidden)  # the model frame: y up
  normals1 = neighbours.local_spread(pc1, 10, tree1)[1][:, :, 0]
  # Each body's refined motion, then its unrefined one: both stay candidates of the body.
  motions = [_icp(target, pc1[sample[_subset(inl, settings.icp_points, rng)]], m,
                  settings.icp_rounds, settings.icp_scales, settings)
             for m, (_, inl) in zip(found, support.members())]
  motions += found
  body_of = np.tile(np.arange(len(found)), 2)
  # At first, the body whose hypothesis a point supported; unsupported points: any motion.
  label_N = np.full(len(pc1), len(found))
  label_N[sample] = np.where(support.label >= 0, support.label, len(found))
  evidence = groups.Evidence(target, view, settings.truncate)
  start_cost = target.plane_distance(pc1 + flow, settings.truncate)[nbr_NxK].mean(1)
  for round_ in range(settings.em_rounds + 1):
    cost_NxH, choice_NxH = _costs(motions, body_of, pc1, flow, label_N, nbr_NxK, target,
                                  settings)
    best_N = _join_world(np.argmin(choice_NxH, 1), motions, body_of, pc1, normals1, target, view,
                         settings)
    label_N = body_of[best_N]
    if round_ == settings.em_rounds:
      break
    motions = [_refit(target, evidence, pc1, np.flatnonzero(best_N == h), m, body_of[h] == 0,
                      settings, rng) for h, m in enumerate(motions)]
  rotations = np.stack([m.rotation for m in motions])[best_N]
  translations = np.stack([m.translation for m in motions])[best_N]
  out = np.einsum("nij,nj->ni", rotations, pc1) + translations - pc1
  # Out of pc2's view, a good fit of the starting flow is a point dragged onto what pc2 saw.
  free = (cost_NxH[np.arange(len(pc1)), best_N] > start_cost + settings.free_margin) & (
    view.state(pc1 + out) != OUTSIDE)
  out[free] = flow[free]
  return out.astype(np.float32), BodiesFit(len(found), int(free.sum()),
                                           motion_of=np.where(free, -1, best_N))
