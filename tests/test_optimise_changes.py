"""Issue 69: optimise's changes since 9d35694 can each be switched back by a setting (the bodies'
draws and world refit), and a call can resume after a stage of an earlier one with the same
result (benchmarks/optimise_changes.py measures the variants on shared starts)."""

import dataclasses
import pathlib

import numpy as np
import pytest

from jaxflow.methods import optimise
from jaxflow.refine import bodies, optimiser
from test_bodies import _pair, _stuck_start


def test_the_bodies_switches_are_checked():
  for name in ("draws", "world_refit"):
    with pytest.raises(ValueError, match=f"bodies {name}"):
      bodies.Settings(**{name: "sometimes"})


@pytest.mark.parametrize("changes", [{"draws": "each"}, {"world_refit": "always"}])
def test_9d35694s_bodies_still_find_the_scene_and_the_switch_changes_the_draws(changes):
  """Either switch back still recovers each body (as test_bodies does for the defaults); the
  draws switch changes which hypotheses are drawn (else it would switch nothing)."""
  pc1, pc2, truth, body = _pair()
  start = _stuck_start(pc1, truth, body)
  flow, found = bodies.rigid_bodies(pc1, pc2, start, bodies.Settings(**changes))
  error = np.linalg.norm(flow - truth, axis=1)
  assert found.bodies >= 3 and error.mean() < 0.025
  if "draws" in changes:
    rng = lambda: np.random.default_rng(0)
    labels = [bodies.hypotheses(pc1, start, bodies.Settings(draws=d), rng())[0].label
              for d in ("once", "each")]
    assert not np.array_equal(*labels)


def test_a_call_resumed_after_the_polish_gives_the_whole_calls_flow():
  pc1, pc2, truth, body = _pair(n=600)
  start = _stuck_start(pc1, truth, body)
  chosen = dataclasses.replace(
    optimise.Optimise(), world=None, rigid_steps=10,
    descent=optimiser.Settings(model="flow", objective="grid", steps=10, learning_rate=0.05),
    polish=optimiser.Settings(model="flow", objective="exact", steps=5, learning_rate=0.02,
                              refresh=5))
  batch = [a[None] for a in (start, pc1, pc2)]
  flows = {}
  whole = np.asarray(optimise.optimise_flow(*batch, chosen, flows=flows)[0])
  assert list(flows) == ["descent", "rigid clusters", "polish", "rigid bodies"]
  np.testing.assert_array_equal(np.asarray(flows["rigid bodies"]), whole)
  again, info = optimise.optimise_flow(*batch, chosen, resume=("polish", flows["polish"]))
  assert info is None
  np.testing.assert_array_equal(np.asarray(again), whole)
  # resumed from another flow, the bodies start from that one: the stages were skipped
  other = optimise.optimise_flow(*batch, chosen, resume=("polish", batch[0]))[0]
  assert not np.array_equal(np.asarray(other), whole)


def test_the_ft3d_halves_split_the_21_shared_pairs_and_are_reported_apart():
  from benchmarks import methods  # pylint: disable=import-outside-toplevel
  choose, report = set(methods.FT3D_CHOOSE), set(methods.FT3D_REPORT)
  assert (len(choose), len(report)) == (10, 11) and not choose & report
  shared = methods.DATA / "FlyingThings3D_subset_processed_35m" / "train"
  if shared.is_dir():
    assert choose | report == {p.name for p in shared.iterdir()}
  per_pair = {f"/x/{name}": float(i) for i, name in enumerate(sorted(choose | report))}
  halves = methods.halves(per_pair)
  for half, names in (("choose", choose), ("report", report)):
    expected = [e for path, e in per_pair.items() if path.rsplit("/", 1)[1] in names]
    assert halves[half] == {"epe": sum(expected) / len(expected), "pairs": len(names)}


@pytest.mark.skipif(not (pathlib.Path(__file__).absolute().parent.parent.parent / "shared" / "data"
                         / "real_sweeps" / "av2_pair_flow_labelled.npz").exists(),
                    reason="the shared labelled AV2 pair is absent")
def test_the_av2_pair_is_cut_to_35_m_in_the_model_frame():
  from benchmarks import methods  # pylint: disable=import-outside-toplevel
  pc1, pc2, flow, mask = methods.av2_cut()
  z = np.load(methods.AV2_LABELLED)
  for cut, raw in ((pc1, z["pc1"]), (pc2, z["pc2"])):
    assert np.linalg.norm(cut[:, [2, 0]], axis=1).max() <= 35.0  # model frame: x left, z forward
    inside = raw[np.hypot(raw[:, 0], raw[:, 1]) <= 35.0]
    np.testing.assert_array_equal(cut, inside[:, [1, 2, 0]])  # the sensor's up (z) is y
  assert len(flow) == len(pc1) == len(mask) and np.isfinite(flow).all()
  assert 0 < mask.sum() < len(mask)
