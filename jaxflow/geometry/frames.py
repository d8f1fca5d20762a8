"""The coordinate frames of jaxflow: the models', a sensor's by its up axis, and the rotations
between them.

    pc_model_Nx3 = to_model(pc_Nx3, up="z")          # a z-up sweep as the network wants it
    flow_Nx3 = from_model(flow_model_Nx3, up="z")    # and its flow back
    flow_fn = in_model_frame(flow_fn, up="z")        # the same around any (pc1, pc2) -> flow
    predict = in_frame(predict, up="y", to="z")      # a batch method working z up, on y-up clouds
    up, note = resolve_up(pc1_Nx3, None, "y", "pc1")  # a user's cloud: the axis it is flat along

THE MODEL FRAME. Every shipped model was trained in the frame x left, y up, z forward, metres,
right-handed (x cross y = z). It is not "x right": that labelling of the same axes is a mirror
image (det -1), and a scene read in it turns the other way. Each dataset reader says the up axis
of its clouds (`Dataset.up`, jaxflow.data.registry; its docstring, how it gets there).

SENSOR CONVENTIONS BY UP AXIS (predict's --up, `Dataset.up`). A sensor frame is named by its up
axis, and the other two follow cyclically, so that every one is right-handed: up axis k, forward
k + 1, left k + 2 (mod 3).
- up z: x forward, y left, z up (LiDAR, ISO 8855 vehicles);
- up y: z forward, x left, y up: the model frame itself;
- up x: y forward, z left, x up.
The rotation into the model frame takes (left, up, forward) to (x, y, z): a cyclic permutation of
the axes, so a proper rotation (det +1, never a mirror). Flows are vectors: they turn the same way.
"""

import numpy as np

from jaxflow.errors import ConfigError, DataError

MODEL_UP = "y"  # the models' up axis (x left, y up, z forward)
UP_AXES = ("x", "y", "z")
SENSOR_AXES = {"z": "x forward, y left, z up", "y": "x left, y up, z forward (the model frame)",
               "x": "x up, y forward, z left"}


def up_index(up: str) -> int:
  """The column of the up axis "x", "y" or "z"; a ConfigError for any other name."""
  if up not in UP_AXES:
    raise ConfigError(f"up must be one of x, y, z, got {up!r}")
  return UP_AXES.index(up)


def permutation(up: str, to: str = MODEL_UP) -> list[int]:
  """Column order taking a frame with up axis `up` into the frame with up axis `to` by a cyclic
  permutation (a proper rotation): new[:, i] = old[:, permutation(up, to)[i]]. The model frame
  (to "y"): left, up, forward; a sensor's z-up frame (to "z"): forward, left, up."""
  k, j = up_index(up), up_index(to)
  return [(k + i - j) % 3 for i in range(3)]


def rotation(up: str, to: str = MODEL_UP) -> np.ndarray:
  """The 3 x 3 rotation R (det +1) with target = R @ source, from a frame with up axis `up` to the
  frame with up axis `to` (default the models')."""
  return np.eye(3)[permutation(up, to)]


def to_model(points_Nx3, up: str) -> np.ndarray:
  """Points (or vectors) of a sensor frame with up axis `up` in the model frame."""
  return np.ascontiguousarray(np.asarray(points_Nx3)[..., permutation(up)])


def from_model(points_Nx3, up: str) -> np.ndarray:
  """The inverse of `to_model`: model-frame points or vectors back in the sensor's frame."""
  inverse = np.argsort(permutation(up))
  return np.ascontiguousarray(np.asarray(points_Nx3)[..., inverse])


def in_model_frame(flow_fn, up: str):
  """(pc1, pc2) -> flow in the sensor frame, from a flow_fn that works in the model frame: the
  clouds are rotated into it before and the flow back after. up "y" (the model frame): flow_fn."""
  if up_index(up) == up_index(MODEL_UP):
    return flow_fn
  return lambda pc1_Nx3, pc2_Mx3: from_model(flow_fn(to_model(pc1_Nx3, up), to_model(pc2_Mx3, up)),
                                             up)


def in_frame(predict, up: str, to: str = MODEL_UP, jitted: bool = False):
  """`in_model_frame` for a batch predict (params..., pc1 B x N x 3, pc2 B x M x 3) -> flow B x N x
  3 or (flow, info) that works in the frame with up axis `to`, given clouds with up axis `up`
  (jaxflow.evaluation.evaluator's). `jitted`: predict is one jitted program, and so is the result
  (`.lower` still works); otherwise the axes are permuted around the Python call."""
  forward, back = permutation(up, to), [int(i) for i in np.argsort(permutation(up, to))]
  if forward == [0, 1, 2]:
    return predict

  def rotated(*args):
    *params, pc1, pc2 = args
    out = predict(*params, pc1[..., forward], pc2[..., forward])
    if isinstance(out, tuple):
      return (out[0][..., back], *out[1:])
    return out[..., back]

  return _jitted(rotated, (predict, up, to)) if jitted else rotated


_JITTED = {}  # (predict, up, to) -> the jitted rotation: its traces reused by later evaluations


def _jitted(rotated, key):
  import jax  # pylint: disable=import-outside-toplevel

  if key not in _JITTED:
    if len(_JITTED) >= 16:  # (the oldest dropped: a process evaluating many models)
      del _JITTED[next(iter(_JITTED))]
    _JITTED[key] = jax.jit(rotated)
  return _JITTED[key]


# A street scene is flat along its up axis: a LiDAR sweep spans metres in height and tens of metres
# across (real street sweeps, raw and from stereo: 0.05-0.14 of the next smallest spread); scenes of
# objects flying before a camera are not (0.42-0.95 over a benchmark's pairs).
FLAT_RATIO = 0.25


def flat_axis(points_Nx3, ratio: float = FLAT_RATIO):
  """(axis, spreads): the axis ("x", "y" or "z") along which the cloud's spread (2nd to 98th
  percentile, m) is under `ratio` times each other axis's, the up axis of a street scene; None
  when no axis is that flat (or under 50 finite points)."""
  p = np.asarray(points_Nx3, np.float64)
  p = p[np.isfinite(p).all(1)]
  if len(p) < 50:
    return None, None
  low, high = np.percentile(p, [2, 98], axis=0)
  spreads = high - low
  k = int(np.argmin(spreads))
  return (UP_AXES[k] if spreads[k] < ratio * np.delete(spreads, k).min() else None), spreads


def resolve_up(points_Nx3, up: str | None, default: str, name: str,
               check: bool = True) -> tuple[str, str | None]:
  """(up axis, note) of a cloud: `up` when given (a DataError naming `name` when the cloud is flat
  along another axis, unless `check` is False); else the axis it is flat along, with a note when
  that is not `default`; else `default`."""
  flat, spreads = flat_axis(points_Nx3) if check or up is None else (None, None)
  if up is not None:
    up_index(up)  # a ConfigError for a wrong name
    if flat is not None and flat != up:
      raise DataError(name, f"the cloud is flat along {flat} ({_spreads(spreads)}), as a street "
                      f"scene is along its up axis, not along --up {up}: give --up {flat} (or "
                      f"--noground_limits, ground_limits=False in Python, if {up} is right)")
    return up, None
  if flat is None or flat == default:
    return default, None
  return flat, (f"{name} is flat along {flat} ({_spreads(spreads)}): read with {flat} up "
                f"({describe(flat)}); --up {default} to read it as {describe(default)}")


def _spreads(spreads) -> str:
  spread = ", ".join(f"{a} {s:.1f} m" for a, s in zip(UP_AXES, spreads))
  return spread + " from 2nd to 98th percentile"


def describe(up: str) -> str:
  """The sensor convention of an up axis, for messages."""
  return SENSOR_AXES[UP_AXES[up_index(up)]]
