"""A compensation applied to survey lines: the scalar magnetometer minus the platform's field, as ``<scalar>_comp``.

``magcal apply comp.json LINE.csv -o out.csv`` with a compensation document (``kind: "compensation"``,
:class:`magcal.fitting.compensation.Compensation`) reads the line whole (its eddy and offset terms need each
sample's neighbours), takes the fluxgate (x, y, z), the scalar column the compensation was fitted on and, when the
compensation has those terms, the current or throttle and the temperature, and writes the line with one more column:
``<scalar>_comp`` (nT), the compensated scalar. A CSV line is written back as it was read (every input line, the
new column appended) when no row was dropped; otherwise, and for Parquet, the columns as magcal reads them (readings
in nT) plus the new one, to CSV or Parquet by the output's name. The line's fluxgate and time are found by name as
the flight's were (:func:`line_mapping`); on Dask partitions: :mod:`magcal.output.compensated_survey`.
"""

from __future__ import annotations

import csv
import io as _io
from dataclasses import dataclass

import numpy as np

from magcal.data.flight_columns import flight_mapping, header_names
from magcal.data.io import atomic_write, is_parquet, parse_column_mapping, read_csv
from magcal.fitting.compensation import Compensation, compensation_record, is_compensation_document
from magcal.output.compensated_file import (
    DOCUMENT_MAX_BYTES,
    LineSummary,
    check_new_columns,
    is_document_file,
    prepare,
    write_line,
)

#: The compensated scalar to 1 pT.
COMPENSATED_FORMAT = "%.3f"

__all__ = [
    "CompensationSummary",
    "apply_compensation_file",
    "compensated_column",
    "is_compensation_file",
    "line_mapping",
    "line_record",
]


#: The largest file :func:`is_compensation_file` reads to tell (a compensation document is a few kB).
COMPENSATION_FILE_MAX_BYTES = DOCUMENT_MAX_BYTES


def is_compensation_file(path) -> bool:
    """Whether ``path`` is a JSON compensation document (``kind: "compensation"``); False for anything else
    (:func:`magcal.output.compensated_file.is_document_file`)."""
    return is_document_file(path, is_compensation_document)


def compensated_column(compensation: Compensation) -> str:
    """The new column's name: ``<scalar>_comp``."""
    return f"{compensation.scalar_column}_comp"


@dataclass
class CompensationSummary(LineSummary):
    """What :func:`apply_compensation_file` wrote: ``column`` the compensated scalar's."""

    column: str = ""

    def text(self) -> str:
        return f"wrote {self.rows} rows to {self.output_path} with {self.column} (nT)"


def apply_compensation_file(
    compensation, survey_path, output_path, columns=None, units=None, drop_bad=False, compression=None
) -> CompensationSummary:
    """Compensate a survey line and write it with ``<scalar>_comp``.

    Parameters
    ----------
    compensation : Compensation or str or os.PathLike
        The compensation or its JSON file.
    survey_path, output_path : str or os.PathLike
        The line (CSV or Parquet, docs/formats.md; its fluxgate as x, y, z or mapped with ``columns``) and the
        output (``.parquet`` for Parquet), written atomically.
    columns, units, drop_bad
        As in :func:`magcal.data.io.read_csv`.
    compression : str, optional
        The float columns' codec of a Parquet output.

    Returns
    -------
    CompensationSummary

    Raises
    ------
    MagcalError
        The line lacks the scalar column, the current the compensation follows, or its rate differs.
    """
    compensation, survey_path, output_path = prepare(compensation, Compensation, survey_path, output_path)
    dataset = read_csv(
        survey_path,
        columns=line_mapping(compensation, survey_path, columns),
        units=units,
        drop_bad=drop_bad,
        warn=False,
    )
    name = compensated_column(compensation)
    check_new_columns(dataset, [name], survey_path)
    record = line_record(compensation, dataset)
    values = compensation.compensate(record)
    notes = [note.text for note in dataset.notes]
    kept_lines = not is_parquet(survey_path) and not is_parquet(output_path)
    if kept_lines and not _append_to_lines(survey_path, output_path, name, values):
        kept_lines = False
    if not kept_lines:
        write_line(output_path, dataset, {name: values}, f"{name} the compensated scalar, nT", compression)
    return CompensationSummary(int(values.size), output_path, notes, column=name)


def line_mapping(compensation: Compensation, path, columns=None) -> dict | None:
    """The column mapping a line is read with: the user's, plus the fluxgate the compensation was fitted on (or the
    first the line names) and MagNav.jl's time ``tt`` (:func:`magcal.data.flight_columns.flight_mapping`)."""
    given = parse_column_mapping(columns) if isinstance(columns, str) else dict(columns or {})
    mapping = flight_mapping(header_names(path), given, preferred=compensation.fluxgate_columns)
    return mapping or None


def line_record(compensation: Compensation, dataset):
    """A line's :class:`~magcal.fitting.compensation.CompensationRecord`, with the compensation's scalar and current
    columns."""
    wanted = compensation.current_columns if "current" in compensation.effects else ()
    current = [c for c in wanted if c in dataset.extra]  # the compensation says which column the line lacks
    return compensation_record(dataset, compensation.scalar_column, current or None)


def _append_to_lines(survey_path: str, output_path: str, name: str, values) -> bool:
    """Write the CSV's lines as they are with ``name`` appended; False (nothing written) when its data lines are
    not one per value (rows dropped on reading)."""
    with open(survey_path, encoding="utf-8", newline="") as fh:
        lines = fh.read().splitlines()
    heads = [k for k, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    if not heads:
        return False
    header, data = heads[0], [k for k in heads[1:]]
    if len(data) != len(values):
        return False
    header_text = _io.StringIO()
    csv.writer(header_text, lineterminator="").writerow([name])
    texts = [COMPENSATED_FORMAT % v for v in np.asarray(values, float)]
    out_lines = list(lines)
    out_lines[header] = lines[header] + "," + header_text.getvalue()
    for k, text in zip(data, texts):
        out_lines[k] = lines[k] + "," + text
    with atomic_write(output_path) as out:
        out.write("# magcal_columns: " + f"{name} the compensated scalar, nT\n")
        out.write("\n".join(out_lines) + "\n")
    return True
