"""Every file a calibration is exported as, built in memory: one function per file, shared by ``magcal export``,
``magcal apply`` and the workbench's Export section, so that the page's download and the command line's file are
the same bytes (``docs/export.md``).

========================  ===========================================================  ====================================
file                      what                                                         command line
========================  ===========================================================  ====================================
``calibration.json``      the calibration (:meth:`Calibration.save`)                   ``magcal calibrate ... -o``
``compass.parm``          ArduPilot parameters (:mod:`magcal.output.export`)           ``magcal export --format ardupilot``
``mag.params``            PX4 / QGroundControl parameters                              ``magcal export --format px4``
``magcal_calibration.h``  the C header                                                 ``magcal export --format c``
(a format's file)         each format a package added (:mod:`magcal.output.formats`)   ``magcal export --format NAME``
``corrected.csv``         the data corrected (:func:`magcal.output.apply.apply_file`)  ``magcal apply``
``corrected.parquet``     the same as Parquet                                          ``magcal apply -o X.parquet``
``raw_mask.csv``          the raw readings, the fit's ``kept`` mask and residuals      ``magcal export --format mask``
``magcal_export.zip``     all of them with a ``README.txt``                            ``magcal export --format all``
========================  ===========================================================  ====================================

Nothing here writes to the user's files: each function returns bytes (temporary files, for the writers that need
a path, are made and removed in a private folder). What could not be written (a firmware that cannot hold the
calibration, data that cannot be corrected) is a :class:`MagcalError` from the one-file functions and a line of the
bundle's ``README.txt`` from :func:`export_all`, never a crash.
"""

from __future__ import annotations

import csv
import io
import json
import os
import tempfile
import zipfile

import numpy as np

from magcal.calibration.calibration import Calibration, document_text
from magcal.core.errors import MagcalError
from magcal.core.notes import texts
from magcal.data import io as mio
from magcal.output.apply import apply_file, refuse_non_finite
from magcal.output.export import export_calibration
from magcal.output.formats import EXPORT_FORMATS, FILE_NAMES

#: The calibration's file name in a bundle and in the parameter files' headers.
CALIBRATION_FILE = "calibration.json"
#: File name of each export format's file (a view of :data:`magcal.output.formats.EXPORT_FORMATS`).
PARAMETER_FILES = FILE_NAMES
#: File name of the corrected data, per kind.
CORRECTED_FILES = {"csv": "corrected.csv", "parquet": "corrected.parquet"}
#: File name of the raw readings with the fit's mask.
MASK_FILE = "raw_mask.csv"
#: File name of the bundle.
BUNDLE_FILE = "magcal_export.zip"
#: A fixed time stamp for the bundle's members, so that the same files give the same zip bytes.
ZIP_DATE_TIME = (1980, 1, 1, 0, 0, 0)


def calibration_bytes(calibration) -> bytes:
    """The calibration's JSON file, byte for byte what :meth:`Calibration.save` writes."""
    return document_text(calibration.to_dict()).encode("utf-8")


def calibration_from_bytes(content: bytes, source: str = CALIBRATION_FILE) -> Calibration:
    """The calibration a JSON file's bytes hold (what ``magcal export`` reads back from the downloaded file)."""
    try:
        doc = json.loads(content.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MagcalError(f"{source}: not a calibration file ({exc})") from None
    return Calibration.from_dict(doc, source=source)


def parameter_bytes(calibration, fmt, sensors=None, slots=None, force=False, source=CALIBRATION_FILE, **options):
    """A format's file (``fmt`` one of :data:`magcal.output.formats.EXPORT_FORMATS`) as bytes, with its
    :class:`~magcal.output.export.Export` (dropped terms, notes, the parameters by name).

    ``source`` is the calibration's name written into the file's header (``magcal export`` gives the path it was
    given); ``options`` (``throttle_full_scale``, ``custom_rotation``) go to
    :func:`magcal.output.export.export_calibration`, whose errors it raises (:class:`MagcalError`)."""
    result = export_calibration(calibration, fmt, sensors=sensors, slots=slots, force=force, source=source, **options)
    return result.text.encode("utf-8"), result


def corrected_bytes(
    calibration, data_path, kind="csv", calibration_name=CALIBRATION_FILE, record_terms=None, force=False
):
    """The data file ``data_path`` corrected by the calibration: byte for byte what ``magcal apply
    CALIBRATION DATA -o corrected.csv`` (or ``.parquet``) writes when ``CALIBRATION`` is ``calibration_name``.

    Returns ``(content, notes)``: ``notes`` holds what ``magcal apply`` says
    (:attr:`magcal.output.apply.ApplySummary.notes`), as text: the sensors refused as not determined (or forced,
    ``force``: :class:`magcal.output.apply.Refusal`), the record-only terms' decision (dropped on another record),
    the reader's findings, the rows without attitude.
    """
    if kind not in CORRECTED_FILES:
        raise MagcalError(f"corrected data: kind {kind!r}: use one of {', '.join(CORRECTED_FILES)}")
    with tempfile.TemporaryDirectory(prefix="magcal-export-") as folder:
        out = os.path.join(folder, CORRECTED_FILES[kind])
        summary = apply_file(
            calibration,
            data_path,
            out,
            progress=False,
            calibration_name=calibration_name,
            record_terms=record_terms,
            force=force,
        )
        with open(out, "rb") as fh:
            return fh.read(), texts(summary.notes)


def mask_from_file(path, n_samples: int) -> np.ndarray:
    """The ``kept`` column (0/1) of a CSV file as a boolean mask of ``n_samples`` samples (``magcal export
    --format mask --mask FILE``: e.g. a ``raw_mask.csv`` the workbench wrote)."""
    name = os.fspath(path)
    try:
        with open(name, newline="", encoding="utf-8") as fh:
            rows = (line for line in fh if not line.startswith("#"))
            reader = csv.DictReader(rows)
            if reader.fieldnames is None or "kept" not in reader.fieldnames:
                raise MagcalError(f"{name}: no 'kept' column; give a file with one (0 rejected, 1 kept) per sample")
            values = []
            for k, row in enumerate(reader, start=1):
                text = (row.get("kept") or "").strip()
                try:
                    value = float(text)
                except ValueError:
                    value = None
                if value not in (0.0, 1.0):
                    raise MagcalError(f"{name}: data row {k}: kept is {text[:20]!r}; give 0 (rejected) or 1 (kept)")
                values.append(value == 1.0)
    except FileNotFoundError:
        raise MagcalError(f"{name}: no such mask file; check the path") from None
    except UnicodeDecodeError:
        raise MagcalError(f"{name}: not a text (CSV) file") from None
    if len(values) != n_samples:
        raise MagcalError(f"{name}: {len(values)} kept values for {n_samples} samples; give one per sample")
    return np.array(values, dtype=bool)


def raw_mask_bytes(calibration, dataset, kept=None, calibration_name=CALIBRATION_FILE, record_terms=None):
    """The raw readings (nT, magcal's CSV layout) with the fit's mask and the total-field residuals: the columns
    of the data, then ``kept`` (1 a sample the fit used, 0 one rejected) and ``s{i}_residual_nT`` (``|B| - F``
    of the corrected field, nT, every sample).

    Parameters
    ----------
    calibration : Calibration
    dataset : Dataset
        The raw data (the record the calibration was fitted on, or any other).
    kept : array_like of bool, shape (N,), optional
        The mask; default every sample kept.
    calibration_name : str
        Written in the file's ``# magcal_calibration:`` line.
    record_terms : {None, 'apply', 'drop'}
        As :meth:`Calibration.correct`; None: applied on the fitted record, dropped on another.

    Returns
    -------
    content : bytes
    notes : list of str
        The record-only terms' decision, when there is one to say.
    """
    n = dataset.n_samples
    kept = np.ones(n, dtype=bool) if kept is None else np.asarray(kept, dtype=bool)
    if kept.shape != (n,):
        raise MagcalError(f"the mask has {kept.size} values for {n} samples; give one per sample")
    notes = []
    if record_terms is None:
        dropped, note = calibration.record_decision(dataset)
        record_terms = "drop" if dropped else "apply"
        if note:
            notes.append(note)
    residual = calibration.total_field_residuals(dataset, record_terms=record_terms)
    names = [f"s{s + 1}_residual_nT" for s in range(dataset.n_sensors)]
    refuse_non_finite(
        np.asarray(residual, dtype=float).T, names, dataset.source or "data", dataset, lambda k: f"sample {k + 1}"
    )
    columns = dict(mio.dataset_columns(dataset))
    for name in ["kept"] + [f"s{s + 1}_residual_nT" for s in range(dataset.n_sensors)]:
        columns.pop(name, None)  # a file that is itself a raw_mask.csv: its old mask and residuals are replaced
    columns["kept"] = np.where(kept, "1", "0")  # written 1/0, not as the floats 1.0/0.0
    for s in range(dataset.n_sensors):
        columns[f"s{s + 1}_residual_nT"] = residual[s]
    meta = {
        **mio.dataset_metadata(dataset),
        "magcal_calibration": calibration_name,
        "magcal_mask": "kept 1 = used by the fit, 0 = rejected; s*_residual_nT = |B corrected| - F (nT)",
    }
    out = io.StringIO(newline="")
    out.write(mio.metadata_text(meta))
    csv.writer(out, lineterminator="\n").writerow(list(columns))
    mio.write_rows(out, columns)
    return out.getvalue().encode("utf-8"), notes


def zip_bytes(files: dict) -> bytes:
    """A zip of ``name -> bytes`` (deflated, fixed time stamps: the same files give the same bytes)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, content in files.items():
            info = zipfile.ZipInfo(name, date_time=ZIP_DATE_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, content)
    return buf.getvalue()


def export_all(
    calibration,
    dataset=None,
    data_path=None,
    kept=None,
    extra_files=None,
    calibration_name=CALIBRATION_FILE,
    parquet=True,
):
    """Every export of a calibration in one zip, with a ``README.txt`` that lists the files, the command that
    writes each, and what was not written and why (a refusal is a line there, never an error).

    Parameters
    ----------
    calibration : Calibration
    dataset : Dataset, optional
        The raw data, for ``raw_mask.csv``.
    data_path : str or os.PathLike, optional
        The data file, for ``corrected.csv`` and ``corrected.parquet`` (``magcal apply`` reads a file).
    kept : array_like of bool, optional
        The fit's mask for ``raw_mask.csv`` (default every sample).
    extra_files : dict of str to bytes, optional
        More files to put in (the workbench's ``session.json``), each with its description:
        ``name -> (content, description)``.
    calibration_name : str
        The calibration's name in the files' headers (the bundle holds it as :data:`CALIBRATION_FILE`).
    parquet : bool
        Also the corrected data as Parquet (needs pyarrow; a line of the README without it).

    Returns
    -------
    content : bytes
        The zip.
    readme : list of str
        The README's lines ("not written" lines included).
    """
    files: dict[str, bytes] = {}
    written: list[str] = []
    missing: list[str] = []
    notes: list[str] = []

    def attempt(name, what, command, build):
        try:
            content, more = build()
        except (MagcalError, OSError, ValueError, ImportError) as exc:
            missing.append(f"{name}: not written: {exc}")
            return
        files[name] = content
        written.append(f"{name}: {what} ({command})")
        notes.extend(f"{name}: {n}" for n in more)

    attempt(
        CALIBRATION_FILE,
        "the calibration",
        "magcal calibrate ... -o calibration.json",
        lambda: (calibration_bytes(calibration), []),
    )
    for fmt, spec in EXPORT_FORMATS.items():

        def params(fmt=fmt):
            content, result = parameter_bytes(calibration, fmt, source=calibration_name)
            return content, result.notes

        attempt(spec.file_name, spec.title, f"magcal export {calibration_name} --format {fmt}", params)
    if data_path is not None:
        kinds = ("csv", "parquet") if parquet else ("csv",)
        for kind in kinds:
            attempt(
                CORRECTED_FILES[kind],
                f"the data corrected ({kind.upper()})",
                f"magcal apply {calibration_name} DATA -o {CORRECTED_FILES[kind]}",
                lambda kind=kind: corrected_bytes(calibration, data_path, kind, calibration_name),
            )
    else:
        missing.append("corrected.csv: not written: no data file given")
    if dataset is not None:
        attempt(
            MASK_FILE,
            "the raw readings, the fit's kept mask (1 kept, 0 rejected) and the total-field residuals",
            f"magcal export {calibration_name} --format mask --data DATA --mask {MASK_FILE}",
            lambda: raw_mask_bytes(calibration, dataset, kept, calibration_name),
        )
    else:
        missing.append(f"{MASK_FILE}: not written: no data given")
    for name, (content, what) in (extra_files or {}).items():
        files[name] = content
        written.append(f"{name}: {what}")
    readme = (
        ["magcal export: the files of one calibration (docs/export.md).", "", "Written:"]
        + [f"  {line}" for line in written]
        + (["", "Not written:"] + [f"  {line}" for line in missing] if missing else [])
        + (["", "Notes:"] + [f"  {line}" for line in notes] if notes else [])
    )
    files["README.txt"] = ("\n".join(readme) + "\n").encode("utf-8")
    return zip_bytes(files), readme
