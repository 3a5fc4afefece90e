"""What the compensations' applies share: a compensation document told from its file, the line and output paths
checked, and the line written with the compensated columns appended.

The scalar compensation (:mod:`magcal.output.compensated_line`, ``<scalar>_comp``) and the cross's
(:mod:`magcal.output.cross_compensated_line`, ``s1x_comp`` ... and the tensor) each compute their own columns; the
document's recognition (:func:`is_document_file`), the paths (:func:`prepare`), the new columns' clash with the
line's (:func:`check_new_columns`), the file written (:func:`write_line`: the line's columns as magcal reads them,
readings in nT, plus the new ones, to CSV or Parquet by the output's name) and the summary
(:class:`LineSummary`) are these.
"""

from __future__ import annotations

import csv
import json
import os
from dataclasses import dataclass, field

from magcal.core.errors import MagcalError
from magcal.core.files import not_regular_reason
from magcal.data.dataset import dataset_columns, dataset_metadata
from magcal.data.io import (
    atomic_write,
    check_output_path,
    is_parquet,
    metadata_text,
    parquet_table,
    parquet_write_options,
    write_rows,
)

__all__ = ["DOCUMENT_MAX_BYTES", "LineSummary", "check_new_columns", "is_document_file", "prepare", "write_line"]

#: The largest file :func:`is_document_file` reads to tell (a compensation document is a few kB).
DOCUMENT_MAX_BYTES = 16 << 20


def is_document_file(path, is_document) -> bool:
    """Whether ``path`` holds a JSON document ``is_document`` (a predicate on the parsed JSON) accepts; False for
    anything else, including a file that is not a regular one (a FIFO would block the read), is larger than
    :data:`DOCUMENT_MAX_BYTES` or cannot be read (the calibration reader then says why)."""
    try:
        if not_regular_reason(path) is not None or os.path.getsize(path) > DOCUMENT_MAX_BYTES:
            return False
        with open(os.fspath(path), encoding="utf-8") as fh:
            return bool(is_document(json.load(fh)))
    except (OSError, UnicodeDecodeError, ValueError):
        return False


def prepare(compensation, kind, survey_path, output_path):
    """``(compensation, survey path, output path)``: the compensation (``kind``, loaded with ``kind.load`` when a
    path is given) and the paths as strings, the output checked (a writable place, not the survey file itself)."""
    check_output_path(output_path, "output")
    if not isinstance(compensation, kind):
        compensation = kind.load(compensation)
    survey_path, output_path = os.fspath(survey_path), os.fspath(output_path)
    if os.path.exists(output_path) and os.path.samefile(survey_path, output_path):
        raise MagcalError(f"{output_path}: the output would overwrite the survey file; choose another name")
    return compensation, survey_path, output_path


def check_new_columns(dataset, names, survey_path) -> None:
    """Refuse a line that already has one of the columns the apply writes (an apply output read again)."""
    clash = [name for name in names if name in dataset.extra]
    if clash:
        raise MagcalError(f"{survey_path}: the line already has a column {clash[0]} (is it an apply output?)")


def write_line(output_path, dataset, new_columns: dict, description: str, compression=None) -> None:
    """Write the line's columns as magcal reads them (readings in nT) and ``new_columns`` (name -> values) to
    ``output_path`` atomically: Parquet for a ``.parquet`` name (floats with ``compression``), else CSV with the
    line's head; ``description`` says what the columns are (``# magcal_columns:``)."""
    columns_out = dict(dataset_columns(dataset)) | dict(new_columns)
    meta = dataset_metadata(dataset) | {"magcal_columns": f"readings in nT; {description}"}
    if is_parquet(output_path):
        import pyarrow.parquet as pq

        table = parquet_table(columns_out, meta)
        with atomic_write(output_path, mode="wb", encoding=None, newline=None) as fh:
            pq.write_table(table, fh, **parquet_write_options(table, compression))
    else:
        with atomic_write(output_path) as out:
            out.write(metadata_text(meta))
            csv.writer(out, lineterminator="\n").writerow(list(columns_out))
            write_rows(out, columns_out)


@dataclass
class LineSummary:
    """What an apply wrote: the rows, the output, the notes of reading the line, the new columns in words."""

    rows: int
    output_path: str
    notes: list = field(default_factory=list)
    wrote: str = ""

    def text(self) -> str:
        return f"wrote {self.rows} rows to {self.output_path} with {self.wrote}"
