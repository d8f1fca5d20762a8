"""notebooks/quickstart.ipynb runs top to bottom (at small sizes), so it cannot rot."""

import os
import pathlib

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "quickstart.ipynb"


def test_notebook_is_committed_without_outputs():
  nb = nbformat.read(NOTEBOOK, as_version=4)
  code = [c for c in nb.cells if c.cell_type == "code"]
  assert code and all(not c.outputs and c.execution_count is None for c in code)


@pytest.mark.slow
def test_quickstart_runs(tmp_path, monkeypatch):
  pytest.importorskip("ipykernel")
  monkeypatch.setenv("JAXFLOW_NOTEBOOK_SMALL", "1")
  monkeypatch.setenv("JAXFLOW_NOTEBOOK_OUT", str(tmp_path))
  monkeypatch.setenv("JAX_PLATFORMS", "cpu")
  nb = nbformat.read(NOTEBOOK, as_version=4)
  client = NotebookClient(nb, timeout=1200, kernel_name="python3",
                          resources={"metadata": {"path": str(ROOT)}})
  client.execute()
  text = "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
  assert "EPE" in text and "zero flow" in text
  for name in ("pair.png", "error.png", "frame1.ply"):
    assert (tmp_path / name).stat().st_size > 0
  assert "raw sweep" in text and "-> flow" in text  # the --lidar cell
  if os.path.exists(ROOT / "jaxflow" / "checkpoints" / "jaxflow_synthetic"):
    assert "command line and Python agree: True" in text
  else:
    assert "WARNING: no checkpoint" in text
