"""The tests' way to run a command (predict, evaluate.py, train.py, ...) in the test's own process
(jaxflow.cli.call): what a subprocess would print and exit with, without its jax import, its
trace of the model and its compiles (shared with the other tests of the process).

    done = commands.run(predict.run, pc1, pc2, "--out", out)   # a subprocess.CompletedProcess
    assert done.returncode == 0, done.stderr

Tests that need the process boundary itself keep a real subprocess, each saying why.
"""

import contextlib
import io
import os
import subprocess

from jaxflow import cli


def run(command, *args, cwd=None, prog=None) -> subprocess.CompletedProcess:
  """`command` (a console-script function such as jaxflow.predict.run) on `args`, in this process,
  with its stdout and stderr captured; `cwd`: the working directory it runs in."""
  stdout, stderr = io.StringIO(), io.StringIO()
  argv = [str(a) for a in args]
  with contextlib.ExitStack() as stack:
    if cwd is not None:
      stack.enter_context(contextlib.chdir(cwd))
    stack.enter_context(contextlib.redirect_stdout(stdout))
    stack.enter_context(contextlib.redirect_stderr(stderr))
    code = cli.call(command, argv, prog=prog and str(prog))
  return subprocess.CompletedProcess(argv, code, stdout.getvalue(), stderr.getvalue())


def script(name: str) -> str:
  """The path of the repository's script NAME (train.py, evaluate.py), the program name that
  `python NAME` would give the command."""
  return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), name)
