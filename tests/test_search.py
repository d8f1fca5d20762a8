"""jaxflow.geometry.neighbours' nearest-point searches: the host's k-d tree against a loop, the
device's brute force and the host's k-d tree give the same neighbours on clouds like real sweeps,
pc2's tree is built once per optimisation, and the device's distance grid holds the exact
distances (the host's is within a cell of them)."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflow.geometry import neighbours
from jaxflow.refine import distance_grid, optimiser


def sweep_like(n: int, seed: int):
  """A LiDAR-like cloud of n points: ground to 35 m, walls and boxes of a street, float32, with
  the range noise of a sensor (so no two distances tie), and the cloud moved by a car's motion."""
  rng = np.random.default_rng(seed)
  kind = rng.integers(0, 3, n)
  r, a = rng.uniform(2, 35, n), rng.uniform(-np.pi, np.pi, n)
  ground = np.c_[r * np.cos(a), r * np.sin(a), rng.normal(-1.7, 0.02, n)]
  wall = np.c_[rng.uniform(-35, 35, n), rng.choice([-8.0, 9.0], n), rng.uniform(-1.7, 3, n)]
  box = rng.uniform(-2, 2, (n, 3)) * [2, 0.9, 0.8] + rng.choice([-12.0, 6.0, 20.0], n)[:, None] * [
    1, 0.3, 0] + [0, 0, -0.9]
  pc1 = np.select([kind[:, None] == 0, kind[:, None] == 1], [ground, wall], box)
  pc1 = (pc1 + rng.normal(0, 0.01, pc1.shape)).astype(np.float32)
  pc2 = (pc1 + [0.8, 0.05, 0.0] + rng.normal(0, 0.02, pc1.shape)).astype(np.float32)
  return pc1, pc2


def reference(query_Nx3, points_Mx3, k: int):
  """float64 squared distances of each query's k + 1 nearest (NumPy, in row blocks), indices."""
  q, p = query_Nx3.astype(np.float64), points_Mx3.astype(np.float64)
  idx, sq = [], []
  for start in range(0, len(q), 1024):
    d = np.sum((q[start:start + 1024, None] - p[None]) ** 2, -1)
    part = np.argpartition(d, k + 1, axis=1)[:, :k + 1]
    order = np.argsort(np.take_along_axis(d, part, 1), axis=1)
    idx.append(np.take_along_axis(part, order, 1))
    sq.append(np.take_along_axis(d, idx[-1], 1))
  return np.concatenate(idx), np.concatenate(sq)


@pytest.mark.parametrize("k", [1, 9])
def test_device_and_host_searches_find_the_same_neighbours_on_a_sweep(k):
  pc1, pc2 = sweep_like(8192, seed=k)
  warped = pc1 + np.float32([0.7, 0.0, 0.0])
  want, sq = reference(warped, pc2, k)
  # A row whose k-th and (k+1)-th distances lie within float32 rounding is a tie (either is right).
  clear = (sq[:, k] - sq[:, k - 1]) > 1e-5 * sq[:, k] + 1e-9
  assert clear.mean() > 0.99, clear.mean()
  got = {s: np.asarray(jax.jit(lambda a, b: neighbours.knn(a, b, k, s))(warped[None], pc2[None]))[0]
         for s in ("host", "device")}
  for search, idx in got.items():
    np.testing.assert_array_equal(idx[clear, :k], want[clear, :k], err_msg=search)
  np.testing.assert_array_equal(got["device"][clear], got["host"][clear])


def test_device_search_in_batches_chunks_and_small_clouds():
  rng = np.random.default_rng(3)
  query = rng.normal(size=(2, 70, 3)).astype(np.float32) * 5
  points = rng.normal(size=(2, 40, 3)).astype(np.float32) * 5
  for block in (40 * 7, 10**6):  # 7 rows a block (70 = 10 blocks), all rows at once
    got = np.asarray(neighbours.device_knn(jnp.asarray(query), jnp.asarray(points), 4, block))
    for b, n in itertools.product(range(2), range(70)):
      d = np.sum((query[b, n] - points[b]) ** 2, axis=1)
      np.testing.assert_array_equal(got[b, n], np.argsort(d)[:4])
  few = neighbours.device_knn(jnp.asarray(query), jnp.asarray(points[:, :3]), 8)
  assert few.shape == (2, 70, 3)
  # Inside vmap (as the optimiser calls it) and for pc1's own neighbours (the point excluded).
  vmapped = jax.jit(jax.vmap(lambda q, p: neighbours.nearest(q[None], p[None], "device")[0]))
  np.testing.assert_array_equal(np.asarray(vmapped(query, points))[..., 0],
                                np.asarray(neighbours.host_knn(query, points, 1))[..., 0])
  nbr = np.asarray(neighbours.nearest_others(jnp.asarray(points), 3, "device"))
  np.testing.assert_array_equal(nbr, np.asarray(neighbours.host_knn(points, points, 4))[..., 1:])


def test_pc2_tree_is_built_once_per_optimisation():
  """The exact objective searches pc2's nearest points at every refresh; pc2 never changes, so
  its k-d tree is built once (then found by content), while the warped cloud's is new each time."""
  pc1, pc2 = sweep_like(500, seed=5)
  chosen = optimiser.Settings(objective="exact", steps=12, refresh=3, search="host")
  neighbours.clear_tree_cache()
  jax.block_until_ready(optimiser.optimise(jnp.zeros((1, 500, 3)), pc1[None], pc2[None], chosen))
  info = neighbours.tree_cache_info()
  searches = 1 + chosen.steps // chosen.refresh  # the starting loss, then one search a block
  # Each search: warped -> pc2 (pc2's tree) and pc2 -> warped (the warped cloud's tree).
  assert info["misses"] + info["hits"] == 2 * searches
  assert info["hits"] >= searches - 1  # pc2's tree, built once; a warped cloud rarely repeats
  assert info["misses"] <= searches + 1
  with pytest.raises(ValueError, match="search must be one of auto, host, device"):
    neighbours.knn(jnp.asarray(pc1[None]), jnp.asarray(pc2[None]), 1, "gpu")


def test_device_distance_grid_is_exact_and_the_host_one_within_a_cell():
  rng = np.random.default_rng(4)
  pts = (rng.uniform(-3, 3, (2, 400, 3)) * [1, 1, 0.3]).astype(np.float32)
  cell, max_cells, margin = 0.25, 6000, 0.6
  host = distance_grid.distance_grid(jnp.asarray(pts), cell, max_cells, margin, "host")
  device = distance_grid.distance_grid(jnp.asarray(pts), cell, max_cells, margin, "device")
  for b in range(2):
    origin, size, dims, _ = distance_grid.distance_grid_np(pts[b].astype(np.float64), cell, max_cells,
                                                        margin)
    np.testing.assert_allclose(np.asarray(device.origin_Bx3[b]), origin, atol=1e-5)
    np.testing.assert_allclose(float(device.cell_B[b]), size, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(device.dims_Bx3[b]), dims)
    g = int(np.prod(dims))
    nodes = origin + size * np.stack(np.unravel_index(np.arange(g), dims), -1)
    exact = np.sqrt(np.min(np.sum((nodes[:, None] - pts[b][None]) ** 2, -1), 1))
    np.testing.assert_allclose(np.asarray(device.values_BxG[b, :g]), exact, atol=2e-5)
    h = np.asarray(host.values_BxG[b, :g])
    assert np.all(h >= exact - 2e-5) and np.all(h <= exact + size * 3**0.5 + 2e-5)


@pytest.mark.slow
def test_the_optimiser_gives_the_same_flow_on_either_search_path():
  """Forced onto the device path on the CPU, the exact objective's optimisation (NSFP's kind)
  follows the host's to float32 rounding: the same neighbours, the same steps."""
  pc1, pc2 = sweep_like(256, seed=6)
  chosen = optimiser.Settings(model="mlp", objective="exact", steps=30, width=16, depth=2,
                              cycle=True, smoothness=0.5, learning_rate=0.01)
  flows = [np.asarray(optimiser.optimise(jnp.zeros((1, 256, 3)), pc1[None], pc2[None],
                                         dataclasses.replace(chosen, search=s))[0])
           for s in ("host", "device")]
  assert np.abs(flows[0]).max() > 1e-3  # it moved
  np.testing.assert_allclose(flows[1], flows[0], atol=1e-4)


def test_host_knn_matches_a_loop():
  rng = np.random.default_rng(7)
  query = rng.normal(size=(2, 50, 3)).astype(np.float32) * 3
  points = rng.normal(size=(2, 40, 3)).astype(np.float32) * 3
  got = np.asarray(neighbours.host_knn(jnp.asarray(query), jnp.asarray(points), 4))
  for b in range(2):
    for n in range(50):
      d = [np.sum((query[b, n] - p) ** 2) for p in points[b]]
      np.testing.assert_array_equal(got[b, n], np.argsort(d)[:4])
  # Fewer points than asked: all of them, nearest first; and the same inside jit and vmap.
  assert neighbours.host_knn(jnp.asarray(query), jnp.asarray(points[:, :3]), 8).shape == (2, 50, 3)
  vmapped = jax.jit(jax.vmap(lambda q, p: neighbours.nearest(q[None], p[None])[0]))(query, points)
  np.testing.assert_array_equal(np.asarray(vmapped)[..., 0], got[..., 0])
