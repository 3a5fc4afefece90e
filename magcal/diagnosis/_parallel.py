"""Independent fits of a diagnosis run side by side on the machine's cores.

The confirming refits of the best candidates and the held-out fits of each scheme and candidate do not depend on
one another; numpy releases the interpreter in its loops and BLAS calls, so threads (not processes: the datasets
stay shared, nothing is pickled) keep both cores of a small machine busy. Results come back in the order of the
calls, so the diagnosis reads the same whatever finishes first.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

#: Threads for independent fits (None: one per core, at most one per fit; 1: one after the other).
PARALLEL_FITS = None


def in_parallel(calls):
    """The results of ``calls`` (functions of no argument), in order, run on up to :data:`PARALLEL_FITS` threads.

    An exception raised by a call is raised here, after the others have finished.
    """
    workers = min(len(calls), PARALLEL_FITS or os.cpu_count() or 1)
    if workers <= 1:
        return [call() for call in calls]
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="magcal-fit") as pool:
        return list(pool.map(lambda call: call(), calls))
