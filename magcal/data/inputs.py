"""Whatever the user holds, made a :class:`~magcal.data.dataset.Dataset`: a dataset, an ``(N, 3)`` or
``(n_sensors, N, 3)`` array of readings in nT with optional channels, or a pandas DataFrame with the data CSV's columns.
"""

from __future__ import annotations

import csv

import numpy as np

from magcal.core import notes as _notes
from magcal.core.errors import DataWarning
from magcal.core.notes import Note
from magcal.data.dataset import Dataset, DatasetError
from magcal.data.io import CsvSource, check_units, columns_block, shown, text_cells


def _is_dataframe(data) -> bool:
    """True for a pandas DataFrame, without importing pandas (it is only loaded if the caller already did)."""
    return any(cls.__name__ == "DataFrame" and cls.__module__.split(".")[0] == "pandas" for cls in type(data).__mro__)


def _readings_from_array(data) -> np.ndarray:
    try:
        readings = np.asarray(data, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DatasetError(
            f"readings: cannot be read as numbers ({exc}); give a numeric array of shape {_ACCEPTED_SHAPES}"
        ) from None
    shape = readings.shape
    hint = ""
    if readings.ndim == 2 and shape[0] == 3 and shape[1] != 3:
        hint = " (it looks transposed: pass readings.T)"
    elif readings.ndim == 3 and shape[2] != 3 and shape[1] == 3:
        hint = " (the axes look swapped: pass readings.transpose(0, 2, 1))"
    elif readings.ndim == 3 and shape[2] == 3 and shape[0] > 4:
        hint = " (at most 4 sensors; is the sample axis first? pass readings.transpose(1, 0, 2))"
    elif readings.ndim == 2 and shape[1] in (6, 9, 12):
        hint = (
            f" (for {shape[1] // 3} sensors stack them as (n_sensors, N, 3): "
            "readings.reshape(N, -1, 3).transpose(1, 0, 2))"
        )
    ok = (readings.ndim == 2 and shape[1] == 3) or (readings.ndim == 3 and shape[2] == 3 and 1 <= shape[0] <= 4)
    if not ok:
        raise DatasetError(f"readings: got an array of shape {shape}; accepted shapes are {_ACCEPTED_SHAPES}{hint}")
    if readings.ndim == 2:
        readings = readings[None]
    if readings.shape[1] == 0:
        raise DatasetError(
            f"readings: got an array of shape {shape} with no samples; accepted shapes are "
            f"{_ACCEPTED_SHAPES} with N >= 1"
        )
    bad = ~np.isfinite(readings)
    if bad.any():
        s, i, a = np.argwhere(bad)[0]
        raise DatasetError(
            f"readings: {int(bad.sum())} value(s) are NaN or infinite, the first at sensor {s + 1}, "
            f"sample {i} (0-based), axis {'xyz'[a]}; drop or fill those samples first"
        )
    return readings


def _channel(values, name, unit, n, allow_scalar=False) -> np.ndarray:
    try:
        values = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{name}: cannot be read as numbers ({exc}); give one value per sample in {unit}") from None
    if values.ndim == 0 and allow_scalar:
        values = np.full(n, float(values))
    if values.shape != (n,):
        scalar = " (or a single number for all samples)" if allow_scalar else ""
        raise DatasetError(
            f"{name}: got shape {values.shape}; accepted is ({n},), one value per sample in {unit}{scalar}"
        )
    bad = ~np.isfinite(values)
    if bad.any():
        raise DatasetError(
            f"{name}: {int(bad.sum())} value(s) are NaN or infinite, the first at sample "
            f"{int(np.argmax(bad))} (0-based)"
        )
    return values


def _check_times(time_s) -> None:
    step = np.diff(time_s)
    if (step <= 0).any():
        i = int(np.argmax(step <= 0)) + 1
        raise DatasetError(
            f"t: sample times must be strictly increasing; sample {i} (0-based) is at "
            f"{time_s[i]:g} s, after {time_s[i - 1]:g} s; sort the samples by time or drop repeats"
        )


def _from_dataframe(frame) -> Dataset:
    """Read a DataFrame whose columns are those of the data CSV (``s1x`` ..., ``x,y,z``, ``t``, ``temp`` ...): its
    ``attrs`` and column names go to the CSV reader as a head with no rows (the layout, units and metadata checks
    are the file's, with the same messages), its columns straight to the reader's dataset builder
    (:func:`magcal.data.io.columns_block`); a message names the frame's row by its index label and the column."""
    import io as _stdio

    if frame.shape[0] == 0:
        raise DatasetError("DataFrame: it has no rows; one row per sample is needed")
    lines = []
    for key, value in frame.attrs.items():  # DataFrame.attrs play the part of the file's "# key: value" lines
        key, value = str(key).strip(), str(value).strip()
        if not key or ":" in key or "\n" in key + value:
            raise DatasetError(
                f"DataFrame.attrs[{key!r}]: keys must be single-line names without ':' and values "
                "single-line text, as the data CSV's '# key: value' lines"
            )
        lines.append(f"# {key}: {value}\n")
    labels = frame.index
    if any(name is not None for name in frame.index.names):
        frame = frame.reset_index()  # a named index (e.g. "t") is a column like the others
    names = [str(c) for c in frame.columns]
    header = _stdio.StringIO()
    csv.writer(header, lineterminator="\n").writerow(names)
    src = CsvSource(_stdio.StringIO("".join(lines) + header.getvalue()), name="DataFrame")
    src._row_label = lambda number: f"row {labels[number - 1]!r}"
    src._sort_what = "rows"

    def numeric(j, name):
        cells = frame.iloc[:, j]
        try:
            return np.asarray(cells, dtype=float)
        except (TypeError, ValueError):
            out = np.empty(len(cells))
            for k, cell in enumerate(cells):
                if isinstance(cell, str) and not cell.strip():
                    out[k] = np.nan  # a blank cell is a missing value, as in the data CSV
                    continue
                try:
                    out[k] = float(cell)
                except (TypeError, ValueError):
                    raise DatasetError(
                        f"DataFrame: {src._where(k + 1)}, column {name}: {shown(str(cell))} is not a number; "
                        "readings, time and channels must be numeric"
                    ) from None
            return out

    def text(j, name):
        return text_cells(frame.iloc[:, j].astype(str).tolist(), "DataFrame", name, lambda k: src._where(k + 1))

    ds = columns_block(src, numeric, text, np.arange(1, frame.shape[0] + 1), block="")
    unit_text = check_units(ds, src.units, src.source, lsb_nT=src.lsb_nT)
    ds.notes = tuple(src.notes) + ((Note(unit_text, DataWarning, "read"),) if unit_text else ())
    return ds


def as_dataset(data, *, reference_total_nT=None, t=None, temp=None, warn=True) -> Dataset:
    """What the user holds, as a :class:`Dataset`.

    Parameters
    ----------
    data : Dataset, array_like or pandas.DataFrame
        A :class:`Dataset` (returned as it is, or a copy if a keyword changes it); an array of raw readings in
        nT of shape ``(N, 3)`` (one sensor) or ``(n_sensors, N, 3)`` (1 to 4 sensors, numbered as in
        :mod:`magcal.core.conventions`); or a pandas DataFrame with the columns of the data CSV
        (``s1x, s1y, s1z`` ... or ``x, y, z``, optional ``t``, ``temp``, ``ref_total``, ``qw..qz``, ``group``; see
        docs/formats.md), read by the same checks as a file; its ``attrs`` (e.g. ``{"baseline_m": 0.5}``) count as
        the file's ``# key: value`` metadata lines, and a named index (e.g. ``t``) counts as a column.
    reference_total_nT : float, optional
        Known total field of the whole record in nT (otherwise fitted, or a ``ref_total`` column).
    t : array_like, shape (N,), optional
        Sample times in s, strictly increasing (needed by time-dependent effects such as ``bias_drift``).
    temp : array_like, shape (N,) or float, optional
        Temperature in degC (needed by ``temperature_bias`` and the other temperature effects).
    warn : bool
        For a DataFrame: raise what its reading has to say (units that look wrong, quaternions normalised...) as
        :class:`~magcal.core.errors.DataWarning` warnings, the default; False leaves it in the dataset's ``notes``.

    Returns
    -------
    Dataset

    Raises
    ------
    DatasetError
        (a ``ValueError``) for a wrong shape (the message gives the shape got and the shapes accepted), values
        that are NaN or infinite, or a channel whose length is not N; for a DataFrame, the reader's message with
        the frame's row (index label) and column.

    Examples
    --------
    >>> import numpy as np
    >>> ds = as_dataset(np.zeros((200, 3)) + [50000.0, 0.0, 0.0], temp=20.0)
    >>> ds.n_sensors, ds.n_samples, sorted(ds.channels)
    (1, 200, ['temperature'])
    >>> as_dataset(np.zeros((3, 200)))  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    magcal.data.dataset.DatasetError: readings: got an array of shape (3, 200); accepted shapes are (N, 3) ... readings.T)
    """
    if isinstance(data, Dataset):
        ds = data
    elif _is_dataframe(data):
        ds = _from_dataframe(data)
        if warn:
            _notes.warn(ds.notes)
    else:
        ds = Dataset(readings_nT=_readings_from_array(data))
    changes: dict = {}
    n = ds.n_samples
    if t is not None:
        changes["time_s"] = _channel(t, "t", "s", n)
        _check_times(changes["time_s"])
    if temp is not None:
        changes["temperature_C"] = _channel(temp, "temp", "degC", n, allow_scalar=True)
    if reference_total_nT is not None:
        try:
            value = float(reference_total_nT)
        except (TypeError, ValueError):
            value = float("nan")
        if not np.isfinite(value) or value <= 0:
            raise DatasetError(
                f"reference_total_nT: got {reference_total_nT!r}; a positive number of nT is needed (e.g. 50000)"
            )
        changes["reference_total_nT"] = value
    return ds.replace(**changes) if changes else ds


# -- conversion of what users hold into a Dataset ------------------------------------------------------------------
_ACCEPTED_SHAPES = "(N, 3) for one sensor or (n_sensors 1-4, N, 3) for an array, in nT"
