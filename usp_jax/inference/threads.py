"""The host's threads around the compiled detector: host work on a thread per core, and NumPy's
matrix products on one BLAS thread.

Matching, the epipolar filter and the match refinement are NumPy and OpenCV work that releases
the GIL in its large array operations, so independent pieces of it (image pairs, chunks of
matches) run side by side on :data:`THREADS` threads (:func:`threaded`).

OpenBLAS's worker threads busy-wait for a while after each multi-threaded product before they
sleep, so the XLA detection that follows a match (the next video frame) finds its cores taken:
on 2 cores a 1000-point match made the next 480 px detection take 95 ms instead of 54 (49 with
no match before it; ``benchmarks/bench_blas_threads.py``), and ``track``'s default frame on
box.mp4 130-150 ms instead of 90-108 (RESULTS.md "Video"). Inside :data:`one_blas_thread` the
product runs on one thread (2.8 -> 4.4 ms), far less than it cost the detection; callers that
match many pairs run them on :func:`threaded`.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor

import threadpoolctl

#: Threads of :func:`threaded`: one per core.
THREADS = os.cpu_count() or 1


def threaded(
    function: Callable, items: Sequence, progress: Callable = iter, pool: Executor | None = None
) -> list:
    """``function`` of each item on :data:`THREADS` threads, the results in order; ``progress``
    wraps the wait for them (a tqdm bar counts finished items). ``pool``: the caller's executor,
    kept across calls (a tracker's frames: a new thread per frame pays OpenCV's set-up of a
    thread each time); None: one for this call. Threads started inside the main thread's
    :data:`one_blas_thread` block share its limit."""
    if pool is None:
        with ThreadPoolExecutor(THREADS) as pool:
            return threaded(function, items, progress, pool)
    futures = [pool.submit(function, item) for item in items]
    return [future.result() for future in progress(futures)]


@functools.cache
def _controller() -> threadpoolctl.ThreadpoolController:
    # Scanning the loaded libraries takes ~0.6 ms; NumPy's BLAS is loaded before this runs.
    return threadpoolctl.ThreadpoolController()


class _OneBlasThread:
    """Context manager: the BLAS libraries on one thread while the main thread is inside it
    (re-entrant), and as they were once it leaves. From any other thread it changes nothing:
    OpenBLAS lets such a thread lower its count but not raise it again, so a worker's limit
    would outlive it."""

    def __init__(self):
        self._inside = 0
        self._limit = None

    def __enter__(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        if self._inside == 0:
            self._limit = _controller().limit(limits=1, user_api="blas")
        self._inside += 1

    def __exit__(self, *exc) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        self._inside -= 1
        if self._inside == 0:
            self._limit.restore_original_limits()
            self._limit = None


#: ``with one_blas_thread: ...`` runs NumPy's matrix products on one thread (module docstring).
one_blas_thread = _OneBlasThread()
