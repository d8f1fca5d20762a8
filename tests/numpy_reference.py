"""Plain NumPy (loop) implementations of the network's operations, written from the papers'
definitions (docs/network.md) independently of jaxflow's vectorised code, for the tests to compare against."""

import numpy as np


def knn(points, k):
  """N x k indices of the k nearest points (self included), by exact distance."""
  n = len(points)
  out = np.zeros((n, k), np.int64)
  for i in range(n):
    d = [float(np.sum((points[j].astype(np.float64) - points[i]) ** 2)) for j in range(n)]
    out[i] = np.argsort(d, kind="stable")[:k]
  return out


def group_norm(x, scale, bias, groups=8, eps=1e-5):
  """x: (..., C) of one sample; statistics over every leading position and the group's channels."""
  c = x.shape[-1]
  g = c // groups
  out = np.empty_like(x, dtype=np.float64)
  for gi in range(groups):
    sl = slice(gi * g, (gi + 1) * g)
    block = x[..., sl].astype(np.float64)
    out[..., sl] = (block - block.mean()) / np.sqrt(block.var() + eps)
  return out * scale + bias


def leaky(x, slope=0.1):
  return np.where(x >= 0, x, slope * x)


def setconv(p, f, xyz, nbr):
  """One cloud: f N x C, xyz N x 3, nbr N x K."""
  n, k = nbr.shape
  edges = np.zeros((n, k, f.shape[1] + 3))
  for i in range(n):
    for a, j in enumerate(nbr[i]):
      edges[i, a] = np.concatenate([f[j] - f[i], xyz[j] - xyz[i]])
  x = leaky(group_norm(edges @ p["fc1"]["kernel"], p["gn1"]["scale"], p["gn1"]["bias"]))
  x = x.max(axis=1)
  x = leaky(group_norm(x @ p["fc2"]["kernel"], p["gn2"]["scale"], p["gn2"]["bias"]))
  return leaky(group_norm(x @ p["fc3"]["kernel"], p["gn3"]["scale"], p["gn3"]["bias"]))


def gcl(p, f, xyz, nbr, supports, similarity="sum"):
  """Paper eq. 4-5 with one support direction per (support, output channel)."""
  w = p["kernel"]["kernel"]
  c = w.shape[1] // (supports + 1)
  e = p["directions"]  # 3 x (L * C), column l * C + ch
  n = len(f)
  out = np.zeros((n, c))
  for i in range(n):
    for ch in range(c):
      total = f[i] @ w[:, ch] + p["bias"][ch]
      for l in range(supports):
        col = (l + 1) * c + ch
        direction = e[:, l * c + ch]
        best = -np.inf
        for j in nbr[i]:
          v = xyz[j].astype(np.float64) - xyz[i]
          nv = np.linalg.norm(v)
          cos = 0.0 if nv == 0 else float(v @ direction) / (nv * np.linalg.norm(direction))
          feat = float(f[j] @ w[:, col])
          sim = feat + cos if similarity == "sum" else max(cos, 0.0) * feat
          best = max(best, sim)
        total += best
      out[i, ch] = total
  return out


def prelu(x, slope):
  return np.where(x >= 0, x, slope * x)


def point_branch(p, corr, cand_xyz, coords, knn_count):
  """corr N x K, cand_xyz N x K x 3, coords N x 3 -> N x 64."""
  n = len(corr)
  feats = np.zeros((n, knn_count, 4))
  for i in range(n):
    d = [float(np.sum((cand_xyz[i, a] - coords[i]) ** 2)) for a in range(corr.shape[1])]
    near = np.argsort(d, kind="stable")[:knn_count]
    for a, j in enumerate(near):
      feats[i, a] = [corr[i, j], *(cand_xyz[i, j] - coords[i])]
  x = feats @ p["knn_conv"]["kernel"] + p["knn_conv"]["bias"]
  x = prelu(group_norm(x, p["knn_norm"]["scale"], p["knn_norm"]["bias"]), p["knn_act"]["negative_slope"])
  return x.max(axis=1) @ p["knn_out"]["kernel"] + p["knn_out"]["bias"]


def voxel_index(cand_xyz, coords, scale):
  """N x K cell (0..26) of each candidate in the 3x3x3 cube around its point, -1 outside."""
  n, k = cand_xyz.shape[:2]
  index = np.full((n, k), -1)
  for i in range(n):
    for a in range(k):
      cell = np.round((cand_xyz[i, a] - coords[i]) / scale)
      if np.all(np.abs(cell) <= 1):
        dx, dy, dz = (cell + 1).astype(int)
        index[i, a] = dx * 9 + dy * 3 + dz
  return index


def voxel_cells(corr, cand_xyz, coords, scale):
  """N x 27 mean correlation per cell of the 3x3x3 cube (0 when empty)."""
  n, k = corr.shape
  index = voxel_index(cand_xyz, coords, scale)
  sums = np.zeros((n, 27))
  counts = np.zeros((n, 27))
  for i in range(n):
    for a in range(k):
      if index[i, a] >= 0:
        sums[i, index[i, a]] += corr[i, a]
        counts[i, index[i, a]] += 1
  return np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)


def sigmoid(x):
  return 1.0 / (1.0 + np.exp(-x))


def gru(p, h, x):
  hx = np.concatenate([h, x], -1)
  z = sigmoid(hx @ p["convz"]["kernel"] + p["convz"]["bias"])
  r = sigmoid(hx @ p["convr"]["kernel"] + p["convr"]["bias"])
  q = np.tanh(np.concatenate([r * h, x], -1) @ p["convq"]["kernel"] + p["convq"]["bias"])
  return (1 - z) * h + z * q


def single_gate(p, h, x):
  return np.tanh(np.concatenate([h, x], -1) @ p["convh"]["kernel"] + p["convh"]["bias"])


def metrics(pred, gt):
  """One pair, every point valid: the five metrics by a per-point loop."""
  errs, s, r, o, ang = [], 0, 0, 0, []
  for p_, g in zip(pred.astype(np.float64), gt.astype(np.float64)):
    e = np.sqrt(np.sum((p_ - g) ** 2))
    rel = e / (np.sqrt(np.sum(g**2)) + 1e-4)
    errs.append(e)
    s += (e < 0.05) or (rel < 0.05)
    r += (e < 0.1) or (rel < 0.1)
    o += (e > 0.3) or (rel > 0.1)
    c = (1 + p_ @ g) / (np.sqrt(1 + p_ @ p_) * np.sqrt(1 + g @ g))
    ang.append(np.arccos(min(max(c, -1.0), 1.0)))
  n = len(errs)
  return dict(epe=np.mean(errs), acc_strict=100 * s / n, acc_relax=100 * r / n,
              outliers=100 * o / n, angle=np.mean(ang))
