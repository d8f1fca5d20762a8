"""benchmarks/segmentation.py: its scores on a hand-made scene whose answer is known (two cars 3 m
apart and a person on flat ground), and the script at toy size (the own segmenter; scikit-learn's
only where it is importable: it is not a dependency)."""

import numpy as np
import pytest

from benchmarks import segmentation as seg


def _box_surface(lo, hi, step=0.1):
  """Points on the sides and top of an axis-aligned box (none on its bottom)."""
  xs, ys, zs = (np.arange(a, b + 1e-9, step) for a, b in zip(lo, hi))
  faces = []
  for x in (lo[0], hi[0]):
    y, z = np.meshgrid(ys, zs)
    faces.append(np.stack([np.full(y.size, x), y.ravel(), z.ravel()], 1))
  for y in (lo[1], hi[1]):
    x, z = np.meshgrid(xs, zs)
    faces.append(np.stack([x.ravel(), np.full(x.size, y), z.ravel()], 1))
  x, y = np.meshgrid(xs, ys)
  faces.append(np.stack([x.ravel(), y.ravel(), np.full(x.size, hi[2])], 1))
  return np.concatenate(faces)


def _scene():
  """Flat ground (z = 0, background), two 4 x 1.8 x 1.5 m cars 3 m apart along x, a 1.7 m tall
  person of 0.3 m radius 3 m to their side: instances 1, 2, 3."""
  gx, gy = np.meshgrid(np.arange(-4, 12, 0.2), np.arange(-6, 6, 0.2))
  ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
  car1 = _box_surface((0.0, 0.0, 0.2), (4.0, 1.8, 1.5))
  car2 = _box_surface((7.0, 0.0, 0.2), (11.0, 1.8, 1.5))
  a, z = np.meshgrid(np.linspace(0, 2 * np.pi, 24, endpoint=False), np.arange(0.1, 1.7, 0.1))
  person = np.stack([2 + 0.3 * np.cos(a.ravel()), -3 + 0.3 * np.sin(a.ravel()), z.ravel()], 1)
  points = np.concatenate([ground, car1, car2, person])
  instance = np.repeat([0, 1, 2, 3], [len(ground), len(car1), len(car2), len(person)])
  category = np.array([0, seg.ss.REGULAR_VEHICLE, seg.ss.REGULAR_VEHICLE,
                       seg.ss.PEDESTRIAN])[instance]
  return seg.Scene(points, points[:, 2], points[:, 2] < 0.05, instance, category)


def _by_instance(rows):
  return {r["instance"]: r for r in rows}


def test_scores_of_a_known_labelling():
  scene = _scene()
  rows = _by_instance(seg.score(scene.instance, scene.category, scene.instance - 1))
  assert sorted(rows) == [1, 2, 3]  # background is no instance
  assert all(r["iou"] == 1 and r["matched"] and not r["merged"] and not r["split"]
             for r in rows.values())
  assert rows[3]["category"] == seg.ss.PEDESTRIAN
  # The two cars in one group: both merged, IoU = own points / both cars' points.
  label = np.where(scene.instance == 2, 1, scene.instance) - 1
  rows = _by_instance(seg.score(scene.instance, scene.category, label))
  n1, n2 = (scene.instance == 1).sum(), (scene.instance == 2).sum()
  assert rows[1]["merged"] and rows[2]["merged"] and not rows[3]["merged"]
  assert rows[1]["iou"] == pytest.approx(n1 / (n1 + n2))
  # The person cut in two halves (by x): split, best IoU about one half.
  person = scene.instance == 3
  label = scene.instance.copy() - 1
  label[person & (scene.points[:, 0] > 2)] = 7
  rows = _by_instance(seg.score(scene.instance, scene.category, label))
  assert rows[3]["split"] and not rows[3]["merged"] and 0.4 < rows[3]["iou"] < 0.6
  # No group at all: IoU 0, split.
  rows = _by_instance(seg.score(scene.instance, scene.category, np.full(len(label), -1)))
  assert all(r["iou"] == 0 and r["split"] and not r["matched"] for r in rows.values())
  summary = seg.breakdown(list(rows.values()))
  assert summary["all"]["instances"] == 3 and summary["pedestrian"]["instances"] == 1


def test_own_segmenter_finds_the_three_objects():
  scene = _scene()
  label = seg.segment(scene, "own", {})
  rows = seg.score(scene.instance, scene.category, label)
  assert len(rows) == 3 and all(r["iou"] == 1 for r in rows)
  assert (label[scene.ground] == -1).all()


def test_sklearn_segmenters_on_the_known_scene():
  pytest.importorskip("sklearn")
  scene = _scene()
  for name, params in (("dbscan", {"eps": 0.5, "min_samples": 3, "dims": 2}),
                       ("dbscan", {"eps": 0.5, "min_samples": 3, "dims": 3}),
                       ("hdbscan", {"min_cluster_size": 20, "min_samples": 5})):
    rows = seg.score(scene.instance, scene.category, seg.segment(scene, name, params))
    assert len(rows) == 3 and all(r["matched"] and not r["merged"] for r in rows), name


def test_script_at_toy_size(tmp_path):
  try:
    import sklearn.cluster  # noqa: F401
    segmenters = "own,dbscan,hdbscan"
  except ImportError:
    segmenters = "own"
  out = seg.main(["--split", "test", "--pairs", "1", "--forms", "generated", "--scale", "0.05",
                  "--segmenters", segmenters, "--json", str(tmp_path / "out.json")])
  assert (tmp_path / "out.json").exists()
  assert {c["name"] for c in out["configs"].values()} == set(segmenters.split(","))
  assert "own" in out["configs"]  # the pipeline's default settings, always reported on test
  own = out["configs"]["own"]
  assert own["scores"]["all"]["instances"] > 0 and own["seconds_per_pair"] > 0
  assert 0 <= own["scores"]["all"]["matched"] <= 1
