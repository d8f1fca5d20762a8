"""jaxflow.evaluation.av2_eval against the official code: the av2 package's own compute_metrics and
results_to_dict, bucketed-scene-flow-eval's own BucketedEPEEvaluator (both installed by .ci/run with
--no-deps; the latter imports open3d and opencv at module level, which stand-ins replace), and a
plain loop written from the bucketed definition: per frame and fine class the mean EPE and speed of
each bucket, count-weighted over frames, then merged into the meta-classes, normalised, and averaged
as its compute_results does."""

import math

import numpy as np
import pytest

from jaxflow.evaluation import av2_eval

av2_eval_module = pytest.importorskip("av2.evaluation.scene_flow.eval",
                                      reason="the av2 package (.ci/run installs it)")
pd = pytest.importorskip("pandas")
from av2.evaluation.scene_flow import constants as av2_constants  # noqa: E402


def random_pairs(seed, count=4, n=600):
  """Pairs whose flows, classes, motion and distances fill every subset, one of them empty."""
  rng = np.random.default_rng(seed)
  pairs = []
  for k in range(count):
    rigid = rng.normal(0, 0.3, (n, 3)).astype(np.float32)
    speed = rng.choice([0.0, 0.01, 0.03, 0.07, 0.3, 1.0, 2.5], n)
    direction = rng.normal(size=(n, 3))
    gt = (rigid + speed[:, None] * direction / np.linalg.norm(direction, axis=1, keepdims=True))
    pred = gt + rng.normal(0, [0.02, 0.08, 0.3][k % 3], (n, 3))
    category = rng.choice([0, 0, 0, 19, 17, 4, 7, 21, 10, 11, 28], n).astype(np.uint8)
    if k == 1:
      category[:] = 0  # a pair with no foreground point
    xy = rng.uniform(-50, 50, (n, 2))
    valid = rng.uniform(size=n) > 0.1
    pairs.append(dict(pred=pred.astype(np.float32), gt=gt.astype(np.float32), rigid=rigid,
                      category=category, ego_xy=xy, valid=valid))
  return pairs


def av2_results(pairs):
  """av2's evaluate_predictions loop on our pair_labels (the files' contents), then
  results_to_dict."""
  rows = []
  for i, p in enumerate(pairs):
    labels = av2_eval.pair_labels(p["pred"], p["gt"], p["rigid"], p["category"], p["ego_xy"],
                                  p["valid"])
    result = av2_eval_module.compute_metrics(
      labels["pred"].astype(float), labels["pred_dynamic"], labels["gt"].astype(float),
      labels["category"], labels["is_dynamic"], labels["is_close"], labels["is_valid"],
      av2_constants.FOREGROUND_BACKGROUND_BREAKDOWN)
    frame = pd.DataFrame(result)
    frame.insert(0, "Example", f"log/{i}.feather")
    rows.append(frame)
  frame = pd.concat(rows, ignore_index=True)
  frame.columns = [getattr(c, "value", c) for c in frame.columns]
  return av2_eval_module.results_to_dict(frame)


def same(a, b):
  return (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, rel=1e-9, abs=1e-12)


def test_breakdown_equals_av2s_compute_metrics_and_results_to_dict():
  pairs = random_pairs(0)
  official = av2_eval.Official()
  for p in pairs:
    batch = {"flow": p["gt"][None], "rigid_flow": p["rigid"][None], "category": p["category"][None],
             "ego_xy": p["ego_xy"][None], "mask": p["valid"][None].astype(np.float32),
             "pair_valid": np.ones(1), "names": ["x"]}
    official.add(p["pred"][None], batch)
  got, want = official.results()["av2"], av2_results(pairs)
  assert set(want) <= set(got) and len(want) == 38
  for key, value in want.items():
    assert same(got[key], value), (key, got[key], value)
  assert got["pairs"] == 4 and got["points"] == sum(int(p["valid"].sum()) for p in pairs)
  # the count weighting: one pair with a single far foreground point moves the split's number
  # by that point's share, not by a pair's share
  assert not math.isnan(got["EPE 3-Way Average"])


def test_breakdown_of_an_empty_subset_is_nan_as_av2s():
  pairs = random_pairs(1, count=1)
  pairs[0]["category"][:] = 0
  official = av2_eval.Official()
  p = pairs[0]
  official.add(p["pred"][None], {"flow": p["gt"][None], "rigid_flow": p["rigid"][None],
                                 "category": p["category"][None], "ego_xy": p["ego_xy"][None],
                                 "mask": p["valid"][None], "pair_valid": [1], "names": ["x"]})
  got, want = official.results()["av2"], av2_results(pairs)
  assert math.isnan(want["EPE/Foreground/Dynamic"]) and math.isnan(got["EPE/Foreground/Dynamic"])
  assert math.isnan(got["EPE 3-Way Average"]) and math.isnan(want["EPE 3-Way Average"])
  for key, value in want.items():
    assert same(got[key], value), key


# bucketed-scene-flow-eval's definition, as a loop (names: its av2 CATEGORY_MAP, BACKGROUND = 0).
def bucketed_reference(pairs, distance=35.0):
  edges = list(np.concatenate([np.linspace(0, 2.0, 51), [np.inf]]))
  buckets = list(zip(edges, edges[1:]))
  name_of = {i: ("BACKGROUND" if i == 0 else n) for i, n in enumerate(av2_eval.CATEGORIES)}
  per_frame = {}  # (class name, bucket) -> [(avg_epe, count, avg_speed)] one per frame
  for p in pairs:
    cells = {}
    for i in range(len(p["gt"])):
      if not p["valid"][i]:
        continue
      x, y = p["ego_xy"][i]
      if max(abs(x), abs(y)) >= distance:
        continue
      g = p["gt"][i].astype(np.float64)
      speed = math.sqrt(sum((g[j] - float(p["rigid"][i][j])) ** 2 for j in range(3)))
      err = math.sqrt(sum((float(p["pred"][i][j]) - g[j]) ** 2 for j in range(3)))
      b = next(k for k, (lo, hi) in enumerate(buckets) if lo <= speed < hi)
      cells.setdefault((name_of[int(p["category"][i])], b), []).append((err, speed))
    for key, values in cells.items():
      per_frame.setdefault(key, []).append((sum(e for e, _ in values) / len(values), len(values),
                                            sum(s for _, s in values) / len(values)))
  merged = {}  # fine class -> bucket -> (epe, speed, count): frames weighted by count
  for (name, b), frames in per_frame.items():
    count = sum(c for _, c, _ in frames)
    merged.setdefault(name, {})[b] = (sum(e * c for e, c, _ in frames) / count,
                                      sum(s * c for _, c, s in frames) / count, count)
  results = {}
  for meta, names in av2_eval.META_CLASSES.items():
    names = ["BACKGROUND" if n == "NONE" else n for n in names]
    cells = {}
    for name in names:  # accumulate_value: a running count-weighted average
      for b, (epe, speed, count) in merged.get(name, {}).items():
        if b in cells:
          e0, s0, c0 = cells[b]
          total = c0 + count
          cells[b] = ((e0 * c0 + epe * count) / total, (s0 * c0 + speed * count) / total, total)
        else:
          cells[b] = (epe, speed, count)
    static = cells[0][0] if 0 in cells else float("nan")
    dynamic = [cells[b][0] / cells[b][1] for b in sorted(cells) if b > 0]
    results[meta] = (static, sum(dynamic) / len(dynamic) if dynamic else float("nan"))
  return results


def test_bucketed_equals_a_loop_of_bucketed_scene_flow_evals_definition():
  pairs = random_pairs(2, count=3, n=400)
  official = av2_eval.Official()
  for p in pairs:
    official.add(p["pred"][None], {"flow": p["gt"][None], "rigid_flow": p["rigid"][None],
                                   "category": p["category"][None], "ego_xy": p["ego_xy"][None],
                                   "mask": p["valid"][None], "pair_valid": [1], "names": ["x"]})
  got = official.results()["bucketed"]
  want = bucketed_reference(pairs)
  assert list(got["classes"]) == sorted(want)  # its merged matrix lists the classes sorted
  for meta, (static, dynamic) in want.items():
    assert same(got["classes"][meta]["static_epe"], static), meta
    assert same(got["classes"][meta]["dynamic_norm_epe"], dynamic), meta
  assert not math.isnan(got["classes"]["CAR"]["dynamic_norm_epe"])
  statics = [s for s, _ in want.values() if not math.isnan(s)]
  dynamics = [d for _, d in want.values() if not math.isnan(d)]
  assert same(got["static_epe"], sum(statics) / len(statics))
  assert same(got["dynamic_norm_epe"], sum(dynamics) / len(dynamics))


def test_official_counts_every_point_once_not_every_pair():
  """Two pairs, one with 1 foreground-static point and one with 99: the split's EPE is the points'
  mean (av2), not the mean of the two pairs' means (OpenSceneFlow's local reading)."""
  official = av2_eval.Official()
  for n, err in ((1, 1.0), (99, 0.0)):
    gt = np.zeros((n, 3), np.float32)
    pred = gt + [err, 0, 0]
    official.add(pred[None], {"flow": gt[None], "rigid_flow": gt[None],
                              "category": np.full((1, n), 19, np.uint8),
                              "ego_xy": np.zeros((1, n, 2)), "mask": np.ones((1, n)),
                              "pair_valid": [1], "names": ["x"]})
  assert official.results()["av2"]["EPE/Foreground/Static"] == pytest.approx(0.01)


def test_bucketed_equals_bucketed_scene_flow_evals_own_code(monkeypatch):
  """bucketed-scene-flow-eval's own BucketedEPEEvaluator (installed by .ci/run with --no-deps):
  its package imports open3d, opencv and pyquaternion at module level for its viewers and loaders,
  which the evaluation never calls, so empty stand-ins are put in their place for the import."""
  import sys  # pylint: disable=import-outside-toplevel
  import types  # pylint: disable=import-outside-toplevel

  class Anything:
    def __getattr__(self, name):
      return Anything()

    def __call__(self, *args, **kwargs):
      return Anything()

  for name in ("open3d", "cv2", "pyquaternion"):
    if name not in sys.modules:
      stub = types.ModuleType(name)
      stub.__getattr__ = lambda attr: Anything()
      monkeypatch.setitem(sys.modules, name, stub)
  bucketed = pytest.importorskip("bucketed_scene_flow_eval.eval.bucketed_epe",
                                 reason="bucketed-scene-flow-eval (.ci/run installs it)")
  meta_classes = pytest.importorskip(
    "bucketed_scene_flow_eval.datasets.argoverse2.av2_metacategories").BUCKETED_METACATAGORIES

  class Points:  # the PointCloud it reads: .points and .shape
    def __init__(self, points):
      self.points, self.shape = points, points.shape

  evaluator = bucketed.BucketedEPEEvaluator.__new__(bucketed.BucketedEPEEvaluator)
  edges = np.concatenate([np.linspace(0, 2.0, 51), [np.inf]])  # its defaults, without its folder
  evaluator.speed_thresholds = list(zip(edges, edges[1:]))
  evaluator.meta_class_lookup = meta_classes
  evaluator.eval_frame_results = []
  # its av2 class ids are av2's index - 1 (BACKGROUND -1)
  evaluator.class_id_to_name = {i - 1: "BACKGROUND" if i == 0 else n
                                for i, n in enumerate(av2_eval.CATEGORIES)}
  official = av2_eval.Official()
  for p in random_pairs(4, count=3, n=400):
    v = p["valid"]
    points = np.c_[p["ego_xy"], np.zeros(len(v))][v]
    rigid = p["rigid"].astype(np.float64)
    frame = evaluator._build_eval_frame_results(  # pylint: disable=protected-access
      Points(points), p["category"][v].astype(int) - 1, (p["gt"] - rigid)[v],
      (p["pred"] - rigid)[v])  # its flows are ego-motion compensated (OpenSceneFlow's v2 eval)
    evaluator.eval_frame_results.append(frame)
    official.add(p["pred"][None], {"flow": p["gt"][None], "rigid_flow": p["rigid"][None],
                                   "category": p["category"][None], "ego_xy": p["ego_xy"][None],
                                   "mask": v[None], "pair_valid": [1], "names": ["x"]})
  # pylint: disable=protected-access
  stats = evaluator._category_to_average_stats(evaluator._category_to_per_frame_stats())
  matrix = evaluator._build_stat_table(stats, 35)  # compute_results' distance: 35 m
  got = official.results()["bucketed"]
  for name, error in matrix.get_overall_class_errors().items():
    assert same(got["classes"][name]["static_epe"], float(error.static_epe)), name
    assert same(got["classes"][name]["dynamic_norm_epe"], float(error.dynamic_error)), name
  mean = matrix.get_mean_average_values()
  assert same(got["static_epe"], float(mean.static_epe))
  assert same(got["dynamic_norm_epe"], float(mean.dynamic_error))


def test_speed_bands_are_the_buckets_merged_as_the_metric_takes_them():
  """Cars at speeds 0.10 and 0.20 (two buckets of the slowest band), 0.5, 1.5 and 2.5 m a frame,
  each with a known error: a band's EPE is its points' mean, its normalised EPE the mean over its
  buckets of EPE / speed (closed form)."""
  speeds = np.array([0.10, 0.20, 0.5, 1.5, 2.5])
  errors = np.array([0.05, 0.10, 0.05, 0.05, 0.05])
  gt = np.c_[speeds, np.zeros((5, 2))]
  pred = gt + np.c_[np.zeros(5), errors, np.zeros(5)]
  sums = av2_eval.bucketed_sums(pred, gt, np.zeros_like(gt), np.full(5, 19), np.zeros((5, 2)),
                                np.ones(5, bool))
  car = av2_eval.bucketed_by_speed(sums)["CAR"]
  assert [b["speeds"] for b in car] == [(0.04, 0.32), (0.32, 1.0), (1.0, 2.0), (2.0, np.inf)]
  assert [b["points"] for b in car] == [2, 1, 1, 1]
  np.testing.assert_allclose([b["epe"] for b in car], [0.075, 0.05, 0.05, 0.05])
  np.testing.assert_allclose([b["dynamic_norm_epe"] for b in car], [0.5, 0.1, 0.05 / 1.5, 0.02])
  assert math.isnan(av2_eval.bucketed_by_speed(sums)["PEDESTRIAN"][0]["epe"])
