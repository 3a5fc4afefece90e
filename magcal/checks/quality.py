"""Data quality of a recording, read before fitting: what the file holds and what that does to the fit.

Real recordings are not the clean samples of a simulation. A MEMS part reports integer counts of 15-300 nT
(quantization), a host that polls faster than the part converts reads the same vector again (stale samples), the
logger's clock repeats or jitters, and the first minutes are often a static warm-up. None of this stops a fit, but
each changes what its figures mean. :func:`assess` measures them and says, for each, what it does to the fit:

=================  =========================================================================================
``sample_rate``    median interval of the time stamps (s) and its jitter (robust spread of the intervals over
                   the median), the mean rate (samples / duration); stamps that arrive in batches
                   (:func:`is_batched`) are named so, with the mean rate as the rate
``gaps``           intervals longer than :data:`GAP_FACTOR` times the median (for batches: the usual interval
                   between batches): count and longest (s)
``time_order``     repeated (equal) or backward time stamps
``stale``          consecutive identical vectors per sensor: fraction of the samples and longest run
``quantization``   step per axis (nT), found as the greatest common step of the sorted distinct values, and its
                   noise floor ``q / sqrt(12)``
``clipping``       readings piling at an axis's extreme (saturation)
``static``         stretches where the vector moves no more than the noise: count, longest, and their scatter per
                   axis (nT) - a direct measurement of the noise
``temperature``    range (degC) and its correlation with time
``field``          after a fit: a fitted field magnitude outside the Earth's 20-70 uT (:func:`field_magnitude_finding`)
``turn_rate``      after a fit: the residual RMS by turn-rate quartile (:func:`turn_rate_finding`)
``other_field``    a part at the start or the end of the record whose total field differs from the rest's (another
                   run, a still phase in another field): its rows, time span and shift (:func:`other_field_finding`;
                   ``--exclude-part`` leaves it out)
=================  =========================================================================================

Each :class:`Finding` has a severity (``info`` or ``warning``), a flag ``notable`` (shown in the text report) and
one sentence on its effect on the fit. ``magcal calibrate`` and ``magcal diagnose`` print the notable ones in a
"Data quality" section, put all of them in ``--json`` under ``quality`` and every warning in ``warnings``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import CalibrationError
from magcal.core.rows import row_norm
from magcal.core.stats import robust_sigma
from magcal.geometry.ellipsoid import field_noise_nT, fit_ellipsoid
from magcal.geometry.shape import field_shape

#: An interval longer than this many median intervals is a gap.
GAP_FACTOR = 3.0
#: Stamps are batched when the median interval is under this fraction of the mean one...
BATCH_SHORT = 0.5
#: ...and at least this share of the intervals is over GAP_FACTOR times the median.
BATCH_LONG_SHARE = 0.05
#: Jitter (robust spread of the intervals / median interval) above which the timing is a warning.
JITTER_WARN = 0.10
#: Fraction of stale (repeated) samples above which they are a warning (any stale sample is notable above 1 %).
STALE_WARN = 0.05
#: Fewest distinct values of an axis needed to claim a quantization step.
MIN_LEVELS = 12
#: Largest |d/q - round(d/q)| for a difference d to count as a multiple of the step q.
MULTIPLE_TOL = 0.1
#: Share of the differences that must be multiples of q.
MULTIPLE_SHARE = 0.95

#: A record of more values than this is first screened on an even subsample of :data:`SCREEN_SAMPLES` values: when
#: that shows no step (continuous readings, most large records) the values are not all sorted. A grid so fine that
#: the subsample's nearest levels are more than ``max_divisor`` steps apart is then not reported: for readings
#: spanning 100 000 nT a step below about 0.04 nT, whose ``q / sqrt(12)`` is below 0.012 nT.
SCREEN_FROM_SAMPLES = 200_000
SCREEN_SAMPLES = 50_000
#: The occupied levels lie on a coarser grid when one spacing holds at least this share of the level spacings...
GRID_MODE_SHARE = 0.5
#: ...and smaller spacings (a grid whose origin shifts puts some levels closer) fewer than this share.
GRID_BELOW_SHARE = 0.35
#: Share of the level spacings off the step from which the report says the grid shifts.
GRID_SHIFT_NOTE = 0.02
#: Quantization noise q/sqrt(12) (nT) from which quantization is a warning (unless far below the noise).
QUANT_WARN_nT = 1.0
#: Samples in the sliding window of the static test (at least; with time stamps at least 1 s of them).
STATIC_WINDOW = 10
#: A window is static if each axis's standard deviation in it is at most this many noise levels...
STATIC_SIGMAS = 2.0
#: ...and at most this fraction of the field magnitude (guards against a noise estimate inflated by motion).
STATIC_FIELD_FRACTION = 0.01
#: Share of the samples in static stretches above which they are a warning.
STATIC_WARN = 0.2
#: |correlation| of temperature with time above which temperature and drift cannot be told apart.
TEMP_TIME_CORR_WARN = 0.9
#: Temperature span (K) below which the correlation is not judged and temperature terms are poorly determined.
TEMP_SPAN_MIN_K = 0.5
#: A readings value counts as piled at an axis extreme if at least this many samples and...
CLIP_MIN_COUNT = 5
#: ...this many times the mean count of the next three levels inward.
CLIP_RATIO = 4.0
#: The residual grows with the turn rate when the fastest quartile's RMS is this many times the slowest's...
TURN_RATE_RATIO = 1.2
#: ...and the rank correlation of |residual| with the rate has a p-value below this.
TURN_RATE_P = 1e-4
#: Range of the Earth's field at the surface, nT.
EARTH_FIELD_RANGE_nT = (20_000.0, 70_000.0)

AXES = ("x", "y", "z")


def _num(v):
    """A JSON-able number (None for None or non-finite)."""
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return _num(value)
    return value


@dataclass
class Finding:
    """One measured property of the data and what it does to the fit.

    Attributes
    ----------
    kind : str
        What was checked: ``sample_rate``, ``gaps``, ``time_order``, ``stale``, ``quantization``, ``clipping``,
        ``static``, ``temperature`` or ``field``.
    severity : str
        ``info`` or ``warning``.
    summary : str
        What was found, with numbers and units (no final full stop).
    effect : str
        One sentence: what this does to the fit.
    sensor : int or None
        1-based sensor number, None for the whole record (time, temperature).
    notable : bool
        Worth showing in the text report (every warning is; clean results are not).
    values : dict
        The numbers (nT, s, Hz, degC, fractions 0-1), JSON-able.
    """

    kind: str
    severity: str
    summary: str
    effect: str
    sensor: int | None = None
    notable: bool = False
    values: dict = field(default_factory=dict)

    def __post_init__(self):
        self.notable = bool(self.notable)
        self.sensor = None if self.sensor is None else int(self.sensor)

    @property
    def where(self) -> str:
        return f"sensor {self.sensor}: " if self.sensor is not None else ""

    def message(self, source=None) -> str:
        """One line for a warning list: ``source: sensor k: summary; effect``."""
        head = f"{source}: " if source else ""
        return f"{head}{self.where}{self.summary}; {self.effect}"

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "severity": self.severity,
            "sensor": self.sensor,
            "notable": self.notable,
            "summary": self.summary,
            "effect": self.effect,
            "values": _jsonable(self.values),
        }

    @classmethod
    def from_dict(cls, doc) -> Finding:
        """The finding :meth:`to_dict` wrote (e.g. from a workbench session or a ``--json`` document)."""
        return cls(
            kind=str(doc["kind"]),
            severity=str(doc["severity"]),
            summary=str(doc["summary"]),
            effect=str(doc["effect"]),
            sensor=doc.get("sensor"),
            notable=bool(doc.get("notable", False)),
            values=dict(doc.get("values") or {}),
        )


@dataclass
class QualityReport:
    """The findings of :func:`assess` (and any added after the fit, e.g. :func:`field_magnitude_finding`).

    Attributes
    ----------
    findings : list of Finding
    n_sensors, n_samples : int
    source : str or None
        The data's name (file path) for warning messages.
    """

    findings: list
    n_sensors: int
    n_samples: int
    source: str | None = None

    def add(self, finding) -> None:
        """Append a finding (None is ignored)."""
        if finding is not None:
            self.findings.append(finding)

    def find(self, kind, sensor=None) -> list:
        """The findings of one kind (and sensor, if given)."""
        return [f for f in self.findings if f.kind == kind and (sensor is None or f.sensor == sensor)]

    @property
    def warnings(self) -> list:
        """Warning-level findings as one-line messages (with the source in front)."""
        return [f.message(self.source) for f in self.findings if f.severity == "warning"]

    def to_dict(self) -> dict:
        """JSON-able: ``n_sensors``, ``n_samples``, ``source``, ``findings`` (every finding, see
        :meth:`Finding.to_dict`)."""
        return {
            "n_sensors": self.n_sensors,
            "n_samples": self.n_samples,
            "source": self.source,
            "findings": [f.to_dict() for f in self.findings],
        }

    @classmethod
    def from_dict(cls, doc) -> QualityReport:
        """The report :meth:`to_dict` wrote: what the workbench stores and shows."""
        return cls(
            [Finding.from_dict(f) for f in doc.get("findings", [])],
            int(doc.get("n_sensors", 0)),
            int(doc.get("n_samples", 0)),
            doc.get("source"),
        )

    def lines(self, notable_only=True) -> list:
        """Text lines: the sample-rate line, then each (notable) finding with its effect on the next line."""
        out = []
        for f in self.findings:
            if f.kind == "sample_rate" and f.severity == "info":
                out.append(f"  {f.summary}")
                continue
            if notable_only and not (f.notable or f.severity == "warning"):
                continue
            tag = "WARNING " if f.severity == "warning" else ""
            out.append(f"  {tag}{f.where}{f.summary}")
            if f.notable or f.severity == "warning":
                out.append(f"      -> {f.effect}")
        if not out:
            out.append("  nothing notable")
        return out

    def section(self, notable_only=True) -> str:
        """The "Data quality" section of a text report (with a trailing newline)."""
        return "\n".join(["Data quality", "------------"] + self.lines(notable_only)) + "\n"

    def __str__(self) -> str:
        return self.section(notable_only=False)


# -- timing --------------------------------------------------------------------------------------------------------
# long: one pass over the time stamps: rate, jitter, batches, gaps, repeated and backward stamps share the
# intervals and their usual value, and each finding is a few lines of its text and values
def timing_findings(time_s) -> list:
    """Sample rate and jitter, gaps, and repeated or backward time stamps.

    Parameters
    ----------
    time_s : numpy.ndarray, shape (N,)
        Sample times in s.

    Returns
    -------
    list of Finding
        ``sample_rate`` (always, with ``interval_s`` and ``rate_Hz``: the sampling interval (s) and rate (Hz),
        the median ones, or the mean ones when the stamps come in batches; ``median_interval_s``,
        ``mean_rate_Hz``, ``duration_s``, ``jitter``, ``batched``), ``gaps``, ``time_order``.
    """
    t = np.asarray(time_s, dtype=float)
    if t.size < 3:
        return []
    dt = np.diff(t)
    n_repeat = int(np.sum(dt == 0))
    n_back = int(np.sum(dt < 0))
    positive = dt[dt > 0]
    out = []
    if positive.size == 0:
        return [
            Finding(
                "sample_rate",
                "warning",
                f"all {t.size} time stamps are equal ({t[0]:.6g} s)",
                "time-dependent terms (drift, bias steps, lag) cannot be fitted from these times",
                notable=True,
                values={"interval_s": None, "rate_Hz": None, "jitter": None},
            )
        ]
    median = float(np.median(positive))
    duration = float(t.max() - t.min())
    mean = duration / (t.size - 1)
    batched = is_batched(dt)
    interval = mean if batched else median  # the sampling interval: the mean when the stamps come in batches
    jitter = float(robust_sigma(positive)) / median
    rate = 1.0 / interval
    values = {
        "interval_s": interval,
        "rate_Hz": rate,
        "jitter": jitter,
        "duration_s": duration,
        "median_interval_s": median,
        "mean_rate_Hz": 1.0 / mean if mean > 0 else None,
        "batched": batched,
    }
    if batched:
        short = float(np.mean(dt < BATCH_SHORT * mean))
        values["short_share"] = short
        summary = (
            f"sample rate {rate:.4g} Hz on average ({t.size} samples in {duration:.4g} s); the samples arrive "
            f"in batches: {100 * short:.0f}% of the intervals are under half the mean (median "
            f"{1000 * median:.3g} ms), the others long (up to {1000 * float(dt.max()):.4g} ms)"
        )
        out.append(
            Finding(
                "sample_rate",
                "warning",
                summary,
                "the stamps are the host's arrival times, not the sensor's sampling times: rates, lags, "
                "time derivatives and periods taken from them are wrong by up to the batch interval "
                "(time-stamp at the sensor, or use the mean rate)",
                notable=True,
                values=values,
            )
        )
    else:
        spread = f"{100 * jitter:.2g}%" if jitter >= 1e-3 else "under 0.1%"
        summary = f"sample rate {rate:.4g} Hz (median interval {interval:.4g} s), jitter {spread} of the interval"
        if abs(mean / median - 1.0) > 0.1:
            summary += f"; mean rate {1.0 / mean:.4g} Hz ({t.size} samples in {duration:.4g} s)"
        if jitter > JITTER_WARN:
            out.append(
                Finding(
                    "sample_rate",
                    "warning",
                    summary,
                    "time-dependent terms (drift, bias steps, lag, time derivatives) take the time stamps "
                    f"as given, so a jitter of {100 * jitter:.0f}% of the interval blurs a lag or rate term "
                    "by as much",
                    notable=True,
                    values=values,
                )
            )
        else:
            out.append(
                Finding(
                    "sample_rate",
                    "info",
                    summary,
                    "time stamps are regular enough for time-dependent terms",
                    values=values,
                )
            )
    # a gap is an interval well beyond the usual: the median one, or for batches the usual batch-to-batch one
    usual = float(np.median(positive[positive >= BATCH_SHORT * mean])) if batched else median
    gaps = positive > GAP_FACTOR * usual
    n_gaps = int(np.sum(gaps))
    longest = float(positive[gaps].max()) if n_gaps else 0.0
    gap_values = {
        "count": n_gaps,
        "longest_s": longest,
        "missing_s": float(np.sum(positive[gaps])) if n_gaps else 0.0,
        "threshold_s": GAP_FACTOR * usual,
    }
    what = "the usual interval between batches" if batched else "the median"
    if n_gaps:
        severe = longest > 10 * usual or n_gaps > 0.01 * dt.size
        out.append(
            Finding(
                "gaps",
                "warning" if severe else "info",
                f"{n_gaps} gap(s) in the time stamps (intervals over {GAP_FACTOR:g}x {what}), longest {longest:.4g} s",
                "drift and lag terms see a jump across a gap and time derivatives there are wrong; the "
                "scalar fit itself only loses the missing directions",
                notable=True,
                values=gap_values,
            )
        )
    else:
        out.append(
            Finding(
                "gaps",
                "info",
                "no gaps in the time stamps",
                "drift and lag terms see a continuous record",
                values=gap_values,
            )
        )
    if n_repeat or n_back:
        parts = ([f"{n_repeat} repeated time stamp(s)"] if n_repeat else []) + (
            [f"{n_back} going back"] if n_back else []
        )
        out.append(
            Finding(
                "time_order",
                "warning",
                " and ".join(parts) + f" among {t.size} samples",
                "rates and lags divide by the interval, so the timing of rate-dependent terms is wrong "
                "where stamps repeat or go back (the logger's clock is coarser than its sample rate?)",
                notable=True,
                values={"repeated": n_repeat, "backward": n_back},
            )
        )
    return out


def is_batched(intervals_s) -> bool:
    """True when time stamps come in batches: most intervals short, the time carried by a few long ones.

    A host that reads a buffered sensor (USB, a serial link, a polled FIFO) stamps the samples as they arrive:
    a burst of near-zero intervals, then a long one. The test: the median interval is under
    :data:`BATCH_SHORT` of the mean (duration / intervals) and at least :data:`BATCH_LONG_SHARE` of the intervals
    are over :data:`GAP_FACTOR` times the median. A few gaps in a regular record raise the mean but not that share.
    """
    dt = np.asarray(intervals_s, dtype=float)
    dt = dt[np.isfinite(dt)]
    if dt.size < 10 or np.sum(dt) <= 0:
        return False
    mean = float(np.mean(dt))
    median = float(np.median(dt))
    return bool(median < BATCH_SHORT * mean and np.mean(dt > GAP_FACTOR * median) >= BATCH_LONG_SHARE)


# -- stale readings ------------------------------------------------------------------------------------------------
def stale_mask(readings_nT) -> np.ndarray:
    """True where a sample repeats the previous one exactly (all three axes), shape (N,)."""
    y = np.asarray(readings_nT, dtype=float)
    same = np.zeros(y.shape[0], dtype=bool)
    if y.shape[0] > 1:
        same[1:] = np.all(y[1:] == y[:-1], axis=1)
    return same


def _runs(mask):
    """(start, stop) index pairs of the runs of True in a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(edges[::2], edges[1::2]))


def stale_finding(readings_nT, sensor=None) -> Finding:
    """Consecutive identical vectors of one sensor: fraction of the samples that repeat the previous one and the
    longest run of identical readings (samples)."""
    same = stale_mask(readings_nT)
    n = same.size
    fraction = float(same.sum()) / max(n, 1)
    runs = _runs(same)
    longest = max((b - a for a, b in runs), default=0) + (1 if runs else 0)
    values = {"fraction": fraction, "count": int(same.sum()), "longest_run": int(longest)}
    if not same.any():
        return Finding(
            "stale",
            "info",
            "no stale readings (no vector repeats the previous one)",
            "every sample is a new measurement, weighted once",
            sensor=sensor,
            values=values,
        )
    return Finding(
        "stale",
        "warning" if fraction >= STALE_WARN else "info",
        f"{100 * fraction:.3g}% of the readings repeat the previous vector exactly (stale), longest run "
        f"{longest} samples",
        "a repeated reading is one point counted twice: it weights that direction twice and adds no new "
        "noise sample, so the noise estimate and the uncertainties come out too small (host polling "
        "faster than the part converts?)",
        sensor=sensor,
        notable=fraction >= 0.01,
        values=values,
    )


# -- quantization --------------------------------------------------------------------------------------------------
def _multiple_share(d, q):
    r = d / q
    return float(np.mean(np.abs(r - np.round(r)) <= MULTIPLE_TOL))


def _common_step(values, min_levels=MIN_LEVELS, max_divisor=50):
    """The greatest common step of one axis's distinct values, robustly, and the spacings of those values.

    The distinct sorted values are differenced; the candidates are the few smallest differences divided by
    1, 2, ... ``max_divisor``; the largest candidate ``q`` of which at least 95 % of the differences are near
    integer multiples (within 0.1 q) is the step. Continuous readings give None: their differences are not
    multiples of a common step. A step more than ``max_divisor`` times finer than the smallest differences (a
    short record of a fine step, e.g. 200 samples printed to 0.1 nT) is not seen; such a step is harmless.

    Parameters
    ----------
    values : array_like, shape (N,)
        Readings of one axis, nT.
    min_levels : int
        Fewest distinct values needed to claim a step.
    max_divisor : int
        Largest divisor of a difference tried (a sparse record's smallest difference may be several steps).

    Returns
    -------
    q : float or None
        The step in nT, or None if the values show none (or too few distinct values to tell).
    spacings : numpy.ndarray
        Differences of the sorted distinct values, nT.
    """
    x = np.asarray(values, dtype=float).ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        return None, np.zeros(0)
    if (
        x.size > SCREEN_FROM_SAMPLES
        and _common_step(x[:: int(np.ceil(x.size / SCREEN_SAMPLES))], min_levels, max_divisor)[0] is None
    ):
        return None, np.zeros(0)  # no step in an even subsample: continuous readings, told without sorting them all
    eps = 1e-9 * max(float(np.max(np.abs(x))), 1.0)  # float noise of a unit conversion
    u = np.unique(x)
    if u.size > 1:
        u = u[np.concatenate([[True], np.diff(u) > eps])]
    d = np.diff(u)
    if u.size < min_levels:
        return None, d
    sample = d if d.size <= 4000 else d[np.linspace(0, d.size - 1, 4000).astype(int)]
    bases = np.unique(np.partition(d, 4)[:5] if d.size > 5 else d)  # the five smallest (no full sort)
    # every candidate step base / k at once: the share of the sample's differences near a multiple of each
    candidates = bases[:, None] / np.arange(1, max_divisor + 1)[None, :]
    # a candidate missed by more than (1 - MULTIPLE_SHARE) of the sample within its first few hundred values
    # cannot pass: those (every candidate of continuous readings) are settled on that head alone
    head = sample[:400]
    ratio = head[None, None, :] / candidates[..., None]
    misses = np.sum(np.abs(ratio - np.round(ratio)) > MULTIPLE_TOL, axis=2)
    shares = np.zeros(candidates.shape)
    open_ = misses <= (1.0 - MULTIPLE_SHARE) * sample.size
    if open_.any():
        ratio = sample[None, :] / candidates[open_][:, None]
        shares[open_] = np.mean(np.abs(ratio - np.round(ratio)) <= MULTIPLE_TOL, axis=1)
    best = None
    for row, share in zip(candidates, shares):
        # the divisors of this base in turn, stopping at the first that passes (or once q is no candidate)
        usable = (row > 10 * eps) if best is None else (row > 10 * eps) & (row > best)
        stop = np.flatnonzero(~usable)
        last = stop[0] if stop.size else row.size
        passing = np.flatnonzero(share[:last] >= MULTIPLE_SHARE)
        if passing.size:
            q = row[passing[0]]
            if sample is d or _multiple_share(d, q) >= MULTIPLE_SHARE:
                best = float(q)
    return best, d


def quantization_grid(values, min_levels=MIN_LEVELS, max_divisor=50):
    """The grid one axis's values lie on: its step and how regular it is.

    Two figures. The *common step* is the greatest step of which (nearly) every difference of the sorted
    distinct values is a multiple: a fine grid sampled sparsely shows all its multiples, the smallest most
    often. The *dominant spacing* is the spacing of the occupied levels: when one multiple ``m`` of the common
    step holds at least :data:`GRID_MODE_SHARE` of the level spacings and smaller ones fewer than
    :data:`GRID_BELOW_SHARE`, the values lie on an ``m``-times coarser grid whose origin shifts now and then
    (QMC5883L z: a 5-count grid shifted by 2-3 counts every ~40 counts; the common step is 1 count). That
    coarser spacing is the quantization the readings carry.

    Parameters
    ----------
    values : array_like, shape (N,)
        Readings of one axis, nT.
    min_levels : int
        Fewest distinct values needed to claim a step.
    max_divisor : int
        Largest divisor of a difference tried for the common step.

    Returns
    -------
    dict or None
        ``step_nT`` (the quantization step: the dominant spacing when there is one, else the common step),
        ``common_step_nT``, ``spacing_multiple`` (``m``, 1 for a regular grid), ``shift_share`` (share of the
        level spacings that are not multiples of the step: how often the grid shifts); None when the values show
        no step.
    """
    q, d = _common_step(values, min_levels, max_divisor)
    if q is None:
        return None
    k = np.round(d / q).astype(np.int64)
    k = k[k > 0]
    multiple = 1
    if k.size:
        levels, counts = np.unique(k, return_counts=True)
        mode = int(levels[np.argmax(counts)])
        share = counts.max() / k.size
        if mode > 1 and share >= GRID_MODE_SHARE and np.mean(k < mode) < GRID_BELOW_SHARE:
            multiple = mode
    step = multiple * q
    r = d[d > 0] / step
    shift = float(np.mean(np.abs(r - np.round(r)) > MULTIPLE_TOL)) if r.size else 0.0
    return {"step_nT": step, "common_step_nT": q, "spacing_multiple": multiple, "shift_share": shift}


def quantization_step(values, min_levels=MIN_LEVELS, max_divisor=50):
    """The quantization step of one axis (nT): the spacing of the grid its values lie on.

    The ``step_nT`` of :func:`quantization_grid` (which says how it is found): the common step of the distinct
    values, or a multiple of it when the occupied levels sit on a coarser grid that shifts now and then.
    Continuous readings, or too few distinct values to tell, give None.

    Parameters
    ----------
    values : array_like, shape (N,)
        Readings of one axis, nT.
    min_levels, max_divisor : int
        As in :func:`quantization_grid`.

    Returns
    -------
    float or None
        The step in nT.

    Examples
    --------
    >>> x = 15.0 * np.round(np.random.default_rng(1).normal(0, 2000, 500))
    >>> float(quantization_step(x))
    15.0
    >>> quantization_step(np.random.default_rng(1).normal(0, 30000, 500)) is None
    True
    """
    grid = quantization_grid(values, min_levels, max_divisor)
    return None if grid is None else float(grid["step_nT"])


def quantization_finding(readings_nT, sensor=None, noise_nT=None, lsb_nT=None, noise_source=None) -> Finding:
    """Quantization step per axis of one sensor and its noise floor ``q / sqrt(12)``.

    Parameters
    ----------
    readings_nT : numpy.ndarray, shape (N, 3)
    sensor : int, optional
        1-based sensor number for the message.
    noise_nT : float, optional
        The per-axis noise (given or measured in static stretches); quantization well below it (under a third of
        it) is only information.
    lsb_nT : float, optional
        The LSB the file declared (raw counts), to say the step in counts.
    noise_source : str, optional
        Where ``noise_nT`` came from, for the text (e.g. ``"second differences"``).
    """
    y = np.asarray(readings_nT, dtype=float)
    grids = [quantization_grid(y[:, k]) for k in range(3)]
    steps = [None if g is None else float(g["step_nT"]) for g in grids]
    found = [q for q in steps if q is not None]
    values = {
        "step_nT": steps,
        "noise_floor_nT": [None if q is None else q / np.sqrt(12) for q in steps],
        "common_step_nT": [None if g is None else float(g["common_step_nT"]) for g in grids],
        "shift_share": [None if g is None else g["shift_share"] for g in grids],
    }
    if not found:
        return Finding(
            "quantization",
            "info",
            "no quantization step found (the readings look continuous)",
            "no rounding floor under the RMS",
            sensor=sensor,
            values=values,
        )
    floor = max(found) / np.sqrt(12)
    text = ", ".join("-" if q is None else f"{q:.4g}" for q in steps)
    counts = ""
    if lsb_nT:
        counts = " = " + ", ".join("-" if q is None else f"{q / lsb_nT:.3g}" for q in steps) + " LSB"
        values["step_counts"] = [None if q is None else q / lsb_nT for q in steps]
    summary = f"quantization step (x, y, z) {text} nT{counts}: noise floor q/sqrt(12) = {floor:.3g} nT"
    shifting = [
        f"{AXES[k]} {100 * g['shift_share']:.0f}%"
        for k, g in enumerate(grids)
        if g is not None and g["shift_share"] >= GRID_SHIFT_NOTE
    ]
    if shifting:
        summary += "; the grid shifts now and then (level spacings off the step: " + ", ".join(shifting) + ")"
    negligible = noise_nT is not None and noise_nT > 0 and floor < noise_nT / 3
    warn = floor >= QUANT_WARN_nT and not negligible
    effect = (
        f"the total-field RMS cannot go below about {floor:.3g} nT, and with little noise to dither it the "
        "rounding is not Gaussian: compare the RMS with this floor, not with zero"
    )
    if negligible:
        source = f" ({noise_source})" if noise_source else ""
        effect = f"well below the {noise_nT:.3g} nT noise{source}, so it only adds q^2/12 to the noise variance"
    return Finding(
        "quantization",
        "warning" if warn else "info",
        summary,
        effect,
        sensor=sensor,
        notable=floor >= 0.1 * QUANT_WARN_nT or warn,
        values=values,
    )


# -- clipping ------------------------------------------------------------------------------------------------------
def clipping_finding(readings_nT, sensor=None, keep=None) -> Finding:
    """Readings piling at an axis's extreme (saturation), per axis and end.

    An end is clipped when its extreme value holds at least :data:`CLIP_MIN_COUNT` samples (and 0.2 % of them),
    and :data:`CLIP_RATIO` times the mean count of the next three distinct values inward. Stale repeats and
    static stretches (``keep`` False) are left out, since they repeat values for other reasons.
    """
    y = np.asarray(readings_nT, dtype=float)
    use = ~stale_mask(y) if keep is None else (np.asarray(keep, dtype=bool) & ~stale_mask(y))
    y = y[use]
    n = y.shape[0]
    clipped = []
    total = 0
    for k, axis in enumerate(AXES):
        if n == 0:
            break
        levels, counts = np.unique(y[:, k], return_counts=True)
        if levels.size < 5:
            continue
        for end, (count, inward, value) in (
            ("min", (counts[0], counts[1:4], levels[0])),
            ("max", (counts[-1], counts[-4:-1], levels[-1])),
        ):
            if count >= max(CLIP_MIN_COUNT, 0.002 * n) and count >= CLIP_RATIO * float(np.mean(inward)):
                clipped.append({"axis": axis, "end": end, "value_nT": float(value), "count": int(count)})
                total += int(count)
    values = {"clipped": clipped, "fraction": total / max(n, 1)}
    if not clipped:
        return Finding(
            "clipping",
            "info",
            "no readings pile at an axis extreme (no clipping)",
            "no reading is cut off inside the ellipsoid",
            sensor=sensor,
            values=values,
        )
    text = ", ".join(f"{c['axis']} at {c['value_nT']:.6g} nT ({c['count']} samples)" for c in clipped)
    return Finding(
        "clipping",
        "warning",
        f"readings pile at an axis extreme (clipped?): {text}",
        "clipped readings lie inside the true ellipsoid, so they pull the bias and shrink the scale of "
        "that axis; drop them or record with a larger range",
        sensor=sensor,
        notable=True,
        values=values,
    )


# -- static stretches ----------------------------------------------------------------------------------------------
def _quiet_windows(x, w, limit):
    """True for every window of ``w`` consecutive rows of ``x`` (N, 3) whose per-axis standard deviation (ddof 0)
    is at most ``limit`` on every axis, shape (N - w + 1,): running sums axis by axis, variances against
    ``limit**2``."""
    n = x.shape[0]
    quiet = np.ones(n - w + 1, bool)
    c1, c2 = np.empty(n + 1), np.empty(n + 1)
    c1[0] = c2[0] = 0.0
    centre = np.median(np.ascontiguousarray(_even(x).T), axis=1)  # running sums of small numbers stay precise
    for k in range(x.shape[1]):
        col = x[:, k] - centre[k]
        np.cumsum(col, out=c1[1:])
        np.cumsum(col * col, out=c2[1:])
        mean = (c1[w:] - c1[:-w]) / w
        var = (c2[w:] - c2[:-w]) / w - mean * mean
        quiet &= var <= limit * limit
    return quiet


#: Most values a robust scale (a median) of this module is taken from: an even subsample of longer series.
SCALE_MAX_SAMPLES = 200_000


def _even(values, m=SCALE_MAX_SAMPLES):
    """An even subsample of at most ``m`` rows (a median of a million values is that of 200 000 of them)."""
    return values if values.shape[0] <= m else values[:: int(np.ceil(values.shape[0] / m))]


def motion_noise_nT(readings_nT) -> float:
    """A quick per-axis noise estimate from second differences, ``robust_sigma(y[i+1] - 2 y[i] + y[i-1]) / sqrt(6)``
    (median over the axes), nT. Right for smooth motion sampled fast; far too large for random attitudes."""
    y = np.asarray(readings_nT, dtype=float)
    if y.shape[0] < 3:
        return float("inf")
    first = np.arange(0, y.shape[0] - 2, max(1, int(np.ceil((y.shape[0] - 2) / SCALE_MAX_SAMPLES))))
    d2 = y[first + 2] - 2 * y[first + 1] + y[first]  # the second differences of an even subsample of the rows
    return float(np.median(robust_sigma(np.ascontiguousarray(d2.T), axis=1))) / np.sqrt(6.0)  # axis by axis


def total_field_scatter_nT(readings_nT) -> float:
    """The noise of one sensor's readings (N, 3) before any fit, nT: the sample-to-sample scatter of the field
    magnitude through the quick shape of :func:`magcal.checks.coverage.field_shape`
    (:func:`magcal.geometry.ellipsoid.field_noise_nT`). Turning the sensor leaves the magnitude alone, so unlike
    :func:`motion_noise_nT` this holds for fast or random attitudes too; NaN for fewer than 3 samples."""

    y = np.asarray(readings_nT, dtype=float)
    if y.shape[0] < 3:
        return float("nan")
    shape = field_shape(y)
    return field_noise_nT(y, shape.centre_nT, shape.cinv)


def static_window(n_samples, interval_s=None) -> int:
    """Samples in the static test's window: :data:`STATIC_WINDOW`, or 1 s of samples if more (at most N/2)."""
    w = STATIC_WINDOW
    if interval_s:
        w = max(w, int(round(1.0 / interval_s)))
    return int(max(3, min(w, n_samples // 2)))


def static_stretches(readings_nT, noise_nT=None, window=STATIC_WINDOW, steps_nT=None):
    """Stretches where the vector moves no more than the noise.

    A window of ``window`` samples is static when every axis's standard deviation in it is at most
    :data:`STATIC_SIGMAS` noise levels and at most :data:`STATIC_FIELD_FRACTION` of the field magnitude; the
    stretches are the unions of overlapping static windows, kept if at least two windows long (a slow turning
    point of a rotation is not a stretch).

    Parameters
    ----------
    readings_nT : numpy.ndarray, shape (N, 3)
    noise_nT : float, optional
        Per-axis noise; default :func:`motion_noise_nT` of the readings.
    window : int
        Window length, samples.
    steps_nT : sequence of float or None, optional
        The axes' quantization steps (:func:`quantization_step`) when the caller has them already.

    Returns
    -------
    list of tuple
        ``(start, stop)`` sample indices of each stretch (``stop`` exclusive).
    """
    y = np.asarray(readings_nT, dtype=float)
    n = y.shape[0]
    if n < 2 * window:
        return []
    sigma = motion_noise_nT(y) if noise_nT is None else float(noise_nT)
    q = [quantization_step(y[:, k]) for k in range(3)] if steps_nT is None else list(steps_nT)
    sigma = max(sigma, max((s for s in q if s is not None), default=0.0) / np.sqrt(12), 1e-3)
    ys = _even(y)
    field_nT = float(np.median(row_norm(ys - np.median(np.ascontiguousarray(ys.T), axis=1))))
    field_nT = max(field_nT, float(np.median(row_norm(ys))))
    limit = min(STATIC_SIGMAS * sigma, STATIC_FIELD_FRACTION * field_nT) if field_nT > 0 else STATIC_SIGMAS * sigma
    quiet = _quiet_windows(y, window, limit)
    # sample i is covered when a quiet window starts in [i - window + 1, i]
    starts = np.concatenate([[0], np.cumsum(quiet), np.full(window - 1, int(quiet.sum()))])
    mask = (starts[1 : n + 1] - starts[np.maximum(np.arange(n) - window + 1, 0)]) > 0
    return [(int(a), int(b)) for a, b in _runs(mask) if b - a >= 2 * window]


def static_scatter_nT(readings_nT, stretches):
    """Per-axis scatter (nT) of the readings about a straight line in each stretch, pooled over the stretches.

    For a still sensor this is its noise (slow drift removed by the line); None without stretches of 3+ samples.
    """
    y = np.asarray(readings_nT, dtype=float)
    ss = np.zeros(3)
    dof = 0
    for a, b in stretches:
        if b - a < 3:
            continue
        seg = y[a:b]
        s = np.arange(b - a, dtype=float)
        design = np.column_stack([np.ones_like(s), s - s.mean()])
        coef, *_ = np.linalg.lstsq(design, seg, rcond=None)
        ss += np.sum((seg - design @ coef) ** 2, axis=0)
        dof += b - a - 2
    return None if dof <= 0 else np.sqrt(ss / dof)


def static_finding(readings_nT, sensor=None, noise_nT=None, time_s=None, interval_s=None):
    """Static stretches of one sensor: count, longest (samples, and s with time stamps), share of the samples and
    their scatter per axis (nT). Returns ``(finding, stretches)``."""
    y = np.asarray(readings_nT, dtype=float)
    n = y.shape[0]
    window = static_window(n, interval_s)
    stretches = static_stretches(y, noise_nT=noise_nT, window=window)
    in_static = sum(b - a for a, b in stretches)
    fraction = in_static / max(n, 1)
    longest = max(stretches, key=lambda ab: ab[1] - ab[0]) if stretches else None
    longest_s = None
    if longest is not None and time_s is not None:
        longest_s = float(time_s[longest[1] - 1] - time_s[longest[0]])
    scatter = static_scatter_nT(y, stretches)
    values = {
        "count": len(stretches),
        "fraction": fraction,
        "window_samples": window,
        "longest_samples": 0 if longest is None else longest[1] - longest[0],
        "longest_s": longest_s,
        "scatter_nT": None if scatter is None else [float(s) for s in scatter],
        "stretches": [list(ab) for ab in stretches],
    }
    if not stretches:
        return Finding(
            "static",
            "info",
            "no static stretches (the vector moves throughout)",
            "no direct measurement of the noise: the floor comes from differences of the readings or the residuals",
            sensor=sensor,
            values=values,
        ), stretches
    span = f"{values['longest_samples']} samples" + (f" = {longest_s:.3g} s" if longest_s is not None else "")
    noise = (
        ""
        if scatter is None
        else (
            "; their scatter (x, y, z) " + ", ".join(f"{s:.3g}" for s in scatter) + " nT is a direct noise measurement"
        )
    )
    summary = (
        f"{len(stretches)} static stretch(es) holding {100 * fraction:.3g}% of the samples, longest {span}" + noise
    )
    if fraction >= STATIC_WARN:
        effect = (
            "the fit weights the static direction by its number of samples and learns nothing about the "
            "others from them: thin them out or leave them out of the fit"
        )
        severity = "warning"
    else:
        effect = "they add little direction information; compare the fit's RMS with their scatter"
        severity = "info"
    return Finding("static", severity, summary, effect, sensor=sensor, notable=True, values=values), stretches


# -- temperature ---------------------------------------------------------------------------------------------------
def temperature_finding(temperature_C, time_s=None) -> Finding | None:
    """Temperature range (degC) and its correlation with time (or the sample index without time stamps)."""
    if temperature_C is None:
        return None
    temp = np.asarray(temperature_C, dtype=float)
    if temp.size < 3:
        return None
    clock = np.arange(temp.size, dtype=float) if time_s is None else np.asarray(time_s, dtype=float)
    lo, hi = float(temp.min()), float(temp.max())
    span = hi - lo
    corr = None
    if span > 0 and np.ptp(clock) > 0:
        corr = float(np.corrcoef(temp, clock)[0, 1])
    against = "time" if time_s is not None else "sample order"
    values = {"min_C": lo, "max_C": hi, "span_K": span, "corr_with_time": corr}
    summary = f"temperature {lo:.3g} to {hi:.3g} degC (span {span:.3g} K)"
    if corr is not None:
        summary += f", correlation with {against} {corr:+.2f}"
    if span < TEMP_SPAN_MIN_K:
        return Finding(
            "temperature",
            "info",
            summary,
            "too small a span to fit temperature terms: their coefficients are poorly determined",
            notable=True,
            values=values,
        )
    if corr is not None and abs(corr) >= TEMP_TIME_CORR_WARN:
        return Finding(
            "temperature",
            "warning",
            summary,
            "a temperature that follows time makes temperature and drift terms indistinguishable: a "
            "fitted temperature coefficient may be a drift, and the other way round",
            notable=True,
            values=values,
        )
    return Finding(
        "temperature",
        "info",
        summary,
        "temperature and time vary differently enough to tell temperature terms from drift",
        values=values,
    )


# -- after the fit -------------------------------------------------------------------------------------------------
def field_magnitude_finding(field_nT, kind="fitted", units_hint=True) -> Finding | None:
    """A warning when the field magnitude a fit found is outside the Earth's field range (20-70 uT).

    Parameters
    ----------
    field_nT : float or None
        The fitted total field, nT.
    kind : str
        Where the magnitude came from (``fitted``); only a fitted magnitude is judged (a given one is the user's).
    units_hint : bool
        Say that the unit or LSB may be wrong.

    Returns
    -------
    Finding or None
    """
    if field_nT is None or kind != "fitted" or not np.isfinite(field_nT):
        return None
    lo, hi = EARTH_FIELD_RANGE_nT
    if lo <= field_nT <= hi:
        return None
    cause = (
        "check --units / --lsb: the unit or the LSB of the readings may be wrong (or the record covers too few "
        "directions to determine the ellipsoid: see any coverage warning; or it was made in a shielded room, a "
        "coil or near iron)"
        if units_hint
        else "the record covers too few directions to determine the ellipsoid, was made in a shielded room, a coil "
        "or near iron, or the readings are scaled"
    )
    side = "below" if field_nT < lo else "above"
    return Finding(
        "field",
        "warning",
        f"the fitted field {field_nT / 1000:.3g} uT is {side} any geomagnetic field (outside the Earth's "
        f"field range of {lo / 1000:.0f}-{hi / 1000:.0f} uT)",
        f"{cause}; the fitted scale factors carry the same error",
        notable=True,
        values={"field_nT": float(field_nT), "range_nT": [lo, hi]},
    )


def turn_rate_finding(directions, residuals_nT, time_s=None, sensor=None) -> Finding | None:
    """After a fit: whether the total-field residual grows with the turn rate.

    The turn rate is the angle between consecutive field directions over the interval (deg/s; deg/sample
    without time stamps). The residuals are split into rate quartiles; the finding gives the RMS per quartile
    and Spearman's rank correlation of ``|residual|`` with the rate. It is a warning when the fastest quartile's
    RMS is :data:`TURN_RATE_RATIO` times the slowest's and the correlation is significant (p below
    :data:`TURN_RATE_P`).

    Parameters
    ----------
    directions : array_like, shape (N, 3)
        Unit field directions of the samples in time order (e.g. the corrected readings, normalised).
    residuals_nT : array_like, shape (N,)
        Total-field residuals of the fit, nT.
    time_s : array_like, shape (N,), optional
        Sample times, s.
    sensor : int, optional
        1-based sensor number.

    Returns
    -------
    Finding or None
        None for fewer than 40 samples or no turning.
    """
    from scipy import stats

    u = np.asarray(directions, dtype=float)
    r = np.asarray(residuals_nT, dtype=float)
    if u.shape[0] < 40:
        return None
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", u[1:], u[:-1]), -1.0, 1.0)))
    step = np.ones(angle.size) if time_s is None else np.diff(np.asarray(time_s, dtype=float))
    ok = step > 0
    rate = np.full(angle.size, np.nan)
    rate[ok] = angle[ok] / step[ok]
    rate = np.concatenate([[np.nan], rate])  # the rate into each sample
    use = np.isfinite(rate) & np.isfinite(r)
    if use.sum() < 40 or np.ptp(rate[use]) <= 0:
        return None
    edges = np.quantile(rate[use], [0.0, 0.25, 0.5, 0.75, 1.0])
    bins = np.clip(np.searchsorted(edges, rate[use], side="right") - 1, 0, 3)
    rms = [float(np.sqrt(np.mean(r[use][bins == k] ** 2))) if np.any(bins == k) else float("nan") for k in range(4)]
    rho, p = stats.spearmanr(np.abs(r[use]), rate[use])
    unit = "deg/s" if time_s is not None else "deg/sample"
    values = {
        "rate_quartile_edges": [float(e) for e in edges],
        "rms_nT": rms,
        "spearman_rho": float(rho),
        "p": float(p),
        "unit": unit,
    }
    summary = (
        f"total-field residual RMS by turn-rate quartile (slow to fast, up to {edges[-1]:.3g} {unit}): "
        + ", ".join(f"{v:.3g}" for v in rms)
        + f" nT (rank correlation of |residual| with the rate {rho:+.2f})"
    )
    grows = rms[3] >= TURN_RATE_RATIO * rms[0] and p < TURN_RATE_P and rho > 0
    if grows:
        return Finding(
            "turn_rate",
            "warning",
            summary,
            "the error grows with the turn rate: the axes are not sampled at the same instant "
            "(axis_timing_skew), the part averages over a turn (oversampling, a filter), or the time "
            "stamps are wrong; a model fitted on this record carries it as misfit",
            sensor=sensor,
            notable=True,
            values=values,
        )
    if p < TURN_RATE_P and rho > 0:
        return Finding(
            "turn_rate",
            "info",
            summary,
            f"the error grows a little with the turn rate (fastest quartile {rms[3] / rms[0]:.2f}x the "
            "slowest): a small timing or filtering effect, under the warning level",
            sensor=sensor,
            notable=True,
            values=values,
        )
    return Finding(
        "turn_rate",
        "info",
        summary,
        "no dependence of the error on how fast the sensor turns was found",
        sensor=sensor,
        values=values,
    )


# -- all together --------------------------------------------------------------------------------------------------
def assess(dataset, noise_nT=None) -> QualityReport:
    """Data quality of a dataset, read before fitting.

    Parameters
    ----------
    dataset : Dataset
    noise_nT : float, optional
        Per-axis noise (nT) used to judge static stretches and quantization; default the dataset's ``noise_nT``,
        else estimated from the readings.

    Returns
    -------
    QualityReport
        Findings in order: timing (``sample_rate``, ``gaps``, ``time_order``) if there are time stamps, then per
        sensor ``static``, ``stale``, ``quantization``, ``clipping``, then ``temperature`` and ``other_field``.
    """
    noise = noise_nT if noise_nT is not None else dataset.noise_nT
    noise = None if noise is None or not noise > 0 else float(noise)
    report = QualityReport([], dataset.n_sensors, dataset.n_samples, dataset.source)
    interval = None
    if dataset.time_s is not None:
        for f in timing_findings(dataset.time_s):
            report.add(f)
            if f.kind == "sample_rate":
                interval = f.values.get("interval_s")
    try:  # raw counts read with an LSB (magcal.data.io keeps it as metadata lsb_nT)
        value = float(dataset.metadata["lsb_nT"])
        lsb = value if np.isfinite(value) and value > 0 else None
    except (KeyError, TypeError, ValueError):
        lsb = None
    for s in range(dataset.n_sensors):
        y = dataset.readings_nT[s]
        sensor = s + 1
        static, stretches = static_finding(y, sensor, noise, dataset.time_s, interval)
        report.add(static)
        measured = static.values.get("scatter_nT")
        sensor_noise = noise if noise is not None else (float(np.median(measured)) if measured else None)
        source = None
        if sensor_noise is None:  # no noise given or measured still: the total field's sample-to-sample scatter
            scatter = total_field_scatter_nT(y)
            if np.isfinite(scatter) and scatter > 0:
                sensor_noise, source = scatter, "the total field's sample-to-sample scatter"
        report.add(stale_finding(y, sensor))
        report.add(quantization_finding(y, sensor, sensor_noise, lsb, source))
        keep = np.ones(y.shape[0], dtype=bool)
        for a, b in stretches:
            keep[a:b] = False
        report.add(clipping_finding(y, sensor, keep))
    report.add(temperature_finding(dataset.temperature_C, dataset.time_s))
    report.add(other_field_finding(dataset))
    return report


# -- a part of the record in another field ----------------------------------------------------------------------

#: A part at the start or the end of a record is in another field when its total field differs from the rest's by at
#: least this many robust spreads of the rest's total-field residual...
PART_MIN_SIGMAS = 5.0
#: ...and by at least this fraction of the field (a record's own misfit is larger than its noise).
PART_MIN_FRACTION = 0.005
#: Fewest samples of a part, and the largest share of the record it may hold (a longer one is the record's field).
PART_MIN_SAMPLES = 5
PART_MAX_SHARE = 0.3
#: Fewest samples of a record the check looks at.
PART_MIN_RECORD = 60
#: Most samples (evenly taken) of the ellipsoid fits of the check.
PART_FIT_SAMPLES = 20_000


def _total_field_residual(readings_nT, keep) -> np.ndarray | None:
    """``|C^-1 (y - b)| - F`` (nT) of every sample under the ellipsoid fitted to the samples ``keep`` (None when no
    ellipsoid fits)."""
    try:
        fit = fit_ellipsoid(readings_nT, mask=keep, strict=False, max_samples=PART_FIT_SAMPLES)
    except CalibrationError:  # no ellipsoid (degenerate readings): the other checks say why
        return None
    return row_norm((readings_nT - fit.bias_nT) @ fit.cinv.T) - fit.field_nT


def _level_change(r, from_end) -> tuple[int, float]:
    """The part at the start (or the end) whose mean differs most from the rest's (the change point of one shift:
    the largest ``k (N - k) / N (mean_part - mean_rest)^2``): its length and the shift (part minus rest, nT)."""
    x = r[::-1] if from_end else r
    n = len(x)
    k = np.arange(PART_MIN_SAMPLES, int(PART_MAX_SHARE * n) + 1)
    if k.size == 0:
        return 0, 0.0
    c = np.cumsum(x)
    part = c[k - 1] / k
    rest = (c[-1] - c[k - 1]) / (n - k)
    score = k * (n - k) / n * (part - rest) ** 2
    best = int(np.argmax(score))
    return int(k[best]), float(part[best] - rest[best])


def other_field_parts(readings_nT) -> list:
    """Parts at the start or the end of a record whose total field differs from the rest's: another run left at the
    start of a file, a still phase at the end in a weaker field.

    Each sensor's readings are fitted with an ellipsoid and the total-field residual (the mean over the sensors) is
    scanned for one level change from each end; a part is flagged when its level differs from the rest's by
    :data:`PART_MIN_SIGMAS` robust spreads and :data:`PART_MIN_FRACTION` of the field, judged again with the
    ellipsoid fitted without it (the ellipsoid fitted to everything bends towards the part).

    Parameters
    ----------
    readings_nT : numpy.ndarray, shape (n_sensors, N, 3)

    Returns
    -------
    list of dict
        ``start`` and ``stop`` (0-based sample indices, stop exclusive), ``shift_nT`` (the part's total field minus
        the rest's), ``spread_nT`` (the rest's robust spread), ``field_nT``.
    """
    y = np.asarray(readings_nT, dtype=float)
    n = y.shape[1]
    if n < PART_MIN_RECORD:
        return []
    keep = np.ones(n, dtype=bool)
    parts = []
    for from_end in (False, True):
        r = _mean_residual(y, np.ones(n, dtype=bool))
        if r is None:
            return []
        k, _ = _level_change(r, from_end)
        if k == 0:
            continue
        part = np.zeros(n, dtype=bool)
        if from_end:
            part[n - k :] = True
        else:
            part[:k] = True
        r = _mean_residual(y, keep & ~part)  # judged with the ellipsoid of the rest
        if r is None:
            continue
        k, shift = _level_change(r, from_end)  # the boundary again, now that the rest's ellipsoid is clean
        part[:] = False
        if from_end:
            part[n - k :] = True
        else:
            part[:k] = True
        spread = float(robust_sigma(r[keep & ~part]))
        field_nT = float(np.median(row_norm(y[0] - y[0].mean(axis=0))))
        if abs(shift) >= PART_MIN_SIGMAS * spread and abs(shift) >= PART_MIN_FRACTION * field_nT:
            keep &= ~part
            start, stop = (n - k, n) if from_end else (0, k)
            parts.append({"start": start, "stop": stop, "shift_nT": shift, "spread_nT": spread, "field_nT": field_nT})
    return parts


def _mean_residual(y, keep):
    residuals = [_total_field_residual(y[s], keep) for s in range(y.shape[0])]
    if any(r is None for r in residuals):
        return None
    return np.mean(residuals, axis=0)


def other_field_finding(dataset) -> Finding | None:
    """A warning naming the parts at the start or the end of the record in another field (:func:`other_field_parts`):
    their rows (counted from 1), time span and shift; None when there is none. ``values["parts"]`` holds each part's
    0-based ``start`` and ``stop`` sample (what :func:`without_other_field_parts` and ``--exclude-part`` drop)."""
    parts = other_field_parts(dataset.readings_nT)
    if not parts:
        return None
    t = dataset.time_s
    texts = []
    for p in parts:
        where = "first" if p["start"] == 0 else "last"
        span = f", {t[p['stop'] - 1] - t[p['start']]:.3g} s from t = {t[p['start']]:.6g} s" if t is not None else ""
        texts.append(
            f"rows {p['start'] + 1}-{p['stop']} (the {where} {p['stop'] - p['start']} samples{span}) read a total "
            f"field {p['shift_nT'] / 1000.0:+.3g} uT from the rest's ({abs(p['shift_nT']) / max(p['spread_nT'], 1e-9):.0f}x "
            "its spread)"
        )
    return Finding(
        "other_field",
        "warning",
        "a part of the record is in another field: " + "; ".join(texts),
        "another run left in the file, or a still phase where the field differs, is fitted as if in this field: it "
        "bends the calibration and reads as a drift or a step in the diagnosis; leave it out "
        "(--exclude-part, or magcal.checks.quality.without_other_field_parts)",
        notable=True,
        values={"parts": parts},
    )


def without_other_field_parts(dataset, finding=None):
    """The dataset without the parts :func:`other_field_finding` flags (``finding``, or found here), and the
    finding (None, and the dataset itself, when there is none)."""
    finding = other_field_finding(dataset) if finding is None else finding
    if finding is None:
        return dataset, None
    keep = np.ones(dataset.n_samples, dtype=bool)
    for p in finding.values["parts"]:
        keep[int(p["start"]) : int(p["stop"])] = False
    return dataset.subset(keep), finding
