"""The accelerometer beside a magnetometer: its columns, their unit, and the samples that measure gravity.

A board that carries a magnetometer usually carries an accelerometer (phones, flight controllers, cave-survey
instruments, tilt-compensated compasses). At rest it measures the specific force, gravity's reaction: ``+g`` along
the axis that points up. Its columns (kept by every reader in :attr:`magcal.data.dataset.Dataset.extra`):

* ``ax, ay, az``: the unit is the file's ``# accel_units:`` line (``g``, ``mg`` or ``m/s^2``), else the one the
  readings' magnitude implies (about 1: g; about 9.8: m/s^2; about 1000: mg), else the record is refused;
* ``ax_g, ay_g, az_g`` (g) or ``ax_m_s2, ay_m_s2, az_m_s2`` (m/s^2): the unit is in the name.

A row whose three cells are empty (or ``nan``) has no accelerometer sample (a stream at another rate); one or two of
them empty, text, or a value :data:`magcal.data.dataset.BAD_VALUE_TEXT` is refused naming the row and the column.
The flight-log readers (:mod:`magcal.data.logs`) write ``ax, ay, az`` in m/s^2 with ``accel_units: m/s^2``.

Only still samples measure gravity: a hand that turns the board also accelerates it. :func:`find_still` keeps the
samples whose accelerometer is steady (its moving standard deviation below :data:`STILL_MOTION_G`), whose gyro (when
the record has one, :func:`magcal.data.attitude.turn_rate_dps`) is quiet and whose ``|a|`` is near its median; a
record without still moments (a board waved continuously) falls back on its quietest samples, with a note.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal.core.stats import moving_mean
from magcal.data.attitude import turn_rate_dps
from magcal.data.dataset import BAD_VALUE_TEXT, MAX_ABS_VALUE, Dataset, DatasetError

#: Standard gravity (m/s^2): the magnitude a still, calibrated accelerometer reads (local gravity differs by at
#: most 0.3 %, which only scales the accelerometer's fitted gain, never a direction or a heading).
STANDARD_GRAVITY_M_S2 = 9.80665

#: Accelerometer unit names (lower case, spaces removed) -> m/s^2 per unit.
ACCEL_UNIT_FACTORS = {
    "g": STANDARD_GRAVITY_M_S2,
    "mg": 1e-3 * STANDARD_GRAVITY_M_S2,
    "m/s^2": 1.0,
    "m/s2": 1.0,
    "m/s/s": 1.0,
    "ms^-2": 1.0,
    "m_s2": 1.0,
}

#: The accelerometer's column triples, with the unit each implies (None: the ``# accel_units:`` line or the
#: magnitude), the first present wins.
ACCEL_COLUMNS = (
    (("ax", "ay", "az"), None),
    (("ax_g", "ay_g", "az_g"), "g"),
    (("ax_m_s2", "ay_m_s2", "az_m_s2"), "m/s^2"),
)

#: Column names a ``--columns`` mapping may map a file's accelerometer columns onto (``ax=accX,ay=accY,az=accZ``).
MAPPABLE_ACCEL_COLUMNS = ACCEL_COLUMNS[0][0]

#: Ranges of the median ``|a|`` (in the unit's numbers) that say which unit unmarked columns are in.
UNIT_BY_MAGNITUDE = (("g", 0.5, 2.0), ("m/s^2", 5.0, 20.0), ("mg", 500.0, 2000.0))

#: A still accelerometer: its moving standard deviation (per axis, over :data:`STILL_WINDOW_S`) below this (g).
#: MEMS parts are 1-5 mg noisy per sample; a hand holding a board still moves it by a few mg.
STILL_MOTION_G = 0.01
#: ... its turn rate (when the record has a gyro or an attitude) below this (deg/s).
STILL_TURN_DPS = 5.0
#: ... and its ``|a|`` within this fraction of the record's median (an uncalibrated part's bias and scale move
#: ``|a|`` by a few percent with attitude; a hand's push by more).
STILL_MAGNITUDE_FRACTION = 0.06
#: The window of the moving standard deviation (s), or :data:`STILL_WINDOW_SAMPLES` samples without times.
STILL_WINDOW_S = 0.3
STILL_WINDOW_SAMPLES = 7
#: Fewest still samples a record must have before the quietest ones are taken instead.
MIN_STILL = 30
#: The quietest samples replace the still ones when they tell this many times more about gravity's direction
#: (their number over the square of their motion): a board waved continuously, with a few still moments only.
QUIETEST_GAIN = 3.0


@dataclass
class Accelerometer:
    """A dataset's accelerometer readings.

    Attributes
    ----------
    m_s2 : numpy.ndarray, shape (N, 3)
        Specific force in m/s^2 in the accelerometer's axes (up when still); NaN rows: no accelerometer sample.
    columns : tuple of str
        The three columns read.
    unit : str
        ``g``, ``mg`` or ``m/s^2``.
    unit_source : str
        ``column name``, ``file`` (the ``# accel_units:`` line), ``given`` or ``magnitude`` (inferred).
    notes : tuple of str
        What the reader has to say (a given unit the magnitude contradicts); the gravity fit passes it on.
    """

    m_s2: np.ndarray
    columns: tuple
    unit: str
    unit_source: str
    notes: tuple = ()

    @property
    def present(self) -> np.ndarray:
        """Rows with an accelerometer sample, bool (N,)."""
        return np.all(np.isfinite(self.m_s2), axis=1)


def accelerometer_columns(dataset: Dataset) -> tuple | None:
    """``(names, unit)`` of the accelerometer columns a dataset holds (:data:`ACCEL_COLUMNS`), or None."""
    for names, unit in ACCEL_COLUMNS:
        if all(n in dataset.extra for n in names):
            return names, unit
    return None


def has_accelerometer(dataset: Dataset) -> bool:
    """Whether the dataset holds accelerometer columns."""
    return accelerometer_columns(dataset) is not None


def parse_accel_units(text, where="accel_units") -> str:
    """The canonical accelerometer unit (``g``, ``mg`` or ``m/s^2``) of a unit name.

    Raises
    ------
    DatasetError
        For a name that is none of them.
    """
    key = str(text).strip().lower().replace(" ", "")
    if key not in ACCEL_UNIT_FACTORS:
        raise DatasetError(f"{where}: unknown accelerometer unit {text!r}; use g, mg or m/s^2")
    factor = ACCEL_UNIT_FACTORS[key]
    return "g" if factor == STANDARD_GRAVITY_M_S2 else "mg" if factor < 1 else "m/s^2"


def _column_numbers(values, name, source) -> np.ndarray:
    """A column's cells as floats: empty or ``nan`` cells NaN; text, infinite or huge values refused."""
    a = np.asarray(values)
    if a.dtype.kind in "fiub":
        out = a.astype(float)
    else:
        out = np.empty(a.shape[0])
        for k, cell in enumerate(a.astype(str)):
            cell = cell.strip()
            if cell == "" or cell.lower() == "nan":
                out[k] = np.nan
                continue
            try:
                out[k] = float(cell)
            except ValueError:
                raise DatasetError(
                    f"{source}: column {name}, data row {k + 1}: {cell[:40]!r} is not a number; the accelerometer "
                    "columns hold numbers (g, mg or m/s^2: '# accel_units:'), or are empty on a row without an "
                    "accelerometer sample"
                ) from None
    with np.errstate(invalid="ignore"):
        bad = np.isinf(out) | (np.abs(out) > MAX_ABS_VALUE)
    if bad.any():
        k = int(np.argmax(bad))
        raise DatasetError(
            f"{source}: column {name}, data row {k + 1}: {out[k]:g} is {BAD_VALUE_TEXT}; fix or delete the row "
            f"({int(bad.sum())} such row(s))"
        )
    return out


def accelerometer(dataset: Dataset, units=None) -> Accelerometer | None:
    """The dataset's accelerometer in m/s^2, or None when it has no accelerometer columns.

    Parameters
    ----------
    dataset : Dataset
    units : str, optional
        The unit of ``ax, ay, az`` (``g``, ``mg``, ``m/s^2``); default the file's ``# accel_units:`` line, else the
        one the magnitude implies. Columns whose name carries a unit keep it.

    Raises
    ------
    DatasetError
        Text or bad values in a column (naming the row and the column), one or two of a row's three cells empty,
        or a magnitude that says no unit.
    """
    found = accelerometer_columns(dataset)
    if found is None:
        return None
    names, implied = found
    where = dataset.source or "data"
    a = np.column_stack([_column_numbers(dataset.extra[n], n, where) for n in names])
    missing = np.isnan(a)
    partial = missing.any(axis=1) & ~missing.all(axis=1)
    if partial.any():
        k = int(np.argmax(partial))
        lacking = [n for n, m in zip(names, missing[k]) if m]
        raise DatasetError(
            f"{where}: data row {k + 1}, column {lacking[0]}: empty or nan while the other accelerometer columns "
            f"hold numbers ({int(partial.sum())} such row(s)); give all three of {', '.join(names)}, or leave all "
            "three empty on a row without an accelerometer sample"
        )
    have = ~missing.any(axis=1)
    median = float(np.median(np.linalg.norm(a[have], axis=1))) if have.any() else float("nan")
    guessed = next((u for u, lo, hi in UNIT_BY_MAGNITUDE if lo <= median <= hi), None)
    if implied is not None:
        unit, source = implied, "column name"
    elif units is not None:
        unit, source = parse_accel_units(units, "--accel-units"), "given"
    elif dataset.metadata.get("accel_units"):
        unit, source = parse_accel_units(dataset.metadata["accel_units"], f"{where}: '# accel_units:'"), "file"
    elif guessed is not None:
        unit, source = guessed, "magnitude"
    else:
        raise DatasetError(
            f"{where}: the accelerometer columns {', '.join(names)} have a median magnitude of {median:.4g}, which "
            "says neither g (about 1), m/s^2 (about 9.8) nor mg (about 1000); give the unit with a "
            "'# accel_units: g' line (g, mg or m/s^2) or --accel-units, and check that the columns are the "
            "accelerometer's"
        )
    notes = []
    if source != "magnitude" and guessed is not None and guessed != unit:
        notes.append(
            f"{where}: the accelerometer is said to read in {unit}, but its median magnitude {median:.4g} looks like "
            f"{guessed}: check '# accel_units:' (or --accel-units)"
        )
    return Accelerometer(a * ACCEL_UNIT_FACTORS[unit], tuple(names), unit, source, tuple(notes))


@dataclass
class StillSamples:
    """The samples whose accelerometer measures gravity (:func:`find_still`).

    Attributes
    ----------
    mask : numpy.ndarray of bool, shape (N,)
    kind : str
        ``still`` (steady accelerometer, quiet gyro) or ``quietest`` (no still moments: the quieter half of the
        samples whose ``|a|`` is near its median; the hand's acceleration then enters the accelerometer's noise).
    motion_g : numpy.ndarray, shape (N,)
        The accelerometer's moving standard deviation (largest axis, g) per sample.
    turn_dps : numpy.ndarray or None
        The turn rate per sample (deg/s), when the record has a gyro or an attitude.
    notes : list of str
    """

    mask: np.ndarray
    kind: str
    motion_g: np.ndarray
    turn_dps: np.ndarray | None
    notes: list

    @property
    def n(self) -> int:
        return int(np.count_nonzero(self.mask))

    def text(self) -> str:
        """One line: how many samples measure gravity and how they were chosen."""
        how = (
            f"accelerometer steady (moving SD < {1000 * STILL_MOTION_G:.0f} mg)"
            + (f", turn rate < {STILL_TURN_DPS:g} deg/s" if self.turn_dps is not None else "")
            if self.kind == "still"
            else "no still moments: the quieter half of the samples with |a| near g"
        )
        return f"{self.n} of {self.mask.size} samples measure gravity ({how})"


def _moving_sd(a, window) -> np.ndarray:
    """Largest per-axis standard deviation over the ``window`` samples around each sample of ``a`` (N, 3), finite
    (a row without a sample is filled from its neighbour first)."""
    sd = np.zeros(a.shape[0])
    for k in range(3):
        x = a[:, k]
        m1 = moving_mean(x, window)
        m2 = moving_mean(x * x, window)
        sd = np.maximum(sd, np.sqrt(np.clip(m2 - m1 * m1, 0.0, None)))
    return sd


def find_still(dataset: Dataset, accel: Accelerometer | None = None, mask=None) -> StillSamples:
    """The samples whose accelerometer measures gravity alone.

    Parameters
    ----------
    dataset : Dataset
        With accelerometer columns (times and a gyro, ``gx_dps..`` or the others of
        :data:`magcal.data.attitude.GYRO_COLUMNS`, used when present).
    accel : Accelerometer, optional
        Its readings (default :func:`accelerometer`).
    mask : array_like of bool, shape (N,), optional
        Samples that may be chosen (default all).

    Returns
    -------
    StillSamples
    """
    accel = accelerometer(dataset) if accel is None else accel
    if accel is None:
        raise DatasetError(
            f"{dataset.source or 'data'}: no accelerometer columns (ax, ay, az; docs/gravity.md); a gravity "
            "calibration needs them"
        )
    n = dataset.n_samples
    allowed = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    present = accel.present & allowed & np.all(np.isfinite(dataset.readings_nT), axis=(0, 2))
    a_g = np.where(present[:, None], accel.m_s2, np.nan) / STANDARD_GRAVITY_M_S2
    filled = a_g.copy()
    if present.any() and not present.all():  # a missing sample takes its nearest neighbour's value
        idx = np.flatnonzero(present)
        nearest = idx[np.clip(np.searchsorted(idx, np.arange(n)), 0, idx.size - 1)]
        filled = a_g[nearest]
    elif not present.any():
        filled = np.zeros_like(a_g)
    t = dataset.time_s
    window = STILL_WINDOW_SAMPLES
    if t is not None and n > 2:
        dt = float(np.median(np.diff(t)))
        if dt > 0:
            window = int(np.clip(round(STILL_WINDOW_S / dt), 3, 101))
    motion = _moving_sd(filled, window)
    norm = np.linalg.norm(filled, axis=1)
    med = float(np.median(norm[present])) if present.any() else 1.0
    near_g = np.abs(norm / med - 1.0) < STILL_MAGNITUDE_FRACTION
    rate = turn_rate_dps(dataset)
    quiet = np.ones(n, bool) if rate is None else np.asarray(rate, float) < STILL_TURN_DPS
    still = present & near_g & quiet & (motion < STILL_MOTION_G)
    candidates = present & near_g
    quietest = candidates & (motion <= float(np.median(motion[candidates]))) if candidates.any() else candidates
    notes: list[str] = []
    if still.sum() >= MIN_STILL and _information(still, motion, filled) >= (
        _information(quietest, motion, filled) / QUIETEST_GAIN
    ):
        return StillSamples(still, "still", motion, rate, notes)
    chosen = quietest if quietest.sum() >= MIN_STILL else candidates
    notes.append(
        f"{dataset.source or 'data'}: only {int(still.sum())} samples are still (accelerometer steady within "
        f"{1000 * STILL_MOTION_G:.0f} mg"
        + (f", turn rate below {STILL_TURN_DPS:g} deg/s" if rate is not None else "")
        + f"); the {int(chosen.sum())} quietest samples with |a| near g are used instead: the hand's acceleration "
        "enters the accelerometer's noise and the dip scatters more. Hold the board still for a second or two at "
        "each attitude"
    )
    return StillSamples(chosen, "quietest", motion, rate, notes)


def _information(chosen, motion, accel) -> float:
    """What a set of samples tells about the rotation between the sensors: their number over the square of their
    typical accelerometer motion (g), times how far their attitudes spread (:func:`direction_spread`: samples at one
    attitude tell nothing)."""
    if not chosen.any():
        return 0.0
    typical = max(float(np.median(motion[chosen])), 1e-4)
    return float(np.count_nonzero(chosen)) / typical**2 * direction_spread(accel[chosen])


def direction_spread(vectors) -> float:
    """Smallest eigenvalue of the mean outer product of the vectors' directions: 1/3 for directions over the whole
    sphere, 0 for directions in one plane or at one attitude.

    Parameters
    ----------
    vectors : array_like, shape (N, 3)
        Any unit.
    """
    v = np.asarray(vectors, dtype=float)
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    return float(np.linalg.eigvalsh(u.T @ u / max(len(u), 1))[0])
