"""The numba options of every compiled kernel, fixed in one place.

* :func:`inline_kernel`: helpers inlined into their callers (never cached on their own);
* :func:`called_kernel`: helpers compiled once and called (the step's rare branches and the
  helpers it calls from many places);
* :func:`sized_kernel`: kernels made per state size by a factory (closures). They are not
  cached: numba keys a cached closure by its name and source line, which every size shares,
  so a cache folder could hand one size's code to another. The module-level entries that call
  them carry their code into the cache instead. Each is named after its variant
  (:func:`_variant_named`): numba's symbol for a function is its qualified name and a counter of
  the process that compiled it, so two entries cached by two processes could both define
  ``run_n$2``, one per size, and a process loading both would call one size's code with the
  other's arrays (it did: heap corruption in ``make demo`` after a piecemeal cache);
* :func:`entry_kernel` (and :func:`parallel_entry_kernel`, with prange loops on all threads):
  module-level entry points, cached on disk (the folder is keyed by the
  sources, see ``transplanter_ident/__init__.py``). ``runtime=False`` compiles without numba's
  runtime (NRT) for kernels that allocate nothing: with it every call increfs and decrefs its
  array arguments atomically, which took half of a filter step (numba issues #2345, #2350).

:func:`load_cached_kernels_lean` lets a process that only runs the filter (the node) load the
cached kernels without the part of numba it does not use.

Every kernel uses numpy's error model: a division by zero gives inf or NaN, which the filter's
health check rolls back, instead of raising from compiled code.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from typing import Any

import numba


def inline_kernel(fn: Callable[..., Any]) -> Any:
    """A helper compiled into each caller."""
    return numba.njit(cache=False, inline="always", error_model="numpy")(fn)


def _variant_named(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` (a factory's closure) renamed after the variant it closes over: sizes, flags, the kernels it calls.

    So the per-size closures of one factory never share a qualified name, whatever the process
    that compiles them (see the module docstring).
    """
    parts = []
    for cell in fn.__closure__ or ():
        try:
            value = cell.cell_contents
        except ValueError:  # a cell not filled yet (a kernel defined later in the factory)
            continue
        if isinstance(value, (bool, int)):
            parts.append(str(int(value)))
        elif isinstance(value, str):
            parts.append(value)
        elif hasattr(value, "py_func"):  # a kernel it calls: that kernel's (variant) name
            parts.append(value.py_func.__name__)
    if parts:  # a short digest: the same in every process, different for every variant
        suffix = "_v" + hashlib.sha1("|".join(parts).encode()).hexdigest()[:10]
        fn.__name__ += suffix
        fn.__qualname__ += suffix
    return fn


def called_kernel(fn: Callable[..., Any]) -> Any:
    """A helper compiled once and called, not inlined into the caller's IR (LLVM may still inline it).

    For branches that rarely run and helpers called from many places: numba's IR inlining
    repeats type inference at every call site, which made most of the step's compile time.
    Without numba's runtime, as the step it serves (nothing allocated, no reference counts).
    """
    return numba.njit(cache=False, error_model="numpy", _nrt=False)(_variant_named(fn))


def _njit(fn: Callable[..., Any] | None, runtime: bool, **options: Any) -> Any:
    """``numba.njit(**options)`` as a decorator with or without arguments; ``runtime=False`` drops NRT."""
    if not runtime:
        options["_nrt"] = False

    def wrap(f: Callable[..., Any]) -> Any:
        return numba.njit(error_model="numpy", **options)(f)

    return wrap(fn) if fn is not None else wrap


def sized_kernel(fn: Callable[..., Any] | None = None, *, runtime: bool = True) -> Any:
    """A kernel made by a per-size factory (not cached, named after its variant; see the module docstring)."""
    if fn is not None:
        return _njit(_variant_named(fn), runtime, cache=False)
    return lambda f: _njit(_variant_named(f), runtime, cache=False)


def entry_kernel(fn: Callable[..., Any] | None = None, *, runtime: bool = True) -> Any:
    """A module-level entry point, cached on disk (``runtime=False``: see the module docstring).

    It releases the GIL while it runs, so this process's other threads go on (the tuning pool's
    hand-out of tasks while this process filters a candidate).
    """
    return _njit(fn, runtime, cache=True, nogil=True)


def parallel_entry_kernel(fn: Callable[..., Any]) -> Any:
    """A module-level entry point whose ``numba.prange`` loops run on all threads, cached on disk."""
    return numba.njit(cache=True, parallel=True, error_model="numpy")(fn)


def load_cached_kernels_lean() -> bool:
    """From now on in this process, load cached kernels without numba's full target refresh.

    Before loading a cached function numba refreshes its target context
    (``numba/core/caching.py: Cache.load_overload``), which imports and registers the lowering of
    everything numba can compile: about 23 MB that a process which only *runs* the filter never
    uses (the node: 186 MB -> 164 MB after its warm-up, measured in-process). This keeps what the
    loaded code needs, numba's runtime (NRT, for kernels that allocate), and skips the rest. A
    kernel that is not in the cache is compiled as usual: numba's compiler refreshes the context
    itself. For the numba version pinned in requirements.txt; with another layout of numba's
    cache class it does nothing and returns False.
    """
    from numba.core import caching
    from numba.core.runtime import rtsys

    cache = caching.Cache
    if not all(hasattr(cache, name) for name in ("load_overload", "_load_overload",
                                                 "_guard_against_spurious_io_errors")):
        return False

    def load_overload(self: Any, sig: Any, target_context: Any) -> Any:
        rtsys.initialize(target_context)
        with self._guard_against_spurious_io_errors():
            return self._load_overload(sig, target_context)
        return None  # an I/O error the guard swallowed: compile instead

    cache.load_overload = load_overload
    return True

