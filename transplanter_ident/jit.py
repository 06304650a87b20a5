"""The numba options of every compiled kernel, fixed in one place.

* :func:`inline_kernel`: helpers inlined into their callers (never cached on their own);
* :func:`called_kernel`: helpers compiled once and called (the step's rare branches and the
  helpers it calls from many places);
* :func:`sized_kernel`: kernels made per state size by a factory (closures). They are not
  cached: numba keys a cached closure by its name and source line, which every size shares,
  so a cache folder could hand one size's code to another. The module-level entries that call
  them carry their code into the cache instead;
* :func:`entry_kernel` (and :func:`parallel_entry_kernel`, with prange loops on all threads):
  module-level entry points, cached on disk (the folder is keyed by the
  sources, see ``transplanter_ident/__init__.py``). ``runtime=False`` compiles without numba's
  runtime (NRT) for kernels that allocate nothing: with it every call increfs and decrefs its
  array arguments atomically, which took half of a filter step (numba issues #2345, #2350).

Every kernel uses numpy's error model: a division by zero gives inf or NaN, which the filter's
health check rolls back, instead of raising from compiled code.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba


def inline_kernel(fn: Callable[..., Any]) -> Any:
    """A helper compiled into each caller."""
    return numba.njit(cache=False, inline="always", error_model="numpy")(fn)


def called_kernel(fn: Callable[..., Any]) -> Any:
    """A helper compiled once and called, not inlined into the caller's IR (LLVM may still inline it).

    For branches that rarely run and helpers called from many places: numba's IR inlining
    repeats type inference at every call site, which made most of the step's compile time.
    Without numba's runtime, as the step it serves (nothing allocated, no reference counts).
    """
    return numba.njit(cache=False, error_model="numpy", _nrt=False)(fn)


def sized_kernel(fn: Callable[..., Any] | None = None, *, runtime: bool = True) -> Any:
    """A kernel made by a per-size factory (not cached; see the module docstring)."""
    options: dict[str, Any] = {"cache": False, "error_model": "numpy"}
    if not runtime:
        options["_nrt"] = False

    def wrap(f: Callable[..., Any]) -> Any:
        return numba.njit(**options)(f)

    return wrap(fn) if fn is not None else wrap


def entry_kernel(fn: Callable[..., Any] | None = None, *, runtime: bool = True) -> Any:
    """A module-level entry point, cached on disk (``runtime=False``: see the module docstring).

    It releases the GIL while it runs, so this process's other threads go on (the tuning pool's
    hand-out of tasks while this process filters a candidate).
    """
    options: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}
    if not runtime:
        options["_nrt"] = False

    def wrap(f: Callable[..., Any]) -> Any:
        return numba.njit(**options)(f)

    return wrap(fn) if fn is not None else wrap


def parallel_entry_kernel(fn: Callable[..., Any]) -> Any:
    """A module-level entry point whose ``numba.prange`` loops run on all threads, cached on disk."""
    return numba.njit(cache=True, parallel=True, error_model="numpy")(fn)
