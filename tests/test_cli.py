"""jaxflow.cli: a user's mistake is one line on stderr and exit code 2; a bug keeps its traceback."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from jaxflow import cli
from jaxflow.errors import CheckpointError

REPO = Path(__file__).absolute().parent.parent


def python(*args, script=None):
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
  argv = [sys.executable, "-c", script] if script else [sys.executable, *args]
  return subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)


def assert_one_line_error(proc, *needles):
  assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
  lines = proc.stderr.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr[-2000:]
  for needle in needles:
    assert needle in lines[0]


def test_guard_prints_one_line_and_exits_2(capsys):
  def main(path):
    raise CheckpointError(f"{path}: truncated\nsecond line")

  with pytest.raises(SystemExit) as info:
    cli.guard(main, "/x/ckpt")
  assert info.value.code == 2
  assert capsys.readouterr().err == "error: /x/ckpt: truncated second line\n"


def test_guard_passes_results_and_bugs_through():
  assert cli.guard(lambda a, b=0: a + b, 1, b=2) == 3
  with pytest.raises(ZeroDivisionError):
    cli.guard(lambda: 1 / 0)


ABSL_MAIN = textwrap.dedent("""
  from absl import flags
  from jaxflow import cli
  from jaxflow.errors import ConfigError
  _N = flags.DEFINE_integer("n", 1, "a number")
  def main(argv):
    if _N.value < 0:
      raise ConfigError(f"--n must be >= 0, got {_N.value}")
    print("n =", _N.value)
  cli.run(main)
""")


def test_run_with_absl_flags():
  proc = python(script=ABSL_MAIN + "\n")
  assert proc.returncode == 0 and proc.stdout == "n = 1\n"
  assert_one_line_error(python("-c", ABSL_MAIN, "--n=-3"), "--n must be >= 0, got -3")
  assert_one_line_error(python("-c", ABSL_MAIN, "--n=abc"), "abc")  # a flag parsing error


def test_train_py_user_errors_are_one_line(tmp_path):
  assert_one_line_error(
    python("train.py", "--config", "configs/default.py:smoke", "--workdir", tmp_path,
           "--config.data.dataset=nosuchformat:/x"),
    "nosuchformat",
  )
  assert_one_line_error(
    python("train.py", "--config", "configs/nosuch.py", "--workdir", tmp_path), "nosuch.py"
  )
  assert_one_line_error(
    python("train.py", "--config", "configs/default.py:smoke", "--workdir", tmp_path,
           "--config.train.stage=3"),
    "config.train.stage must be 1 or 2",
  )
  assert_one_line_error(
    python("train.py", "--config", "configs/default.py:smoke", "--workdir", tmp_path,
           "--config.train.nosuch=3"),
    "unknown config field 'nosuch' in --config.train.nosuch=3",
  )
  assert_one_line_error(
    python("train.py", "--config", "configs/default.py:bogus", "--workdir", tmp_path), "bogus"
  )
