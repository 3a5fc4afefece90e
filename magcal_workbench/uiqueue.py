"""The one way a background thread changes the page.

The engine's worker, a live session's threads (the source, its refits) and the time scrubber's playback run off
viser's callback threads. None of them touches a panel, the scene or a widget: each hands a callable to
:meth:`UiQueue.post`, and one thread (``workbench-ui``) runs them in the order they came. :meth:`UiQueue.wait`
returns once everything posted before it has run, so a caller that waits for a job (``Worker.wait``) also sees
the page it left.
"""

from __future__ import annotations

import queue
import threading
import traceback
from collections.abc import Callable


class UiQueue:
    """Callables run one at a time on one thread, in the order posted."""

    def __init__(self):
        self._queue: queue.Queue = queue.Queue()
        self._stopped = False
        self._thread = threading.Thread(target=self._drain, name="workbench-ui", daemon=True)
        self._thread.start()

    def post(self, func: Callable[[], object]) -> None:
        """Run ``func()`` on the UI thread (at once when called there: a callback a UI update set off)."""
        if threading.current_thread() is self._thread or self._stopped:
            self._run(func)  # after stop: in the caller's thread (the page is gone)
        else:
            self._queue.put(func)

    def run(self, func: Callable[[], object], timeout: float | None = 60.0) -> None:
        """Run ``func()`` on the UI thread and wait for it (and for everything posted before it)."""
        self.post(func)
        self.wait(timeout)

    def wait(self, timeout: float | None = 60.0) -> bool:
        """Block until everything posted so far has run; returns False on timeout. On the UI thread itself it
        returns at once (it cannot wait for itself)."""
        if threading.current_thread() is self._thread or self._stopped:
            return True
        done = threading.Event()
        self._queue.put(done.set)
        return done.wait(timeout)

    def stop(self) -> None:
        """Run what is queued, then end the thread; later posts run in the caller's thread."""
        if self._stopped:
            return
        self.wait()
        self._stopped = True
        self._queue.put(None)

    @staticmethod
    def _run(func) -> None:
        try:
            func()
        except Exception:  # a failed update must not stop the page's updates
            traceback.print_exc()

    def _drain(self) -> None:
        while True:
            func = self._queue.get()
            if func is None:
                return
            self._run(func)
