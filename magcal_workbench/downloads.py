"""Files the page downloads: the calibration JSON, the corrected CSV (and the evidence plots,
:mod:`magcal_workbench.evidence`)."""

from __future__ import annotations

from .actions import action


class Downloads:
    """Sends files to the browser that asked; the last one is kept (:attr:`last`) for tests and scripts.

    Parameters
    ----------
    ctrl : callable
        Returns the current :class:`~magcal_workbench.controller.Controller`.
    """

    def __init__(self, ctrl):
        self._ctrl = ctrl
        #: ``(filename, content)`` of the last download.
        self.last: tuple[str, bytes] | None = None

    def send(self, event, filename: str, content: bytes) -> None:
        """Send ``content`` as ``filename`` to the browser of ``event`` (none: only kept as :attr:`last`)."""
        self.last = (filename, content)
        client = getattr(event, "client", None)
        if client is not None:
            client.send_file_download(filename, content)

    @action
    def do_download_calibration(self, event):
        self.send(event, "calibration.json", self._ctrl().calibration_json())

    @action
    def do_download_corrected(self, event):
        self.send(event, "corrected.csv", self._ctrl().corrected_csv())
