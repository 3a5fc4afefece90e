"""The cross's compensation applied to a survey line: each sensor's compensated vector and the compensated gradient
tensor.

``magcal apply cross.json LINE.csv -o out.csv`` with a cross compensation document (``kind:
"cross_compensation"``, :class:`magcal.fitting.cross_compensation.CrossCompensation`) reads the line whole (the
eddy terms need each sample's neighbours), takes the four sensors' readings (s1x .. s4z), the time (the eddy
term's rate) and, when the compensation has the current term, the current's column it was fitted with, and writes
the line's columns as magcal reads them (readings in nT) plus ``s{i}x_comp, s{i}y_comp, s{i}z_comp`` (nT, the
platform's body frame, or the four's mean frame for a ``mean`` reference) and the tensor of the compensated sensors
under the names a calibrated cross's apply writes (:data:`magcal.output.apply.TENSOR_COLUMNS`, nT/m, and the
invariants ``I0, I1, I2``), to CSV or Parquet by the output's name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.core import conventions
from magcal.core.errors import MagcalError
from magcal.data.io import read_csv
from magcal.fitting.cross_compensation import CrossCompensation, is_cross_compensation_document
from magcal.output.apply import INVARIANT_COLUMNS, TENSOR_COLUMNS, tensor_invariants
from magcal.output.compensated_file import LineSummary, check_new_columns, is_document_file, prepare, write_line

__all__ = [
    "CrossCompensationSummary",
    "apply_cross_compensation_file",
    "compensated_columns",
    "is_cross_compensation_file",
]


def is_cross_compensation_file(path) -> bool:
    """Whether ``path`` is a JSON cross compensation document; False for anything else
    (:func:`magcal.output.compensated_file.is_document_file`)."""
    return is_document_file(path, is_cross_compensation_document)


def compensated_columns() -> list[str]:
    """The columns the apply appends: each sensor's compensated vector, the tensor and its invariants."""
    return [f"s{i}{a}_comp" for i in range(1, 5) for a in "xyz"] + list(TENSOR_COLUMNS) + list(INVARIANT_COLUMNS)


@dataclass
class CrossCompensationSummary(LineSummary):
    """What :func:`apply_cross_compensation_file` wrote."""

    def text(self) -> str:
        return (
            f"wrote {self.rows} rows to {self.output_path} with s1x_comp .. s4z_comp (nT) and the compensated "
            "tensor Gxx .. Gzz (nT/m)"
        )


def _line_current(compensation: CrossCompensation, dataset, survey_path):
    if not compensation.current:
        return None
    names = compensation.current_columns or (compensation.current_column or "current_A",)
    for name in names:
        if name not in dataset.extra:
            raise MagcalError(
                f"{survey_path}: the compensation follows the platform's current (column {name!r}); the line has "
                "no such column: add it or map it with --columns"
            )
    return np.column_stack([np.asarray(dataset.extra[name], dtype=float) for name in names])


def apply_cross_compensation_file(
    compensation, survey_path, output_path, columns=None, units=None, drop_bad=False, compression=None
) -> CrossCompensationSummary:
    """Compensate a line of the cross and write it with the compensated vectors and tensor.

    Parameters
    ----------
    compensation : CrossCompensation or str or os.PathLike
        The compensation or its JSON file.
    survey_path, output_path : str or os.PathLike
        The line (CSV or Parquet with s1x .. s4z and t) and the output (``.parquet`` for Parquet), written
        atomically.
    columns, units, drop_bad
        As in :func:`magcal.data.io.read_csv`.
    compression : str, optional
        The float columns' codec of a Parquet output.

    Returns
    -------
    CrossCompensationSummary

    Raises
    ------
    MagcalError
        The line lacks four sensors, the times or the current the compensation follows.
    """
    compensation, survey_path, output_path = prepare(compensation, CrossCompensation, survey_path, output_path)
    dataset = read_csv(survey_path, columns=columns, units=units, drop_bad=drop_bad, warn=False)
    if dataset.n_sensors != 4:
        raise MagcalError(f"{survey_path}: the cross's compensation needs four sensors (s1x .. s4z); the line has "
                          f"{dataset.n_sensors}")  # fmt: skip
    check_new_columns(dataset, compensated_columns(), survey_path)
    notes = [note.text for note in dataset.notes]
    if dataset.time_s is None:
        notes.append(
            f"the line has no time column t: its rate is taken as the fit's, {compensation.sample_rate_hz:g} Hz"
        )
    try:
        vectors = compensation.compensate(
            dataset.readings_nT, time_s=dataset.time_s, current_A=_line_current(compensation, dataset, survey_path)
        )
    except MagcalError as exc:
        raise MagcalError(f"{survey_path}: {exc}") from None
    baseline = compensation.baseline_m or dataset.baseline_m
    if not baseline:
        raise MagcalError(f"{survey_path}: the tensor needs the cross's baseline: add '# baseline_m: 0.5' (m)")
    comps = conventions.tensor_components(vectors, baseline)
    invariants = tensor_invariants(conventions.tensor_matrix(comps))
    new = {f"s{i + 1}{a}_comp": vectors[i][:, k] for i in range(4) for k, a in enumerate("xyz")}
    new |= {name: np.asarray(comps[name], dtype=float) for name in TENSOR_COLUMNS}
    new |= dict(zip(INVARIANT_COLUMNS, invariants))
    description = "s*_comp the compensated vectors, nT; G* the compensated tensor, nT/m"
    write_line(output_path, dataset, new, description, compression)
    return CrossCompensationSummary(int(vectors.shape[1]), output_path, notes)
