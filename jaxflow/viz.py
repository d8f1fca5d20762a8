"""Pictures of scene flow (matplotlib Agg: headless, PNG).

    render_pair(pc1_Nx3, pc2_Mx3, flow_Nx3, "pair.png", gt=flow_gt_Nx3)   # the paper's Fig. 2 view
    render_error(pc1_Nx3, flow_Nx3, flow_gt_Nx3, "error.png")            # per-point EPE, clipped
    plot_learning_curves("runs/x/metrics.jsonl", "curve.png")            # jaxflow.curves' plot

Clouds are in the readers' frame (x right, y up, z forward, metres: FT3D after its flip and KITTI).
The 3D views put depth (z) into the screen and y up, and look from behind and above the sensor
(elevation 26 deg, azimuth 22 deg off the viewing direction), which reads well for driving scenes
(the road recedes, cars stand on it) and FT3D scenes (objects in front of a back wall) alike. Axes
have equal scales (the box has the data's proportions) and span the points, up to a quarter of
the span beyond their 0.5th-99.5th percentiles: the far returns of a raw sweep outside that box
are not drawn (the title counts them). To stay quick and legible a cloud above `MAX_DRAWN` points
is drawn as a seeded random subset of that size (the title says so).
"""

import json
import os
import pathlib
import shutil
import tempfile
import textwrap

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # pylint: disable=wrong-import-position
from matplotlib.lines import Line2D  # pylint: disable=wrong-import-position
import numpy as np  # pylint: disable=wrong-import-position

from jaxflow import curves  # pylint: disable=wrong-import-position

BLUE, RED, GREEN = "#1f4fd6", "#d62728", "#15a336"  # pc1, pc2, pc1 + flow (paper Fig. 2)
ELEVATION, AZIMUTH = 26.0, -112.0  # degrees; azimuth -90 looks straight down +z (depth)
MAX_DRAWN = 12000  # points drawn per cloud
ERROR_CLIP = 0.3  # metres: the error colour scale saturates here (the outlier threshold)
PERCENTILES = (0.5, 99.5)  # the view: these, padded by REACH of their span (far returns: out)
REACH = 0.25  # the real FT3D and KITTI samples and the synthetic scenes lose no point at this


def _screen(points_Nx3) -> tuple:
  """(x, z, y): matplotlib's vertical axis is its third, the readers' vertical is y."""
  p = np.asarray(points_Nx3, np.float32)
  return p[:, 0], p[:, 2], p[:, 1]


def _subset(n: int, seed: int = 0) -> np.ndarray | None:
  if n <= MAX_DRAWN:
    return None
  return np.sort(np.random.default_rng(seed).choice(n, MAX_DRAWN, replace=False))


def _point_size(n: int) -> float:
  return float(np.clip(3000.0 / max(n, 1), 0.3, 4.0))


def view_limits(clouds) -> tuple[np.ndarray, np.ndarray]:
  """(lo, hi) of the view in screen order (x, z, y): the data's extent, but at most REACH of the
  PERCENTILES' span beyond them, so that the far returns of a raw sweep do not shrink the scene to
  a dot."""
  xyz = np.concatenate([np.stack(_screen(c), -1) for c in clouds])
  lo, hi = np.percentile(xyz, PERCENTILES[0], axis=0), np.percentile(xyz, PERCENTILES[1], axis=0)
  span = np.maximum(hi - lo, 1e-3).max()
  # A scene's own edges lie within REACH of the span beyond its percentiles; far returns do not.
  lo, hi = np.maximum(xyz.min(0), lo - REACH * span), np.minimum(xyz.max(0), hi + REACH * span)
  pad = 0.03 * np.maximum(hi - lo, 1e-3).max()
  return lo - pad, hi + pad


def _inside(points_Nx3, limits) -> np.ndarray:
  """Which points lie in the view: matplotlib's 3D axes do not clip, they draw past the box."""
  lo, hi = limits
  xyz = np.stack(_screen(points_Nx3), -1)
  return np.all((xyz >= lo) & (xyz <= hi), axis=1)


def _frame(ax, limits, zoom: float = 1.35):
  """Equal scales: the view's limits, box with the data's proportions; the sensor's view.
  `zoom` fills the panel with a flat (driving) scene; a tall box gets less so it is not cut."""
  lo, hi = limits
  ax.set_xlim(lo[0], hi[0])
  ax.set_ylim(lo[1], hi[1])
  ax.set_zlim(lo[2], hi[2])
  box = np.maximum(hi - lo, 0.1 * (hi - lo).max())  # a flat road keeps some height
  ax.set_box_aspect(box, zoom=zoom if box[2] < 0.35 * box.max() else min(zoom, 1.1))
  ax.computed_zorder = False  # draw in the order added: pc1, pc2, then pc1 + flow on top
  ax.view_init(elev=ELEVATION, azim=AZIMUTH)
  ax.set_xlabel("x (m)", labelpad=-6, fontsize=7)
  ax.set_ylabel("z, depth (m)", labelpad=-6, fontsize=7)
  ax.set_zlabel("y (m)", labelpad=-8, fontsize=7)
  ax.tick_params(labelsize=6, pad=-2)


def _panel(ax, pc1_Nx3, pc2_Mx3, flow_Nx3, title, idx1, idx2, limits) -> int:
  """Draws one view; returns how many points fell outside it (not drawn)."""
  size = _point_size(len(pc1_Nx3) if idx1 is None else len(idx1))
  pick1 = (lambda a: a) if idx1 is None else (lambda a: a[idx1])
  pick2 = (lambda a: a) if idx2 is None else (lambda a: a[idx2])
  moved_Nx3 = pick1(pc1_Nx3) + pick1(flow_Nx3)
  outside = 0
  for points, colour, label in ((pick1(pc1_Nx3), BLUE, "pc1"), (pick2(pc2_Mx3), RED, "pc2"),
                                (moved_Nx3, GREEN, "pc1 + flow")):
    keep = _inside(points, limits)
    outside += int((~keep).sum())
    ax.scatter(*_screen(points[keep]), s=size, c=colour, alpha=0.6, linewidths=0,
               depthshade=False, label=label)
  _frame(ax, limits)
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


def pair_figure(pc1_Nx3, pc2_Mx3, flow_Nx3, gt=None, title=None, mask=None):
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
                       + [pick1(pc1_Nx3) + pick1(flow) for _, flow in panels])
  width = 6.4 * len(panels)
  fig = plt.figure(figsize=(width, 4.8))
  outside = 0
  for i, (name, flow) in enumerate(panels):
    ax = fig.add_subplot(1, len(panels), i + 1, projection="3d")
    outside = max(outside, _panel(ax, pc1_Nx3, pc2_Mx3, flow, name, idx1, idx2, limits))
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
  plt.close(fig)
  return path


def render_pair(pc1_Nx3, pc2_Mx3, flow_Nx3, path, gt=None, title=None, mask=None) -> pathlib.Path:
  """Saves the Fig. 2 view of a pair (see `pair_figure`) as a PNG at `path`."""
  return _save(pair_figure(pc1_Nx3, pc2_Mx3, flow_Nx3, gt=gt, title=title, mask=mask), path)


def error_figure(pc1_Nx3, flow_Nx3, gt_Nx3, mask_N=None, clip: float = ERROR_CLIP, title=None):
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
  limits = view_limits([pc1_Nx3])
  keep = _inside(pc1_Nx3, limits)
  fig = plt.figure(figsize=(7.6, 4.8))
  ax = fig.add_subplot(1, 1, 1, projection="3d")
  art = ax.scatter(*_screen(pc1_Nx3[keep]), s=2 * _point_size(len(pc1_Nx3)),
                   c=np.minimum(err_N[keep], clip), cmap="inferno_r", vmin=0.0, vmax=clip,
                   linewidths=0, depthshade=False)
  _frame(ax, limits, zoom=1.1)
  bar = fig.colorbar(art, cax=fig.add_axes((0.84, 0.2, 0.022, 0.6)))
  bar.set_label(f"end-point error (m), clipped at {clip:g}")
  notes = [f"{int((~keep).sum())} far points outside the view not drawn"] if (~keep).any() else []
  _title(fig, [title or "", f"EPE {epe:.3f} m (mean over points)", *notes], 7.6)
  fig.subplots_adjust(left=0.05, right=0.82, bottom=0.02, top=0.95)
  return fig


def render_error(pc1_Nx3, flow_Nx3, gt_Nx3, path, mask_N=None, clip: float = ERROR_CLIP,
                 title=None) -> pathlib.Path:
  """Saves the per-point end-point-error map (see `error_figure`) as a PNG at `path`."""
  return _save(error_figure(pc1_Nx3, flow_Nx3, gt_Nx3, mask_N, clip, title), path)


def plot_learning_curves(metrics_jsonl, path) -> pathlib.Path | None:
  """Loss (log) and gradient norm vs step, one line per training stage, from a metrics.jsonl
  (jaxflow.curves' plot; an eval.json or eval_metrics.jsonl beside it adds the evaluation EPEs).
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
