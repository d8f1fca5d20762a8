"""The package's imports go one way (no cycle, module-level or inside functions) and no module is
over 400 lines (the synthetic scene generator excepted). Read with `ast`, nothing is imported."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).absolute().parent.parent / "jaxflow"
MAX_LINES = 400
LONG_ON_PURPOSE = {"jaxflow.data.synthetic"}  # the scene generator: one idea, many scenes



def modules(package: Path = PACKAGE) -> dict[str, Path]:
  """{dotted module name: file} of every module of the package (a package is its __init__.py)."""
  found = {}
  for path in sorted(package.rglob("*.py")):
    parts = path.relative_to(package.parent).with_suffix("").parts
    found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
  return found


def imports(name: str, path: Path, known) -> set[str]:
  """The package modules `path` imports anywhere in it (`from jaxflow.x import y` names the module
  jaxflow.x.y when that is a module, else jaxflow.x)."""
  package = name if path.name == "__init__.py" else name.rpartition(".")[0]
  found = set()
  for node in ast.walk(ast.parse(path.read_text(), str(path))):
    if isinstance(node, ast.Import):
      found |= {a.name for a in node.names}
    elif isinstance(node, ast.ImportFrom):
      base = node.module or ""
      if node.level:  # relative: from . import x, from .y import z
        anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
        base = ".".join(anchor + ([base] if base else []))
      for alias in node.names:
        found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base)
  return {m for m in found if m in known and m != name}


def import_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
  known = modules(package)
  return {name: imports(name, path, known) for name, path in known.items()}


def cycles(graph) -> list[list[str]]:
  """The strongly connected components with more than one module (Tarjan), each sorted."""
  index, low, stack, on_stack, found = {}, {}, [], set(), []

  def visit(v):
    index[v] = low[v] = len(index)
    stack.append(v)
    on_stack.add(v)
    for w in sorted(graph[v]):
      if w not in index:
        visit(w)
        low[v] = min(low[v], low[w])
      elif w in on_stack:
        low[v] = min(low[v], index[w])
    if low[v] == index[v]:
      component = []
      while True:
        w = stack.pop()
        on_stack.discard(w)
        component.append(w)
        if w == v:
          break
      if len(component) > 1:
        found.append(sorted(component))

  for v in sorted(graph):
    if v not in index:
      visit(v)
  return found


def test_cycle_finder_finds_cycles_through_function_level_imports(tmp_path):
  """The reader itself: a function-level import back up is a cycle; relative imports resolve."""
  pkg = tmp_path / "jaxflow"
  (pkg / "sub").mkdir(parents=True)
  (pkg / "__init__.py").write_text("")
  (pkg / "a.py").write_text("from jaxflow import b\n")
  (pkg / "b.py").write_text("def f():\n  from jaxflow.sub import c\n")
  (pkg / "sub" / "__init__.py").write_text("")
  (pkg / "sub" / "c.py").write_text("def g():\n  from .. import a\n")
  (pkg / "d.py").write_text("import jaxflow.b\n")
  graph = import_graph(pkg)
  assert graph["jaxflow.b"] == {"jaxflow.sub.c"} and graph["jaxflow.sub.c"] == {"jaxflow.a"}
  assert cycles(graph) == [["jaxflow.a", "jaxflow.b", "jaxflow.sub.c"]]


def test_no_import_cycle():
  graph = import_graph()
  assert "jaxflow.training" in graph and "jaxflow.data.registry" in graph
  assert cycles(graph) == []


def test_no_module_over_400_lines():
  lines = {name: len(path.read_text().splitlines()) for name, path in modules().items()}
  too_long = {n: c for n, c in lines.items() if c > MAX_LINES
              and n not in LONG_ON_PURPOSE}
  assert too_long == {}
