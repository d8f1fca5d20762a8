"""The commands' persistent compilation cache (jaxflow.runtime.compile_cache): a second `predict` in a new
process compiles nothing; a corrupt entry or an unwritable folder costs one line, never an error."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from jaxflow.runtime import compile_cache

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# predict in a process that counts JAX's compilation-cache events and prints them at exit.
COUNTING = ("import atexit, collections, json, runpy, sys\n"
            "import jax.monitoring\n"
            "seen = collections.Counter()\n"
            "jax.monitoring.register_event_listener(lambda event, **_: seen.update([event]))\n"
            "atexit.register(lambda: print('EVENTS ' + json.dumps(seen), file=sys.stderr))\n"
            "sys.argv = ['jaxflow.predict'] + sys.argv[1:]\n"
            "runpy.run_module('jaxflow.predict', run_name='__main__')\n")


@pytest.fixture(scope="module")
def clouds(tmp_path_factory):
  d = tmp_path_factory.mktemp("pair")
  rng = np.random.default_rng(0)
  pc1 = rng.uniform(-2, 2, (200, 3)).astype(np.float32)
  np.save(d / "pc1.npy", pc1)
  np.save(d / "pc2.npy", pc1 + np.float32([0.1, 0.0, 0.05]))
  return d


def _predict(clouds, checkpoint, cache, out, *extra):
  """(returncode, stderr without the events line, programs compiled, cache hits)."""
  env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
         "JAX_PLATFORMS": "cpu"}
  proc = subprocess.run([sys.executable, "-c", COUNTING, clouds / "pc1.npy", clouds / "pc2.npy",
                         "--out", out, "--checkpoint", checkpoint, "--steps", "10",
                         "--compilation_cache", cache, *extra],
                        env=env, capture_output=True, text=True, timeout=900, check=False)
  lines = proc.stderr.splitlines()
  events = json.loads(next(l for l in lines if l.startswith("EVENTS "))[7:])
  asked = events.get("/jax/compilation_cache/compile_requests_use_cache", 0)
  hits = events.get("/jax/compilation_cache/cache_hits", 0)
  return proc.returncode, [l for l in lines if not l.startswith("EVENTS ")], asked - hits, hits


@pytest.mark.slow
def test_second_run_compiles_nothing_and_a_broken_cache_costs_one_line(clouds, smoke_checkpoint,
                                                                      tmp_path):
  cache = tmp_path / "xla"
  rc, err, compiled, _ = _predict(clouds, smoke_checkpoint, cache, tmp_path / "f1.npy")
  assert rc == 0, err
  assert compiled > 0 and any(cache.glob("*-cache"))
  rc, err, compiled, hits = _predict(clouds, smoke_checkpoint, cache, tmp_path / "f2.npy")
  assert rc == 0, err
  assert compiled == 0 and hits > 0  # the optimise method has no host callback in any program
  first = np.load(tmp_path / "f1.npy")
  np.testing.assert_array_equal(np.load(tmp_path / "f2.npy"), first)

  # The broken cache and the blocked folder with the network method (its few programs compiled
  # again, not optimise's dozens): its entries written first, then every entry cut short.
  network = ("--method", "network", "--iters", "2")
  rc, err, _, _ = _predict(clouds, smoke_checkpoint, cache, tmp_path / "f3.npy", *network)
  assert rc == 0, err
  reference = np.load(tmp_path / "f3.npy")
  for entry in cache.glob("*-cache"):
    entry.write_bytes(entry.read_bytes()[:20])
  rc, err, compiled, _ = _predict(clouds, smoke_checkpoint, cache, tmp_path / "f4.npy", *network)
  assert rc == 0 and compiled > 0, err
  notes = [l for l in err if "compilation cache" in l]
  assert len(notes) == 1 and "could not be read" in notes[0], err
  assert not any("Traceback" in l or "UserWarning" in l for l in err), err
  np.testing.assert_array_equal(np.load(tmp_path / "f4.npy"), reference)
  rc, err, compiled, _ = _predict(clouds, smoke_checkpoint, cache, tmp_path / "f5.npy", *network)
  assert rc == 0 and compiled == 0, err  # the broken entries were written again

  blocked = tmp_path / "a_file"
  blocked.write_text("not a folder")
  rc, err, compiled, _ = _predict(clouds, smoke_checkpoint, blocked / "xla", tmp_path / "f6.npy",
                                  *network)
  assert rc == 0, err
  notes = [l for l in err if "compilation cache" in l]
  assert len(notes) == 1 and "cannot be written" in notes[0] and str(blocked) in notes[0], err
  np.testing.assert_array_equal(np.load(tmp_path / "f6.npy"), reference)


CONFIG = ("jax_enable_compilation_cache", "jax_compilation_cache_dir",
          "jax_persistent_cache_min_compile_time_secs")


def test_folder_choice(monkeypatch, tmp_path):
  import warnings  # pylint: disable=import-outside-toplevel

  import jax  # pylint: disable=import-outside-toplevel
  from jax.experimental.compilation_cache import compilation_cache  # pylint: disable=import-outside-toplevel

  before = {name: getattr(jax.config, name) for name in CONFIG}
  monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)
  try:
    monkeypatch.setenv(compile_cache.ENV, str(tmp_path / "from_env"))
    assert compile_cache.enable(None) is None
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "from_env")
    assert (tmp_path / "from_env").is_dir()
    assert compile_cache.enable(str(tmp_path / "from_flag")) is None  # the flag wins
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "from_flag")
    monkeypatch.setenv(compile_cache.ENV, "off")
    assert compile_cache.enable(None) is None and not jax.config.jax_enable_compilation_cache
    monkeypatch.delenv(compile_cache.ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    jax.config.update("jax_compilation_cache_dir", None)
    assert compile_cache.default_dir() == str(tmp_path / "xdg" / "jaxflow" / "xla")
    jax.config.update("jax_compilation_cache_dir", "/somewhere/set")  # JAX's own setting
    assert compile_cache.default_dir() == "/somewhere/set"
  finally:
    for name, value in before.items():
      jax.config.update(name, value)
    compilation_cache.reset_cache()
