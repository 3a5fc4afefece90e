"""The dataset: raw readings of one to four triaxial sensors plus optional channels and metadata.

A :class:`Dataset` is what every later step takes: the fitter, the diagnosis, the calibration's ``apply``,
and the workbench. It is immutable in spirit: methods return new datasets.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .errors import MagcalError

#: Channel names a model term may require, and the Dataset attribute each one lives in.
CHANNELS = {
    "time": "time_s",
    "temperature": "temperature_C",
    "attitude": "attitude_wxyz",
    "reference": "ref_total_nT",
    "group": "group",
}


class DatasetError(MagcalError, ValueError):
    """Bad input data; the message names the file, row or column and what to do."""


@dataclass
class Dataset:
    """Raw magnetometer readings and their channels.

    Parameters
    ----------
    readings_nT : numpy.ndarray, shape (n_sensors, N, 3)
        Raw readings of each sensor's x, y, z axes in nT.
    time_s : numpy.ndarray, shape (N,), optional
        Sample times in s (strictly increasing when present).
    temperature_C : numpy.ndarray, shape (N,), optional
        Sensor (or array) temperature in degC.
    ref_total_nT : numpy.ndarray, shape (N,), optional
        Per-sample scalar reference of the total field (e.g. a proton magnetometer) in nT.
    attitude_wxyz : numpy.ndarray, shape (N, 4), optional
        Attitude quaternions ``(qw, qx, qy, qz)`` rotating array-frame vectors into the world frame.
    group : numpy.ndarray of str, shape (N,), optional
        Text label per sample (e.g. ``x_up``, ``y_up``, ``z_up`` for the level-table procedure).
    reference_total_nT : float, optional
        Known total field (nT) for the whole record; ``None`` means it is unknown and will be fitted.
    baseline_m : float, optional
        Array baseline ``d`` in m (distance between sensors 1 and 3).
    noise_nT : float, optional
        Per-axis noise standard deviation in nT, if known.
    metadata : dict
        Every ``# key: value`` line of the file, as text.
    extra : dict of str to numpy.ndarray
        Columns magcal does not use, kept so that ``apply`` can write them back.
    source : str, optional
        Where the data came from (a file path), used in messages.
    """

    readings_nT: np.ndarray
    time_s: np.ndarray | None = None
    temperature_C: np.ndarray | None = None
    ref_total_nT: np.ndarray | None = None
    attitude_wxyz: np.ndarray | None = None
    group: np.ndarray | None = None
    reference_total_nT: float | None = None
    baseline_m: float | None = None
    noise_nT: float | None = None
    metadata: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    source: str | None = None

    def __post_init__(self):
        r = np.asarray(self.readings_nT, dtype=float)
        if r.ndim == 2:
            r = r[None]
        if r.ndim != 3 or r.shape[2] != 3 or not 1 <= r.shape[0] <= 4:
            raise DatasetError(
                f"{self.source or 'dataset'}: readings must have shape (n_sensors 1-4, N, 3), got {r.shape}"
            )
        self.readings_nT = r
        n = r.shape[1]
        for attr in ("time_s", "temperature_C", "ref_total_nT"):
            value = getattr(self, attr)
            if value is not None:
                value = np.asarray(value, dtype=float).reshape(-1)
                if value.shape[0] != n:
                    raise DatasetError(f"{self.source or 'dataset'}: {attr} has {value.shape[0]} rows, expected {n}")
                setattr(self, attr, value)
        if self.attitude_wxyz is not None:
            q = np.asarray(self.attitude_wxyz, dtype=float)
            if q.shape != (n, 4):
                raise DatasetError(f"{self.source or 'dataset'}: attitude must have shape ({n}, 4), got {q.shape}")
            self.attitude_wxyz = q
        if self.group is not None:
            self.group = np.asarray(self.group).astype(str)
        self.extra = {k: np.asarray(v) for k, v in self.extra.items()}

    @property
    def n_sensors(self) -> int:
        """Number of triaxial sensors (1 to 4)."""
        return self.readings_nT.shape[0]

    @property
    def n_samples(self) -> int:
        """Number of samples N."""
        return self.readings_nT.shape[1]

    @property
    def channels(self) -> frozenset:
        """The channels present, by their names in :data:`CHANNELS`."""
        return frozenset(name for name, attr in CHANNELS.items() if getattr(self, attr) is not None)

    def has(self, channel: str) -> bool:
        """True if the channel (a key of :data:`CHANNELS`) is present."""
        return getattr(self, CHANNELS[channel]) is not None

    def subset(self, index) -> "Dataset":
        """A new dataset with the samples selected by a boolean mask or an index array."""
        index = np.asarray(index)

        def take(a):
            return None if a is None else np.asarray(a)[index]

        return dataclasses.replace(
            self,
            readings_nT=self.readings_nT[:, index],
            time_s=take(self.time_s),
            temperature_C=take(self.temperature_C),
            ref_total_nT=take(self.ref_total_nT),
            attitude_wxyz=take(self.attitude_wxyz),
            group=take(self.group),
            extra={k: v[index] for k, v in self.extra.items()},
            metadata=dict(self.metadata),
        )

    def sensors(self, indices) -> "Dataset":
        """A new dataset with only the listed sensors (0-based indices)."""
        return dataclasses.replace(self, readings_nT=self.readings_nT[list(indices)], metadata=dict(self.metadata))

    def to_dataframe(self):
        """The data as a pandas DataFrame with the data CSV's columns (readings in nT) and the metadata in
        ``attrs``; :func:`as_dataset` reads it back."""
        import pandas as pd

        from .io import dataset_columns, dataset_metadata

        frame = pd.DataFrame({k: np.asarray(v) for k, v in dataset_columns(self).items()})
        frame.attrs = dataset_metadata(self)
        return frame

    def replace(self, **changes) -> "Dataset":
        """A copy with some fields replaced (see :func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)

    def describe(self) -> str:
        """One line: sensors, samples, channels, reference, baseline."""
        ref = f"{self.reference_total_nT:.1f} nT" if self.reference_total_nT else "unknown (fitted)"
        chans = ", ".join(sorted(self.channels)) or "none"
        base = f", baseline {self.baseline_m} m" if self.baseline_m else ""
        return f"{self.n_sensors} sensor(s), {self.n_samples} samples, channels: {chans}, reference field {ref}{base}"


# -- conversion of what users hold into a Dataset ------------------------------------------------------------------
_ACCEPTED_SHAPES = "(N, 3) for one sensor or (n_sensors 1-4, N, 3) for an array, in nT"


def _is_dataframe(data) -> bool:
    """True for a pandas DataFrame, without importing pandas (it is only loaded if the caller already did)."""
    return any(cls.__name__ == "DataFrame" and cls.__module__.split(".")[0] == "pandas" for cls in type(data).__mro__)


def _readings_from_array(data) -> np.ndarray:
    try:
        readings = np.asarray(data, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"readings: cannot be read as numbers ({exc}); give a numeric array of shape "
                           f"{_ACCEPTED_SHAPES}") from None
    shape = readings.shape
    hint = ""
    if readings.ndim == 2 and shape[0] == 3 and shape[1] != 3:
        hint = " (it looks transposed: pass readings.T)"
    elif readings.ndim == 3 and shape[2] != 3 and shape[1] == 3:
        hint = " (the axes look swapped: pass readings.transpose(0, 2, 1))"
    elif readings.ndim == 3 and shape[2] == 3 and shape[0] > 4:
        hint = " (at most 4 sensors; is the sample axis first? pass readings.transpose(1, 0, 2))"
    elif readings.ndim == 2 and shape[1] in (6, 9, 12):
        hint = (f" (for {shape[1] // 3} sensors stack them as (n_sensors, N, 3): "
                "readings.reshape(N, -1, 3).transpose(1, 0, 2))")
    ok = (readings.ndim == 2 and shape[1] == 3) or (readings.ndim == 3 and shape[2] == 3 and 1 <= shape[0] <= 4)
    if not ok:
        raise DatasetError(f"readings: got an array of shape {shape}; accepted shapes are {_ACCEPTED_SHAPES}{hint}")
    if readings.ndim == 2:
        readings = readings[None]
    if readings.shape[1] == 0:
        raise DatasetError(f"readings: got an array of shape {shape} with no samples; accepted shapes are "
                           f"{_ACCEPTED_SHAPES} with N >= 1")
    bad = ~np.isfinite(readings)
    if bad.any():
        s, i, a = np.argwhere(bad)[0]
        raise DatasetError(f"readings: {int(bad.sum())} value(s) are NaN or infinite, the first at sensor {s + 1}, "
                           f"sample {i} (0-based), axis {'xyz'[a]}; drop or fill those samples first")
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
        raise DatasetError(f"{name}: got shape {values.shape}; accepted is ({n},), one value per sample in "
                           f"{unit}{scalar}")
    bad = ~np.isfinite(values)
    if bad.any():
        raise DatasetError(f"{name}: {int(bad.sum())} value(s) are NaN or infinite, the first at sample "
                           f"{int(np.argmax(bad))} (0-based)")
    return values


def _check_times(time_s) -> None:
    step = np.diff(time_s)
    if (step <= 0).any():
        i = int(np.argmax(step <= 0)) + 1
        raise DatasetError(f"t: sample times must be strictly increasing; sample {i} (0-based) is at "
                           f"{time_s[i]:g} s, after {time_s[i - 1]:g} s; sort the samples by time or drop repeats")


def _from_dataframe(frame) -> "Dataset":
    """Read a DataFrame whose columns are those of the data CSV (``s1x`` ..., ``x,y,z``, ``t``, ``temp`` ...)."""
    import io as _io

    from .io import read_csv  # lazily: io is heavier than this module and imports it

    if frame.shape[0] == 0:
        raise DatasetError("DataFrame: it has no rows; one row per sample is needed")
    lines = []
    for key, value in frame.attrs.items():  # DataFrame.attrs play the part of the file's "# key: value" lines
        key, value = str(key).strip(), str(value).strip()
        if not key or ":" in key or "\n" in key + value:
            raise DatasetError(f"DataFrame.attrs[{key!r}]: keys must be single-line names without ':' and values "
                               "single-line text, as the data CSV's '# key: value' lines")
        lines.append(f"# {key}: {value}\n")
    labels = frame.index
    if any(name is not None for name in frame.index.names):
        frame = frame.reset_index()  # a named index (e.g. "t") is a column like the others
    frame = frame.rename(columns=str)
    text = "".join(lines) + frame.to_csv(index=False, lineterminator="\n")
    try:
        return read_csv(_io.StringIO(text), name="DataFrame")
    except DatasetError as exc:
        raise DatasetError(_frame_message(str(exc), labels, first_line=len(lines) + 2)) from None


def _frame_message(message: str, index, first_line: int) -> str:
    """A reader's message about the CSV text of a DataFrame, with its line numbers turned into the frame's rows."""
    import re

    def row(match):
        k = int(match.group(1)) - first_line
        if not 0 <= k < len(index):
            return match.group(0)  # the header or a metadata line
        return f"row {index[k]!r}"

    message, n = re.subn(r"\bline\s(\d+)", row, message)
    message = message.replace("drop them with --drop-bad (drop_bad=True)", "drop them with frame.dropna()")
    if n:
        message = message.replace(" row(s) in this block", " row(s)").replace("Sort the file", "Sort the rows")
    return message


def as_dataset(data, *, reference_total_nT=None, t=None, temp=None) -> Dataset:
    """What the user holds, as a :class:`Dataset`.

    Parameters
    ----------
    data : Dataset, array_like or pandas.DataFrame
        A :class:`Dataset` (returned as it is, or a copy if a keyword changes it); an array of raw readings in
        nT of shape ``(N, 3)`` (one sensor) or ``(n_sensors, N, 3)`` (1 to 4 sensors, numbered as in
        :mod:`magcal.conventions`); or a pandas DataFrame with the columns of the data CSV
        (``s1x, s1y, s1z`` ... or ``x, y, z``, optional ``t``, ``temp``, ``ref_total``, ``qw..qz``, ``group``; see
        docs/formats.md), read by the same checks as a file; its ``attrs`` (e.g. ``{"baseline_m": 0.5}``) count as
        the file's ``# key: value`` metadata lines, and a named index (e.g. ``t``) counts as a column.
    reference_total_nT : float, optional
        Known total field of the whole record in nT (otherwise fitted, or a ``ref_total`` column).
    t : array_like, shape (N,), optional
        Sample times in s, strictly increasing (needed by time-dependent effects such as ``bias_drift``).
    temp : array_like, shape (N,) or float, optional
        Temperature in degC (needed by ``temperature_bias`` and the other temperature effects).

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
    magcal.dataset.DatasetError: readings: got an array of shape (3, 200); accepted shapes are (N, 3) ... readings.T)
    """
    if isinstance(data, Dataset):
        ds = data
    elif _is_dataframe(data):
        ds = _from_dataframe(data)
    else:
        ds = Dataset(readings_nT=_readings_from_array(data))
    changes = {}
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
            raise DatasetError(f"reference_total_nT: got {reference_total_nT!r}; a positive number of nT is needed "
                               "(e.g. 50000)")
        changes["reference_total_nT"] = value
    return ds.replace(**changes) if changes else ds
