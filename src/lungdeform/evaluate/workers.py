"""Worker processes that fit lungs side by side: a subject's two lungs on two cores.

A lung's fit runs mostly on one core (its BLAS held to one thread, :mod:`lungdeform.blas`; its
Python between the dense steps), so on a machine of two cores the two lungs of a subject fitted at
once take about the time of the slower one instead of the sum (``validate copd --workers``,
``bench fit``). :class:`LungWorkers` keeps ``count`` processes for its ``with`` block:

- started with ``spawn`` (the parent has run Numba's threading layer, which is not safe to fork)
  and kept, so that each pays the imports and the compiled kernels' cache once;
- each limited to one Numba thread and one BLAS thread (``count`` processes, ``count`` cores);
- :meth:`LungWorkers.map` runs a top-level function on each argument tuple and returns, in order,
  :class:`Done` records: the value, and the task's wall and CPU seconds in its worker (a parent's
  ``time.process_time`` does not count its children's CPU).

Interrupts: the workers ignore SIGINT (Ctrl-C reaches the whole process group; the parent decides).
When the parent is interrupted (KeyboardInterrupt, or SIGTERM turned into one by the CLI) while
tasks run, it sends SIGTERM to every worker: a running task unwinds as the serial run would (the
folders it was writing are removed, :func:`lungdeform.atomic.atomic_dir`), an idle worker ends; the
parent waits for them, then re-raises. An exception in a task is re-raised in the parent, with the
worker's traceback chained by :mod:`concurrent.futures`.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from concurrent.futures import Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Callable

import numba
from threadpoolctl import threadpool_limits

from lungdeform.errors import InputError

#: Seconds the parent waits for interrupted workers to unwind before it kills them.
STOP_WAIT_S = 20.0


@dataclass(frozen=True)
class Done:
    """One finished task of :meth:`LungWorkers.map`: its ``value``, and its ``seconds`` (wall) and
    ``cpu_seconds`` (its worker process's CPU, every thread) from call to return."""

    value: Any
    seconds: float
    cpu_seconds: float


def _start_worker() -> None:
    """Each worker: Ctrl-C left to the parent, SIGTERM ends it quietly while idle; one Numba thread,
    one BLAS thread (the parent's processes share the cores, one each)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    numba.set_num_threads(1)
    threadpool_limits(limits=1, user_api="blas")


def _stop_task(signum, frame):
    raise KeyboardInterrupt("terminated by the parent")


def _run(fn: Callable, args: tuple) -> Done:
    """``fn(*args)`` in a worker, timed; SIGTERM raises KeyboardInterrupt while it runs (its
    clean-up runs), and ends the worker quietly again after."""
    signal.signal(signal.SIGTERM, _stop_task)
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        value = fn(*args)
        return Done(value, time.perf_counter() - t0, time.process_time() - c0)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


class LungWorkers:
    """``count`` worker processes for a ``with`` block (module docstring); ``count`` ≥ 1."""

    def __init__(self, count: int):
        if not (isinstance(count, int) and not isinstance(count, bool) and count >= 1):
            raise InputError(f"workers must be a whole number >= 1, got {count!r}")
        self.count = count
        self._pool: ProcessPoolExecutor | None = None

    def __enter__(self) -> "LungWorkers":
        self._pool = ProcessPoolExecutor(self.count, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_start_worker)
        return self

    def __exit__(self, kind, exc, tb) -> None:
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def map(self, fn: Callable, tasks: list[tuple]) -> list[Done]:
        """``fn(*args)`` for each ``args`` of ``tasks``, at most ``count`` at once; the :class:`Done`
        records in the order of ``tasks``. ``fn`` and its arguments must pickle (a module-level
        function; no callbacks into the parent)."""
        if self._pool is None:
            raise InputError("LungWorkers.map needs the workers started: use it inside `with LungWorkers(count)`")
        futures = [self._pool.submit(_run, fn, tuple(args)) for args in tasks]
        try:
            wait(futures)
        except KeyboardInterrupt:
            self._stop(futures)
            raise
        return [f.result() for f in futures]

    def _stop(self, futures: list[Future]) -> None:
        """Tasks not started are cancelled; SIGTERM to every worker: a running task unwinds (its
        clean-up runs) and reports, an idle worker ends. Waits up to :data:`STOP_WAIT_S` for the
        running tasks, then kills every worker left (the pool is not used again)."""
        for f in futures:
            f.cancel()
        workers = list((self._pool._processes or {}).values())  # the pool's own processes (no public API)
        for p in workers:
            if p.is_alive():
                os.kill(p.pid, signal.SIGTERM)
        wait(futures, timeout=STOP_WAIT_S)
        for p in workers:
            if p.is_alive():
                p.kill()
            p.join(STOP_WAIT_S)
