"""The slow parts of a step, run after its result is on the page.

A fit's result (its RMS, the corrected clouds, the message line) is shown as soon as it exists; what takes longer
-- the held-out check, the autosave that records it -- follows in a background thread, and the page marks it
``pending...`` until then. The engine's worker is free meanwhile, so the next click starts at once.

Each fit opens a new *generation* (:meth:`Pending.next_generation`); a slow part is handed the generation it
belongs to and asks :meth:`Pending.current` before it starts and before it publishes: a part whose fit has been
followed by another one is stale, and is dropped unseen. :meth:`Pending.wait` returns once no part runs (the
workbench's :meth:`~magcal_workbench.jobs.Worker.wait` waits for them too, so a script or a test that waits for a
job sees its held-out figure).
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable

#: How the page marks a part that is still being computed.
PENDING = "pending..."


class Pending:
    """Background slow parts, each tagged with the generation (the fit) it belongs to."""

    def __init__(self):
        self._lock = threading.Condition()
        self._generation = 0
        self._running = 0
        #: Names of the parts running now (e.g. ``"heldout"``), for the page's pending markers and for tests.
        self.names: list[str] = []
        #: Parts dropped because a newer fit came first (a count, for tests and the benchmark).
        self.n_stale = 0

    @property
    def generation(self) -> int:
        """The newest generation."""
        return self._generation

    def next_generation(self) -> int:
        """A new fit: every part of an older generation becomes stale. Returns the new generation."""
        with self._lock:
            self._generation += 1
            return self._generation

    def current(self, generation: int) -> bool:
        """Whether ``generation`` is still the newest (its parts may publish)."""
        return generation == self._generation

    def busy(self) -> bool:
        """Whether a part runs."""
        return self._running > 0

    def start(self, generation: int, name: str, part: Callable[[Callable[[], bool]], object]) -> None:
        """Run ``part(still_current)`` in a background thread; ``still_current()`` says whether ``generation``
        is still the newest. A part that finds itself stale at its start is not run (and counted in
        :attr:`n_stale`); one that does, publishes nothing after it (its own check)."""
        with self._lock:
            self._running += 1
            self.names.append(name)

        def still_current() -> bool:
            return self.current(generation)

        def run():
            try:
                if still_current():
                    part(still_current)
            except Exception:  # a slow part that fails must not stop the page's later updates
                traceback.print_exc()
            finally:
                with self._lock:
                    if not still_current():
                        self.n_stale += 1
                    self._running -= 1
                    self.names.remove(name)
                    self._lock.notify_all()

        threading.Thread(target=run, name=f"workbench-pending-{name}", daemon=True).start()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until no part runs; False on timeout."""
        with self._lock:
            return self._lock.wait_for(lambda: self._running == 0, timeout)
