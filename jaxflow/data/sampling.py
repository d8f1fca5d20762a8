"""Fixed-size sampling of a Pair and the optional training augmentation."""

import numpy as np

from jaxflow.data.registry import Pair
from jaxflow.errors import ConfigError, DataError

AUGMENT_KEYS = ("rotation_deg", "scale", "jitter")


def take(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
  """a[idx] along the first axis; several times faster than fancy indexing on N x 3 rows."""
  return a.take(idx, axis=0)


def sample_indices(n: int, num_points: int, rng: np.random.Generator) -> tuple[np.ndarray, bool]:
  """num_points indices into n; with n < num_points every point once plus random repeats."""
  if n >= num_points:
    return rng.choice(n, num_points, replace=False), False
  extra = rng.choice(n, num_points - n, replace=True)
  return rng.permutation(np.concatenate([np.arange(n), extra])), True


def sample_pair(pair: Pair, num_points: int, rng: np.random.Generator) -> tuple[Pair, int]:
  """Samples pc1 and pc2 to num_points each with independent indices (no correspondence kept).

  A cloud with fewer points is sampled with replacement (each point at least once); the int
  returned counts such clouds (0, 1 or 2). The pair is never replaced by another one.
  """
  if len(pair.pc1) == 0 or len(pair.pc2) == 0:
    raise DataError(pair.name, "cannot sample an empty cloud")
  idx1, rep1 = sample_indices(len(pair.pc1), num_points, rng)
  idx2, rep2 = sample_indices(len(pair.pc2), num_points, rng)
  labels = {} if not pair.has_labels else dict(rigid_flow=take(pair.rigid_flow, idx1),
                                                foreground=take(pair.foreground, idx1))
  if pair.category is not None:  # Argoverse 2 labels (jaxflow.evaluation.av2_eval)
    labels.update(category=take(pair.category, idx1), ego_xy=take(pair.ego_xy, idx1))
  sampled = Pair(pc1=take(pair.pc1, idx1), pc2=take(pair.pc2, idx2), flow=take(pair.flow, idx1),
                 mask=take(pair.mask, idx1), name=pair.name, **labels)
  return sampled, int(rep1) + int(rep2)


def crop_pair(pair: Pair, num_points: int, rng: np.random.Generator,
              mask_outside: bool = False) -> Pair:
  """A local window of num_points points of each cloud, at the density of the cloud given.

  The window of pc1 is the num_points points nearest a random pc1 point c; the window of pc2 is the
  num_points pc2 points nearest c + flow(c), so that it follows the scene's motion as a whole cloud
  does. Training on windows of a densely sampled pair teaches a network at the test density
  (8192 points) for the cost of a few hundred points: the graph, correlation and voxel features are
  all local and in metres, so the density, not the extent, is what must match.

  A pc1 point of the window whose target (point + flow) lies farther from c + flow(c) than the
  farthest pc2 point of the window moves out of what the network sees of pc2: no correlation can
  find its match. mask_outside=True drops those points from the loss (mask False) instead of
  training the network to guess where they went.
  """
  for name in ("pc1", "pc2"):
    if len(getattr(pair, name)) < num_points:
      raise ConfigError(f"crop_pair: {pair.name}: {name} has {len(getattr(pair, name))} points, "
                        f"fewer than the window's {num_points}")
  centre = int(rng.integers(len(pair.pc1)))

  def nearest(cloud, point):
    d = np.sum((cloud - point) ** 2, axis=1)
    idx = np.sort(np.argpartition(d, num_points - 1)[:num_points])
    return idx, d[idx].max()  # the window and its squared radius

  idx1, _ = nearest(pair.pc1, pair.pc1[centre])
  target = pair.pc1[centre] + pair.flow[centre]
  idx2, radius_sq = nearest(pair.pc2, target)
  mask = take(pair.mask, idx1)
  if mask_outside:
    moved_to = pair.pc1[idx1] + pair.flow[idx1]
    mask = mask & (np.sum((moved_to - target) ** 2, axis=1) <= radius_sq)
  return Pair(pc1=take(pair.pc1, idx1), pc2=take(pair.pc2, idx2), flow=take(pair.flow, idx1),
              mask=mask, name=pair.name)


def check_augment(augment: dict | None) -> dict:
  """Validates an augmentation dict: {"rotation_deg": 10, "scale": (0.95, 1.05), "jitter": 0.01}."""
  augment = dict(augment or {})
  unknown = set(augment) - set(AUGMENT_KEYS)
  if unknown:
    raise ConfigError(f"augment: unknown keys {sorted(unknown)}; expected {AUGMENT_KEYS}")
  scale = augment.get("scale")
  if scale is not None and (len(scale) != 2 or not 0 < scale[0] <= scale[1]):
    raise ConfigError(f"augment: scale must be (low, high) with 0 < low <= high, got {scale}")
  if augment.get("rotation_deg", 0) < 0 or augment.get("jitter", 0) < 0:
    raise ConfigError(f"augment: rotation_deg and jitter must be >= 0, got {augment}")
  identity = {"rotation_deg": 0, "scale": (1, 1), "jitter": 0}
  same = lambda a, b: tuple(np.atleast_1d(a)) == tuple(np.atleast_1d(b))
  return {k: v for k, v in augment.items() if not same(v, identity[k])}  # no-ops dropped


def augment_pair(pair: Pair, augment: dict, rng: np.random.Generator) -> Pair:
  """Rotation about the vertical (y) axis, uniform scale and per-point jitter.

  Rotation and scale act identically on both clouds about the origin, so the flow becomes
  s R flow (pc1 + flow still lands where the transformed pc2 surface is). Jitter is Gaussian
  sensor noise (sigma in metres, clipped at 3 sigma) drawn independently for every point of pc1
  and pc2; it leaves the flow unchanged, as the noise moves the measurement, not the surface.
  """
  if not augment:
    return pair
  angle = np.deg2rad(rng.uniform(-1, 1) * augment.get("rotation_deg", 0.0))
  low, high = augment.get("scale", (1.0, 1.0))
  s = rng.uniform(low, high)
  c, si = np.cos(angle), np.sin(angle)
  rot_3x3 = s * np.array([[c, 0, si], [0, 1, 0], [-si, 0, c]])
  pc1 = pair.pc1 @ rot_3x3.T
  pc2 = pair.pc2 @ rot_3x3.T
  flow = pair.flow @ rot_3x3.T
  sigma = augment.get("jitter", 0.0)
  if sigma:
    pc1 = pc1 + np.clip(rng.normal(0, sigma, pc1.shape), -3 * sigma, 3 * sigma)
    pc2 = pc2 + np.clip(rng.normal(0, sigma, pc2.shape), -3 * sigma, 3 * sigma)
  f32 = lambda a: a.astype(np.float32)
  return Pair(pc1=f32(pc1), pc2=f32(pc2), flow=f32(flow), mask=pair.mask, name=pair.name)
