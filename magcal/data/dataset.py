"""The dataset: raw readings of one to four triaxial sensors plus optional channels and metadata.

A :class:`Dataset` is what every later step takes: the fitter, the diagnosis, the calibration's ``apply``,
and the workbench. Its arrays are read-only (a writable array given to it is copied first) and its methods return
new datasets, so nothing computed from a dataset goes stale.
"""

from __future__ import annotations

import dataclasses
import hashlib
import threading
import weakref
from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import MagcalError
from magcal.data.site import SITE_KEYS

#: Channel names a model term may require, and the Dataset attribute each one lives in.
CHANNELS = {
    "time": "time_s",
    "temperature": "temperature_C",
    "attitude": "attitude_wxyz",
    "reference": "ref_total_nT",
    "group": "group",
}


def _frozen(value, dtype=float) -> np.ndarray:
    """``value`` as a read-only array that no one else can change: the caller's own array (or a view of one) is
    copied, a fresh array is only marked read-only, a read-only array is kept as it is.

    A dataset's arrays never change after it is made, so what is computed from them can be kept
    (:class:`magcal.core.readings_cache.ReadingsCache`) and a user who later changes their array in place changes
    nothing the dataset holds.
    """
    a = np.asarray(value, dtype=dtype)
    if a.flags.writeable:
        if a is value or a.base is not None:
            a = a.copy()
        a.flags.writeable = False
    return a


#: :meth:`Dataset.masked`'s datasets: (id of the dataset, the mask's digest) -> weak references to the dataset and
#: to its masked one (an entry whose dataset or masked dataset is gone is dropped).
_MASKED: dict = {}
_MASKED_LOCK = threading.Lock()


class DatasetError(MagcalError, ValueError):
    """Bad input data; the message names the file, row or column and what to do."""


# -- the one rule for numbers read from any file or stream ----------------------------------------------------------
#: Largest magnitude a number read from a file or a stream may hold (readings, time stamps, channels, in any unit):
#: far beyond any reading, temperature or time stamp (epoch ns are ~2e18), and small enough that sums of squares
#: and fourth powers stay finite in float64. The CSV and Parquet readers, the flight-log readers and the live
#: sources and recorder all apply it through :func:`bad_values`.
MAX_ABS_VALUE = 1e30

#: How the rule reads in a message.
BAD_VALUE_TEXT = f"NaN, infinite or beyond +-{MAX_ABS_VALUE:g}"


def bad_values(values, axis=None):
    """Where numbers break magcal's one rule for read values: NaN, +-inf or a magnitude above :data:`MAX_ABS_VALUE`.

    Parameters
    ----------
    values : array_like of float
    axis : int or tuple of int, optional
        Reduce over these axes (True where any value along them is bad), e.g. ``axis=1`` for rows of an (N, k)
        array; default element-wise.

    Returns
    -------
    numpy.ndarray of bool
    """
    v = np.asarray(values, dtype=float)
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(v) <= MAX_ABS_VALUE)  # NaN compares False: bad
    return bad if axis is None else bad.any(axis=axis)


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
    notes : tuple of Note
        What the reader that made the dataset had to say (:class:`~magcal.core.notes.Note`: rows dropped, units
        that look wrong, magnetometers left out...), set by the reader; raised as warnings only by the public
        readers (:func:`magcal.read_csv`, :func:`magcal.read_log`), printed by the command line. Not compared.
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
    notes: tuple = field(default=(), compare=False, repr=False)

    def __post_init__(self):
        r = _frozen(self.readings_nT)
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
                value = _frozen(np.asarray(value, dtype=float).reshape(-1))
                if value.shape[0] != n:
                    raise DatasetError(f"{self.source or 'dataset'}: {attr} has {value.shape[0]} rows, expected {n}")
                setattr(self, attr, value)
        if self.attitude_wxyz is not None:
            q = _frozen(self.attitude_wxyz)
            if q.shape != (n, 4):
                raise DatasetError(f"{self.source or 'dataset'}: attitude must have shape ({n}, 4), got {q.shape}")
            self.attitude_wxyz = q
        if self.group is not None:
            self.group = _frozen(np.asarray(self.group).astype(str), dtype=None)
        self.extra = {k: _frozen(v, dtype=None) for k, v in self.extra.items()}

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

    def subset(self, index) -> Dataset:
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

    def masked(self, mask) -> Dataset:
        """The samples a boolean ``mask`` selects: :meth:`subset`, but the same dataset for the same mask while
        anything still holds it (this dataset when the mask selects every sample).

        What is computed from a dataset's arrays alone (a step scan, the noise's still stretches and quantization:
        :class:`magcal.core.readings_cache.ReadingsCache`) is then computed once for a record with rejected
        samples too, where each fit used to cut the samples anew. Like every dataset, the one returned must not be
        changed (its metadata and extra channels are shared with the other users of the same mask).

        Parameters
        ----------
        mask : numpy.ndarray of bool, shape (n_samples,)
        """
        mask = np.asarray(mask, bool)
        if mask.shape != (self.n_samples,):
            raise DatasetError(f"mask has shape {mask.shape}, expected ({self.n_samples},)")
        if mask.all():
            return self
        key = (id(self), hashlib.blake2b(np.packbits(mask).tobytes(), digest_size=16).digest())
        with _MASKED_LOCK:
            hit = _MASKED.get(key)
            if hit is not None and hit[0]() is self:
                kept = hit[1]()
                if kept is not None:
                    return kept
        kept = self.subset(mask)
        with _MASKED_LOCK:
            for k in [k for k, (parent, sub) in _MASKED.items() if parent() is None or sub() is None]:
                del _MASKED[k]
            _MASKED[key] = (weakref.ref(self), weakref.ref(kept))
        return kept

    def sensors(self, indices) -> Dataset:
        """A new dataset with only the listed sensors (0-based indices)."""
        return dataclasses.replace(self, readings_nT=self.readings_nT[list(indices)], metadata=dict(self.metadata))

    def to_dataframe(self):
        """The data as a pandas DataFrame with the data CSV's columns (readings in nT) and the metadata in
        ``attrs``; :func:`magcal.data.inputs.as_dataset` reads it back."""
        import pandas as pd

        frame = pd.DataFrame({k: np.asarray(v) for k, v in dataset_columns(self).items()})
        frame.attrs = dataset_metadata(self)
        return frame

    def replace(self, **changes) -> Dataset:
        """A copy with some fields replaced (see :func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)

    def describe(self, reference: str | None = None) -> str:
        """One line: sensors, samples, channels, reference, baseline (``reference``: what to say of it instead,
        e.g. a vector calibration's field vector)."""
        ref = f"{self.reference_total_nT:.1f} nT" if self.reference_total_nT else "unknown (fitted)"
        if reference is not None:
            ref = reference
        chans = ", ".join(sorted(self.channels)) or "none"
        base = f", baseline {self.baseline_m} m" if self.baseline_m else ""
        return f"{self.n_sensors} sensor(s), {self.n_samples} samples, channels: {chans}, reference field {ref}{base}"


QUATERNION_COLUMNS = ("qw", "qx", "qy", "qz")


SENSOR_AXES = ("x", "y", "z")


def dataset_columns(dataset):
    """Ordered mapping column name -> array for a :class:`Dataset` in the documented layout (nT)."""
    cols = {}
    if dataset.time_s is not None:
        cols["t"] = dataset.time_s
    for i in range(dataset.n_sensors):
        for k, a in enumerate(SENSOR_AXES):
            cols[f"s{i + 1}{a}"] = dataset.readings_nT[i, :, k]
    if dataset.temperature_C is not None:
        cols["temp"] = dataset.temperature_C
    if dataset.ref_total_nT is not None:
        cols["ref_total"] = dataset.ref_total_nT
    if dataset.attitude_wxyz is not None:
        for k, name in enumerate(QUATERNION_COLUMNS):
            cols[name] = dataset.attitude_wxyz[:, k]
    if dataset.group is not None:
        cols["group"] = dataset.group
    for name, value in dataset.extra.items():
        if name not in cols:
            cols[name] = value
    return cols


def dataset_metadata(dataset):
    """Metadata lines for a dataset: its metadata dict with the numeric fields and ``units: nT``; the numbers read
    from a ``# site:`` line (:data:`magcal.data.site.SITE_KEYS`) are left to the line, which is written."""
    derived = SITE_KEYS if "site" in dataset.metadata else ()
    meta = {k: v for k, v in dataset.metadata.items() if k not in derived}
    if dataset.baseline_m is not None:
        meta["baseline_m"] = repr(float(dataset.baseline_m))
    if dataset.reference_total_nT is not None:
        meta["reference_total_nT"] = repr(float(dataset.reference_total_nT))
    if dataset.noise_nT is not None:
        meta["noise_nT"] = repr(float(dataset.noise_nT))
    meta["units"] = "nT"
    return meta
