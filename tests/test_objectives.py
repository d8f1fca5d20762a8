"""jaxflow.refine.distance_grid: the distance grid and its trilinear read against NumPy loops, the
fast objective against the exact one, the grid's bound."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from jaxflow.refine import distance_grid


def test_distance_grid_matches_a_brute_force_reference():
  rng = np.random.default_rng(0)
  pts = rng.uniform(0, 1.2, (15, 3))
  origin, cell, dims, values = distance_grid.distance_grid_np(pts, 0.25, 10**6, margin=0.3)
  np.testing.assert_allclose(origin, pts.min(0) - 0.3)
  assert cell == 0.25 and values.shape == (np.prod(dims),)
  # Plain loops: each point occupies its nearest node (the first point of a node holds it).
  holder = {}
  for i, p in enumerate(pts):
    holder.setdefault(tuple(np.clip(np.rint((p - origin) / cell), 0, dims - 1).astype(int)), i)
  occupied = np.array(list(holder), float)
  for flat, node in enumerate(itertools.product(*(range(d) for d in dims))):
    d2 = np.sum((occupied - node) ** 2, axis=1)
    ties = [holder[tuple(occupied[j].astype(int))] for j in np.flatnonzero(d2 == d2.min())]
    at = origin + cell * np.array(node)
    options = [np.linalg.norm(at - pts[h]) for h in ties]  # any nearest occupied node is exact
    assert min(abs(values[flat] - o) for o in options) < 1e-5, (node, values[flat], options)
    true = np.min(np.linalg.norm(pts - at, axis=1))
    assert true - 1e-5 <= values[flat] <= true + cell * np.sqrt(3) + 1e-5


def test_trilinear_read_matches_a_loop():
  rng = np.random.default_rng(1)
  dims = np.array([4, 3, 5])
  values = rng.uniform(0, 2, np.prod(dims)).astype(np.float32)
  origin, cell = np.array([-1.0, 0.5, 2.0]), 0.4
  pts = origin + rng.uniform(0, 1, (30, 3)) * (dims - 1) * cell
  pts[0] = origin  # a node
  pts[1] = origin + (dims - 1) * cell  # the last node
  grid = distance_grid.Grid(jnp.asarray(origin[None], jnp.float32), jnp.asarray([cell], jnp.float32),
                         jnp.asarray(dims[None], jnp.int32),
                         jnp.asarray(np.pad(values, (0, 7))[None]))  # padded like the callback's
  got = np.asarray(distance_grid.grid_distance(grid, jnp.asarray(pts[None], jnp.float32))[0])
  v = values.reshape(dims)
  for p, g in zip(pts, got):
    u = (p - origin) / cell
    i0 = np.minimum(np.floor(u).astype(int), dims - 2)
    t = u - i0
    expected = 0.0
    for di, dj, dk in itertools.product((0, 1), repeat=3):
      w = ((t[0] if di else 1 - t[0]) * (t[1] if dj else 1 - t[1]) * (t[2] if dk else 1 - t[2]))
      expected += w * v[i0[0] + di, i0[1] + dj, i0[2] + dk]
    np.testing.assert_allclose(g, expected, rtol=1e-4, atol=1e-5)


def test_trilinear_gradient_matches_central_differences():
  """The read's written-out gradient (jax.grad of grid_chamfer) against central differences of
  a NumPy trilinear read, inside cells; zero across an axis where a point is clamped to the box."""
  rng = np.random.default_rng(4)
  dims = np.array([5, 4, 6])
  values = rng.uniform(0, 2, np.prod(dims))
  origin, cell = np.array([-1.0, 0.5, 2.0]), 0.4
  v = values.reshape(dims)

  def read(p):  # float64 NumPy, clamped like the grid's
    u = np.clip((p - origin) / cell, 0, dims - 1)
    i0 = np.minimum(np.floor(u).astype(int), dims - 2)
    t = u - i0
    return sum(((t[0] if a else 1 - t[0]) * (t[1] if b else 1 - t[1]) * (t[2] if c else 1 - t[2]))
               * v[i0[0] + a, i0[1] + b, i0[2] + c]
               for a, b, c in itertools.product((0, 1), repeat=3))

  # Cell fractions kept away from the cells' faces (where the read's derivative jumps).
  pts = origin + (rng.integers(0, dims - 1, (40, 3)) + rng.uniform(0.1, 0.9, (40, 3))) * cell
  pts[0, 1] = origin[1] - 0.3  # below the box in y: clamped
  grid = distance_grid.Grid(jnp.asarray(origin[None], jnp.float32), jnp.asarray([cell], jnp.float32),
                         jnp.asarray(dims[None], jnp.int32),
                         jnp.asarray(np.pad(values, (0, 3))[None], jnp.float32))
  got = np.asarray(jax.grad(lambda x: jnp.sum(distance_grid.grid_distance(grid, x)))(
    jnp.asarray(pts[None], jnp.float32))[0])
  h = 1e-4
  for p, g in zip(pts, got):
    want = [(read(p + h * e) - read(p - h * e)) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(g, want, rtol=1e-3, atol=1e-3)
  assert got[0, 1] == 0.0 and np.any(got[0] != 0.0)
  # Through the truncated Chamfer term: d/dp mean(min(d, T)^2) = 2 d d'(p) / N below T.
  chamfer = np.asarray(jax.grad(lambda x: distance_grid.grid_chamfer(grid, x, 10.0)[0])(
    jnp.asarray(pts[None], jnp.float32))[0])
  d = np.array([read(p) for p in pts])
  np.testing.assert_allclose(chamfer, 2 * d[:, None] * got / len(pts), rtol=1e-3, atol=1e-5)


def test_fast_objective_agrees_with_the_exact_one():
  rng = np.random.default_rng(2)
  # A dense surface (a wavy sheet) as pc2; queries near it, inside the grid, within the truncation.
  xy = rng.uniform(-2, 2, (3000, 2))
  pc2 = np.c_[xy, 0.3 * np.sin(xy[:, 0])].astype(np.float32)
  near = (pc2[:400] + rng.normal(0, 0.3, (400, 3))).astype(np.float32)
  cell, truncate = 0.05, 1.0
  grid = distance_grid.distance_grid(jnp.asarray(pc2[None]), cell, 2**20, margin=truncate + 2 * cell)
  fast = np.asarray(distance_grid.grid_distance(grid, jnp.asarray(near[None]))[0])
  exact = np.min(np.linalg.norm(near[:, None] - pc2[None], axis=-1), axis=1)
  assert np.max(np.abs(fast - exact)) < cell, np.max(np.abs(fast - exact))
  assert np.mean(np.abs(fast - exact)) < 0.2 * cell
  f = float(distance_grid.grid_chamfer(grid, jnp.asarray(near[None]), truncate)[0])
  e = float(np.mean(np.minimum(exact, truncate) ** 2))  # the exact one-way truncated term
  np.testing.assert_allclose(f, e, rtol=0.05)
  # Far beyond the truncation (and outside the grid) both are truncate^2 with no pull.
  far = jnp.asarray(pc2[None, :10] + [0.0, 0.0, 50.0])
  np.testing.assert_allclose(np.asarray(distance_grid.grid_chamfer(grid, far, truncate)), truncate**2)


def test_grid_is_bounded_for_large_extents():
  rng = np.random.default_rng(3)
  pts = rng.uniform(-500, 500, (2000, 3)) * [1, 0.05, 1]  # a 1 km sweep
  origin, cell, dims, values = distance_grid.distance_grid_np(pts, 0.1, 4096, margin=2.0)
  assert np.prod(dims) <= 4096 and cell > 10 and np.isfinite(values).all()
  assert np.all(origin + (dims - 1) * cell >= pts.max(0) + 2.0 - 1e-6)  # the box is covered
