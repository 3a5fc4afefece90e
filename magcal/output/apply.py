"""Survey correction (patent S9-S10): apply a calibration to a survey file, streaming, and write the results.

``apply_file(calibration, survey.csv, out.csv)`` copies every input line unchanged and appends

* ``s{i}x_cal, s{i}y_cal, s{i}z_cal`` for every sensor: the corrected field vector in nT, in the calibration's
  frame (``platform`` after a level-table alignment, otherwise sensor 1's frame);
* with a vector calibration (``mode: vector``, :mod:`magcal.fitting.vector`) those are body-frame components, and
  when the survey has the attitude (``qw..qz`` or ``roll_deg, pitch_deg, yaw_deg``) also the world
  (north-east-down) components ``s{i}n_cal, s{i}e_cal, s{i}d_cal`` (and, for four sensors, the tensor in world
  coordinates ``Gnn, Gne, Gnd, Gee, Ged, Gdd`` = ``R G R^T``);
* with a gravity calibration (``mode: gravity``, :mod:`magcal.fitting.gravity`) and the survey's accelerometer
  (``ax, ay, az``): the tilt-compensated magnetic heading of the board's x axis ``s{i}_heading_deg`` ([0, 360)),
  the dip ``s{i}_dip_deg`` and the board's tilt ``tilt_deg`` (:meth:`Calibration.heading`);
* for four sensors with a baseline: the tensor components ``Gxx, Gxy, Gxz, Gyy, Gyz, Gzz`` of eq. (1) (Chi et al.
  2017) and ``Gyx`` (the second estimate of the xy component; ``Gxy - Gyx`` is a check), in nT/m, and the
  rotational invariants of the symmetric part ``G = (T + T^T)/2`` (Pedersen & Rasmussen 1990)::

      I0 = tr G                                  (nT/m; zero by construction of eq. (1)'s Gzz)
      I1 = Gxx Gyy + Gyy Gzz + Gxx Gzz - Gxy^2 - Gyz^2 - Gxz^2      ((nT/m)^2)
      I2 = det G                                 ((nT/m)^3)

The file is read and written in chunks (``chunk_rows`` lines at a time), so memory stays flat however long the
survey; the output is written to a temporary file and renamed at the end (atomic), so a failure leaves no partial
output. A progress bar (tqdm) is shown when stderr is a terminal.
"""

from __future__ import annotations

import csv
import io as _io
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from magcal.calibration.calibration import Calibration, RecordHasher
from magcal.core import conventions
from magcal.core.errors import DataWarning, MagcalError, RecordTermWarning
from magcal.core.files import check_regular_file
from magcal.core.notes import Note, runs, runs_text
from magcal.data.accelerometer import ACCEL_COLUMNS, has_accelerometer
from magcal.data.attitude import EULER_COLUMNS, attitude_present, attitude_source
from magcal.data.dataset import DatasetError, dataset_columns, dataset_metadata
from magcal.data.io import (
    CsvSource,
    ParquetSource,
    atomic_write,
    check_output_path,
    check_parquet_codec,
    check_units,
    is_parquet,
    metadata_text,
    parquet_table,
    parquet_write_options,
    parse_column_mapping,
    write_rows,
)
from magcal.data.logs import is_log, read_log
from magcal.model.terms import CORRECTION_STAGES

#: Output formats: corrected vectors and tensor components to 1 pT / 1 pT/m; invariants to 7 significant digits.
VECTOR_FORMAT = "%.3f"
TENSOR_FORMAT = "%.3f"
INVARIANT_FORMAT = "%.7g"
#: Standard deviations (``--uncertainty``): 4 significant digits.
SD_FORMAT = "%.4g"
#: Headings, dips and tilts (deg) to a thousandth of a degree.
HEADING_FORMAT = "%.3f"

#: Tensor columns written for a four-sensor array (eq. 1), in order.
TENSOR_COLUMNS = ("Gxx", "Gxy", "Gxz", "Gyy", "Gyz", "Gzz", "Gyx")
INVARIANT_COLUMNS = ("I0", "I1", "I2")
#: The tensor in world (north-east-down) coordinates, written with a vector calibration and attitude.
WORLD_TENSOR_COLUMNS = ("Gnn", "Gne", "Gnd", "Gee", "Ged", "Gdd")
_WORLD_TENSOR_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@dataclass(frozen=True)
class Refusal:
    """The sensors an application of a calibration leaves out: those the fit marked not determined by its record
    (:meth:`magcal.calibration.calibration.Calibration.undetermined`), unless forced.

    Attributes
    ----------
    refused : tuple of int
        The 0-based sensors whose corrected columns are left out (empty when forced or all determined).
    note : Note or None
        What was refused or forced, and why (:meth:`~magcal.calibration.calibration.Calibration.refusal_note`).
    forced : bool
        Undetermined sensors applied anyway.
    """

    refused: tuple = ()
    note: Note | None = None
    forced: bool = False

    @classmethod
    def of(cls, calibration, force=False, where="the calibration") -> Refusal:
        """The refusal for applying ``calibration`` (``force``: apply its undetermined sensors too).

        Raises
        ------
        MagcalError
            Every sensor is undetermined and ``force`` is false: nothing would be applied.
        """
        undetermined = calibration.undetermined()
        if undetermined and not force and len(undetermined) == calibration.n_sensors:
            said = "; ".join(f"sensor {s + 1}: {why}" for s, why in undetermined.items())
            raise MagcalError(
                f"{where}: not applied: {said}. Recalibrate on a record that determines it (docs/vector.md), or "
                "force it (--force) knowing its corrected values may be far off"
            )
        note = calibration.refusal_note(force)
        return cls(() if force else tuple(sorted(undetermined)), note, bool(force and undetermined))

    def metadata(self) -> dict:
        """The output header's line on it: ``magcal_refused`` or ``magcal_forced`` (none when all are determined)."""
        if self.note is None:
            return {}
        return {"magcal_forced" if self.forced else "magcal_refused": self.note.text}


def load_calibration(path, n_sensors=None):
    """Load a calibration file with every check a user needs (:meth:`magcal.calibration.calibration.Calibration.load`).

    Parameters
    ----------
    path : str or os.PathLike
    n_sensors : int, optional
        Refuse a calibration made for a different number of sensors.

    Returns
    -------
    magcal.calibration.calibration.Calibration
    """

    return Calibration.load(path, n_sensors=n_sensors)


def tensor_invariants(tensor):
    """Invariants I0, I1, I2 (Pedersen & Rasmussen 1990) of the symmetric part of (N, 3, 3) tensors in nT/m."""
    t = np.asarray(tensor, dtype=float)
    g = 0.5 * (t + np.swapaxes(t, -1, -2))
    i0 = np.trace(g, axis1=-2, axis2=-1)
    gxx, gyy, gzz = g[..., 0, 0], g[..., 1, 1], g[..., 2, 2]
    gxy, gxz, gyz = g[..., 0, 1], g[..., 0, 2], g[..., 1, 2]
    i1 = gxx * gyy + gyy * gzz + gxx * gzz - gxy**2 - gyz**2 - gxz**2
    # the determinant of the symmetric 3 x 3, written out (numpy's batched LU is ~10x slower per sample)
    i2 = gxx * (gyy * gzz - gyz**2) - gxy * (gxy * gzz - gyz * gxz) + gxz * (gxy * gyz - gyy * gxz)
    return i0, i1, i2


def gives_tensor(calibration) -> bool:
    """Whether corrected vectors of ``calibration`` give a gradient tensor: a cross of four sensors with its
    baseline known."""
    return calibration.n_sensors == 4 and bool(calibration.baseline_m)


def heading_columns(n_sensors) -> list[str]:
    """The columns a gravity calibration adds (:meth:`Calibration.heading`): per sensor the heading and the dip,
    then the board's tilt (deg)."""
    return (
        [f"s{i + 1}_heading_deg" for i in range(n_sensors)]
        + [f"s{i + 1}_dip_deg" for i in range(n_sensors)]
        + ["tilt_deg"]
    )


def writes_heading(calibration, dataset=None, layout=None) -> bool:
    """True when ``apply`` writes the heading: a gravity calibration and a survey with accelerometer columns (a
    dataset, or a CSV file's :class:`magcal.data.io.Layout`)."""
    if getattr(calibration, "mode", "scalar") != "gravity":
        return False
    if layout is not None:
        return any(all(n in layout.extra for n in names) for names, _ in ACCEL_COLUMNS)
    return dataset is not None and has_accelerometer(dataset)


def output_columns(n_sensors, tensor, uncertainty=False, world=False, heading=False, refused=()):
    """Names of the columns ``apply`` appends (with ``uncertainty``: the calibration's standard deviations,
    ``s{i}x_cal_sd ..``, ``s{i}_F_sd`` for ``|B|``, ``G.._sd``; with ``world``: the north-east-down components
    ``s{i}n_cal ..`` and, for arrays, ``Gnn ..``). The sensors ``refused`` (0-based, :class:`Refusal`) have none,
    and with one refused no tensor is written (it needs every sensor)."""
    sensors = [i for i in range(n_sensors) if i not in set(refused)]
    tensor = tensor and not refused
    names = [f"s{i + 1}{a}_cal" for i in sensors for a in "xyz"]
    if tensor:
        names += list(TENSOR_COLUMNS) + list(INVARIANT_COLUMNS)
    if world:
        names += [f"s{i + 1}{a}_cal" for i in sensors for a in "ned"]
        if tensor:
            names += list(WORLD_TENSOR_COLUMNS)
    if uncertainty:
        names += [f"s{i + 1}{a}_cal_sd" for i in sensors for a in "xyz"]
        names += [f"s{i + 1}_F_sd" for i in sensors]
        if tensor:
            names += [f"{c}_sd" for c in TENSOR_COLUMNS]
    if heading:
        names += [n for n in heading_columns(n_sensors) if not n.startswith(tuple(f"s{i + 1}_" for i in refused))]
    return names


def column_format(name: str) -> str:
    """The printf format of one output column (:func:`output_columns`) in a CSV: vectors and tensors to 1 pT (per
    m), invariants to 7 digits, standard deviations to 4, angles to a thousandth of a degree."""
    if name.endswith("_sd"):
        return SD_FORMAT
    if name in INVARIANT_COLUMNS:
        return INVARIANT_FORMAT
    if name in TENSOR_COLUMNS or name in WORLD_TENSOR_COLUMNS:
        return TENSOR_FORMAT
    if name.endswith("_deg"):
        return HEADING_FORMAT
    return VECTOR_FORMAT


def writes_world(calibration, dataset=None, layout=None) -> bool:
    """True when ``apply`` writes world components: a vector calibration and a survey with attitude (a dataset,
    or a CSV file's :class:`magcal.data.io.Layout`)."""
    if getattr(calibration, "mode", "scalar") != "vector":
        return False
    if layout is not None:
        return layout.quaternion is not None or all(c in layout.extra for c in EULER_COLUMNS)
    return dataset is not None and attitude_source(dataset) is not None


def input_columns(where, dataset, names) -> dict:
    """The block's own columns (:func:`magcal.data.dataset.dataset_columns`), checked not to hold any of the
    output columns ``names`` (a file that is already an apply output); ``where`` names the file in the message."""
    cols = dataset_columns(dataset)
    clash = sorted(set(names) & set(cols))
    if clash:
        raise MagcalError(
            f"{where}: the file already has column(s) {', '.join(clash)} (is it an apply output?); "
            "rename them or correct the raw survey"
        )
    return cols


def correct_block(calibration, dataset, record_terms, uncertainty=False, world=False, heading=False, refused=()):
    """New column values (N, k) for one block: corrected vectors, and the tensor and invariants for arrays; with
    ``uncertainty`` also the calibration's standard deviations of each (:meth:`Calibration.uncertainty`), in the
    order of :func:`output_columns`.

    ``record_terms``: ``'apply'`` or ``'drop'``, decided once for the whole file (:func:`record_choice`, which
    says why). ``world``: also the north-east-down components (a vector
    calibration and the block's attitude, :meth:`Calibration.world`). A sample without attitude gets NaN
    corrected vectors where an acting effect needs it (``site_gradient``), unsaid here: the callers count such
    rows over the survey (:class:`AttitudeGaps`) and say it once. ``refused``: the sensors left out
    (:class:`Refusal`, :func:`output_columns`); every other sensor is corrected, forced or not.
    """
    vectors = calibration.correct(dataset, record_terms, warn=False, force=True)
    n = dataset.n_samples
    parts = [vectors.transpose(1, 0, 2).reshape(n, -1)]
    tensor = gives_tensor(calibration) and not refused
    if tensor:
        comps = calibration.tensor(dataset, vectors)  # in the cross's own frame (a vector calibration's too)
        parts.append(np.column_stack([comps[c] for c in TENSOR_COLUMNS]))
        i0, i1, i2 = tensor_invariants(conventions.tensor_matrix(comps))
        parts.append(np.column_stack([i0, i1, i2]))
    if world:
        parts.append(calibration.world(dataset, vectors).transpose(1, 0, 2).reshape(n, -1))
        if tensor:
            g = calibration.world_tensor(dataset, vectors)
            parts.append(np.column_stack([g[:, i, j] for i, j in _WORLD_TENSOR_INDEX]))
    if uncertainty:
        u = calibration.uncertainty(dataset, vectors, record_terms)
        if u is None:
            raise MagcalError(
                "this calibration carries no parameter covariance (it was made before magcal saved "
                "one, or without a maximum-likelihood fit): recalibrate to get error bars"
            )
        parts.append(u["vector_sd_nT"].transpose(1, 0, 2).reshape(n, -1))
        parts.append(u["total_sd_nT"].T)
        if tensor:
            parts.append(np.column_stack([u["tensor_sd_nT_per_m"][c] for c in TENSOR_COLUMNS]))
    if heading:  # a gravity calibration: the tilt-compensated compass
        h = calibration.heading(dataset, vectors)
        parts += [h["heading_deg"].T, h["dip_deg"].T, h["tilt_deg"][:, None]]
    values = np.hstack(parts)
    if not refused:
        return values
    every = output_columns(calibration.n_sensors, tensor, uncertainty, world, heading)
    kept = set(output_columns(calibration.n_sensors, tensor, uncertainty, world, heading, refused))
    return values[:, [k for k, name in enumerate(every) if name in kept]]


def refuse_non_finite(values, names, source, dataset=None, row_name=None) -> None:
    """Refuse output values that are not finite numbers: nothing non-finite is ever written.

    A NaN on a row without attitude (``dataset``'s attitude channel NaN there) is the documented gap of the world
    columns (and of every corrected column when an acting effect needs the attitude, :class:`AttitudeGaps`), and
    is kept; any other NaN or infinity (a calibration whose values overflow on these readings, a channel an
    effect needs holding NaN) is refused, naming the first row and column.

    Parameters
    ----------
    values : numpy.ndarray, shape (N, k)
    names : sequence of str
        The ``k`` column names.
    source : str
        The file, for the message.
    dataset : Dataset, optional
        The block the values were computed from (its attitude says which rows may hold NaN).
    row_name : callable, optional
        How the message names the block's row ``k`` (0-based): ``"line 12"``; default ``"row {k + 1}"``.

    Raises
    ------
    MagcalError
    """
    values = np.asarray(values, dtype=float)
    bad = ~np.isfinite(values)
    if not bad.any():
        return
    have = attitude_present(dataset) if dataset is not None else None
    if have is not None:
        bad &= ~(np.isnan(values) & ~np.asarray(have, dtype=bool)[:, None])
    if bad.any():
        k, j = (int(i) for i in np.argwhere(bad)[0])
        raise MagcalError(
            f"{source}: {row_name(k) if row_name else f'row {k + 1}'}: {names[j]} would be {float(values[k, j])!r}, not a finite number ({int(bad.sum())} such "
            "value(s) in this block); nothing is written. The calibration's values are too large for these "
            "readings, or a channel it needs (temperature, current...) is missing there: check both"
        )


class AttitudeGaps:
    """The survey's rows without attitude, counted block by block as :func:`apply_file` corrects them: their world
    (north-east-down) columns are NaN, their body-frame columns are written as on every row; one note counts them.

    Attributes
    ----------
    rows : int
        Rows seen.
    missing : int
        Rows without attitude (NaN angles or quaternion: before the first attitude message, a gap in a log).
    row_runs : list of (int, int)
        Their runs of consecutive data rows, counted from 1.
    """

    def __init__(self):
        self.rows = 0
        self.missing = 0
        self.row_runs: list[tuple[int, int]] = []

    def add(self, dataset) -> None:
        """Count one block (the next ``dataset.n_samples`` rows)."""
        have = attitude_present(dataset)
        if have is not None and not have.all():
            new = runs(~have, first_row=self.rows + 1)
            if self.row_runs and new and new[0][0] == self.row_runs[-1][1] + 1:  # a run across the blocks' edge
                self.row_runs[-1] = (self.row_runs[-1][0], new.pop(0)[1])
            self.row_runs += new
            self.missing += int(np.count_nonzero(~have))
        self.rows += dataset.n_samples

    def note(self, n_sensors, tensor=False, terms=()) -> str | None:
        """The note (None when every row had an attitude); ``terms``: the acting effects that need the attitude
        (:meth:`Calibration.attitude_terms`), which make every corrected column of such a row NaN."""
        if not self.missing:
            return None
        return attitude_gap_text(self.missing, self.rows, n_sensors, tensor, terms, runs_text(self.row_runs))


def attitude_gap_text(missing, rows, n_sensors, tensor=False, terms=(), where=None) -> str:
    """What ``magcal apply`` says of its ``missing`` rows (of ``rows``) without attitude, in ``where`` (row runs):
    their world columns are NaN; with ``terms`` (effects that need the attitude, ``site_gradient``) every
    corrected column is."""
    head = f"{missing} of {rows} rows have no attitude" + (f" ({where})" if where else "")
    if terms:
        body = ", ".join(f"s{i + 1}x_cal, s{i + 1}y_cal, s{i + 1}z_cal" for i in range(n_sensors))
        return (
            f"{head}: {', '.join(terms)} cannot be applied to them, so their corrected columns ({body}"
            f"{' and the tensor' if tensor else ''}) are NaN; --record-terms drop corrects every row with the base "
            "terms"
        )
    world = ", ".join(f"s{i + 1}n_cal, s{i + 1}e_cal, s{i + 1}d_cal" for i in range(n_sensors))
    if tensor:
        world += ", " + ", ".join(WORLD_TENSOR_COLUMNS)
    return f"{head}: their world components ({world}) are NaN; the body-frame columns are written for every row"


@dataclass
class ApplySummary:
    """What :func:`apply_file` did, and what it has to say (``notes``: :class:`~magcal.core.notes.Note` list, never
    raised here: the record-only terms' decision, the reader's findings, the rows without attitude)."""

    rows: int
    columns_added: list
    seconds: float
    output: str
    frame: str
    notes: list = field(default_factory=list)

    @property
    def rows_per_s(self) -> float:
        return self.rows / self.seconds if self.seconds > 0 else float("inf")

    def text(self) -> str:
        return (
            f"corrected {self.rows} rows in {self.seconds:.1f} s ({self.rows_per_s:,.0f} rows/s); wrote "
            f"{self.output} with {len(self.columns_added)} new columns (frame: {self.frame})"
        )


def _progress_bar(total_bytes, enabled):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:  # tqdm is a dependency, but the correction must not fail without it
        return None
    return tqdm(total=total_bytes, unit="B", unit_scale=True, desc="magcal apply", file=sys.stderr, leave=False)


def file_fingerprint(survey_path, columns=None, units=None, drop_bad=False, chunk_rows=20_000, stop_after=None):
    """The record fingerprint (:func:`magcal.calibration.calibration.record_fingerprint`) of a CSV file, streamed.

    ``stop_after``: stop reading once the file has more samples than this (it cannot be that record); the
    fingerprint then covers the samples read.
    """
    # the reader's notes are left unsaid: the correcting pass says the data's problems
    with CsvSource(os.fspath(survey_path), columns=columns, units=units) as src:
        return _hashed((c.dataset for c in src.chunks(chunk_rows, drop_bad=drop_bad, text_columns=False)), stop_after)


def _hashed(datasets, stop_after=None) -> dict:
    """The record fingerprint of the samples of ``datasets`` (blocks, in order), read until more than
    ``stop_after`` samples have come (None: all)."""
    hasher = RecordHasher()
    for ds in datasets:
        hasher.update(ds)
        if stop_after is not None and hasher.n_samples > stop_after:
            break
    return hasher.fingerprint()


def apply_file(
    calibration,
    survey_path,
    output_path,
    columns=None,
    units=None,
    drop_bad=False,
    chunk_rows=20_000,
    progress=None,
    calibration_name=None,
    record_terms=None,
    uncertainty=False,
    compression=None,
    force=False,
):
    """Correct a survey file with a calibration, streaming, writing the input plus the corrected columns.

    A CSV in and out keeps the input's lines as they are and adds the corrected columns; Parquet input or output
    and flight-controller logs write the survey's columns as magcal reads them (readings in nT; a log's time,
    temperature and attitude) plus the corrected ones, to Parquet (``.parquet``: one row group per block, the
    metadata in the schema) or CSV. Memory stays flat either way (a log is read whole).

    Parameters
    ----------
    calibration : Calibration or str or os.PathLike
        The calibration or its JSON file.
    survey_path, output_path : str or os.PathLike
        Input (CSV, docs/formats.md; Parquet; a flight-controller log) and output (CSV or ``.parquet``); the
        output is written atomically.
    columns, units, drop_bad
        As in :func:`magcal.data.io.read_csv` (a CSV input's).
    chunk_rows : int
        Lines per block; memory use is proportional to it, not to the file.
    progress : bool, optional
        Show a tqdm progress bar (CSV to CSV); default: when stderr is a terminal.
    record_terms : {None, 'apply', 'drop'}
        The calibration's record-only terms (bias drift, bias step...: they describe the recording it was fitted
        on). ``None`` (default): applied when the file is that record (same fingerprint), dropped with one
        :class:`~magcal.core.errors.RecordTermWarning` note otherwise. ``'apply'`` forces them (you assert it is the
        same record, or have a reference for it); ``'drop'`` leaves them out.
    uncertainty : bool
        Also write the calibration's standard deviations of every new column (:func:`output_columns`), from its
        parameter covariance (:mod:`magcal.calibration.uncertainty`).
    compression : str, optional
        Codec of the float columns of a Parquet output (:data:`magcal.data.io.PARQUET_CODECS`; default snappy,
        :data:`magcal.data.io.PARQUET_FLOAT_CODEC`).
    force : bool
        Apply the sensors whose calibration the fit marked not determined by its record too. By default they are
        refused (:class:`Refusal`): their columns are left out, a note names them and why, and so does the output's
        header (``magcal_refused``; ``magcal_forced`` when forced); the other sensors are corrected.

    Returns
    -------
    ApplySummary
        Its ``notes`` (never raised here; ``magcal apply`` prints them): the sensors refused or forced, the
        record-only terms dropped, what the reader found in the data, the rows without attitude.

    Raises
    ------
    MagcalError
        Bad calibration file, a calibration for another number of sensors, missing channels, bad data; every
        sensor not determined (without ``force``).
    """
    t0 = time.perf_counter()
    check_output_path(output_path, "output")  # before any work: a folder, a missing folder
    if not os.path.isfile(survey_path):
        if os.path.isdir(survey_path):
            raise DatasetError(f"{os.fspath(survey_path)}: is a directory, not a survey file")
        check_regular_file(survey_path, "file", DatasetError)  # missing, a FIFO, a device: named, never opened
    if compression is not None and not is_parquet(output_path):
        raise MagcalError(
            f"{os.fspath(output_path)}: a compression ({compression!r}) is for Parquet output; name "
            "the output .parquet or leave the compression out"
        )
    compression = check_parquet_codec(compression)  # a bad name before any work
    if isinstance(columns, str):
        columns = parse_column_mapping(columns)
    if not hasattr(calibration, "correct"):
        calibration_name = calibration_name or os.fspath(calibration)
        calibration = load_calibration(calibration)
    survey_path, output_path = os.fspath(survey_path), os.fspath(output_path)
    if os.path.exists(output_path) and os.path.exists(survey_path) and os.path.samefile(survey_path, output_path):
        raise MagcalError(f"{output_path}: the output would overwrite the survey file; choose another name")
    refusal = Refusal.of(calibration, force, calibration_name or "the calibration")
    choice, record_note = record_choice(calibration, survey_path, record_terms, columns, units, drop_bad, chunk_rows)
    notes = [refusal.note] if refusal.note else []
    notes += [Note(record_note, RecordTermWarning, "apply")] if record_note else []
    run = _ApplyRun(calibration, survey_path, output_path, choice, calibration_name, uncertainty, notes, refusal)
    if is_log(survey_path) or is_parquet(survey_path) or is_parquet(output_path):
        _apply_columns(run, columns, units, drop_bad, chunk_rows, compression)
    else:
        _apply_csv(run, columns, units, drop_bad, chunk_rows, sys.stderr.isatty() if progress is None else progress)
    gap_note = run.gaps.note(calibration.n_sensors, gives_tensor(calibration), run.terms)
    if gap_note:
        notes.append(Note(f"{survey_path}: {gap_note}", DataWarning, "apply"))
    return ApplySummary(run.rows, run.names, time.perf_counter() - t0, output_path, calibration.frame, notes)


@dataclass
class _ApplyRun:
    """What the two writers of :func:`apply_file` share: the calibration, the paths, the record-only terms'
    choice, the notes said so far, and what they count (rows written, the output's new columns, rows without
    attitude)."""

    calibration: Calibration
    survey_path: str
    output_path: str
    choice: str
    calibration_name: str | None
    uncertainty: bool
    notes: list
    refusal: Refusal = field(default_factory=Refusal)
    rows: int = 0
    names: list = field(default_factory=list)
    gaps: AttitudeGaps = field(default_factory=lambda: AttitudeGaps())

    @property
    def terms(self) -> list:
        """The acting effects that need each row's attitude (:meth:`Calibration.attitude_terms`)."""
        return self.calibration.attitude_terms(self.choice)


def _apply_csv(run: _ApplyRun, columns, units, drop_bad, chunk_rows, progress) -> None:
    """:func:`apply_file` from a CSV to a CSV: the input's lines as they are, plus the corrected columns."""
    calibration, survey_path = run.calibration, run.survey_path
    with CsvSource(survey_path, columns=columns, units=units) as src:
        if src.layout.n_sensors != calibration.n_sensors:
            raise MagcalError(
                f"{survey_path}: the survey has {src.layout.n_sensors} sensor(s) but the calibration"
                f"{' ' + run.calibration_name if run.calibration_name else ''} is for {calibration.n_sensors} "
                "sensor(s); use the calibration made for this instrument"
            )
        tensor = gives_tensor(calibration)
        world = writes_world(calibration, layout=src.layout)
        heading = writes_heading(calibration, layout=src.layout)
        refused = run.refusal.refused
        new_names = output_columns(calibration.n_sensors, tensor, run.uncertainty, world, heading, refused)
        clash = sorted(set(new_names) & set(src.header))
        if clash:
            raise MagcalError(
                f"{survey_path}: the file already has column(s) {', '.join(clash)} (is it an apply output?); rename "
                "them or correct the raw survey"
            )
        fmt = ",".join(column_format(name) for name in new_names)
        meta = {}
        if run.calibration_name:
            meta["magcal_calibration"] = run.calibration_name
        meta.update(run.refusal.metadata())
        meta["magcal_frame"] = calibration.frame
        meta["magcal_columns"] = "readings converted to nT; *_cal in nT" + (
            ", G* in nT/m" if tensor and not refused else ""
        )
        bar = _progress_bar(os.path.getsize(survey_path), bool(progress))
        terms = run.terms
        try:
            with atomic_write(run.output_path) as out:
                for line in src.metadata_lines:
                    out.write(line + "\n")
                out.write(metadata_text(meta))
                header = _io.StringIO()
                csv.writer(header, lineterminator="\n").writerow(list(src.header) + new_names)
                out.write(header.getvalue())
                last_pos = src._file.tell()
                for chunk in src.chunks(chunk_rows, drop_bad=drop_bad, text_columns=reads_extras(calibration)):
                    if run.rows == 0:
                        calibration.check(chunk.dataset)
                        _moved(src.notes, run.notes)  # in the order said: the head's and this block's first
                        unit_text = check_units(chunk.dataset, src.units, src.source)
                        if unit_text:
                            run.notes.append(Note(unit_text, DataWarning, "read"))
                    values = correct_block(
                        calibration, chunk.dataset, run.choice, run.uncertainty, world, heading, refused
                    )
                    refuse_non_finite(
                        values, new_names, survey_path, chunk.dataset, lambda k, c=chunk: f"line {c.line_numbers[k]}"
                    )
                    if world or terms:
                        run.gaps.add(chunk.dataset)
                    out.write(
                        "".join(f"{line},{fmt % tuple(row)}\n" for line, row in zip(chunk.lines, values.tolist()))
                    )
                    run.rows += chunk.dataset.n_samples
                    if bar is not None:
                        pos = src._file.tell()
                        bar.update(pos - last_pos)
                        last_pos = pos
                _moved(src.notes, run.notes)
                if run.rows == 0:
                    raise DatasetError(f"{survey_path}: no data rows after the header; nothing to correct")
        finally:
            if bar is not None:
                bar.close()
    run.names = new_names


def _moved(said: list, notes: list) -> None:
    """Move what a streaming reader has ``said`` so far (its ``notes``) to the end of ``notes``, in order."""
    notes.extend(said)
    said.clear()


def reads_extras(calibration) -> bool:
    """Whether correcting with ``calibration`` needs the columns a CSV reader keeps as extras (a vector
    calibration's attitude as ``roll_deg, pitch_deg, yaw_deg``, its platform terms' ``current_A``, ``throttle``; a
    gravity calibration's accelerometer ``ax, ay, az``): then the CSV readers read them too (``text_columns``), which
    they skip otherwise for speed."""
    return getattr(calibration, "mode", "scalar") in ("vector", "gravity")


def survey_chunks(survey_path, columns=None, units=None, drop_bad=False, chunk_rows=20_000, extras=False):
    """The survey as datasets of at most ``chunk_rows`` samples (readings in nT), its ``# key: value``
    metadata and its reader's notes: ``(metadata, iterator, notes)``, ``notes`` a list of
    :class:`~magcal.core.notes.Note` that fills as the iterator reads (:attr:`magcal.data.io.CsvSource.notes`). A CSV is streamed by :class:`magcal.data.io.CsvSource`; a Parquet file by its
    record batches; a flight-controller log (:mod:`magcal.data.logs`) is read whole, as one block (its reader decodes
    every message anyway). ``columns`` and ``units`` apply to a CSV only, as does ``extras``: also read the columns
    a CSV keeps as extra channels (:func:`reads_extras`)."""

    path = os.fspath(survey_path)
    if is_log(path):
        dataset = read_log(path, warn=False)
        return dataset_metadata(dataset), iter([dataset]), list(dataset.notes)
    if not is_parquet(path):
        src = CsvSource(path, columns=columns, units=units)

        def csv_chunks():
            with src:
                for chunk in src.chunks(chunk_rows, drop_bad=drop_bad, text_columns=extras):
                    yield chunk.dataset

        return dict(src.metadata), csv_chunks(), src.notes
    parquet = ParquetSource(path)
    return dict(parquet.metadata), parquet.chunks(chunk_rows), parquet.notes


def _parquet_rows(path) -> int | None:
    """Rows of a Parquet file from its footer, or None for another kind of file (or one pyarrow cannot open: the
    reader then says what is wrong)."""
    path = os.fspath(path)
    if is_log(path) or not is_parquet(path):
        return None
    try:
        import pyarrow.parquet as pq

        return int(pq.ParquetFile(path).metadata.num_rows)
    except Exception:  # unreadable: survey_chunks gives the message naming the file
        return None


def survey_rows(survey_path, columns=None, units=None, drop_bad=False) -> int | None:
    """The samples the reader yields from a survey file, known without parsing a row, or None when they cannot be.

    A Parquet file's rows come from its footer (its reader refuses a bad value, never drops a row, ``drop_bad`` or
    not). A CSV's head (metadata, header, layout, units) is read by :class:`~magcal.data.io.CsvSource` itself --
    a head it refuses is refused here, with its message -- and its data rows are counted from the bytes
    (:meth:`~magcal.data.io.CsvSource.count_rows`: the lines it reads as rows, every line after the header but the
    blank ones, whatever the line ends): exactly the samples it yields when it reads the file without an error. With
    ``drop_bad`` a CSV reader may drop rows, so their number is not known: None. None for a log (read whole).
    """
    path = os.fspath(survey_path)
    if is_log(path):
        return None
    if is_parquet(path):
        return _parquet_rows(path)
    if drop_bad:
        return None
    with CsvSource(path, columns=columns, units=units) as src:  # its notes unsaid: the correcting pass says them
        return src.count_rows()


def record_choice(
    calibration, survey_path, record_terms=None, columns=None, units=None, drop_bad=False, chunk_rows=20_000
):
    """Decide once for a whole survey file (CSV, Parquet or a flight-controller log) whether the calibration's
    record-only terms act on it: ``('apply' | 'drop', note or None)``, the note the
    :class:`~magcal.core.errors.RecordTermWarning` message (None when nothing needs saying).

    The decision is :meth:`~magcal.calibration.calibration.Calibration.record_decision`'s on the file's
    fingerprint, the samples its reader yields hashed (:class:`RecordHasher`): the file is the fitted record, and
    keeps its drifts and steps, only when it has the record's samples and their hash. The file is read for the
    hash only when the calibration holds record-only terms acting on the corrected vectors, it says which record it
    was fitted on, ``record_terms`` is None, and the number of samples cannot tell:

    * the samples are first known without parsing a row (:func:`survey_rows`: a Parquet file's footer, a CSV's
      line ends counted in large blocks): a file of another number than the record's samples is another record,
      without a row read or hashed (a survey of 1e9 rows is not parsed twice, nor through one process, to learn
      that it is not the calibration record; the note then gives its samples, not its time span);
    * a file of the record's number of samples, or one whose samples are not known so (a CSV with ``drop_bad``,
      which may drop rows; a log), is hashed as it is read, up to one block past the record's samples (more
      cannot be that record).

    So the decision is the one hashing the whole file would give, in every case: the count is the number of
    samples the hash would cover (the reader yields one sample for each counted line, or refuses the file), a file
    is only declared another record when that number differs from the record's, and the record itself (equal
    count) is always hashed. A file whose head the reader refuses is refused here; one with a bad row further on
    and another length is refused by the correcting pass, with the same message.
    """

    if not calibration.record_terms(CORRECTION_STAGES):
        return "apply", None
    fingerprint = None
    record = calibration.record
    if record_terms is None and record:
        fingerprint = survey_fingerprint(survey_path, record.get("n_samples"), columns, units, drop_bad, chunk_rows)
    dropped, note = calibration.record_decision(
        None, record_terms, CORRECTION_STAGES, fingerprint=fingerprint if fingerprint is not None else {}
    )
    return ("drop" if dropped else "apply"), note


def survey_fingerprint(survey_path, record_samples, columns=None, units=None, drop_bad=False, chunk_rows=20_000):
    """The fingerprint of a survey file as far as it tells whether the file is a record of ``record_samples``
    samples (:func:`record_choice`): its samples alone (``readings_sha256`` None) when :func:`survey_rows` knows
    them and they are another number, else the hash of the samples read, up to the block past ``record_samples``."""
    counted = isinstance(record_samples, int) and not isinstance(record_samples, bool)
    rows = survey_rows(survey_path, columns, units, drop_bad)
    if rows is not None and rows != record_samples:
        return {"n_samples": rows, "time_start_s": None, "time_end_s": None, "readings_sha256": None}
    path = os.fspath(survey_path)
    if not is_log(path) and not is_parquet(path):
        return file_fingerprint(path, columns, units, drop_bad, chunk_rows, record_samples if counted else None)
    chunks = survey_chunks(path, columns, units, drop_bad, chunk_rows)[1]  # notes unsaid: the correcting pass says them
    return _hashed(chunks, record_samples if counted else None)


def _apply_columns(run: _ApplyRun, columns, units, drop_bad, chunk_rows, compression) -> None:
    """:func:`apply_file` for Parquet input or output and for flight-controller logs: the survey's columns as magcal
    writes them (readings in nT; a log's time, temperature and attitude) plus the corrected ones, chunk by chunk
    (memory stays flat), to Parquet (``.parquet``: one row group per chunk, the metadata in the schema) or CSV."""
    import contextlib

    calibration, survey_path, output_path = run.calibration, run.survey_path, run.output_path
    extras = reads_extras(calibration)
    meta, chunks, said = survey_chunks(survey_path, columns, units, drop_bad, chunk_rows, extras=extras)
    tensor = gives_tensor(calibration)
    refused = run.refusal.refused
    names = output_columns(calibration.n_sensors, tensor, run.uncertainty, refused=refused)
    meta = {
        **meta,
        "units": "nT",
        "magcal_frame": calibration.frame,
        "magcal_columns": "readings in nT; *_cal in nT" + (", G* in nT/m" if tensor and not refused else ""),
        **run.refusal.metadata(),
    }
    if run.calibration_name:
        meta["magcal_calibration"] = run.calibration_name
    terms = run.terms
    to_parquet = is_parquet(output_path)
    tmp = f"{output_path}.tmp-{os.getpid()}"
    writer = behind = None
    try:
        with contextlib.nullcontext() if to_parquet else open(tmp, "w", encoding="utf-8", newline="") as fh:
            for ds in chunks:
                if run.rows == 0:
                    world = writes_world(calibration, ds)
                    heading = writes_heading(calibration, ds)
                    names = output_columns(calibration.n_sensors, tensor, run.uncertainty, world, heading, refused)
                    if ds.n_sensors != calibration.n_sensors:
                        raise MagcalError(
                            f"{survey_path}: the survey has {ds.n_sensors} sensor(s) but the calibration is for "
                            f"{calibration.n_sensors} sensor(s); use the calibration made for this instrument"
                        )
                    calibration.check(ds)
                values = correct_block(calibration, ds, run.choice, run.uncertainty, world, heading, refused)
                refuse_non_finite(values, names, survey_path, ds, lambda k, first=run.rows: f"row {first + k + 1}")
                if world or terms:
                    run.gaps.add(ds)
                cols = input_columns(survey_path, ds, names)
                cols.update({name: values[:, k] for k, name in enumerate(names)})
                if to_parquet:
                    import pyarrow.parquet as pq

                    table = parquet_table(cols, meta)
                    if writer is None:
                        writer = pq.ParquetWriter(tmp, table.schema, **parquet_write_options(table, compression))
                        behind = _WriteBehind()
                    assert behind is not None  # made with the writer
                    behind.put(lambda table=table, writer=writer: writer.write_table(table))
                else:
                    assert fh is not None  # a CSV output's temporary file
                    if run.rows == 0:
                        fh.write(metadata_text(meta) + ",".join(cols) + "\n")
                    write_rows(fh, cols)
                run.rows += ds.n_samples
            _moved(said, run.notes)
            if writer is not None:
                behind, done = None, behind
                assert done is not None  # made with the writer
                done.close()  # every block written (or the first error raised)
                writer.close()
                writer = None
        if run.rows == 0:
            raise DatasetError(f"{survey_path}: no data rows; nothing to correct")
        os.replace(tmp, output_path)
    finally:
        if behind is not None:  # an error while reading or correcting: stop the writing thread first
            behind.close(raise_error=False)
        if writer is not None:
            writer.close()
        if os.path.exists(tmp):
            os.remove(tmp)
    run.names = names


class _WriteBehind:
    """Writes of a Parquet output on a thread of their own, at most ``depth`` blocks behind the reading and
    correcting: pyarrow's encoding and compression and the disk release the interpreter, so the file's writing
    overlaps the next blocks' work (memory stays bounded by ``depth`` blocks). Calls run in order; after the first
    error the rest are skipped and the error is raised by the next :meth:`put` or by :meth:`close`."""

    def __init__(self, depth=2):
        import queue
        import threading

        self._queue = queue.Queue(maxsize=depth)
        self._error = None
        self._thread = threading.Thread(target=self._run, name="magcal-write", daemon=True)
        self._thread.start()

    def _run(self):
        while True:
            call = self._queue.get()
            if call is None:
                return
            if self._error is None:
                try:
                    call()
                except BaseException as exc:
                    self._error = exc

    def put(self, call):
        """Queue ``call`` (a function of no argument); waits while ``depth`` calls are queued."""
        if self._error is not None:
            raise self._error
        self._queue.put(call)

    def close(self, raise_error=True):
        """Wait for every queued call, stop the thread; raise the first error (unless ``raise_error`` is False)."""
        self._queue.put(None)
        self._thread.join()
        if raise_error and self._error is not None:
            raise self._error
