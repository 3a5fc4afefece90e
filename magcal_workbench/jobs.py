"""One long job at a time, off the page's callback threads.

viser runs GUI callbacks in a thread pool, so two quick clicks would start two fits at once. The workbench
sends every engine step through one :class:`Worker`: a job runs in its own thread, :meth:`Worker.submit`
refuses a second job while one runs (and says which), and listeners hear when the busy state changes so the
buttons of every connected browser can be disabled and re-enabled.
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable

from .pending import Pending


class Worker:
    """Runs at most one job at a time in a background thread."""

    def __init__(self, settle: Callable[[], object] | None = None):
        #: Called when :meth:`wait` finds the worker idle (the workbench: until the page shows the job's end).
        self._settle = settle
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.current: str | None = None
        self.last_error: BaseException | None = None
        self._listeners: list[Callable[[bool, str | None], None]] = []
        self._idle = threading.Event()
        self._idle.set()
        #: The slow parts of the jobs' steps, run after their results are shown (:mod:`.pending`).
        self.pending = Pending()

    @property
    def busy(self) -> bool:
        return not self._idle.is_set()

    def on_busy_change(self, func: Callable[[bool, str | None], None]) -> None:
        """``func(busy, job_name)`` is called when a job starts and when it ends."""
        self._listeners.append(func)

    def submit(
        self,
        name: str,
        job: Callable[[], object],
        on_done: Callable[[object], None] | None = None,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> bool:
        """Start ``job`` in the background unless another job runs; returns False (and starts nothing) if busy.

        ``on_done(result)`` or ``on_error(exc)`` run in the worker thread after the job.
        """
        with self._lock:
            if self.busy:
                return False
            self._idle.clear()
            self.current = name
            self._thread = threading.Thread(
                target=self._run, args=(name, job, on_done, on_error), name=f"workbench-{name}", daemon=True
            )
        self._notify(True, name)
        self._thread.start()
        return True

    def run_now(self, name: str, job: Callable[[], object]):
        """Run ``job`` in the calling thread if nothing else runs (for tests and scripts); returns its result.

        Raises
        ------
        RuntimeError
            If another job is running.
        """
        with self._lock:
            if self.busy:
                raise RuntimeError(f"busy with {self.current}")
            self._idle.clear()
            self.current = name
        self._notify(True, name)
        try:
            return job()
        finally:
            self._finish(name)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until idle and the jobs' slow parts (:attr:`pending`) have ended (and, with ``settle``, the
        updates they handed on have run); False on timeout."""
        idle = self._idle.wait(timeout) and self.pending.wait(timeout)
        if idle and self._settle is not None:
            self._settle()
        return idle

    def in_job(self) -> bool:
        """Whether the calling thread is the running job's thread."""
        return self._thread is not None and threading.current_thread() is self._thread

    def _run(self, name, job, on_done, on_error):
        try:
            result = job()
        except BaseException as exc:  # reported to the page, never lost
            self.last_error = exc
            if on_error is not None:
                try:
                    on_error(exc)
                except Exception:
                    traceback.print_exc()
            else:
                traceback.print_exc()
        else:
            self.last_error = None
            if on_done is not None:
                try:
                    on_done(result)
                except Exception as exc:
                    self.last_error = exc
                    traceback.print_exc()
        finally:
            self._finish(name)

    def _finish(self, name):
        self._notify(False, name)  # listeners first, so that wait() returning means the page is updated too
        with self._lock:
            self.current = None
            self._idle.set()

    def _notify(self, busy, name):
        for func in list(self._listeners):
            try:
                func(busy, name)
            except Exception:
                traceback.print_exc()
