"""Reading data for the workbench: a file, an upload's bytes (a CSV or a flight-controller log), magcal's own
CSV of what was read, and the engine's messages in the page's words. (A session's effects files are loaded only
when the user asks: :meth:`magcal_workbench.controller.Controller.load_session_effects_files`.)"""

from __future__ import annotations

import io
import os
import tempfile

from magcal.data import io as mio
from magcal.data.logs import is_log


def load_dataset(source, name: str | None = None, **options):
    """Read a CSV (a path or an open file object) with the engine's reader; messages and the dataset's source
    name ``name`` when given; ``options`` (``columns``, ``units``, ``lsb_nT``) go to :func:`magcal.data.io.read_csv`.
    Returns the dataset and the reader's warnings as text (a clear :class:`MagcalError` on problems)."""
    options = {k: v for k, v in options.items() if v is not None}
    # the reader's notes as values, not warnings (this may run on the workbench's worker thread)
    ds = mio.read_csv(source, name=name, warn=False, **options)
    return ds, [note.text for note in ds.notes]


def read_bytes_dataset(name: str, content: bytes, **options):
    """Read an uploaded file from its bytes; messages name the upload (its base name). A flight-controller log
    (``.bin``, ``.ulg``; :mod:`magcal.data.logs`) is written to a temporary file for its reader, which needs a path, and
    the column and unit options do not apply to it (a note says so when some were given)."""
    name = os.path.basename(name) or "upload.csv"
    if not is_log(name):
        return load_dataset(io.BytesIO(content), name, **options)
    with tempfile.TemporaryDirectory(prefix="magcal-upload-") as folder:
        path = os.path.join(folder, "upload" + os.path.splitext(name)[1].lower())
        with open(path, "wb") as fh:
            fh.write(content)
        ds, notes = load_dataset(path, name)
    given = [k for k, v in options.items() if v is not None]
    if given:
        notes.append(f"{name}: a flight-controller log carries its own fields and units; {', '.join(given)} ignored")
    return ds, notes


def canonical_csv(dataset) -> bytes:
    """The dataset as magcal's own CSV (readings in nT, canonical column names): what a session keeps of data
    that needed a column mapping, units or a log reader to open, so that it reopens without them."""
    with tempfile.TemporaryDirectory(prefix="magcal-canonical-") as folder:
        path = os.path.join(folder, "data.csv")
        mio.write_csv(path, dataset)
        with open(path, "rb") as fh:
            return fh.read()


def page_words(text: str) -> str:
    """An engine message with the command line's option names replaced by the page's widgets."""
    for flag, widget in (
        ("--columns", "the Files tab's Columns box:"),
        ("--units", "the Files tab's Units choice"),
        ("--lsb", "the Files tab's LSB box"),
    ):
        text = text.replace(flag, widget)
    return text
