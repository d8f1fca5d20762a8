"""The package's imports go one way (no cycle, module-level or inside functions; each layer of
jaxflow/__init__.py imports only itself and the layers below), no module is over 400 lines (the
synthetic scene generator excepted) and no function over 60. Read with `ast`, nothing is
imported."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).absolute().parent.parent / "jaxflow"
MAX_LINES = 400
LONG_ON_PURPOSE = {"jaxflow.data.synthetic"}  # the scene generator: one idea, many scenes
MAX_FUNCTION_LINES = 60  # from its def line to its last (decorators not counted)
# Functions allowed over MAX_FUNCTION_LINES, each with why (dotted: module.Class.function).
LONG_FUNCTIONS = {}
# jaxflow's layers, lowest first: a unit (a subpackage, or a top-level module) may import its own
# modules and the units of lower layers; units of one layer never import each other.
LAYERS = (
  ("jaxflow", "jaxflow.errors"),
  ("jaxflow.configs", "jaxflow.runtime"),
  ("jaxflow.geometry",),
  ("jaxflow.data", "jaxflow.network"),
  ("jaxflow.lidar", "jaxflow.viz", "jaxflow.refine"),  # refine: the methods' engines
  ("jaxflow.methods",),  # the lidar method runs jaxflow.lidar's pipeline
  ("jaxflow.evaluation",),
  ("jaxflow.training",),
  ("jaxflow.cli", "jaxflow.inference"),
  ("jaxflow.predict_log",),  # predict on a list of sweeps
  ("jaxflow.predict", "jaxflow.evaluate", "jaxflow.train", "jaxflow.summary", "jaxflow.import_pvraft"),
  ("jaxflow.nsfp",),  # predict with another default
)



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


def unit(module: str) -> str:
  """The layer unit of a module: jaxflow.X for jaxflow.X.anything."""
  return ".".join(module.split(".")[:2])


def layer_violations(graph, layers=LAYERS) -> list[str]:
  """"a -> b" for every import of a unit of the same or a higher layer than the importer's (and
  "a: no layer" for a unit the layers do not name)."""
  rank = {u: i for i, layer in enumerate(layers) for u in layer}
  found = []
  for a in sorted(graph):
    if unit(a) not in rank:
      found.append(f"{a}: no layer")
      continue
    for b in sorted(graph[a]):
      if unit(b) != unit(a) and rank.get(unit(b), len(layers)) >= rank[unit(a)]:
        found.append(f"{a} -> {b}")
  return found


def test_layer_check_finds_imports_up_and_across(tmp_path):
  """The check itself: an import of a higher layer, one across a layer and an unnamed unit."""
  pkg = tmp_path / "jaxflow"
  for sub in ("geometry", "lidar", "methods"):
    (pkg / sub).mkdir(parents=True)
    (pkg / sub / "__init__.py").write_text("")
  (pkg / "__init__.py").write_text("")
  (pkg / "geometry" / "rigid.py").write_text("def f():\n  from jaxflow.lidar import ego\n")
  (pkg / "lidar" / "ego.py").write_text("from jaxflow.geometry import rigid\nfrom jaxflow.methods import bodies\n")
  (pkg / "methods" / "bodies.py").write_text("from jaxflow.geometry import rigid\n")
  (pkg / "stray.py").write_text("")
  layers = (("jaxflow",), ("jaxflow.geometry",), ("jaxflow.methods", "jaxflow.lidar"))
  assert layer_violations(import_graph(pkg), layers) == [
    "jaxflow.geometry.rigid -> jaxflow.lidar.ego", "jaxflow.lidar.ego -> jaxflow.methods.bodies",
    "jaxflow.stray: no layer"]


def test_imports_go_down_the_layers():
  assert layer_violations(import_graph()) == []


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
  assert "jaxflow.training.trainer" in graph and "jaxflow.data.registry" in graph
  assert cycles(graph) == []


def test_no_module_over_400_lines():
  lines = {name: len(path.read_text().splitlines()) for name, path in modules().items()}
  too_long = {n: c for n, c in lines.items() if c > MAX_LINES
              and n not in LONG_ON_PURPOSE}
  assert too_long == {}


def long_functions(files: dict[str, Path]) -> dict[str, int]:
  """{module.Class.function: lines} of every function (methods and nested ones included) over
  MAX_FUNCTION_LINES in `files` ({dotted module name: file})."""
  found = {}

  def visit(node, prefix):
    for child in ast.iter_child_nodes(node):
      name = prefix
      if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        name = f"{prefix}.{child.name}"
        lines = child.end_lineno - child.lineno + 1
        if not isinstance(child, ast.ClassDef) and lines > MAX_FUNCTION_LINES:
          found[name] = lines
      visit(child, name)

  for module, path in files.items():
    visit(ast.parse(path.read_text(), str(path)), module)
  return found


def test_long_function_check_finds_functions_methods_and_nested_ones(tmp_path):
  """The check itself: a 61-line function, method and nested function are found, a 60-line one
  is not."""
  body = lambda n: "".join(f"  x{i} = {i}\n" for i in range(n - 1))
  (tmp_path / "m.py").write_text(
    f"def ok():\n{body(60)}def long():\n{body(61)}class C:\n  def method(self):\n"
    + body(61).replace("  ", "    ") + "def outer():\n  def inner():\n"
    + body(61).replace("  ", "    ") + "  return inner\n")
  assert long_functions({"m": tmp_path / "m.py"}) == {
    "m.long": 61, "m.C.method": 61, "m.outer": 63, "m.outer.inner": 61}


def test_no_function_over_60_lines():
  files = {**modules(), **{p.stem: p for p in (PACKAGE.parent / "train.py",
                                               PACKAGE.parent / "evaluate.py")}}
  too_long = {n: c for n, c in long_functions(files).items() if n not in LONG_FUNCTIONS}
  assert too_long == {}


# Imports with an effect on the importer, each checked in a fresh process: matplotlib's backend
# chosen (a notebook's inline plots lost), absl flags defined (a tool's flags clash with the
# importer's), environment variables set (XLA_FLAGS read by a backend started later), jax's
# config changed (x64, a compilation cache, matmul precision), handlers added to the root logger
# (every library's log lines printed twice). The child imports the third-party packages first,
# records their state, then forks once per module (each module imported into a fresh copy).
SIDE_EFFECTS = r"""
import json, logging, os, sys, warnings
import absl.app, absl.flags, absl.logging, matplotlib  # absl.app and logging define their flags
import jax, flax, optax, numpy, ml_collections, orbax.checkpoint, scipy.spatial  # noqa: F401
# (third-party: paid once before the forks; orbax defines absl flags of its own at import)
backend = dict.__getitem__(matplotlib.rcParams, "backend")
flags = sorted(absl.flags.FLAGS)
environ = dict(os.environ)
config = {k: repr(v) for k, v in jax.config.values.items()}
handlers = list(logging.getLogger().handlers)
showwarning = warnings.showwarning
found = {}
for name in sys.argv[1:]:
  read, write = os.pipe()
  pid = os.fork()
  if pid == 0:
    os.close(read)
    try:
      __import__(name)
      got = {"backend": str(dict.__getitem__(matplotlib.rcParams, "backend"))
                        if dict.__getitem__(matplotlib.rcParams, "backend") is not backend else None,
             "flags": sorted(set(absl.flags.FLAGS) - set(flags)),
             "environ": sorted(k for k in set(os.environ) | set(environ)
                               if os.environ.get(k) != environ.get(k)),
             "config": sorted(k for k, v in jax.config.values.items() if config.get(k) != repr(v)),
             "handlers": [repr(h) for h in logging.getLogger().handlers if h not in handlers],
             "showwarning": warnings.showwarning is not showwarning}
    except Exception as e:  # noqa: BLE001
      got = {"error": f"{type(e).__name__}: {e}"}
    os.write(write, json.dumps(got).encode())
    os._exit(0)
  os.close(write)
  with os.fdopen(read) as f:
    found[name] = json.loads(f.read() or '{"error": "no report"}')
  os.waitpid(pid, 0)
print(json.dumps(found))
"""
def test_importing_a_module_changes_nothing_of_the_importer():
  import json
  import os
  import subprocess
  import sys

  names = sorted(modules())
  env = {**os.environ, "PYTHONPATH": str(PACKAGE.parent), "JAX_PLATFORMS": "cpu"}
  done = subprocess.run([sys.executable, "-c", SIDE_EFFECTS, *names], capture_output=True,
                        text=True, timeout=600, env=env, cwd=PACKAGE.parent)
  assert done.returncode == 0, done.stderr[-3000:]
  found = json.loads(done.stdout.strip().splitlines()[-1])
  assert set(found) == set(names)
  errors = {n: r["error"] for n, r in found.items() if "error" in r}
  assert errors == {}
  effects = {n: r for n, r in found.items()
             if r["backend"] is not None or any(r[k] for k in r if k != "backend")}
  assert effects == {}, effects


def test_the_side_effect_check_can_fail(tmp_path):
  """The same child on a module that sets an environment variable, jax's config and a root
  logger handler: each is reported."""
  import json
  import os
  import subprocess
  import sys

  (tmp_path / "noisy.py").write_text(
    "import logging, os, jax\nos.environ['XLA_FLAGS'] = '--xla_dump_to=/tmp'\n"
    "jax.config.update('jax_enable_x64', True)\nlogging.getLogger().addHandler(logging.StreamHandler())\n")
  env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{PACKAGE.parent}", "JAX_PLATFORMS": "cpu"}
  done = subprocess.run([sys.executable, "-c", SIDE_EFFECTS, "noisy"], capture_output=True,
                        text=True, timeout=300, env=env)
  assert done.returncode == 0, done.stderr[-3000:]
  got = json.loads(done.stdout.strip().splitlines()[-1])["noisy"]
  assert got["environ"] == ["XLA_FLAGS"] and "jax_enable_x64" in got["config"] and got["handlers"]


def test_a_point_file_reader_imports_neither_h5py_nor_the_scene_generator():
  import os
  import subprocess
  import sys

  code = ("import sys\n"
          "from jaxflow.data.pointfiles import read_points\n"
          "assert 'h5py' not in sys.modules and 'jaxflow.data.synthetic' not in sys.modules\n"
          "from jaxflow.data import open_dataset\n"
          "print(len(open_dataset('synthetic_lidar:2', split='val')))\n")
  env = {**os.environ, "PYTHONPATH": str(PACKAGE.parent)}
  done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                        env=env)
  assert done.returncode == 0 and done.stdout.strip() == "2", done.stderr[-2000:]
