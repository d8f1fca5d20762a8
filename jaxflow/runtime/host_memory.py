"""Freed host memory kept for reuse, so that XLA's CPU programs do not fault in fresh pages.

    note = host_memory.keep()   # before jax starts its backend; None when set

A compiled program allocates its temporaries on every call (4 GiB in a PV-RAFT training step of
2 x 2048 points). glibc's malloc serves blocks that large by mmap and unmaps them when freed, so
each call faults in, and the kernel zeroes, a million fresh 4 KiB pages: a fifth of that step's
time on a 2-core CPU (benchmarks/MODEL.md). `keep` tells malloc to serve every block from its
heap, one arena for all threads, and never to hand freed memory back: from the second call on, a
program reuses the pages of the first. The price: the process holds its memory until it exits,
and a heap holding blocks of many sizes fragments (an 8192-point PV-RAFT inference, called again
and again, grew its process from 1.9 to 3.4 GiB; a training step's stayed at 4.9). So train.py
keeps by default (its step 1.26x-1.29x faster), predict and evaluate.py release by default (their
programs are compute-bound: no gain measured); `--host_memory keep|release`, else
$JAXFLOW_HOST_MEMORY, overrides. Elsewhere than glibc it does nothing (a note when asked for by
name). Results do not change: only where the bytes live.
"""

import ctypes
import ctypes.util
import os

ENV = "JAXFLOW_HOST_MEMORY"
KEEP, RELEASE = "keep", "release"
CHOICES = (KEEP, RELEASE)

# mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8


def choice(flag: str | None = None, default: str = KEEP) -> str:
  """The setting in force: `flag`, else $JAXFLOW_HOST_MEMORY, else `default`; ValueError naming
  the source for anything else."""
  value, source = (flag, "--host_memory") if flag is not None else (os.environ.get(ENV), ENV)
  if value is None or value == "":
    return default
  if value not in CHOICES:
    raise ValueError(f"{source} must be one of {', '.join(CHOICES)}, got {value!r}")
  return value


def _glibc_mallopt():
  """glibc's mallopt, or None where the C library is another."""
  try:
    if not os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc"):
      return None
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
  except (AttributeError, ValueError, OSError):
    return None


def keep(flag: str | None = None, default: str = KEEP) -> str | None:
  """Makes malloc keep freed memory for reuse (module docstring) unless the setting (`choice`) is
  release. Returns None when set or left as asked; one line when it could not be set and was
  asked for by name (elsewhere than glibc a default stays silent)."""
  asked = flag if flag is not None else os.environ.get(ENV)
  if choice(flag, default) == RELEASE:
    return None
  mallopt = _glibc_mallopt()
  if mallopt is None:
    return "host memory: the C library is not glibc; malloc left as it is" if asked else None
  # Trim threshold -1 is SIZE_MAX to malloc (its argument is converted to size_t): never trim.
  if not all([mallopt(_M_ARENA_MAX, 1), mallopt(_M_MMAP_MAX, 0), mallopt(_M_TRIM_THRESHOLD, -1)]):
    return "host memory: glibc refused a malloc setting; freed memory is released as usual"
  return None
