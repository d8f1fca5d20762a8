"""Per-pair flow optimisation with no ground truth: NSFP, the fast optimiser, test-time refinement.

    flow_BxNx3, info = optimise(init_BxNx3, pc1_BxNx3, pc2_BxMx3, Settings(...))

The flow is `init + g(params)`, where g is either a free vector per point (`model="flow"`: the
warm-started refinement of a network's flow) or NSFP's coordinate MLP of pc1 (`model="mlp"`). Adam
minimises, per pair,
  Chamfer(pc1 + flow, pc2) + smoothness x kNN smoothness [+ Chamfer(back, pc1), the cycle term:
  back = pc1 + flow - h(pc1 + flow), h a second MLP (NSFP's backward flow)],
with the Chamfer terms either exact (two-way, nearest points searched every `refresh` steps and held
fixed in between) or read from distance grids built once per pair (`objective="grid"`: the one-way
pc1 + flow -> pc2 term, O(N) a step; jaxflow.refine.objectives). Every pair runs its own early
stopping (the loss has not fallen by `min_delta` for `patience` steps) and returns the flow of its
lowest loss. The loop is one `lax.while_loop` over blocks of `refresh` scanned steps: no host round
trip per step (`search` "auto": the nearest points are searched on the device on a GPU or TPU, by
the host's k-d tree on the CPU; jaxflow.geometry.neighbours). Every matmul runs at `precision`
(exact float32 by default: a GPU's TF32 would move the points of a cluster tens of metres wide by
centimetres). Clouds are centred on pc1's mean first (the flow does not change with a translation of
both; far from the origin float32 would lose the centimetres).
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import optax

from jaxflow.geometry import neighbours, rigid
from jaxflow.refine import distance_grid, objectives, rigid_clusters
from jaxflow.refine.progress import Progress
from jaxflow.network.layers import PRECISIONS

MODELS = ("flow", "mlp", "rigid")
OBJECTIVES = ("exact", "grid")


@dataclasses.dataclass(frozen=True)
class Settings:
  model: str = "flow"
  objective: str = "grid"
  steps: int = 1000  # at most
  learning_rate: float = 0.01
  weight_decay: float = 0.0  # L2 on the parameters, added to the gradient (torch Adam's)
  smoothness: float = 0.0
  neighbours: int = 8
  truncate: float = 2.0  # metres: a farther nearest point stops pulling
  cycle: bool = False  # model "mlp": NSFP's backward MLP and its Chamfer to pc1
  patience: int = 0  # early stopping (0: run every step)
  min_delta: float = 1e-4
  refresh: int = 10  # steps between two nearest-point searches (exact), and between stopping tests
  cell: float = 0.1  # metres, the finest grid cell (objective "grid")
  max_cells: int = 2**22  # nodes per grid at most (16 MB); cells grow for large extents
  width: int = 128  # model "mlp"
  depth: int = 8  # ReLU layers of the MLP (then a linear one)
  seed: int = 0  # the MLP's initial weights
  precision: str = "highest"  # of every matmul (jaxflow.network.layers.PRECISIONS)
  search: str = "auto"  # where nearest points are searched (jaxflow.geometry.neighbours.SEARCHES)

  def __post_init__(self):
    if self.model not in MODELS:
      raise ValueError(f"optimiser model must be one of {', '.join(MODELS)}, got {self.model!r}")
    if self.objective not in OBJECTIVES:
      raise ValueError(f"optimiser objective must be one of {', '.join(OBJECTIVES)}, "
                       f"got {self.objective!r}")
    for name, least in (("steps", 0), ("neighbours", 1), ("patience", 0), ("refresh", 1),
                        ("max_cells", 8), ("width", 1), ("depth", 1)):
      if not isinstance(getattr(self, name), int) or getattr(self, name) < least:
        raise ValueError(f"optimiser {name} must be an integer >= {least}, "
                         f"got {getattr(self, name)!r}")
    for name in ("learning_rate", "weight_decay", "smoothness", "truncate", "min_delta"):
      if not getattr(self, name) >= 0:
        raise ValueError(f"optimiser {name} must be >= 0, got {getattr(self, name)!r}")
    if not self.cell > 0:
      raise ValueError(f"optimiser cell must be > 0, got {self.cell!r}")
    if self.precision not in PRECISIONS:
      raise ValueError(f"optimiser precision must be one of {', '.join(PRECISIONS)}, "
                       f"got {self.precision!r}")
    neighbours.check_search(self.search, "optimiser search")


def init_mlp(key, width: int, depth: int):
  """[(W, b)] of depth + 1 dense layers 3 -> width ... -> 3, torch's default initialisation
  (uniform in +-1/sqrt(fan_in)), as NSFP's published MLP."""
  sizes = [3] + [width] * depth + [3]
  layers = []
  for key, (fan_in, fan_out) in zip(jax.random.split(key, len(sizes) - 1), zip(sizes, sizes[1:])):
    kw, kb = jax.random.split(key)
    bound = fan_in**-0.5
    layers.append((jax.random.uniform(kw, (fan_in, fan_out), jnp.float32, -bound, bound),
                   jax.random.uniform(kb, (fan_out,), jnp.float32, -bound, bound)))
  return layers


def apply_mlp(layers, x_Nx3, precision: str = "highest"):
  matmul = functools.partial(jnp.matmul, precision=jax.lax.Precision(precision))
  h = x_Nx3
  for w, b in layers[:-1]:
    h = jax.nn.relu(matmul(h, w) + b)
  w, b = layers[-1]
  return matmul(h, w) + b


def _init_params(settings: Settings, n: int):
  if settings.model == "flow":
    return {"flow": jnp.zeros((n, 3), jnp.float32)}
  if settings.model == "rigid":  # a rotation vector and a translation a cluster slot
    zeros = jnp.zeros((n, 3), jnp.float32)
    return {"rotation": zeros, "translation": zeros}
  forward, backward = jax.random.split(jax.random.key(settings.seed))
  params = {"mlp": init_mlp(forward, settings.width, settings.depth)}
  if settings.cycle:
    params["inverse"] = init_mlp(backward, settings.width, settings.depth)
  return params


def _flow(params, init_Nx3, pc1_Nx3, clusters, precision: str):
  # clusters: (labels N, R N x 3 x 3, centroid, translation) of rigid_clusters.fit
  if "rotation" in params:
    labels_N, r_Nx3x3, cen_Nx3, t_Nx3 = clusters
    r_Nx3x3 = jnp.einsum("nij,njk->nik", r_Nx3x3,
                         rigid.rotations_from_vectors(params["rotation"], precision),
                         precision=jax.lax.Precision(precision))
    return rigid_clusters.rigid_flow(pc1_Nx3, labels_N, r_Nx3x3, cen_Nx3,
                                     t_Nx3 + params["translation"], precision)
  residual = (params["flow"] if "flow" in params
              else apply_mlp(params["mlp"], pc1_Nx3, precision))
  return init_Nx3 + residual


def _loss(params, pair, nbr_NxK, grids, match, settings: Settings):
  """The minimised loss of one pair; `match`: the held nearest points of the exact objective."""
  init_Nx3, pc1_Nx3, pc2_Mx3, clusters = pair
  flow = _flow(params, init_Nx3, pc1_Nx3, clusters, settings.precision)
  warped = (pc1_Nx3 + flow)[None]
  if settings.objective == "grid":
    loss = distance_grid.grid_chamfer(grids[0], warped, settings.truncate)
  else:
    loss = objectives.chamfer_terms(warped, pc2_Mx3[None], match[:2], settings.truncate)
  if "inverse" in params:
    back = warped - apply_mlp(params["inverse"], warped[0], settings.precision)[None]
    if settings.objective == "grid":
      loss = loss + distance_grid.grid_chamfer(grids[1], back, settings.truncate)
    else:
      loss = loss + objectives.chamfer_terms(back, pc1_Nx3[None], match[2:], settings.truncate)
  if settings.smoothness:
    loss = loss + settings.smoothness * objectives.smoothness(flow[None], nbr_NxK[None])
  return loss[0]


def _search(params, pair, settings: Settings):
  """The nearest points of the exact objective for the current flow (empty for the grid one)."""
  if settings.objective == "grid":
    return ()
  init_Nx3, pc1_Nx3, pc2_Mx3, clusters = pair
  warped = (pc1_Nx3 + _flow(params, init_Nx3, pc1_Nx3, clusters, settings.precision))[None]
  near = functools.partial(neighbours.nearest, search=settings.search)
  match = (near(warped, pc2_Mx3[None]), near(pc2_Mx3[None], warped))
  if "inverse" in params:
    back = warped - apply_mlp(params["inverse"], warped[0], settings.precision)[None]
    match += (near(back, pc1_Nx3[None]), near(pc1_Nx3[None], back))
  return match


def _loop(pair, grids, nbr_NxK, settings: Settings):
  """The pieces of one pair's optimisation: (carry, block(carry, match) -> carry, running(carry),
  finish(carry, start loss) -> (flow, info)). A block is `refresh` scanned steps with the nearest
  points `match` (of `_search`) held fixed."""
  init_Nx3, pc1_Nx3, _, clusters = pair
  grids = jax.tree.map(lambda a: a[None], grids)  # the objectives take batches
  opt = optax.chain(optax.add_decayed_weights(settings.weight_decay),
                    optax.adam(settings.learning_rate))
  params = _init_params(settings, pc1_Nx3.shape[0])
  flow_of = lambda params: _flow(params, init_Nx3, pc1_Nx3, clusters, settings.precision)
  loss_grad = jax.value_and_grad(_loss)
  patience = settings.patience or settings.steps + 1

  def step(carry, match):
    params, state, best, best_flow, since, count = carry
    active = (since < patience) & (count < settings.steps)
    loss, grads = loss_grad(params, pair, nbr_NxK, grids, match, settings)
    # The loss is that of the parameters before the step (as NSFP records it).
    better = active & (loss < best) & jnp.isfinite(loss)
    best_flow = jnp.where(better, flow_of(params), best_flow)
    improved = active & (loss < best - settings.min_delta)
    since = jnp.where(improved, 0, since + active)
    best = jnp.where(better, loss, best)
    updates, new_state = opt.update(grads, state, params)
    keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(active, a, b), new, old)
    params = keep(optax.apply_updates(params, updates), params)
    return (params, keep(new_state, state), best, best_flow, since, count + active), None

  def block(carry, match):
    return jax.lax.scan(lambda c, _: step(c, match), carry, None, length=settings.refresh)[0]

  def running(carry):
    return (carry[4] < patience) & (carry[5] < settings.steps)

  def finish(carry, start):
    params, _, best, best_flow, since, count = carry
    if settings.steps == 0:
      best, best_flow = start, flow_of(params)
    # A flow that went non-finite (it cannot with finite inputs, but a user's cloud can surprise)
    # falls back to the starting flow.
    finite = jnp.all(jnp.isfinite(best_flow))
    best_flow = jnp.where(finite, best_flow, init_Nx3)
    info = {"steps": count, "stopped": since >= patience, "loss_start": start,
            "loss_best": best, "finite": finite}
    return best_flow, info

  zero = jnp.zeros((), jnp.int32)
  carry = (params, opt.init(params), jnp.float32(jnp.inf), flow_of(params), zero, zero)
  return carry, block, running, finish


def _neighbours(pc1_Nx3, settings: Settings):
  """pc1's kNN graph of the smoothness term (a placeholder without it)."""
  if not settings.smoothness:
    return jnp.zeros((pc1_Nx3.shape[0], 1), jnp.int32)
  return neighbours.nearest_others(pc1_Nx3[None], settings.neighbours, settings.search)[0]


def _one_pair(pair, grids, nbr_NxK, settings: Settings):
  nbr_NxK = _neighbours(pair[1], settings) if nbr_NxK is None else nbr_NxK
  carry, block, running, finish = _loop(pair, grids, nbr_NxK, settings)
  start = _loss(carry[0], pair, nbr_NxK, jax.tree.map(lambda a: a[None], grids),
                _search(carry[0], pair, settings), settings)
  carry = jax.lax.while_loop(running, lambda c: block(c, _search(c[0], pair, settings)), carry)
  return finish(carry, start)


def _centre(pc1_BxNx3):
  return jnp.mean(pc1_BxNx3, axis=1, keepdims=True)


def distance_grids(pc1_BxNx3, pc2_BxMx3, settings: Settings, now: bool = False):
  """The distance grids `optimise` builds for the grid objective (of pc2, and of pc1 for NSFP's
  cycle term), in its centred frame: build once, pass to several `optimise` calls on a pair.
  `now`: built at once, outside jit, with no host callback (distance_grid.distance_grid_now)."""
  if settings.objective != "grid":
    return ((), ())
  build = distance_grid.distance_grid_now if now else distance_grid.distance_grid
  centre_Bx1x3 = _centre(pc1_BxNx3)
  margin = settings.truncate + 2 * settings.cell
  grids = (build(pc2_BxMx3 - centre_Bx1x3, settings.cell, settings.max_cells, margin,
                 settings.search),)
  if settings.model == "mlp" and settings.cycle:
    return grids + (build(pc1_BxNx3 - centre_Bx1x3, settings.cell, settings.max_cells, margin,
                          settings.search),)
  return grids + (grids[0],)  # unused


def _centred(init_BxNx3, pc1_BxNx3, pc2_BxMx3, clusters):
  """The pair (init, pc1, pc2, clusters) in the frame centred on pc1's mean."""
  centre_Bx1x3 = _centre(pc1_BxNx3)
  if clusters:  # the centroids move with the clouds
    clusters = (clusters[0], clusters[1], clusters[2] - centre_Bx1x3, clusters[3])
  return init_BxNx3, pc1_BxNx3 - centre_Bx1x3, pc2_BxMx3 - centre_Bx1x3, clusters


def _check(settings: Settings, clusters):
  if settings.model == "rigid" and len(clusters) != 4:
    raise ValueError("optimiser model 'rigid' needs clusters = (labels, R, centroid, translation)")


@functools.partial(jax.jit, static_argnames="settings")
def optimise(init_BxNx3, pc1_BxNx3, pc2_BxMx3, settings: Settings, clusters=(), grids=None,
             nbr_BxNxK=None):
  """(flow B x N x 3 of the lowest loss, info: B-vectors steps, stopped (early stopping fired),
  loss_start, loss_best, finite). Model "rigid" needs `clusters` = (labels, R, centroid,
  translation) from jaxflow.refine.rigid_clusters (`clusters`, `fit`) and does not use `init`.
  `grids`: those of `distance_grids` for these clouds and settings (None: built here); `nbr_BxNxK`:
  pc1's
  graph of the smoothness term (neighbours.nearest_others; None: searched here)."""
  _check(settings, clusters)
  if grids is None:
    grids = distance_grids(pc1_BxNx3, pc2_BxMx3, settings)
  pair = _centred(init_BxNx3, pc1_BxNx3, pc2_BxMx3, clusters)
  if nbr_BxNxK is None:
    return jax.vmap(lambda *a: _one_pair(a[:4], a[4], None, settings))(*pair, grids)
  return jax.vmap(lambda *a: _one_pair(a[:4], a[4], a[5], settings))(*pair, grids, nbr_BxNxK)


# The same optimisation driven from Python: every nearest-point search runs between compiled
# blocks, so no compiled program calls back to the host (JAX's persistent compilation cache keeps
# only such programs: a second process reads them back instead of compiling).


@functools.partial(jax.jit, static_argnames="settings")
def _host_start(init_BxNx3, pc1_BxNx3, pc2_BxMx3, clusters, settings: Settings):
  pair = _centred(init_BxNx3, pc1_BxNx3, pc2_BxMx3, clusters)
  dummy = jnp.zeros(pc1_BxNx3.shape[:2] + (1,), jnp.int32)
  carry = jax.vmap(lambda *p: _loop(p[:4], ((), ()), p[4], settings)[0])(*pair, dummy)
  return pair, carry


@functools.partial(jax.jit, static_argnames="settings")
def _host_warped(carry, pair, settings: Settings):
  """The clouds the exact objective searches for the current parameters: ((query, points), ...)."""
  init, pc1, pc2, clusters = pair
  flow = jax.vmap(lambda p, i, a, c: _flow(p, i, a, c, settings.precision))(
    carry[0], init, pc1, clusters)
  warped = pc1 + flow
  searched = ((warped, pc2), (pc2, warped))
  if "inverse" in carry[0]:
    back = warped - jax.vmap(lambda w, x: apply_mlp(w, x, settings.precision))(
      carry[0]["inverse"], warped)
    searched += ((back, pc1), (pc1, back))
  return searched


@functools.partial(jax.jit, static_argnames="settings")
def _host_block(carry, pair, grids, nbr_BxNxK, match, settings: Settings):
  """One block of every pair, and whether any pair still runs after it."""
  def one(carry, pair, grids, nbr, match):
    _, block, running, _ = _loop(pair, grids, nbr, settings)
    carry = block(carry, match)
    return carry, running(carry)
  carry, running_B = jax.vmap(one)(carry, pair, grids, nbr_BxNxK, match)
  return carry, jnp.any(running_B)


@functools.partial(jax.jit, static_argnames="settings")
def _host_loss(carry, pair, grids, nbr_BxNxK, match, settings: Settings):
  def one(carry, pair, grids, nbr, match):
    return _loss(carry[0], pair, nbr, jax.tree.map(lambda a: a[None], grids), match, settings)
  return jax.vmap(one)(carry, pair, grids, nbr_BxNxK, match)


@functools.partial(jax.jit, static_argnames="settings")
def _host_result(carry, pair, grids, nbr_BxNxK, start_B, settings: Settings):
  def one(carry, pair, grids, nbr, start):
    return _loop(pair, grids, nbr, settings)[3](carry, start)
  return jax.vmap(one)(carry, pair, grids, nbr_BxNxK, start_B)


def optimise_host_loop(init_BxNx3, pc1_BxNx3, pc2_BxMx3, settings: Settings, clusters=(),
                       grids=None, nbr_BxNxK=None, progress: bool | None = None):
  """`optimise`'s result, the nearest points of the exact objective searched from Python between
  compiled blocks of `refresh` steps (neighbours.host_search on the CPU, the device's search
  elsewhere) instead of inside one compiled loop. `grids` (grid objective) and `nbr_BxNxK`
  (smoothness) are searched here when not given, the same way. `progress`: a bar on stderr of the
  steps, the lowest loss and the time left; None: the bar on a terminal, and elsewhere (a log file)
  plain lines when the run is expected to take over 30 s: that estimate first, then a line every
  10% of the steps (jaxflow.refine.progress)."""
  _check(settings, clusters)
  search = settings.search
  if grids is None:
    grids = distance_grids(pc1_BxNx3, pc2_BxMx3, settings, now=True)
  if nbr_BxNxK is None:
    nbr_BxNxK = (neighbours.nearest_others_now(pc1_BxNx3, settings.neighbours, search)
                 if settings.smoothness else jnp.zeros(pc1_BxNx3.shape[:2] + (1,), jnp.int32))
  pair, carry = _host_start(init_BxNx3, pc1_BxNx3, pc2_BxMx3, clusters, settings)

  def match(carry):
    if settings.objective == "grid":
      return ()
    return tuple(neighbours.nearest_now(q, p, search)[:, None]  # each pair's as a batch of one
                 for q, p in _host_warped(carry, pair, settings))

  held = match(carry)
  start = _host_loss(carry, pair, grids, nbr_BxNxK, held, settings)
  running = settings.steps > 0  # (patience >= 1: every pair runs its first step)
  shown = Progress(f"{settings.model} optimisation", settings.steps, progress)
  try:
    while running:
      carry, running = _host_block(carry, pair, grids, nbr_BxNxK, held, settings)
      running = bool(running)
      if running:
        held = match(carry)
      if shown.active:  # the furthest pair's steps (early stopping ends the others sooner)
        shown.update(int(jnp.max(carry[5])), lambda: float(jnp.min(carry[2])))
  finally:
    shown.close()
  if shown.lines:
    shown.done(int(jnp.max(carry[5])))
  return _host_result(carry, pair, grids, nbr_BxNxK, start, settings)


# NSFP's published settings (github.com/Lilac-Lee/Neural_Scene_Flow_Prior): MLP 8 x 128, ReLU,
# linear output; forward and backward MLPs; Adam lr 0.008 with weight decay 1e-4 (L2 added to the
# gradient); the two-way Chamfer with squared distances over 2 m^2 truncated (clipped here: the same
# gradients); nearest points searched every step; up to 5000 steps, early stopping patience 100,
# min delta 1e-4.
NSFP = Settings(model="mlp", objective="exact", steps=5000, learning_rate=0.008,
                weight_decay=1e-4, smoothness=0.0, truncate=2**0.5, cycle=True, patience=100,
                min_delta=1e-4, refresh=1)
