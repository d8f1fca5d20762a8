"""Evaluation streams its batches: the host memory an `Evaluator` call needs does not grow with the
number of pairs (the batches are sampled again on every call, not kept), its results stay those of
`evaluate_zero_flow` on the same pairs, and a progress bar in pairs/s goes to stderr."""

import tracemalloc

import pytest

from jaxflow.configs import default
from jaxflow.data import open_dataset
from jaxflow.evaluation import evaluator
from jaxflow.network.model import build_model

POINTS = 4096
BYTES_PER_PAIR = POINTS * (3 + 3 + 3 + 1) * 4  # float32 pc1, pc2, flow (N x 3) and mask (N)


def make_evaluator(pairs: int) -> evaluator.Evaluator:
  model = build_model(default.get_config("smoke").model, inference=True)
  return evaluator.Evaluator(model, open_dataset(f"synthetic_lidar:{pairs}", split="test"),
                             num_points=POINTS, batch_size=2, num_iters=1)


def peak_bytes(pairs: int) -> tuple[int, dict]:
  """numpy registers its buffers with tracemalloc: the peak of making an Evaluator and calling it."""
  tracemalloc.start()
  try:
    results = make_evaluator(pairs).zero_flow()
    return tracemalloc.get_traced_memory()[1], results
  finally:
    tracemalloc.stop()


def test_evaluator_memory_is_flat_in_the_number_of_pairs(capsys):
  peak_bytes(4)  # compiles the metrics, starts the thread pools
  few, results = peak_bytes(16)
  many, _ = peak_bytes(64)
  # Keeping every batch (the old Evaluator) adds 48 pairs' arrays, 7.9 MB: 7.7 MB measured.
  assert many - few < 0.2 * 48 * BYTES_PER_PAIR, (few, many)
  assert results["pairs"] == 16
  # The bar is a terminal's; stderr here is not one (a log gets a line every 10 s: issue 68).
  assert "pair/s" not in capsys.readouterr().err


def test_streamed_evaluator_gives_the_results_of_one_pass():
  ev = make_evaluator(5)
  ds = open_dataset("synthetic_lidar:5", split="test")
  once = evaluator.evaluate_zero_flow(ds, num_points=POINTS, batch_size=2)
  for results in (ev.zero_flow(), ev.zero_flow()):  # re-sampled each call: the same pairs
    assert set(results) == set(once)
    for k in ("epe", "acc_strict", "acc_relax", "outliers", "angle", "pairs"):
      assert results[k] == pytest.approx(once[k], rel=0, abs=0), k
