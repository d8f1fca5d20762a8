"""jaxflow.viz.figures: PNGs are written, and the Fig. 2 view draws what it says."""

import json
import os
import pathlib

import numpy as np
import pytest

from jaxflow.evaluation import reporting
from jaxflow.viz import figures

import zup_scene

ROOT = pathlib.Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"


def _pair(n=300, m=280, seed=0):
  rng = np.random.default_rng(seed)
  pc1 = rng.uniform([-5, -1.5, 3], [5, 2, 30], (n, 3)).astype(np.float32)
  pc2 = rng.uniform([-5, -1.5, 3], [5, 2, 30], (m, 3)).astype(np.float32)
  flow = rng.normal(0, 0.3, (n, 3)).astype(np.float32)
  return pc1, pc2, flow


def _is_png(path):
  data = path.read_bytes()
  return data.startswith(PNG) and len(data) > 1000


def _artists(fig, label):
  return [c for ax in fig.axes for c in ax.collections if c.get_label() == label]


def _drawn(artist):
  """The x, y, z data of a 3D scatter, in the readers' frame (viz draws (x, z, y))."""
  xs, zs, ys = (np.asarray(a) for a in artist._offsets3d)  # pylint: disable=protected-access
  return np.stack([xs, ys, zs], -1)


def test_green_points_are_pc1_plus_flow():
  pc1, pc2, flow = _pair()
  gt = flow + np.float32(0.5)
  fig = figures.pair_figure(pc1, pc2, flow, gt=gt, title="t")
  green = _artists(fig, "pc1 + flow")
  assert len(green) == 2  # ground-truth panel first, then the prediction (the paper's layout)
  np.testing.assert_allclose(_drawn(green[0]), pc1 + gt, atol=1e-5)
  np.testing.assert_allclose(_drawn(green[1]), pc1 + flow, atol=1e-5)
  np.testing.assert_allclose(_drawn(_artists(fig, "pc1")[0]), pc1, atol=1e-6)
  np.testing.assert_allclose(_drawn(_artists(fig, "pc2")[0]), pc2, atol=1e-6)
  colours = {c.get_label(): tuple(np.round(c.get_facecolor()[0][:3], 2)) for c in fig.axes[0].collections}
  assert colours["pc1"][2] > 0.6 and colours["pc2"][0] > 0.6 and colours["pc1 + flow"][1] > 0.5
  assert [t.get_text() for t in fig.legends[0].get_texts()] == ["pc1", "pc2", "pc1 + flow"]


def test_large_clouds_are_subsampled_consistently(monkeypatch):
  monkeypatch.setattr(figures, "MAX_DRAWN", 100)
  pc1, pc2, flow = _pair(n=500, m=400)
  fig = figures.pair_figure(pc1, pc2, flow)
  blue, green = _drawn(_artists(fig, "pc1")[0]), _drawn(_artists(fig, "pc1 + flow")[0])
  assert len(blue) == len(green) == 100
  rows = [int(np.flatnonzero((pc1 == p).all(1))[0]) for p in blue]  # the same pc1 points, moved
  np.testing.assert_allclose(green, pc1[rows] + flow[rows], atol=1e-5)
  assert "drawn" in fig._suptitle.get_text()  # pylint: disable=protected-access


def test_render_pair_and_error_write_pngs(tmp_path):
  pc1, pc2, flow = _pair()
  assert _is_png(figures.render_pair(pc1, pc2, flow, tmp_path / "a" / "pair.png", title="x"))
  assert _is_png(figures.render_pair(pc1, pc2, flow, tmp_path / "pair_gt.png", gt=flow * 0))
  fig = figures.error_figure(pc1, flow, flow * 0, mask_N=np.arange(len(pc1)) % 2 == 0)
  label = fig.axes[-1].get_ylabel()
  assert "clipped at 0.3" in label
  art = fig.axes[0].collections[0]
  assert art.get_array().max() <= figures.ERROR_CLIP + 1e-6 and len(art.get_array()) == len(pc1) // 2
  assert _is_png(figures.render_error(pc1, flow, flow * 0, tmp_path / "err.png"))


def test_evaluate_render_calls_match(tmp_path, monkeypatch):
  """evaluate.py --render_dir goes through reporting.render_batch -> figures.render_pair, with the pair's name
  and the prediction's EPE over the pair's valid points in the picture."""
  pc1, pc2, flow = _pair()
  mask = np.arange(len(pc1)) % 3 > 0
  pred = flow * 0.9
  batch = {"pc1": pc1[None], "pc2": pc2[None], "flow": flow[None], "mask": mask[None],
           "names": ["ft3d/val/0000007"], "pair_valid": np.ones(1, np.float32)}
  drawn = []
  real_save = figures._save  # pylint: disable=protected-access
  monkeypatch.setattr(figures, "_save", lambda fig, path: (drawn.append(fig), real_save(fig, path))[1])
  reporting.render_batch(tmp_path, batch, pred[None])
  assert _is_png(tmp_path / "ft3d_val_0000007.png") and _is_png(tmp_path / "ft3d_val_0000007_top.png")
  epe = np.mean([np.sqrt(((pred[i] - flow[i]) ** 2).sum()) for i in range(len(pc1)) if mask[i]])
  fig, top = drawn
  assert top.axes[2].get_title() == f"end-point error: EPE {epe:.3f} m"  # the top view's third
  assert "ft3d/val/0000007" in fig._suptitle.get_text()  # pylint: disable=protected-access
  assert [ax.get_title() for ax in fig.axes] == ["ground truth", f"prediction: EPE {epe:.3f} m"]


def _boxes(fig):
  """Window extents of the figure's texts: title, legend, panel titles, axis and colour-bar
  labels."""
  fig.canvas.draw()
  renderer = fig.canvas.get_renderer()
  texts = {"title": fig._suptitle} if fig._suptitle else {}  # pylint: disable=protected-access
  for i, ax in enumerate(fig.axes):
    texts[f"axes {i} title"] = ax.title
    for name in ("xaxis", "yaxis", "zaxis"):
      if hasattr(ax, name) and getattr(ax, name).label.get_text():
        texts[f"axes {i} {name} label"] = getattr(ax, name).label
  boxes = {k: t.get_window_extent(renderer) for k, t in texts.items() if t.get_text()}
  for legend in fig.legends:
    boxes["legend"] = legend.get_window_extent(renderer)
  return boxes, fig.bbox


@pytest.mark.parametrize("with_gt", [False, True])
def test_pair_view_title_clears_the_legend_and_stays_inside(with_gt):
  pc1, pc2, flow = _pair()
  long = "a_rather_long_scan_name_frame_000001.ply -> a_rather_long_scan_name_frame_000002.ply"
  fig = figures.pair_figure(pc1, pc2, flow, gt=flow * 0 if with_gt else None, title=long)
  boxes, page = _boxes(fig)
  assert not boxes["title"].overlaps(boxes["legend"])
  for name, box in boxes.items():
    assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1, name


def test_error_view_labels_are_inside_the_figure():
  rng = np.random.default_rng(0)  # a wide, flat driving scene (KITTI's) pushed "y (m)" out
  pc1 = rng.uniform([-30, -1.4, 0], [30, 2, 35], (3000, 3)).astype(np.float32)
  flow = rng.normal(0, 0.3, (3000, 3)).astype(np.float32)
  fig = figures.error_figure(pc1, flow, flow * 0, title="scene")
  boxes, page = _boxes(fig)
  assert "axes 0 zaxis label" in boxes and "axes 1 yaxis label" in boxes  # y (m), the colour bar
  for name, box in boxes.items():
    assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1, name


def test_far_returns_are_left_out_of_the_view_and_counted():
  pc1, pc2, flow = _pair(n=2000, m=2000)
  far = np.float32([[300.0, 0.0, 250.0], [-200.0, 40.0, -300.0]])  # two stray returns of a sweep
  fig = figures.pair_figure(np.concatenate([pc1, far]), pc2, np.concatenate([flow, far * 0]))
  ax = fig.axes[0]
  limits = np.sort([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()], axis=1)  # x inverted: left, left
  assert ax.get_xlim()[0] > ax.get_xlim()[1]
  assert limits[0, 1] < 20 and limits[1, 1] < 50  # the scene, not the strays, sets the view
  for art in ax.collections:
    offsets = art._offsets3d  # pylint: disable=protected-access
    drawn = np.stack([np.asarray(a) for a in offsets], -1)
    assert ((drawn >= limits[:, 0]) & (drawn <= limits[:, 1])).all()  # nothing past the axes
  blue = _drawn(_artists(fig, "pc1")[0])
  assert len(blue) == len(pc1)  # every point of the scene drawn, the two strays left out
  assert "4 far points outside the view not drawn" in fig._suptitle.get_text()  # pc1 and moved


@pytest.mark.parametrize("with_stage", [True, False])
def test_learning_curves(tmp_path, with_stage):
  lines = []
  for step in range(10, 210, 10):
    r = {"step": step, "loss": 3.0 / step**0.5, "grad_norm": 1.0}
    if with_stage:
      r["stage"] = 1 if step <= 100 else 2
    lines.append(json.dumps(r))
  (tmp_path / "metrics.jsonl").write_text("\n".join(lines) + "\n")
  out = figures.plot_learning_curves(tmp_path / "metrics.jsonl", tmp_path / "plots" / "curve.png")
  assert out is not None and _is_png(out)
  assert not (tmp_path / "learning_curve.png").exists()  # nothing written beside the log
  (tmp_path / "empty.jsonl").write_text("")
  assert figures.plot_learning_curves(tmp_path / "empty.jsonl", tmp_path / "none.png") is None


def test_importing_viz_keeps_the_sessions_backend(tmp_path):
  """A notebook's backend (here pdf, any but Agg) survives importing jaxflow.viz.figures and writing its PNGs."""
  import subprocess  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  code = ("import matplotlib; matplotlib.use('pdf'); import numpy as np; from jaxflow.viz import figures; "
          "p = np.random.default_rng(0).uniform(0, 9, (200, 3)).astype('f4'); "
          f"figures.render_pair(p, p, p * 0, r'{tmp_path / 'a.png'}'); "
          f"figures.render_sweep(p, p, p * 0, r'{tmp_path / 'b.png'}', up='z'); "
          "print(matplotlib.get_backend())")
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
  assert out.stdout.strip() == "pdf"
  assert _is_png(tmp_path / "a.png") and _is_png(tmp_path / "b.png")


def _top_artists(fig, label):
  return [c for c in fig.axes[0].collections + fig.axes[1].collections if c.get_label() == label]


@pytest.mark.parametrize("up", ["z", "y"])
def test_top_view_is_seen_from_above_not_mirrored(up):
  """Screen right x screen up = the cloud's up (out of the page), whatever the up axis; the view
  spans the range, and a point beyond it is not drawn."""
  scene = zup_scene.sweep_pair(n_ground=800, reach=60.0)
  to_frame = (lambda p: p) if up == "z" else (lambda p: p[:, [1, 2, 0]])  # (y, z, x): y up
  pc1, pc2, flow = (to_frame(a) for a in (scene.pc1, scene.pc2, scene.flow))
  fig = figures.sweep_figure(pc1, pc2, flow, up=up, ground1=scene.ground1, max_range=35.0)
  ax = fig.axes[0]
  (art,) = _top_artists(fig, "pc1")
  drawn = np.asarray(art.get_offsets())
  # Which cloud axes the screen shows, and their direction (xlim / ylim order).
  column = lambda v: [i for i in range(3) if np.isin(v, pc1[:, i]).all()]
  (h,), (v,) = column(drawn[:, 0]), column(drawn[:, 1])
  right = -np.eye(3)[h] if ax.get_xlim()[0] > ax.get_xlim()[1] else np.eye(3)[h]
  screen_up = np.eye(3)[v] if ax.get_ylim()[0] < ax.get_ylim()[1] else -np.eye(3)[v]
  np.testing.assert_array_equal(np.cross(right, screen_up), np.eye(3)["xyz".index(up)])
  assert sorted(np.abs(ax.get_xlim())) == [35.0, 35.0]
  horizontal = np.hypot(drawn[:, 0], drawn[:, 1])
  assert horizontal.max() < 35.0 and (np.hypot(pc1[:, h], pc1[:, v]) >= 35.0).any()
  (ground,) = _top_artists(fig, "removed ground")
  near = np.hypot(pc1[:, h], pc1[:, v]) <= 35.0
  assert len(ground.get_offsets()) == (scene.ground1 & near).sum() > 0  # ground marked


def test_static_world_15mm_off_looks_different_from_29cm_off():
  """The colour of the static points follows their speed relative to the ego-motion: 1.5 cm and
  29 cm differ, and the moving boxes stand out from a static world 1.5 cm off."""
  scene = zup_scene.sweep_pair(n_ground=500)
  colours = {}
  for off in (0.015, 0.29):
    flow = scene.flow + np.float32([off, 0, 0]) * ~scene.moving1[:, None]
    fig = figures.sweep_figure(scene.pc1, scene.pc2, flow, up="z", ego_flow=scene.ego_flow,
                           ground1=scene.ground1)
    (art,) = _top_artists(fig, "pc1")
    values = np.asarray(art.get_array())
    rgba = art.to_rgba(values)
    static = np.isclose(values, off, rtol=1e-3)
    moving = values > 1.0 - 1e-6  # 1.6 m and 0.8 m moves: clipped at the scale's top (1 m)
    assert static.sum() > 100 and moving.sum() > 100
    colours[off] = rgba[static].mean(0)[:3], rgba[moving].mean(0)[:3]
  (s_small, m_small), (s_big, _) = colours[0.015], colours[0.29]
  if os.environ.get("JAXFLOW_DOCS_IMAGES"):  # the top view docs/users.md shows
    figures.render_sweep(scene.pc1, scene.pc2, scene.flow + np.float32([0.015, 0, 0]) * ~scene.moving1[
      :, None], ROOT / "docs" / "images" / "top_view.png", up="z", ego_flow=scene.ego_flow,
      ground1=scene.ground1, title="synthetic z-up sweep: true flow, static world 1.5 cm off")
  assert np.linalg.norm(s_small - s_big) > 0.3
  assert np.linalg.norm(s_small - m_small) > 0.6


def test_pc1_plus_flow_lies_under_pc2():
  scene = zup_scene.sweep_pair(n_ground=500)
  fig = figures.sweep_figure(scene.pc1, scene.pc2, scene.flow, up="z")
  labels = [c.get_label() for c in fig.axes[1].collections]
  assert labels == ["pc1 + flow", "pc2"]  # drawn first: underneath
  warped, pc2 = fig.axes[1].collections
  assert warped.get_sizes()[0] > 2 * pc2.get_sizes()[0]  # a larger halo that pc2 does not hide
  assert "no ego-motion given" in fig.axes[0].get_title()
