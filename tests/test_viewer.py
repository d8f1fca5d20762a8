"""jaxflow.viz.viewer: predict --render FILE.html writes a self-contained 3D page that draws the points.

The page is opened in headless Chromium and its screenshot inspected for drawn points (saturated
pixels in the plot area; the same page with every layer hidden is the control). The test skips
when plotly or chromium is absent. JAXFLOW_DOCS_IMAGES=1 also stores the screenshot as
docs/images/viewer.png (the picture docs/users.md shows).
"""

import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

from jaxflow import predict
from jaxflow.errors import ConfigError
from jaxflow.viz import viewer

import commands
import zup_scene

ROOT = pathlib.Path(__file__).resolve().parents[1]
CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                 if shutil.which(n)), None)


def test_layers_hold_the_region_and_the_dynamic_points():
  pytest.importorskip("plotly")
  scene = zup_scene.sweep_pair()
  drawn = viewer.layers(scene.pc1, scene.pc2, scene.flow, ego_flow=scene.ego_flow,
                        ground1=scene.ground1, max_range=35.0, up="z")
  near = np.hypot(scene.pc1[:, 0], scene.pc1[:, 1]) < 35.0
  expected = near & ~scene.ground1  # a loop-free reference: the masks themselves
  assert len(drawn["pc1"][0]) == expected.sum()
  dynamic = expected & (np.linalg.norm(scene.flow - scene.ego_flow, axis=1) >= 0.05)
  assert dynamic.sum() == (expected & scene.moving1).sum() > 0  # exactly the moving boxes
  np.testing.assert_array_equal(np.sort(drawn["dynamic"][0], axis=0),
                                np.sort(scene.pc1[dynamic], axis=0))
  np.testing.assert_allclose(drawn["pc1 + flow"][0], drawn["pc1"][0] + scene.flow[expected])
  assert len(drawn["removed ground"][0]) == (near & scene.ground1).sum()
  fig = viewer.figure(scene.pc1, scene.pc2, scene.flow, up="z", ego_flow=scene.ego_flow)
  assert fig.layout.scene.camera.up.z == 1 and fig.layout.scene.camera.up.y == 0  # z is up


def test_html_without_plotly_names_the_extra(monkeypatch, tmp_path):
  monkeypatch.setitem(sys.modules, "plotly", None)  # import plotly -> ImportError
  monkeypatch.setitem(sys.modules, "plotly.graph_objects", None)
  scene = zup_scene.sweep_pair(n_ground=500)
  with pytest.raises(ConfigError, match=r"jaxflow\[viewer\]"):
    viewer.render(tmp_path / "x.html", scene.pc1, scene.pc2, scene.flow, up="z")
  with pytest.raises(ConfigError, match=r"\.png .* or \.html"):
    viewer.render(tmp_path / "x.jpg", scene.pc1, scene.pc2, scene.flow, up="z")


def _screenshot(html, png):
  subprocess.run([CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu",
                  "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--hide-scrollbars",
                  "--window-size=1100,750", "--virtual-time-budget=8000", f"--screenshot={png}",
                  pathlib.Path(html).absolute().as_uri()],
                 check=True, capture_output=True, timeout=120)
  import matplotlib.image  # pylint: disable=import-outside-toplevel
  return matplotlib.image.imread(png)[..., :3]


def _points_drawn(rgb) -> int:
  """Point pixels in the plot area (not the legend at the top left, nor the colour bar at the
  right): the background is white and the grid light grey-blue; the points are saturated colours
  or dark (Viridis' low end: the static points, moving with the ego-motion)."""
  h, w, _ = rgb.shape
  area = rgb[int(0.3 * h):int(0.95 * h), int(0.05 * w):int(0.9 * w)]
  return int((((area.max(-1) - area.min(-1)) > 0.35) | (area.max(-1) < 0.5)).sum())


@pytest.mark.slow
def test_predict_renders_a_page_that_chromium_draws(tmp_path):
  pytest.importorskip("plotly")
  if CHROMIUM is None:
    pytest.skip("no chromium (apt-get install chromium) to take the screenshot")
  scene = zup_scene.sweep_pair()
  np.save(tmp_path / "sweep1.npy", scene.pc1)
  np.save(tmp_path / "sweep2.npy", scene.pc2)
  run = commands.run(predict.run, "sweep1.npy", "sweep2.npy", "--lidar", "--method", "network",
                     "--max_points", "2048", "--iters", "4", "--out", "flow.npy", "--render",
                     "flow.html", cwd=tmp_path)  # `python -m jaxflow.predict ...`, in this process
  assert run.returncode == 0, run.stderr
  page = (tmp_path / "flow.html").read_text()
  assert "<html" in page and "plotly" in page and "src=\"http" not in page  # self-contained
  shot = _screenshot(tmp_path / "flow.html", tmp_path / "flow.png")
  drawn = _points_drawn(shot)
  # The control: the same page with every layer switched off draws grid and axes only.
  hidden = page.replace('"visible":true', '"visible":"legendonly"')
  assert hidden != page
  (tmp_path / "hidden.html").write_text(hidden)
  blank = _points_drawn(_screenshot(tmp_path / "hidden.html", tmp_path / "hidden.png"))
  print(f"saturated pixels: {drawn} drawn, {blank} with every layer hidden")
  assert drawn > 3000 and drawn > 20 * max(blank, 1), (drawn, blank)
  if os.environ.get("JAXFLOW_DOCS_IMAGES"):
    (ROOT / "docs" / "images").mkdir(exist_ok=True)
    shutil.copy(tmp_path / "flow.png", ROOT / "docs" / "images" / "viewer.png")


def test_predict_checks_the_viewer_extra_before_the_work(tmp_path):
  """`predict --render X.html` without plotly stops at once, naming the extra, and writes no flow."""
  blocked = tmp_path / "blocked" / "plotly"
  blocked.mkdir(parents=True)
  (blocked / "__init__.py").write_text("raise ImportError('plotly blocked for this test')\n")
  scene = zup_scene.sweep_pair(n_ground=500)
  np.save(tmp_path / "a.npy", scene.pc1)
  np.save(tmp_path / "b.npy", scene.pc2)
  root = pathlib.Path(__file__).absolute().parent.parent
  # A subprocess: plotly blocked on its path (this process may have imported it already).
  env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "blocked"), str(root)])}
  proc = subprocess.run([sys.executable, "-m", "jaxflow.predict", str(tmp_path / "a.npy"),
                         str(tmp_path / "b.npy"), "--lidar", "--out", str(tmp_path / "f.npy"),
                         "--render", str(tmp_path / "v.html")], env=env, capture_output=True,
                        text=True, timeout=300)
  assert proc.returncode == 2 and "jaxflow[viewer]" in proc.stderr, proc.stderr
  assert not (tmp_path / "f.npy").exists()
