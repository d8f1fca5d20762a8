"""JAX's persistent compilation cache for the commands: a program compiled by one run of predict,
evaluate.py or train.py is read back by the next instead of being compiled again.

    note = compile_cache.enable(None)   # before the first compilation; None: the default folder

The folder is `--compilation_cache DIR`, else $JAXFLOW_COMPILATION_CACHE, else JAX's own setting
(`jax_compilation_cache_dir`, e.g. $JAX_COMPILATION_CACHE_DIR), else ~/.cache/jaxflow/xla
($XDG_CACHE_HOME/jaxflow/xla where that is set). The value `off` (flag or variable) turns it off.
A folder that cannot be written turns it off too, with one note; an entry that cannot be read (a
truncated or foreign file) is compiled again and rewritten, with one line on stderr, never an error.
Every program is cached whatever its compile time (JAX's default skips those under a second, which
are most of a small pair's). Nothing is evicted (JAX's size bound evicts under a file lock that
concurrent runs sharing a folder trip over): the folder grows with each new cloud size a method
sees, and deleting it is always safe. Programs that call back to the host (a k-d tree inside jit)
are never cached by JAX; jaxflow's methods compile none (docs/methods.md).
"""

import os
import pathlib
import sys
import tempfile
import warnings

import jax
from jax.experimental.compilation_cache import compilation_cache

ENV = "JAXFLOW_COMPILATION_CACHE"
OFF = "off"
_UNREADABLE = "Error reading persistent compilation cache entry"
_UNWRITABLE = "Error writing persistent compilation cache entry"


def default_dir() -> str:
  """The folder used when neither the flag nor $JAXFLOW_COMPILATION_CACHE names one."""
  if jax.config.jax_compilation_cache_dir:
    return jax.config.jax_compilation_cache_dir
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return os.path.join(base, "jaxflow", "xla")


def _writable(folder: pathlib.Path) -> str | None:
  """None when files can be written in `folder` (made if missing), else why not."""
  try:
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
      pass
  except OSError as e:
    return f"{type(e).__name__}: {e.strerror or e}"
  return None


def _one_line_warnings(show, folder: pathlib.Path):
  """warnings.showwarning with JAX's warnings of an entry it could not read or write turned into
  one note a process (each has two lines an entry); an unreadable program's entries are removed,
  so that this run writes them again (JAX never overwrites an entry)."""
  said = []

  def showwarning(message, category, filename, lineno, file=None, line=None):
    text = str(message)
    if not text.startswith((_UNREADABLE, _UNWRITABLE)):
      show(message, category, filename, lineno, file, line)
      return
    program = text.split("'")[1] if text.count("'") >= 2 else None
    if text.startswith(_UNREADABLE):
      for entry in folder.glob(f"{program}-*") if program else ():
        entry.unlink(missing_ok=True)
    if not said:
      said.append(text)
      what = "read" if text.startswith(_UNREADABLE) else "written"
      print(f"note: an entry of the compilation cache {folder} could not be {what} "
            f"({text.split(': ', 1)[-1]}); compiled "
            + ("again and rewritten" if what == "read" else "and used without it"),
            file=sys.stderr)

  showwarning.jaxflow, showwarning.shown = True, show
  return showwarning


def enable(folder: str | None = None) -> str | None:
  """Turns the cache on in `folder` (None: $JAXFLOW_COMPILATION_CACHE or `default_dir()`; "off":
  off). Returns a note for the user when it stays off for a reason they did not ask for."""
  folder = folder if folder is not None else os.environ.get(ENV) or default_dir()
  if folder == OFF:
    jax.config.update("jax_enable_compilation_cache", False)
    compilation_cache.reset_cache()
    return None
  path = pathlib.Path(folder).expanduser()
  why = _writable(path)
  if why is not None:
    jax.config.update("jax_enable_compilation_cache", False)
    compilation_cache.reset_cache()
    return f"compilation cache off: {path} cannot be written ({why}); every run compiles"
  jax.config.update("jax_enable_compilation_cache", True)
  jax.config.update("jax_compilation_cache_dir", str(path))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
  compilation_cache.reset_cache()  # a program compiled before this call set the cache up without it
  if getattr(warnings.showwarning, "jaxflow", False):  # enabled before: that folder's handler
    warnings.showwarning = warnings.showwarning.shown
  warnings.showwarning = _one_line_warnings(warnings.showwarning, path)
  return None


_SETTINGS = ("jax_enable_compilation_cache", "jax_compilation_cache_dir",
             "jax_persistent_cache_min_compile_time_secs")


def settings():
  """JAX's compilation-cache settings and warnings.showwarning, as `enable` leaves them: what
  `restore` puts back (jaxflow.cli.call runs a command in the caller's process)."""
  return {name: getattr(jax.config, name) for name in _SETTINGS}, warnings.showwarning


def restore(saved):
  """Puts back what `settings()` returned; the cache is reset only where a setting changed."""
  values, warnings.showwarning = saved
  if any(getattr(jax.config, name) != value for name, value in values.items()):
    for name, value in values.items():
      jax.config.update(name, value)
    compilation_cache.reset_cache()
