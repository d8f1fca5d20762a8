"""A 3D viewer of a scene-flow pair: one self-contained, interactive HTML page (plotly).

    write_html("flow.html", pc1_Nx3, pc2_Mx3, flow_Nx3, up="z", ego_flow=ego_Nx3, ground1=g_N)
    render("flow.png" or "flow.html", pc1_Nx3, pc2_Mx3, flow_Nx3, up="z", sweep=info)  # predict's
    python -m jaxflow.predict s1.bin s2.bin --lidar --out flow.npy --render flow.html

Layers (each switched on and off by clicking its legend entry): pc1 (blue), pc2 (red), pc1 + flow
(green), pc1 coloured by its speed relative to the ego-motion (|flow - ego_flow|, m per frame, log
colour scale from 1 cm to 1 m as jaxflow.viz.figures's top view; |flow| without an ego-motion), the
dynamic points (speed >= 5 cm, Argoverse 2's threshold) marked, and the removed ground grey. The
camera's up is the sensor's up (jaxflow.geometry.frames), and the page opens on the region the flow
was estimated on (`max_range` metres around the sensor). plotly.js is embedded in the page (4.8 MB;
7.3 MB in all for a real Argoverse 2 sweep pair): it opens offline. Needs the optional extra
`viewer` (pip install 'jaxflow[viewer]', i.e. plotly).
"""

import pathlib

import numpy as np

from jaxflow.errors import ConfigError
from jaxflow.geometry import frames
from jaxflow.viz import figures

# Points a layer: a seeded random subset above this (the page stays responsive and light: 4 bytes
# a coordinate, base64; plotly.js itself is 4.8 MB). The grey ground is context only.
MAX_POINTS, MAX_GROUND = 30000, 10000
DYNAMIC, SPEED_RANGE = figures.DYNAMIC, figures.SPEED_RANGE  # 5 cm (AV2's dynamic), the log colour scale
COLOURS = {"pc1": "#1f4fd6", "pc2": "#d62728", "pc1 + flow": "#15a336",
           "removed ground": "#a0a0a0", "dynamic": "#e8175d"}


def require_plotly():
  """plotly.graph_objects; a ConfigError naming the extra to install when plotly is missing."""
  try:
    import plotly.graph_objects as go  # pylint: disable=import-outside-toplevel
  except ImportError:
    raise ConfigError("--render FILE.html needs plotly, the optional extra 'viewer': "
                      "pip install 'jaxflow[viewer]' (or pip install plotly)") from None
  return go


def _pick(n: int, seed: int, most: int = MAX_POINTS) -> np.ndarray:
  if n <= most:
    return np.arange(n)
  return np.sort(np.random.default_rng(seed).choice(n, most, replace=False))


def layers(pc1_Nx3, pc2_Mx3, flow_Nx3, ego_flow=None, ground1=None, ground2=None,
           max_range: float | None = None, up: str = "z") -> dict:
  """{layer name: (points K x 3, per-point values or None)}: what the page draws (see the module
  docstring), inside `max_range` of horizontal distance, each at most MAX_POINTS points (the
  ground MAX_GROUND)."""
  pc1, pc2, flow = (np.asarray(a, np.float32) for a in (pc1_Nx3, pc2_Mx3, flow_Nx3))
  if ego_flow is not None and hasattr(ego_flow, "flow"):
    ego_flow = ego_flow.flow(pc1)
  rel = flow if ego_flow is None else flow - np.asarray(ego_flow, np.float32)
  speed = np.linalg.norm(rel.astype(np.float64), axis=1)
  g1 = np.zeros(len(pc1), bool) if ground1 is None else np.asarray(ground1, bool)
  g2 = np.zeros(len(pc2), bool) if ground2 is None else np.asarray(ground2, bool)
  left, up_axis, forward = frames.permutation(up)

  def near(p):
    return np.hypot(p[:, left], p[:, forward]) < max_range if max_range else np.ones(len(p), bool)

  in1, in2 = near(pc1), near(pc2)
  a1 = np.flatnonzero(in1 & ~g1)
  a1 = a1[_pick(len(a1), 1)]
  a2 = np.flatnonzero(in2 & ~g2)
  a2 = a2[_pick(len(a2), 2)]
  ground = np.flatnonzero(in1 & g1)
  ground = ground[_pick(len(ground), 3, MAX_GROUND)]
  dynamic = a1[speed[a1] >= DYNAMIC]
  return {"removed ground": (pc1[ground], None), "pc1": (pc1[a1], None), "pc2": (pc2[a2], None),
          "pc1 + flow": (pc1[a1] + flow[a1], None), "speed": (pc1[a1], speed[a1]),
          "dynamic": (pc1[dynamic], speed[dynamic])}


def figure(pc1_Nx3, pc2_Mx3, flow_Nx3, up: str = "z", ego_flow=None, ground1=None, ground2=None,
           max_range: float | None = None, title=None, gt=None, mask=None):
  """The plotly Figure of `write_html` (gt and mask are accepted for the views' common arguments;
  the page shows the prediction)."""
  del gt, mask
  go = require_plotly()
  drawn = layers(pc1_Nx3, pc2_Mx3, flow_Nx3, ego_flow, ground1, ground2, max_range, up)
  relative = "relative to the ego-motion" if ego_flow is not None else "(no ego-motion given)"
  traces = []
  for name, (points, values) in drawn.items():
    marker = dict(size=1.6, color=COLOURS.get(name, "#000000"))
    label = name
    if name == "speed":
      marker = dict(size=2.0, color=np.log10(np.clip(values, *SPEED_RANGE)), colorscale="Viridis",
                    cmin=np.log10(SPEED_RANGE[0]), cmax=np.log10(SPEED_RANGE[1]),
                    colorbar=dict(title=dict(text="speed (m)"), tickvals=[-2, -1, 0],
                                  ticktext=["0.01", "0.1", "1"]))
      label = f"pc1 by speed {relative}"
    elif name == "dynamic":
      marker = dict(size=2.4, color=COLOURS["dynamic"], symbol="circle-open")  # colours show
      where = f"within {max_range:g} m, " if max_range else ""
      label = (f"dynamic (speed >= {DYNAMIC:g} m): {len(points)} of the drawn points "
               f"({where}no ground)")
    traces.append(go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers",
                               marker=marker, name=label,
                               visible=True if name in ("speed", "dynamic", "removed ground")
                               else "legendonly"))
  eye = np.zeros(3)
  left, up_axis, forward = frames.permutation(up)
  eye[forward], eye[left], eye[up_axis] = -2.1, 0.6, 2.1  # behind, a little left, above
  axis_up = dict(zip("xyz", np.eye(3)[up_axis].tolist()))
  fig = go.Figure(traces)
  fig.update_layout(
    title=dict(text=title or "scene flow", font=dict(size=14)), margin=dict(l=0, r=0, t=40, b=0),
    legend=dict(itemsizing="constant", x=0.0, y=0.98),
    scene=dict(aspectmode="data", camera=dict(up=axis_up, eye=dict(zip("xyz", eye.tolist()))),
               xaxis_title="x (m)", yaxis_title="y (m)", zaxis_title="z (m)"))
  return fig


def write_html(path, pc1_Nx3, pc2_Mx3, flow_Nx3, **kwargs) -> pathlib.Path:
  """Writes the self-contained page (plotly.js embedded) of `figure(pc1, pc2, flow, **kwargs)`."""
  fig = figure(pc1_Nx3, pc2_Mx3, flow_Nx3, **kwargs)
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  fig.write_html(path, include_plotlyjs=True, full_html=True)
  return path


def render(path, pc1_Nx3, pc2_Mx3, flow_Nx3, up: str = "z", sweep=None, title=None, **kwargs):
  """predict's --render: by the suffix of `path`, .png the top view (jaxflow.viz.figures.render_sweep) or
  .html this page. `sweep` (jaxflow.lidar.sweep.SweepInfo of predict --lidar) gives the
  ego-motion, the removed ground and the range; kwargs go to the view."""
  if sweep is not None:
    kwargs = dict(ego_flow=sweep.motion.flow(pc1_Nx3), ground1=sweep.ground_masks[0],
                  ground2=sweep.ground_masks[1], max_range=sweep.max_range, **kwargs)
  suffix = pathlib.Path(path).suffix.lower()
  if suffix == ".html":
    return write_html(path, pc1_Nx3, pc2_Mx3, flow_Nx3, up=up, title=title, **kwargs)
  if suffix != ".png":
    raise ConfigError(f"--render {path}: expected a .png (picture) or .html (3D viewer) file")
  return figures.render_sweep(pc1_Nx3, pc2_Mx3, flow_Nx3, path, up=up, title=title, **kwargs)
