"""The model-API example of docs/network.md runs as it is written (users paste it first)."""

import contextlib
import io
import re
from pathlib import Path

DOC = Path(__file__).absolute().parent.parent / "docs" / "network.md"


def test_network_doc_python_block_runs_as_written():
  (block,) = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
  printed = io.StringIO()
  with contextlib.redirect_stdout(printed):
    exec(compile(block, str(DOC), "exec"), {})  # pylint: disable=exec-used
  assert printed.getvalue().strip() == "(1, 8, 256, 3) (1, 256, 3)"
