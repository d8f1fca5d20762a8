"""A plain (non-editable) `pip install .` WITH its dependencies into a fresh virtual environment, as a
user does: the declared dependencies alone must run every module, the README's commands and its
Python block, each run from an empty folder, with jaxflow imported from the fresh install.

The venv sees nothing of this environment (no .pth, no --no-deps): pip resolves pyproject.toml's
dependencies from the package index it is configured with. The releases are constrained to the ones
this environment has (`name==version` of every installed distribution): the same code the rest of
the suite runs against, and what pip's cache (or a local mirror) holds, so nothing large is
downloaded twice (about a minute here). Where the index cannot be reached the test skips, saying so.
"""

import importlib.metadata
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).absolute().parent.parent
OFFLINE = ("NewConnectionError", "Failed to establish a new connection", "Name or service not known",
           "Temporary failure in name resolution", "Network is unreachable")


def _env():
  env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
  return dict(env, JAX_PLATFORMS="cpu", PIP_DISABLE_PIP_VERSION_CHECK="1",
              PIP_NO_WARN_SCRIPT_LOCATION="1", PYTHONDONTWRITEBYTECODE="1")


def _constraints(path: Path) -> Path:
  """name==version of this environment's distributions (jaxflow itself left out)."""
  pins = {}
  for dist in importlib.metadata.distributions():
    name = dist.metadata["Name"]
    if name and name.lower() != "jaxflow" and re.fullmatch(r"[\w.!+-]+", dist.version):
      pins.setdefault(name.lower(), f"{name}=={dist.version}")
  path.write_text("\n".join(sorted(pins.values())) + "\n")
  return path


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
  """(python of a fresh venv holding a non-editable install of this tree, an empty folder)."""
  root = tmp_path_factory.mktemp("install")
  src = root / "src"  # the tree a clone has, tests and their data included (they must not ship)
  src.mkdir()
  for name in ("pyproject.toml", "README.md"):
    shutil.copy(REPO / name, src / name)
  for name in ("jaxflow", "tests"):
    shutil.copytree(REPO / name, src / name,
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info"))
  venv = root / "venv"
  subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=1200)
  python = venv / "bin" / "python"
  proc = subprocess.run(
    [python, "-m", "pip", "install", "-q", "--timeout", "30", "--retries", "2",
     "-c", _constraints(root / "constraints.txt"), str(src)],
    capture_output=True, text=True, env=_env(), timeout=1200)
  if proc.returncode and any(s in proc.stdout + proc.stderr for s in OFFLINE):
    pytest.skip("the package index is unreachable: the declared dependencies are not checked")
  assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
  work = root / "work"
  work.mkdir()
  return python, work


def _run(argv, cwd):
  return subprocess.Popen([str(a) for a in argv], cwd=cwd, env=_env(), stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)


def _wait(proc, timeout=1200, returncode=0):
  out, err = proc.communicate(timeout=timeout)
  assert proc.returncode == returncode, f"{proc.args}\n{out[-2000:]}\n{err[-3000:]}"
  return out, err


def _readme_block() -> str:
  text = (REPO / "README.md").read_text()
  return re.search(r"```python\n(.*?)```", text, re.S).group(1)


def _readme_predict_commands() -> list[list[str]]:
  """The README's `python3 -m jaxflow.predict ...` lines, comments cut, as argument lists."""
  text = (REPO / "README.md").read_text()
  lines = re.findall(r"^    python3? -m jaxflow\.predict (.*?)(?:\s+#.*)?$", text, re.M)
  return [line.split() for line in lines]


def _write_inputs(work: Path) -> dict:
  """The README's input files, written from their documented layouts (not by jaxflow), each pair
  in its own folder (both commands write flow.npy): {first file: (its points, the true motion)}."""
  rng = np.random.default_rng(0)
  (work / "sweeps").mkdir()
  from jaxflow.data import synthetic_sweep  # pylint: disable=import-outside-toplevel
  raw = synthetic_sweep.sweep_pair("val", 1)  # z up, 360 degrees, ground kept, ego-motion
  sweep1, ground_ego = raw.pc1, np.median(raw.ego_flow[raw.ground], axis=0)
  for name, xyz in (("sweep1.bin", raw.pc1), ("sweep2.bin", raw.pc2)):
    table = np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype("<f4")  # KITTI: x y z intensity
    (work / "sweeps" / name).write_bytes(table.tobytes())
  (work / "clouds").mkdir()
  pc1 = rng.uniform([-4, -1, 4], [4, 1, 20], (300, 3)).astype(np.float32)
  shift = np.float32([0.3, 0.0, 0.5])
  for name, xyz in (("pc1.ply", pc1), ("pc2.ply", pc1 + shift)):  # binary little-endian PLY
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    (work / "clouds" / name).write_bytes(header.encode() + xyz.astype("<f4").tobytes())
  return {"sweep1.bin": (work / "sweeps", sweep1, ground_ego, raw.ground),
          "pc1.ply": (work / "clouds", pc1, shift, None)}


@pytest.mark.slow
def test_fresh_install_runs_the_documented_commands(fresh):
  python, work = fresh
  venv, bin_dir = python.parent.parent, python.parent
  # The dependencies pip installed agree with each other, and the wheel ships no tests or test data.
  _wait(_run([python, "-m", "pip", "check"], work))
  files = _wait(_run([python, "-m", "pip", "show", "-f", "jaxflow"], work))[0]
  assert "jaxflow/predict.py" in files and "tests/" not in files and ".npz" not in files, files
  where = _wait(_run([python, "-c", "import jaxflow; print(jaxflow.__file__)"], work))[0].strip()
  assert Path(where).is_relative_to(venv) and not Path(where).is_relative_to(REPO), where
  inputs = _write_inputs(work)
  commands = _readme_predict_commands()
  assert [c[0] for c in commands] == ["sweep1.bin", "s0.bin", "pc1.ply", "pc1.ply"], commands
  # The log (s0.bin ...) and --method nsfp on the same clouds run in tests/test_docs.py.
  commands = [commands[0], commands[2]]
  every_module = ("import importlib, pkgutil, jaxflow\n"
                  "names = [m.name for m in pkgutil.walk_packages(jaxflow.__path__, 'jaxflow.')]\n"
                  "for name in names: importlib.import_module(name)\nprint(len(names))")
  procs = {  # in parallel: each is mostly imports and one compilation
    "modules": _run([python, "-c", every_module], work),  # an undeclared import fails here
    "readme": _run([python, "-c", _readme_block()], work),
    "evaluate": _run([bin_dir / "jaxflow-evaluate", "--dataset", "synthetic_lidar:1", "--json",
                      "e.json", "--config.eval.num_points=64", "--config.eval.num_iters=2"], work),
    **{argv[0]: _run([python, "-m", "jaxflow.predict", *argv], inputs[argv[0]][0])
       for argv in commands},
  }
  out, err = _wait(_run([bin_dir / "jaxflow-train", "--config", "configs/default.py:smoke",
                         "--print_config"], work))
  assert "config.train.batch_size = 2  # pairs per step" in out, err
  helps = {"jaxflow-predict": ["--out:", "--lidar:", "--columns:"],
           "jaxflow-evaluate": ["--dataset:", "--checkpoint:"], "jaxflow-train": ["--workdir:"]}
  for tool, flags in helps.items():
    out, err = _wait(_run([bin_dir / tool, "--help"], work))
    assert all(f in out + err for f in flags) and "print_config:" in out + err, (tool, out, err)
  out, _ = _wait(_run([python, "-m", "jaxflow.nsfp", "--help"], work))
  assert "--out" in out and "--columns" in out and "nsfp" in out, out

  results = {name: _wait(proc) for name, proc in procs.items()}
  assert int(results["modules"][0]) >= 50  # every module of the package imported
  # The README block prints the flow's shape and mean (the scene moved by (0.2, 0, 0.5) m).
  printed = re.fullmatch(r"\((\d+), (\d+)\) \[(.*)\]", results["readme"][0].strip())
  assert printed, results["readme"]
  mean = np.array(printed.group(3).split(), float)
  assert printed.group(1, 2) == ("2000", "3") and mean.shape == (3,) and np.isfinite(mean).all()
  print("README block:", results["readme"][0].strip())
  for first, (folder, pc1, motion, _) in inputs.items():
    flow = np.load(folder / "flow.npy")
    assert flow.shape == pc1.shape and np.isfinite(flow).all(), first
    if first == "sweep1.bin":  # a 360-degree sweep: no method runs, no checkpoint is read
      assert "no checkpoint loaded" in results[first][1], results[first][1]
    else:
      assert str(venv) in results[first][1]  # the shipped checkpoint of the fresh install
    print(first, "mean flow", flow.mean(axis=0), "true", motion)
  ego, ground = inputs["sweep1.bin"][2:]
  shift = inputs["pc1.ply"][2]
  # The ground moves with the sweep's true ego-motion (jaxflow.lidar.sweep's ICP).
  ground_flow = np.median(np.load(work / "sweeps" / "flow.npy")[ground], axis=0)
  np.testing.assert_allclose(ground_flow, ego, atol=0.02)
  # The clouds' command (predict's default method, optimise) recovers their translation.
  np.testing.assert_allclose(np.load(work / "clouds" / "flow.npy").mean(axis=0), shift, atol=0.02)
  assert (work / "clouds" / "view.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
  evaluated = json.loads((work / "e.json").read_text())
  assert Path(evaluated["checkpoint"]).is_relative_to(venv) and evaluated["pairs"] == 1
  assert np.isfinite(evaluated["epe"])
  assert sorted(p.name for p in work.rglob("*")) == [
    "clouds", "e.json", "flow.npy", "flow.npy", "pc1.ply", "pc2.ply", "sweep1.bin", "sweep2.bin",
    "sweeps", "view.png"]


def _declared(requirements) -> set:
  return {re.split(r"[<>=!~;\[ ]", r, maxsplit=1)[0].strip().lower().replace("_", "-")
          for r in requirements}


# Imported only inside the functions that need them, each declared in an extra: import_pvraft's
# PyTorch checkpoints (torch), the AV2 feather files (av2: pyarrow), the 3D viewer (viewer: plotly).
OPTIONAL = {"torch", "pyarrow", "plotly"}


def test_every_imported_package_is_declared():
  """Each third-party package jaxflow imports (at the top or lazily) is a declared dependency, or
  one of an extra's: found from the code's imports, not from what the install happens to pull in
  (jax alone brings numpy and scipy, which hid scipy's missing declaration)."""
  import ast
  import tomllib
  project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
  required = _declared(project["dependencies"])
  extras = _declared(r for reqs in project["optional-dependencies"].values() for r in reqs)
  distributions = importlib.metadata.packages_distributions()
  imported = {}
  for path in sorted((REPO / "jaxflow").rglob("*.py")):
    for node in ast.walk(ast.parse(path.read_text())):
      names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
               [node.module] if isinstance(node, ast.ImportFrom) and not node.level else [])
      for name in names:
        top = name.split(".")[0]
        if top not in sys.stdlib_module_names and top != "jaxflow":
          imported.setdefault(top, path.relative_to(REPO))
  assert {"jax", "scipy", "h5py", "orbax"} <= set(imported), imported  # the scan sees them
  for top, where in imported.items():
    dists = {d.lower().replace("_", "-") for d in distributions.get(top, [top])}
    assert dists & (required | extras), f"{where} imports {top} ({dists}): not in pyproject.toml"
    if top not in OPTIONAL:
      assert dists & required, f"{where} imports {top}: not a runtime dependency"


def test_readme_states_the_commands_ci_runs():
  readme, ci = (REPO / "README.md").read_text(), (REPO / ".ci" / "run").read_text()
  assert 'python -m pip install -q -e ".[dev]"' in ci and "\npython -m pytest -q\n" in ci
  assert "--durations=25" in (REPO / "pyproject.toml").read_text()  # the slowest tests in CI's log
  commands = ['python3 -m pip install -e ".[dev]"',
              'python3 -m pip install --no-deps "av2==0.3.6" "bucketed-scene-flow-eval==2.0.25"',
              "apt-get install -y chromium",
              "python3 -m pytest -q"]
  block = [line.split("  #")[0].rstrip() for line in readme.splitlines()]
  start = block.index(f"    {commands[0]}")
  assert block[start:start + len(commands)] == [f"    {c}" for c in commands]  # in CI's order
  assert "apt-get install -y -q chromium" in ci  # (as root, where apt-get exists)
  for command in commands[1:2]:  # each evaluator CI installs, pinned as the README says
    for package in command.split()[-2:]:
      assert f"--no-deps {package}" in ci, package
