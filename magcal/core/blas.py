"""BLAS (and OpenMP) on one thread in this process while a block runs, shared by every user in the process.

The engine's heavy matrix products are tall and thin: a fit's normal equations are sums of ``(k, m) @ (m, k)``
products of a few dozen columns over thousands of rows, a diagnosis's Jacobian blocks the same with ~170 columns.
OpenBLAS splits such a product over every core and its threads spin while they wait for one another, so when
anything else keeps a core busy (the workbench's browser drawing beside it, a diagnosis's worker processes, another
program) each product waits for a thread that is not running: measured on the 2-core development machine with other
programs running (load 5-8), a warm refit of 4 x 1e5 samples with one effect took 8.9 s on OpenBLAS's default two
threads against 0.32 s on one (``benchmarks/refit_latency.py``; notes in ``benchmarks/notes/page_latency.md``).

:func:`one_blas_thread` is the one switch: threadpoolctl's limits are the process's, not a thread's, so the limit
is set by the first block that enters and put back by the last that leaves, whoever they are (a fit on the
workbench's job thread, a diagnosis on another session's), and two users never leave it changed.

A caveat of OpenBLAS (0.3.31, pthreads, the build numpy and scipy ship; seen on the development machine): the thread
count is the process's, set from any thread, until the main thread has set one; from then on a count set from
another thread is ignored. The workbench's main thread never sets one (its fits and diagnoses run on job threads), and
the command line's fits run on the main thread, so the limit holds in both; a program that sets BLAS threads on its
main thread and fits on other threads keeps its own setting (the results are the same either way).
"""

from __future__ import annotations

import contextlib
import threading

_LOCK = threading.Lock()
_USERS = 0
_LIMITER = None


@contextlib.contextmanager
def one_blas_thread(active: bool = True):
    """BLAS (and OpenMP) on one thread in this process while the block runs, when ``active``.

    Entering costs a few milliseconds the first time (threadpoolctl looks the loaded libraries up) and nothing
    while another block already holds the limit.

    Parameters
    ----------
    active : bool
        False: the block runs with the process's settings as they are (a caller that decides per call).
    """
    global _USERS, _LIMITER
    if not active:
        yield
        return
    with _LOCK:
        if _USERS == 0:
            from threadpoolctl import threadpool_limits

            _LIMITER = threadpool_limits(limits=1)
        _USERS += 1
    try:
        yield
    finally:
        with _LOCK:
            _USERS -= 1
            if _USERS == 0 and _LIMITER is not None:
                _LIMITER.restore_original_limits()
                _LIMITER = None


def holders() -> int:
    """How many blocks hold the one-thread limit now (0: the process's own settings apply)."""
    return _USERS
