"""Independent fits of a diagnosis run side by side on the machine's cores.

The confirming refits of the best candidates and the held-out fits of each scheme and candidate do not depend on
one another; numpy releases the interpreter in its loops and BLAS calls, so threads (not processes: the datasets
stay shared, nothing is pickled) keep both cores of a small machine busy. Results come back in the order of the
calls, so the diagnosis reads the same whatever finishes first.

:func:`in_parallel` runs a batch and waits for all of it. A :class:`Pool` lives for a whole diagnosis and starts
each piece of work as soon as what it needs is ready (a candidate's held-out fits the moment its refit returns,
the evidence about the base fit while the refits run), by priority, so that the longest chain of dependent fits
is never queued behind work that can wait.
"""

from __future__ import annotations

import itertools
import os
import queue
import threading
from concurrent.futures import Future, ThreadPoolExecutor

#: Threads for independent fits (None: one per core, at most :data:`MAX_THREADS` and one per fit; 1: one after
#: the other).
PARALLEL_FITS = None

#: Most threads by default: every fit in flight holds its own temporaries (about 100 MB for 4 x 1e5 samples), and
#: a diagnosis rarely has more than a dozen pieces of work at once.
MAX_THREADS = 8

#: Priorities of a :class:`Pool`'s work (lower first): fits on the longest chain (refits and the held-out fits
#: they lead to), fits every candidate waits for, and evidence that is only read at the end.
CHAIN, SHARED, FILLER = 0, 1, 2


def _workers(n_calls=None):
    workers = PARALLEL_FITS or min(os.cpu_count() or 1, MAX_THREADS)
    return workers if n_calls is None else min(n_calls, workers)


def in_parallel(calls):
    """The results of ``calls`` (functions of no argument), in order, run on up to :data:`PARALLEL_FITS` threads.

    An exception raised by a call is raised here, after the others have finished.
    """
    workers = _workers(len(calls))
    if workers <= 1:
        return [call() for call in calls]
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="magcal-fit") as pool:
        return list(pool.map(lambda call: call(), calls))


class Pool:
    """Threads (:data:`PARALLEL_FITS`) that run submitted calls by priority, then in the order submitted.

    A call may submit further calls (its follow-ups). With one thread every call runs at once, in the caller's
    thread, at :meth:`submit`. Use as a context manager: leaving it waits for every call submitted.
    """

    def __init__(self):
        workers = _workers()
        self._queue = queue.PriorityQueue()
        self._order = itertools.count()
        self._threads = []
        if workers > 1:
            for k in range(workers):
                thread = threading.Thread(target=self._work, name=f"magcal-fit_{k}", daemon=True)
                thread.start()
                self._threads.append(thread)

    def submit(self, call, priority=CHAIN) -> Future:
        """A :class:`~concurrent.futures.Future` of ``call()`` (a function of no argument)."""
        future: Future = Future()
        if not self._threads:
            _run(call, future)
        else:
            self._queue.put((priority, next(self._order), call, future))
        return future

    def _work(self):
        while True:
            _, _, call, future = self._queue.get()
            if call is None:
                return
            _run(call, future)

    def close(self, cancel=False):
        """Wait for every call submitted, then stop the threads; with ``cancel``, calls not yet started are
        cancelled instead (their futures raise :class:`~concurrent.futures.CancelledError`)."""
        if cancel:
            while True:
                try:
                    *_, future = self._queue.get_nowait()
                except queue.Empty:
                    break
                future.cancel()
        for _ in self._threads:
            self._queue.put((FILLER + 1, next(self._order), None, None))
        for thread in self._threads:
            thread.join()
        self._threads = []

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close(cancel=exc_type is not None)  # after an error (or Ctrl-C) nothing more is started


def _run(call, future):
    if future.set_running_or_notify_cancel():
        try:
            future.set_result(call())
        except BaseException as exc:
            future.set_exception(exc)
