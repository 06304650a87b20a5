"""Where the tuning objective (eq. 21 or the NLL, per bag) is evaluated: here, a process pool or a Dask cluster.

A *backend* runs two kinds of work, always returning results in the order asked:

* :meth:`Backend.map`: one call per item (decoding bags into epochs);
* :meth:`Backend.evaluate`: the objective of a batch of candidates (log10 Q/R, eq. 22) on each
  of several bags, as a (bags, candidates) array. Each bag's candidates are split into
  contiguous chunks, about ``CHUNKS_PER_SLOT`` per parallel slot in proportion to the bag's
  epochs, and the chunks run as independent tasks, largest first.

Every candidate's value comes from the same compiled kernel (``TuningProblem.evaluate_serially``:
the sequence objective, one candidate after another in the task's thread), which runs each
candidate on its own copies of the data: a value does not depend on which chunk, process or
machine computed it. So the tuning result for a seed is the same, bit for bit, whatever the
number of jobs or the cluster (the bags are summed in a fixed order by the caller).

* :class:`SerialBackend` (``--jobs 1``): in this process;
* :class:`ProcessBackend` (``--jobs N``): this process and N - 1 worker processes of a
  ``concurrent.futures.ProcessPoolExecutor`` with the ``forkserver`` start method (``spawn``
  where there is none), the next task going to whoever is free; the workers start on first
  use or by :meth:`ProcessBackend.start`. Each worker loads the compiled kernels from numba's
  disk cache as it starts (``warm_up``, :func:`warm_kernels`). A task carries its bag's epochs
  (56 bytes per epoch), which costs far less than filtering them;
* :class:`DaskBackend` (``--dask ADDRESS``): a ``dask.distributed`` cluster; each bag is
  scattered to the workers once, and chunks are submitted as tasks.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, wait
from typing import Any, Protocol

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.epochs.epoch import Epoch, EpochArrays
from transplanter_ident.evaluation.cramer_rao import cramer_rao_bound
from transplanter_ident.tuning.problem import TuningProblem

#: chunks per parallel slot (more balances uneven tasks better, fewer costs less overhead)
CHUNKS_PER_SLOT = 2
#: tasks a pool worker holds at once (handed out as it returns one)
WORKER_QUEUE = 1
#: seconds a starting worker waits for this process's warm-up before going on without it
HOST_WARM_UP_TIMEOUT = 120.0
#: seconds to wait for a Dask scheduler
DASK_CONNECT_TIMEOUT = 20.0


def default_jobs() -> int:
    """The number of cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _still_epochs() -> EpochArrays:
    """Three epochs of straight driving at 1 m/s: enough to run (so load or compile) a kernel."""
    return EpochArrays([Epoch(t=0.2 * i, longitudinal_velocity=1.0, lateral_velocity=0.0, heading=0.0, yaw_rate=0.0,
                              steering=0.0, steering_rate=0.0, speed=1.0) for i in range(3)])


def warm_kernels(config: EstimatorConfig) -> None:
    """Load (or compile) the sequence objective for ``config``'s state size, on three still epochs."""
    problem = TuningProblem.from_epochs(config, _still_epochs(), "nll")
    problem.evaluate_serially(problem.start[None, :])


def warm_worker(config: EstimatorConfig, wait_for_host: Callable[[], bool]) -> None:
    """A worker's start: the Cramér-Rao kernel, then the objective.

    On a cold start the host compiles the step and the objective meanwhile (``host_warm_up`` of
    :class:`ProcessBackend`). The worker compiles the bound's kernel, which does not use the
    step, then waits for the host and finds the objective, step included, in numba's disk cache:
    the step, most of the compile time, is compiled once, and the compiles run on both cores.
    The filter run of Table 2 (``run_sequence``) is left to the first task that needs it (cold,
    ~3 s to link the cached step into it): the worker takes candidates that much sooner.
    """
    cramer_rao_bound(config, _still_epochs(), config.noise.initial_stiffness, config.vehicle.steering_offset)
    wait_for_host()
    warm_kernels(config)


def _start_worker(warm_up: Callable[[Callable[[], bool]], None] | None, host_ready: Any) -> None:
    """Pool initializer: the optional warm-up (loading the kernels), given a wait for the host's."""
    if warm_up is not None:
        warm_up(lambda: host_ready.wait(HOST_WARM_UP_TIMEOUT))


def _ready() -> None:
    """A task that does nothing (makes the pool start a worker)."""


def evaluate_chunk(problem: TuningProblem, positions: np.ndarray) -> np.ndarray:
    """The objective of ``positions`` (m, D) on one bag, in this thread (a task of one slot)."""
    return problem.evaluate_serially(positions)


def plan_chunks(sizes: Sequence[int], candidates: int, slots: int) -> list[tuple[int, int, int]]:
    """Tasks ``(bag, first, stop)``: each bag's candidates in contiguous chunks, largest task first.

    A bag gets about ``CHUNKS_PER_SLOT * slots`` chunks in proportion to its share of the epochs
    (at least one, at most one per candidate); with one slot every bag is one task.
    """
    total = sum(sizes)
    tasks: list[tuple[int, int, int]] = []
    for bag, size in enumerate(sizes):
        wanted = 1 if slots <= 1 or total <= 0 else math.ceil(CHUNKS_PER_SLOT * slots * size / total)
        chunks = max(1, min(candidates, wanted))
        edges = np.linspace(0, candidates, chunks + 1).round().astype(int)
        tasks += [(bag, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]
    tasks.sort(key=lambda task: (-(task[2] - task[1]) * sizes[task[0]], task[0], task[1]))
    return tasks


class Backend(Protocol):
    """Runs the tuner's work; see the module docstring."""

    @property
    def slots(self) -> int:
        """Tasks that run at the same time."""

    def map(self, fn: Callable[..., Any], items: Iterable[tuple[Any, ...]]) -> list[Any]:
        """``[fn(*item) for item in items]``, possibly in parallel, in order."""

    def evaluate(self, problems: Sequence[TuningProblem], positions: np.ndarray) -> np.ndarray:
        """(len(problems), m) objective values of the candidates ``positions`` (m, D)."""

    def close(self) -> None:
        """Release workers and connections."""


def _assemble(problems: Sequence[TuningProblem], positions: np.ndarray, tasks: list[tuple[int, int, int]],
              results: Sequence[np.ndarray]) -> np.ndarray:
    values = np.full((len(problems), len(positions)), np.nan)
    for (bag, first, stop), result in zip(tasks, results, strict=True):
        values[bag, first:stop] = result
    return values


class SerialBackend:
    """Everything in this process, one numba thread (``--jobs 1``)."""

    slots = 1

    def map(self, fn: Callable[..., Any], items: Iterable[tuple[Any, ...]]) -> list[Any]:
        """In order, here."""
        return [fn(*item) for item in items]

    def evaluate(self, problems: Sequence[TuningProblem], positions: np.ndarray) -> np.ndarray:
        """One call per bag, here."""
        return np.vstack([evaluate_chunk(p, positions) for p in problems]) if problems else np.empty((0, 0))

    def close(self) -> None:
        """Nothing to release."""


def _pool_context() -> multiprocessing.context.BaseContext:
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")


class ProcessBackend:
    """``jobs`` parallel slots (``--jobs N``): this process and a pool of ``jobs - 1`` worker processes.

    Tasks go to whoever is free next: each worker holds ``WORKER_QUEUE`` (one: the compiled calls
    here release the GIL, so the pool's callback hands the next one out at once) and gets the next
    as it returns one; this process runs the next pending one itself meanwhile. So this process
    never idles while workers compute, and candidates are not handed to workers that are still
    starting (measured on 4 three-minute bags, 2 cores, idle machine: this process + 1 worker
    4.3 s, 2 workers with this process waiting 4.7-5.2 s, serial 6.6 s). With one task queued
    per worker and two chunks per slot, `--jobs 2` took 0.629 of `--jobs 1` (6 pairs; with two
    queued and four chunks, 0.664), since a worker holds no queued task when this process runs
    out of them.
    """

    def __init__(self, jobs: int, warm_up: Callable[[Callable[[], bool]], None] | None = None,
                 host_warm_up: Callable[[], None] | None = None) -> None:
        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        # run once in each worker as it starts (e.g. :func:`warm_worker`), given a wait for host_warm_up
        self.warm_up = warm_up
        # run once here before the workers get their first call (e.g. :func:`warm_kernels`)
        self.host_warm_up = host_warm_up
        self._host_ready = _pool_context().Event()
        self._pool: Executor | None = None
        self._boot: list[Future] = []  # one no-op per worker, done once the workers are up

    @property
    def slots(self) -> int:
        """This process plus the workers."""
        return self.jobs

    def _executor(self) -> Executor | None:
        if self._pool is None and self.jobs > 1:
            self._pool = ProcessPoolExecutor(self.jobs - 1, mp_context=_pool_context(), initializer=_start_worker,
                                             initargs=(self.warm_up, self._host_ready))
        return self._pool

    def start(self) -> None:
        """Start every worker now, then ``host_warm_up`` here (the workers get ready while the caller goes on)."""
        pool = self._executor()
        if pool is not None and not self._boot:
            self._boot = [pool.submit(_ready) for _ in range(self.jobs - 1)]
            self._warm_host()

    def _warm_host(self) -> None:
        """``host_warm_up`` here, once, then let the workers' warm-ups go on."""
        if not self._host_ready.is_set():
            try:
                if self.host_warm_up is not None:
                    self.host_warm_up()
            finally:
                self._host_ready.set()

    def ready(self) -> bool:
        """Whether every worker has started (and warmed up)."""
        return bool(self._boot) and all(f.done() for f in self._boot)

    def wait_ready(self) -> None:
        """Start the workers if needed and wait until they are up."""
        self.start()
        wait(self._boot)

    def _run(self, calls: Sequence[tuple[Callable[..., Any], tuple[Any, ...]]], *,
             wait_for_workers: bool = True) -> list[Any]:
        """``[fn(*args) for fn, args in calls]`` on the workers and here, in order of the calls.

        Each worker holds ``WORKER_QUEUE`` calls and is handed the next pending one as it
        returns one (from the pool's callback thread); this process takes the next pending call
        whenever it is free. Unless ``wait_for_workers``, workers that are still starting get
        nothing (this process runs every call: short calls should not wait for a start-up).
        """
        results: list[Any] = [None] * len(calls)
        pending = deque(range(len(calls)))
        lock = threading.Lock()
        handed_out: list[tuple[int, Future]] = []
        reserved = [0]  # calls taken for a worker (appended to handed_out right after submitting)
        pool = self._executor() if len(calls) > 1 else None
        if pool is not None:
            self._warm_host()
        if pool is not None and not wait_for_workers:
            self.start()
            pool = pool if self.ready() else None

        def take(for_worker: bool) -> int | None:
            with lock:
                if not pending:
                    return None
                reserved[0] += for_worker
                return pending.popleft()

        def hand_out(_: Future | None = None) -> None:
            index = take(True)
            if index is None:
                return
            fn, args = calls[index]
            future = pool.submit(fn, *args)
            with lock:
                handed_out.append((index, future))
            future.add_done_callback(hand_out)

        for _ in range(WORKER_QUEUE * (self.jobs - 1) if pool is not None else 0):
            hand_out()
        try:
            while (index := take(False)) is not None:
                fn, args = calls[index]
                results[index] = fn(*args)
        except BaseException:
            with lock:
                pending.clear()  # hand nothing more out
            raise
        while True:  # the workers' calls; a callback may still be submitting the last one it took
            with lock:
                unfinished = [f for _, f in handed_out if not f.done()]
                complete = not unfinished and len(handed_out) == reserved[0]
            if complete:
                break
            if unfinished:
                wait(unfinished)
            else:
                time.sleep(0.0002)
        for index, future in handed_out:
            results[index] = future.result()
        return results

    def map(self, fn: Callable[..., Any], items: Iterable[tuple[Any, ...]]) -> list[Any]:
        """On the workers and here, in order (a single item runs here, without starting the pool)."""
        return self._run([(fn, tuple(item)) for item in items])

    def evaluate(self, problems: Sequence[TuningProblem], positions: np.ndarray) -> np.ndarray:
        """Chunks of every bag on the workers and here."""
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        tasks = plan_chunks([len(p.kernel_input) for p in problems], len(positions), self.slots)
        results = self._run([(evaluate_chunk, (problems[bag], positions[a:b])) for bag, a, b in tasks],
                            wait_for_workers=False)
        return _assemble(problems, positions, tasks, results)

    def close(self) -> None:
        """Stop the workers."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


class DaskBackend:
    """A ``dask.distributed`` cluster at ``address`` (``--dask tcp://host:8786``)."""

    def __init__(self, address: str, *, timeout: float | None = None) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise ValueError("--dask needs dask.distributed, which is not installed "
                             "(pip install 'dask[distributed]')") from None
        timeout = DASK_CONNECT_TIMEOUT if timeout is None else timeout
        try:
            self._client = Client(address, timeout=timeout, set_as_default=False)
        except (OSError, ValueError) as exc:
            reason = " ".join(str(exc).split()) or type(exc).__name__
            raise ValueError(f"--dask {address}: cannot connect to the Dask scheduler ({reason})") from None
        self.address = address
        self._scattered: dict[int, tuple[TuningProblem, Any]] = {}

    @property
    def slots(self) -> int:
        """Worker threads in the cluster (at least 1)."""
        return max(1, sum(self._client.nthreads().values()))

    def map(self, fn: Callable[..., Any], items: Iterable[tuple[Any, ...]]) -> list[Any]:
        """On the cluster, in order."""
        futures = [self._client.submit(fn, *item, pure=False) for item in items]
        return self._client.gather(futures)

    def _remote(self, problem: TuningProblem) -> Any:
        """The problem's future on the cluster (scattered to every worker once)."""
        key = id(problem)
        if key not in self._scattered:
            future = self._client.scatter(problem, broadcast=True, hash=False)
            self._scattered[key] = (problem, future)  # holding the problem keeps its id unique
        return self._scattered[key][1]

    def evaluate(self, problems: Sequence[TuningProblem], positions: np.ndarray) -> np.ndarray:
        """Chunks of every bag as cluster tasks."""
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        tasks = plan_chunks([len(p.kernel_input) for p in problems], len(positions), self.slots)
        futures = [self._client.submit(evaluate_chunk, self._remote(problems[bag]), positions[a:b], pure=False)
                   for bag, a, b in tasks]
        return _assemble(problems, positions, tasks, self._client.gather(futures))

    def close(self) -> None:
        """Release the scattered data and disconnect (the cluster keeps running)."""
        self._scattered.clear()
        self._client.close()


def open_backend(jobs: int | None = None, dask_address: str | None = None) -> Backend:
    """The backend for ``--jobs`` / ``--dask``: Dask if an address is given, else a pool, or serial for 1 job."""
    if dask_address:
        return DaskBackend(dask_address)
    jobs = default_jobs() if jobs is None else jobs
    return SerialBackend() if jobs <= 1 else ProcessBackend(jobs)
