"""Named spans of the server's work, logged when asked (``magcal-workbench --timing`` or ``MAGCAL_TIMING=1``).

``benchmarks/page_latency.py`` reads these lines from the workbench's standard error to split a click's wait into
the server's parts (fit, held-out check, uncertainty, coverage, scene, plots, send) and the browser's rest. Each
line is ``magcal-timing: NAME START_S SECONDS``: the span's start on the process's monotonic clock
(:func:`time.perf_counter`, seconds) and its length in seconds. Off by default: a span then costs one test.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from contextlib import contextmanager

#: The environment variable that turns the log on (any value but ``""`` and ``"0"``).
ENV = "MAGCAL_TIMING"

_enabled = os.environ.get(ENV, "") not in ("", "0")
_lock = threading.Lock()


def enable(on: bool = True) -> None:
    """Turn the span log on (``--timing``) or off."""
    global _enabled
    _enabled = bool(on)


def enabled() -> bool:
    """Whether spans are logged."""
    return _enabled


def log(name: str, start_s: float, seconds: float) -> None:
    """Write one span's line to standard error (when enabled)."""
    if not _enabled:
        return
    with _lock:
        print(f"magcal-timing: {name} {start_s:.4f} {seconds:.4f}", file=sys.stderr, flush=True)


@contextmanager
def span(name: str):
    """Time the ``with`` block as the span ``name`` (logged when enabled, also when the block raises)."""
    if not _enabled:
        yield
        return
    t0 = time.perf_counter()
    try:
        yield
    finally:
        log(name, t0, time.perf_counter() - t0)
