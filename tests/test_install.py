"""A plain (non-editable) `pip install .` into a fresh virtual environment works from any folder:
predict with the shipped checkpoint, evaluate, the console scripts and the README's first Python
block, each run from an empty temporary folder, with jaxflow imported from the fresh install.

Nothing is downloaded: the fresh venv sees this environment's packages through a .pth file (the
dependencies are reused, `--no-deps`), and the wheel is built with this environment's setuptools
(`--no-build-isolation`) when it can build wheels (setuptools >= 70.1 or the `wheel` package, as
the dev extra installs); otherwise pip builds it in isolation, which fetches setuptools alone.
"""

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).absolute().parent.parent


def _env():
  env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
  return dict(env, JAX_PLATFORMS="cpu", PIP_DISABLE_PIP_VERSION_CHECK="1",
              PIP_NO_WARN_SCRIPT_LOCATION="1", PYTHONDONTWRITEBYTECODE="1")


def _can_build_wheels() -> bool:
  import setuptools  # pylint: disable=import-outside-toplevel

  version = tuple(int(p) for p in re.findall(r"\d+", setuptools.__version__)[:2])
  return version >= (70, 1) or importlib.util.find_spec("wheel") is not None


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
  """(python of a fresh venv holding a non-editable install of this tree, an empty folder)."""
  root = tmp_path_factory.mktemp("install")
  src = root / "src"  # only what the build reads: the tree stays clean (no build/, no egg-info)
  src.mkdir()
  for name in ("pyproject.toml", "README.md"):
    shutil.copy(REPO / name, src / name)
  shutil.copytree(REPO / "jaxflow", src / "jaxflow",
                  ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
  venv = root / "venv"
  subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
  python = venv / "bin" / "python"
  site = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        capture_output=True, text=True, check=True).stdout.strip()
  here = sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]})
  Path(site, "_jaxflow_test_parent_env.pth").write_text("\n".join(here) + "\n")
  isolation = ["--no-build-isolation"] if _can_build_wheels() else []
  proc = subprocess.run([python, "-m", "pip", "install", "-q", "--no-deps", *isolation, str(src)],
                        capture_output=True, text=True, env=_env(), timeout=300)
  assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
  work = root / "work"
  work.mkdir()
  return python, work


def _run(argv, cwd, timeout=300):
  return subprocess.Popen([str(a) for a in argv], cwd=cwd, env=_env(), stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)


def _wait(proc, timeout=300):
  out, err = proc.communicate(timeout=timeout)
  assert proc.returncode == 0, f"{proc.args}\n{out[-2000:]}\n{err[-3000:]}"
  return out, err


def _readme_block() -> str:
  text = (REPO / "README.md").read_text()
  return re.search(r"```python\n(.*?)```", text, re.S).group(1)


def test_fresh_install_runs_from_any_folder(fresh):
  python, work = fresh
  venv = python.parent.parent
  where = _wait(_run([python, "-c", "import jaxflow; print(jaxflow.__file__)"], work))[0].strip()
  assert Path(where).is_relative_to(venv) and not Path(where).is_relative_to(REPO), where
  rng = np.random.default_rng(0)
  pc1 = rng.uniform([-4, -1, 4], [4, 1, 20], (200, 3)).astype(np.float32)
  np.save(work / "a.npy", pc1)
  np.save(work / "b.npy", pc1 + np.float32([0.3, 0.0, 0.5]))
  bin_dir = python.parent
  procs = {  # in parallel: each is mostly one compilation
    "predict": _run([python, "-m", "jaxflow.predict", "a.npy", "b.npy", "--out", "f.npy",
                     "--iters", "2"], work),
    "evaluate": _run([bin_dir / "jaxflow-evaluate", "--dataset", "synthetic_lidar:1", "--json",
                      "e.json", "--config.eval.num_points=64", "--config.eval.num_iters=2"], work),
    "readme": _run([python, "-c", _readme_block()], work),
  }
  out, err = _wait(_run([bin_dir / "jaxflow-train", "--config", "configs/default.py:smoke",
                         "--print_config"], work))
  assert "config.train.batch_size = 2  # pairs per step" in out, err
  out, err = _run([bin_dir / "jaxflow-predict", "--help"], work).communicate(timeout=300)
  assert "--out:" in out + err and "print_config:" in out + err  # absl's --help exits with 1
  results = {name: _wait(proc) for name, proc in procs.items()}
  flow = np.load(work / "f.npy")
  assert flow.shape == (200, 3) and np.isfinite(flow).all()
  assert str(venv) in results["predict"][1]  # the shipped checkpoint of the fresh install
  evaluated = json.loads((work / "e.json").read_text())
  assert Path(evaluated["checkpoint"]).is_relative_to(venv) and evaluated["pairs"] == 1
  assert np.isfinite(evaluated["epe"])
  assert sorted(p.name for p in work.iterdir()) == ["a.npy", "b.npy", "e.json", "f.npy"]


def test_readme_states_the_commands_ci_runs():
  readme, ci = (REPO / "README.md").read_text(), (REPO / ".ci" / "run").read_text()
  assert 'python -m pip install -q -e ".[dev]"' in ci and "\npython -m pytest -q\n" in ci
  assert 'python3 -m pip install -e ".[dev]" && python3 -m pytest -q' in readme
