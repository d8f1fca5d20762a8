"""Host memory kept for reuse (jaxflow.runtime.host_memory): with it, a freed block's pages serve the next
allocation (no fresh page faults, counted by the kernel); train keeps by default, the other
commands release; --host_memory, else $JAXFLOW_HOST_MEMORY, decides; a bad value is one line."""

import json
import os
import subprocess
import sys

import pytest

from jaxflow.runtime import host_memory

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BLOCK = 128 * 2**20  # bytes: far above glibc's largest mmap threshold (32 MiB)
PAGES = BLOCK // 4096

# Allocates, writes and frees one block four times with libc itself (no numpy: it asks the kernel
# for huge pages), printing the minor page faults of rounds 2-4. `how`: "keep" calls
# host_memory.keep() first, "cli" runs the probe as the main of a command whose default is argv[2]
# (jaxflow.cli's flags).
PROBE = """
import ctypes, ctypes.util, json, resource, sys
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]

def probe(argv=None):
  faults = []
  for _ in range(4):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = libc.malloc({block})
    ctypes.memset(block, 1, {block})
    libc.free(block)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
  print("FAULTS " + json.dumps(faults[1:]))

how = sys.argv[1]
if how == "keep":
  from jaxflow.runtime import host_memory
  print("NOTE", host_memory.keep())
if how == "cli":  # the probe as a command's main; argv: the command's default, then its flags
  from jaxflow import cli
  default, sys.argv = sys.argv[2], ["probe"] + sys.argv[3:]
  cli.run(probe, host_memory_default=default)
else:
  probe()
""".format(block=BLOCK)

glibc_only = pytest.mark.skipif(host_memory._glibc_mallopt() is None, reason="not glibc")


def _faults(how, *args, env=None):
  """(returncode, faults of rounds 2-4 or None, stderr) of the probe in a new process."""
  env = {**{k: v for k, v in os.environ.items() if k != host_memory.ENV},
         "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
         "JAX_PLATFORMS": "cpu", **(env or {})}
  proc = subprocess.run([sys.executable, "-c", PROBE, how, *args], env=env, capture_output=True,
                        text=True, timeout=300, check=False)
  line = next((l for l in proc.stdout.splitlines() if l.startswith("FAULTS ")), None)
  return proc.returncode, None if line is None else json.loads(line[7:]), proc.stderr


@glibc_only
def test_kept_memory_is_reused_without_fresh_pages():
  code, released, _ = _faults("plain")
  assert code == 0 and min(released) > PAGES // 2  # every round faults its block in afresh
  code, kept, _ = _faults("keep")
  assert code == 0 and max(kept) < PAGES // 50  # the first round's pages serve the next


@glibc_only
def test_the_flag_then_the_variable_then_the_commands_default_decide():
  kept_ = lambda faults: max(faults) < PAGES // 50
  released_ = lambda faults: min(faults) > PAGES // 2
  for args, env, default, expect in [((), {}, "release", released_), ((), {}, "keep", kept_),
                                     ((), {host_memory.ENV: "keep"}, "release", kept_),
                                     (("--host_memory", "release"), {host_memory.ENV: "keep"},
                                      "keep", released_)]:
    code, faults, err = _faults("cli", default, *args, env=env)
    assert code == 0 and expect(faults), (args, env, default, faults, err)


def test_train_keeps_by_default_predict_and_evaluate_release(monkeypatch):
  from jaxflow import cli, evaluate, predict, train  # pylint: disable=import-outside-toplevel
  seen = {}
  monkeypatch.setattr(cli, "run", lambda main, *a, **kw: seen.update(
    {main.__module__: kw.get("host_memory_default", "release")}))
  for command in (train, predict, evaluate):
    command.run()
  assert seen == {"jaxflow.train": "keep", "jaxflow.predict": "release",
                  "jaxflow.evaluate": "release"}


def test_a_bad_setting_is_one_line_naming_where_it_came_from(monkeypatch):
  code, faults, err = _faults("cli", "release", env={host_memory.ENV: "hold"})
  assert code == 2 and faults is None
  assert err.strip().splitlines()[-1].endswith(
    "JAXFLOW_HOST_MEMORY must be one of keep, release, got 'hold'"), err
  code, faults, err = _faults("cli", "release", "--host_memory", "hold")
  assert code == 2 and faults is None and "host_memory" in err and "Traceback" not in err
  monkeypatch.setenv(host_memory.ENV, "release")
  assert host_memory.choice() == "release" and host_memory.choice("keep") == "keep"
  monkeypatch.delenv(host_memory.ENV)
  assert host_memory.choice() == "keep"
  with pytest.raises(ValueError, match="--host_memory must be one of keep, release, got 'x'"):
    host_memory.choice("x")
