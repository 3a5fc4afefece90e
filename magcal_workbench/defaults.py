"""The workbench's default bounds, in a module that imports nothing: the launcher's command line
(:mod:`magcal_workbench.startup`) reads them before the heavy parts are imported."""

from __future__ import annotations

#: Most points drawn per cloud (one sensor's raw or corrected readings); larger data are drawn decimated.
MAX_POINTS = 20_000
#: Default upload limit, MB (10^6 bytes; ``--max-upload-mb``).
DEFAULT_MAX_UPLOAD_MB = 100.0
#: Default bound of the session folder, bytes (``--max-sessions-mb``).
MAX_STORE_BYTES = 2_000_000_000
