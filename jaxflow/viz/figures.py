"""Pictures of scene flow: PNGs written headless, without touching the session's matplotlib backend
(figures are `matplotlib.figure.Figure`s with their own Agg canvas, never pyplot: a notebook that
imports this module keeps its inline plots).

    render_pair(pc1_Nx3, pc2_Mx3, flow_Nx3, "pair.png", gt=flow_gt_Nx3, up="y")  # Fig. 2, in 3D
    render_sweep(pc1_Nx3, pc2_Mx3, flow_Nx3, "top.png", up="z", ego_flow=ego_Nx3,
                 ground1=ground_N, max_range=35.0)   # a raw sweep from above, residual speed
    render_error(pc1_Nx3, flow_Nx3, flow_gt_Nx3, "error.png")            # per-point EPE, clipped
    plot_learning_curves("runs/x/metrics.jsonl", "curve.png")            # jaxflow.viz.curves' plot

Clouds are in a frame named by its up axis (jaxflow.geometry.frames: "y" the readers' and models', x
left, y up, z forward; "z" a LiDAR's, x forward, y left, z up). Every view draws up as up and left
on the left (never a mirror image). The 3D views put the forward axis into the screen and look from
behind and above the sensor (elevation 26 deg, azimuth 22 deg off the viewing direction). Axes have
equal scales and span the points, up to a quarter of the span beyond their 0.5th-99.5th percentiles:
the far returns of a raw sweep outside that box are not drawn (the title counts them). A cloud above
`MAX_DRAWN` points is drawn as a seeded random subset (the title says so).

The top view of a sweep (`sweep_figure`) draws the region the flow was estimated on (`max_range`
metres of horizontal distance), up out of the page, forward up the page: pc1 coloured by its speed
relative to the ego-motion, |flow - ego_flow| (m per frame, log scale from 1 cm to 1 m: a static
world 1.5 cm off and one 29 cm off look different, moving objects stand out), removed ground in
grey; then pc2 (red) over pc1 + flow (green, larger and underneath, so it hides neither).
"""

import json
import os
import pathlib
import shutil
import tempfile
import textwrap

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
import mpl_toolkits.mplot3d  # noqa: F401  (registers the "3d" projection)
import numpy as np

from jaxflow.geometry import frames
from jaxflow.viz import curves

BLUE, RED, GREEN = "#1f4fd6", "#d62728", "#15a336"  # pc1, pc2, pc1 + flow (paper Fig. 2)
ELEVATION, AZIMUTH = 26.0, -112.0  # degrees; azimuth -90 looks straight down +z (depth)
MAX_DRAWN = 12000  # points drawn per cloud
ERROR_CLIP = 0.3  # metres: the error colour scale saturates here (the outlier threshold)
PERCENTILES = (0.5, 99.5)  # the view: these, padded by REACH of their span (far returns: out)
REACH = 0.25  # the real FT3D and KITTI samples and the synthetic scenes lose no point at this

GREY = "#9a9a9a"  # removed ground
SPEED_RANGE = (0.01, 1.0)  # metres per frame: the log colour scale of the residual speed
DYNAMIC = 0.05  # metres: a point moving this much relative to the ego-motion is dynamic (AV2's)


def _axes(up: str) -> list[int]:
  """Columns (left, forward, up) of a frame with this up axis (jaxflow.geometry.frames' convention)."""
  left, up_axis, forward = frames.permutation(up)
  return [left, forward, up_axis]


def _screen(points_Nx3, up: str = "y") -> tuple:
  """(left, forward, up) coordinates: matplotlib's 3D axes (the first inverted: left is left)."""
  p = np.asarray(points_Nx3, np.float32)
  return tuple(p[:, i] for i in _axes(up))


def _labels(up: str) -> tuple[str, str, str]:
  names = "xyz"
  return tuple(f"{names[i]} (m), {w}" for i, w in zip(_axes(up), ("left", "forward", "up")))


def _subset(n: int, seed: int = 0) -> np.ndarray | None:
  if n <= MAX_DRAWN:
    return None
  return np.sort(np.random.default_rng(seed).choice(n, MAX_DRAWN, replace=False))


def _point_size(n: int) -> float:
  return float(np.clip(3000.0 / max(n, 1), 0.3, 4.0))


def figure(width_in: float, height_in: float) -> Figure:
  """A Figure with its own Agg canvas: drawn and saved without pyplot or the global backend."""
  fig = Figure(figsize=(width_in, height_in))
  FigureCanvasAgg(fig)
  return fig


def view_limits(clouds, up: str = "y") -> tuple[np.ndarray, np.ndarray]:
  """(lo, hi) of the view in screen order (left, forward, up): the data's extent, but at most
  REACH of the PERCENTILES' span beyond them, so that the far returns of a raw sweep do not shrink
  the scene to a dot."""
  xyz = np.concatenate([np.stack(_screen(c, up), -1) for c in clouds])
  lo, hi = np.percentile(xyz, PERCENTILES[0], axis=0), np.percentile(xyz, PERCENTILES[1], axis=0)
  span = np.maximum(hi - lo, 1e-3).max()
  # A scene's own edges lie within REACH of the span beyond its percentiles; far returns do not.
  lo, hi = np.maximum(xyz.min(0), lo - REACH * span), np.minimum(xyz.max(0), hi + REACH * span)
  pad = 0.03 * np.maximum(hi - lo, 1e-3).max()
  return lo - pad, hi + pad


def _inside(points_Nx3, limits, up: str = "y") -> np.ndarray:
  """Which points lie in the view: matplotlib's 3D axes do not clip, they draw past the box."""
  lo, hi = limits
  xyz = np.stack(_screen(points_Nx3, up), -1)
  return np.all((xyz >= lo) & (xyz <= hi), axis=1)


def _frame(ax, limits, up: str = "y", zoom: float = 1.35):
  """Equal scales: the view's limits, box with the data's proportions; the sensor's view, left on
  the left. `zoom` fills the panel with a flat (driving) scene; a tall box gets less."""
  lo, hi = limits
  ax.set_xlim(hi[0], lo[0])  # inverted: left (+) on the left
  ax.set_ylim(lo[1], hi[1])
  ax.set_zlim(lo[2], hi[2])
  box = np.maximum(hi - lo, 0.1 * (hi - lo).max())  # a flat road keeps some height
  ax.set_box_aspect(box, zoom=zoom if box[2] < 0.35 * box.max() else min(zoom, 1.1))
  ax.computed_zorder = False  # draw in the order added: pc1, pc2, then pc1 + flow on top
  ax.view_init(elev=ELEVATION, azim=AZIMUTH)
  for setter, label, pad in zip((ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), _labels(up),
                                (-6, -6, -8)):
    setter(label, labelpad=pad, fontsize=7)
  ax.tick_params(labelsize=6, pad=-2)


def _panel(ax, pc1_Nx3, pc2_Mx3, flow_Nx3, title, idx1, idx2, limits, up) -> int:
  """Draws one view; returns how many points fell outside it (not drawn)."""
  size = _point_size(len(pc1_Nx3) if idx1 is None else len(idx1))
  pick1 = (lambda a: a) if idx1 is None else (lambda a: a[idx1])
  pick2 = (lambda a: a) if idx2 is None else (lambda a: a[idx2])
  moved_Nx3 = pick1(pc1_Nx3) + pick1(flow_Nx3)
  outside = 0
  for points, colour, label in ((pick1(pc1_Nx3), BLUE, "pc1"), (pick2(pc2_Mx3), RED, "pc2"),
                                (moved_Nx3, GREEN, "pc1 + flow")):
    keep = _inside(points, limits, up)
    outside += int((~keep).sum())
    ax.scatter(*_screen(points[keep], up), s=size, c=colour, alpha=0.6, linewidths=0,
               depthshade=False, label=label)
  _frame(ax, limits, up)
  ax.set_title(title, fontsize=10, y=0.9)  # the zoomed box leaves the top of the axes empty
  return outside


def _epe(flow_Nx3, gt_Nx3, mask_N=None) -> float:
  err_N = np.linalg.norm(flow_Nx3 - gt_Nx3, axis=-1)
  if mask_N is not None:
    err_N = err_N[np.asarray(mask_N, bool)]
  return float(err_N.mean()) if len(err_N) else float("nan")


def _title(fig, lines, width_in: float):
  """The figure's title, each line wrapped to the figure's width (a long file name stays inside)."""
  chars = max(int(width_in * 11), 30)  # ~11 characters of 11-point text an inch
  text = "\n".join(textwrap.fill(l, chars) for l in lines if l)
  if text:
    fig.suptitle(text, fontsize=11, y=0.99, va="top")


def pair_figure(pc1_Nx3, pc2_Mx3, flow_Nx3, gt=None, title=None, mask=None, up: str = "y"):
  """The Fig. 2 view as a Figure: pc1 blue, pc2 red, pc1 + flow green; a ground-truth panel first
  when `gt` is given (the paper's layout), and then the prediction's EPE (over `mask`'s points).
  Scatter artists are labelled "pc1", "pc2", "pc1 + flow"; the legend sits below the views."""
  pc1_Nx3, pc2_Mx3, flow_Nx3 = (np.asarray(a, np.float32) for a in (pc1_Nx3, pc2_Mx3, flow_Nx3))
  idx1, idx2 = _subset(len(pc1_Nx3), 1), _subset(len(pc2_Mx3), 2)
  panels = [("prediction", flow_Nx3)]
  if gt is not None:
    gt = np.asarray(gt, np.float32)
    panels = [("ground truth", gt),
              (f"prediction: EPE {_epe(flow_Nx3, gt, mask):.3f} m", flow_Nx3)]
  pick1 = (lambda a: a) if idx1 is None else (lambda a: a[idx1])
  pick2 = (lambda a: a) if idx2 is None else (lambda a: a[idx2])
  limits = view_limits([pick1(pc1_Nx3), pick2(pc2_Mx3)]
                       + [pick1(pc1_Nx3) + pick1(flow) for _, flow in panels], up)
  width = 6.4 * len(panels)
  fig = figure(width, 4.8)
  outside = 0
  for i, (name, flow) in enumerate(panels):
    ax = fig.add_subplot(1, len(panels), i + 1, projection="3d")
    outside = max(outside, _panel(ax, pc1_Nx3, pc2_Mx3, flow, name, idx1, idx2, limits, up))
  handles = [Line2D([], [], ls="", marker="o", ms=6, color=c, label=l)
             for c, l in ((BLUE, "pc1"), (RED, "pc2"), (GREEN, "pc1 + flow"))]
  fig.legend(handles=handles, loc="lower center", ncol=3, frameon=False, fontsize=9)
  notes = []
  if idx1 is not None or idx2 is not None:
    notes.append(f"drawn: {MAX_DRAWN} random points per cloud")
  if outside:
    notes.append(f"{outside} far points outside the view not drawn")
  _title(fig, [title or "", f"({'; '.join(notes)})" if notes else ""], width)
  fig.subplots_adjust(left=0.02, right=0.98, bottom=0.06, top=0.92, wspace=0.0)
  return fig


def _save(fig, path) -> pathlib.Path:
  path = pathlib.Path(path)
  path.parent.mkdir(parents=True, exist_ok=True)
  fig.savefig(path, dpi=110, format="png")
  return path


def render_pair(pc1_Nx3, pc2_Mx3, flow_Nx3, path, gt=None, title=None, mask=None,
                up: str = "y") -> pathlib.Path:
  """Saves the Fig. 2 view of a pair (see `pair_figure`) as a PNG at `path`."""
  return _save(pair_figure(pc1_Nx3, pc2_Mx3, flow_Nx3, gt=gt, title=title, mask=mask, up=up), path)


def error_figure(pc1_Nx3, flow_Nx3, gt_Nx3, mask_N=None, clip: float = ERROR_CLIP, title=None,
                 up: str = "y"):
  """pc1 coloured by its end-point error |flow - gt| (m), the colour scale clipped at `clip`."""
  pc1_Nx3, flow_Nx3, gt_Nx3 = (np.asarray(a, np.float32) for a in (pc1_Nx3, flow_Nx3, gt_Nx3))
  err_N = np.linalg.norm(flow_Nx3 - gt_Nx3, axis=-1)
  if mask_N is not None:
    keep = np.asarray(mask_N, bool)
    pc1_Nx3, err_N = pc1_Nx3[keep], err_N[keep]
  epe = float(err_N.mean()) if len(err_N) else float("nan")
  idx = _subset(len(pc1_Nx3), 1)
  if idx is not None:
    pc1_Nx3, err_N = pc1_Nx3[idx], err_N[idx]
  limits = view_limits([pc1_Nx3], up)
  keep = _inside(pc1_Nx3, limits, up)
  fig = figure(7.6, 4.8)
  ax = fig.add_subplot(1, 1, 1, projection="3d")
  art = ax.scatter(*_screen(pc1_Nx3[keep], up), s=2 * _point_size(len(pc1_Nx3)),
                   c=np.minimum(err_N[keep], clip), cmap="inferno_r", vmin=0.0, vmax=clip,
                   linewidths=0, depthshade=False)
  _frame(ax, limits, up, zoom=1.1)
  bar = fig.colorbar(art, cax=fig.add_axes((0.84, 0.2, 0.022, 0.6)))
  bar.set_label(f"end-point error (m), clipped at {clip:g}")
  notes = [f"{int((~keep).sum())} far points outside the view not drawn"] if (~keep).any() else []
  _title(fig, [title or "", f"EPE {epe:.3f} m (mean over points)", *notes], 7.6)
  fig.subplots_adjust(left=0.05, right=0.82, bottom=0.02, top=0.95)
  return fig


def render_error(pc1_Nx3, flow_Nx3, gt_Nx3, path, mask_N=None, clip: float = ERROR_CLIP,
                 title=None, up: str = "y") -> pathlib.Path:
  """Saves the per-point end-point-error map (see `error_figure`) as a PNG at `path`."""
  return _save(error_figure(pc1_Nx3, flow_Nx3, gt_Nx3, mask_N, clip, title, up), path)


def residual_speed(flow_Nx3, ego_flow=None) -> np.ndarray:
  """|flow - ego_flow| (m per frame, N): each point's motion relative to the ego-motion; |flow|
  when `ego_flow` is None."""
  flow = np.asarray(flow_Nx3, np.float64)
  rel = flow if ego_flow is None else flow - np.asarray(ego_flow, np.float64)
  return np.linalg.norm(rel, axis=1)


def _horizontal(points_Nx3, up):
  """(left, forward) coordinates: the top view, up out of the page."""
  left, forward, _ = _axes(up)
  p = np.asarray(points_Nx3, np.float32)
  return p[:, left], p[:, forward]


def _top_limits(clouds, up, max_range):
  lo, hi = (-np.full(2, max_range), np.full(2, max_range)) if max_range else view_limits(clouds, up)
  return lo[:2], hi[:2]


def _top_axes(ax, limits, up, title):
  (lo, hi), names = limits, _labels(up)
  ax.set_xlim(hi[0], lo[0])  # left on the left
  ax.set_ylim(lo[1], hi[1])
  ax.set_aspect("equal")
  ax.set_xlabel(names[0], fontsize=8)
  ax.set_ylabel(names[1], fontsize=8)
  ax.tick_params(labelsize=7)
  ax.set_title(title, fontsize=9)


def _in_view(points_Nx3, limits, up):
  """In the view's box and, when it is a range's (a square of side 2 R), within R horizontally."""
  (h, v), (lo, hi) = _horizontal(points_Nx3, up), limits
  inside = (h >= lo[0]) & (h <= hi[0]) & (v >= lo[1]) & (v <= hi[1])
  return inside & (np.hypot(h, v) < hi[0]) if np.allclose(-lo, hi) else inside


def _speed_panel(fig, ax, pc1, values, ground1, limits, up, title, label, name):
  """pc1 coloured by `values` (m, log scale SPEED_RANGE), the fastest drawn last; ground grey."""
  size = float(np.clip(6000.0 / max(len(pc1), 1), 0.4, 6.0))
  g = ground1 & _in_view(pc1, limits, up)
  ax.scatter(*_horizontal(pc1[g], up), s=size, c=GREY, linewidths=0, label="removed ground")
  rest = np.flatnonzero(~ground1 & _in_view(pc1, limits, up))
  rest = rest[np.argsort(values[rest], kind="stable")]
  art = ax.scatter(*_horizontal(pc1[rest], up), s=size, c=np.clip(values[rest], *SPEED_RANGE),
                   cmap="viridis", norm=LogNorm(*SPEED_RANGE), linewidths=0, label=name)
  _top_axes(ax, limits, up, title)
  bar = fig.colorbar(art, ax=ax, fraction=0.045, pad=0.02)
  bar.set_label(label, fontsize=8)
  bar.ax.tick_params(labelsize=7)
  if g.any():
    ax.legend(loc="lower left", fontsize=7, markerscale=4, frameon=True)


def _stats(v) -> str:
  return f"median {100 * np.median(v):.1f} cm, {100 * np.mean(v >= DYNAMIC):.0f}% >= 5 cm" if len(
    v) else "no points"


def sweep_figure(pc1_Nx3, pc2_Mx3, flow_Nx3, up: str = "z", ego_flow=None, ground1=None,
                 ground2=None, max_range: float | None = 35.0, gt=None, mask=None, title=None):
  """The top view of a sweep pair (see the module docstring) as a Figure: panel 1 pc1 coloured by
  `residual_speed(flow, ego_flow)` (`ego_flow`: N x 3, or a motion with `.flow(points)` such as
  jaxflow.geometry.rigid.Motion; None: the speed itself), ground1 (bool N: removed ground) grey;
  panel 2
  pc2 over pc1 + flow; with `gt`, panel 3 pc1 coloured by the end-point error (over `mask`)."""
  pc1, pc2, flow = (np.asarray(a, np.float32) for a in (pc1_Nx3, pc2_Mx3, flow_Nx3))
  if ego_flow is not None and hasattr(ego_flow, "flow"):
    ego_flow = ego_flow.flow(pc1)
  speed = residual_speed(flow, ego_flow)
  ground1 = np.zeros(len(pc1), bool) if ground1 is None else np.asarray(ground1, bool)
  ground2 = np.zeros(len(pc2), bool) if ground2 is None else np.asarray(ground2, bool)
  mask = None if mask is None else np.asarray(mask) > 0  # a batch's mask may be float
  idx1, idx2 = _subset(len(pc1), 1), _subset(len(pc2), 2)
  if idx1 is not None:
    pc1, flow, speed, ground1 = pc1[idx1], flow[idx1], speed[idx1], ground1[idx1]
    gt = None if gt is None else np.asarray(gt, np.float32)[idx1]
    mask = None if mask is None else mask[idx1]
  if idx2 is not None:
    pc2, ground2 = pc2[idx2], ground2[idx2]
  limits = _top_limits([pc1[~ground1], pc2[~ground2]], up, max_range)
  panels = 3 if gt is not None else 2
  fig = figure(5.4 * panels, 5.4)
  axes = [fig.add_subplot(1, panels, i + 1) for i in range(panels)]
  relative = "relative to the ego-motion" if ego_flow is not None else "(no ego-motion given)"
  moving = speed[~ground1 & _in_view(pc1, limits, up)]
  _speed_panel(fig, axes[0], pc1, speed, ground1, limits, up, f"pc1: speed {relative}\n"
               f"{_stats(moving)}", "|flow - ego-motion flow| (m), log" if ego_flow is not None
               else "|flow| (m), log", "pc1")
  size = float(np.clip(6000.0 / max(len(pc1), 1), 0.4, 6.0))
  ax = axes[1]
  for cloud, g, colour, s, alpha, label in ((pc1 + flow, ground1, GREEN, 3 * size, 0.35, "pc1 + "
                                             "flow"), (pc2, ground2, RED, size, 0.9, "pc2")):
    keep = ~g & _in_view(cloud, limits, up)
    ax.scatter(*_horizontal(cloud[keep], up), s=s, c=colour, alpha=alpha, linewidths=0,
               label=label)
  _top_axes(ax, limits, up, "pc2 (red) over pc1 + flow (green)")
  ax.legend(loc="lower left", fontsize=7, markerscale=3, frameon=True)
  if gt is not None:
    err = residual_speed(flow, gt)
    shown = np.ones(len(pc1), bool) if mask is None else mask
    _speed_panel(fig, axes[2], pc1[shown], err[shown], ground1[shown], limits, up,
                 f"end-point error: EPE {err[shown].mean():.3f} m" if shown.any() else "no valid",
                 "|flow - ground truth| (m), log", "pc1")
  outside = int((~_in_view(pc1, limits, up)).sum())
  notes = [f"region: {max_range:g} m around the sensor" if max_range else "",
           f"{outside} pc1 points beyond it not drawn" if outside else "",
           f"drawn: {MAX_DRAWN} random points per cloud" if idx1 is not None or idx2 is not None
           else ""]
  _title(fig, [title or "", "; ".join(n for n in notes if n)], 5.4 * panels)
  fig.subplots_adjust(left=0.05, right=0.97, bottom=0.08, top=0.83, wspace=0.25)
  return fig


def render_sweep(pc1_Nx3, pc2_Mx3, flow_Nx3, path, **kwargs) -> pathlib.Path:
  """Saves `sweep_figure(pc1, pc2, flow, **kwargs)` as a PNG at `path`."""
  return _save(sweep_figure(pc1_Nx3, pc2_Mx3, flow_Nx3, **kwargs), path)


def render_batch(render_dir, batch, pred_BxNx3, up: str = "y") -> list[pathlib.Path]:
  """evaluate.py --render: for every real pair of a batch, NAME.png (the Fig. 2 view with the
  ground truth) and NAME_top.png (the top view; ego-motion from the batch's rigid_flow)."""
  written = []
  for i, name in enumerate(batch["names"]):
    if not batch["pair_valid"][i]:
      continue
    stem = str(name).strip("/").replace("/", "_").replace(":", "_")
    mask = batch["mask"][i] if "mask" in batch else None
    pc1, pc2, flow, gt = batch["pc1"][i], batch["pc2"][i], pred_BxNx3[i], batch["flow"][i]
    written.append(render_pair(pc1, pc2, flow, pathlib.Path(render_dir) / f"{stem}.png", gt=gt,
                               title=str(name), mask=mask, up=up))
    ego = batch["rigid_flow"][i] if "rigid_flow" in batch else None
    written.append(render_sweep(pc1, pc2, flow, pathlib.Path(render_dir) / f"{stem}_top.png",
                                up=up, ego_flow=ego, max_range=None, gt=gt, mask=mask,
                                title=str(name)))
  return written


def plot_learning_curves(metrics_jsonl, path) -> pathlib.Path | None:
  """Loss (log) and gradient norm vs step, one line per training stage, from a metrics.jsonl
  (jaxflow.viz.curves' plot; an eval.json or eval_metrics.jsonl beside it adds the evaluation EPEs).
  None when it is empty."""
  metrics_jsonl = pathlib.Path(metrics_jsonl)
  with tempfile.TemporaryDirectory() as tmp:
    records = [json.loads(l) for l in metrics_jsonl.read_text().splitlines() if l.strip()]
    for r in records:  # curves groups by stage; a log without one is a single stage-1 run
      r.setdefault("stage", 1)
      r.setdefault("grad_norm", None)
    (pathlib.Path(tmp) / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    for beside in ("eval.json", "eval_metrics.jsonl"):
      if (metrics_jsonl.parent / beside).exists():
        shutil.copy(metrics_jsonl.parent / beside, pathlib.Path(tmp) / beside)
    made = curves.plot_learning_curve(tmp)
    if made is None:
      return None
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(os.fspath(made), os.fspath(path))
  return path
