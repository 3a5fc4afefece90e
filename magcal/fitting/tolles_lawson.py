"""The Tolles-Lawson fit of a compensation flight, and the compensation of a survey line with it.

:func:`fit_tolles_lawson` takes a calibration flight's fluxgate vector, scalar magnetometer and sample rate (or
times), band-passes the design matrix of :mod:`magcal.model.tolles_lawson` and the scalar alike, drops the filter's
start-up at both ends, and solves the (ridge) least squares for the coefficients. :class:`TLCompensation` holds
them with what the fit saw (the conditioning, the band-passed residual, the compensated signal) and compensates
any line flown by the same platform: the scalar minus the platform field ``A c`` (its unfiltered design, so the
compensated line keeps the geology and the slow field).

The ridge is MagNav.jl's: ``(A^T A + ridge I) c = A^T y`` on the band-passed design as it is scaled (the
columns' sizes are :attr:`magcal.model.tolles_lawson.Conditioning.column_rms`), solved as an augmented least
squares.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from magcal.core.errors import MagcalError
from magcal.core.jsonable import jsonable
from magcal.model.tolles_lawson import (
    DEFAULT_PASSBAND_HZ,
    DEFAULT_TERMS,
    Conditioning,
    DEFAULT_SCALE_nT,
    bandpass,
    bandpass_columns,
    check_terms,
    conditioning,
    design_matrix,
    term_labels,
)

__all__ = ["TLCompensation", "fit_tolles_lawson", "sample_rate_from_times", "solve_ridge"]


def sample_rate_from_times(time_s) -> float:
    """The sample rate (Hz) of evenly spaced times (s); a :class:`MagcalError` naming the first uneven step."""
    t = np.asarray(time_s, dtype=float)
    steps = np.diff(t)
    if t.ndim != 1 or t.size < 3 or not np.all(np.isfinite(steps)) or np.any(steps <= 0):
        raise MagcalError("the times must be increasing, finite seconds, one per sample (at least 3)")
    step = float(np.median(steps))
    uneven = np.abs(steps - step) > 0.05 * step
    if uneven.any():
        row = int(np.argmax(uneven)) + 1
        raise MagcalError(
            f"the samples are not evenly spaced (step {steps[row - 1]:.4g} s at row {row}, median {step:.4g} s): "
            "the band-pass needs a constant rate; resample the flight first"
        )
    return 1.0 / step


def _rate(sample_rate_hz, time_s) -> float:
    if sample_rate_hz is not None:
        if not np.isfinite(sample_rate_hz) or sample_rate_hz <= 0:
            raise MagcalError(f"the sample rate must be a positive number of Hz, got {sample_rate_hz!r}")
        return float(sample_rate_hz)
    if time_s is None:
        raise MagcalError("give the sample rate (sample_rate_hz) or the samples' times (time_s)")
    return sample_rate_from_times(time_s)


def _checked_scalar(scalar_nT, n: int) -> np.ndarray:
    y = np.asarray(scalar_nT, dtype=float)
    if y.shape != (n,):
        raise MagcalError(f"the scalar magnetometer has shape {y.shape}; the fluxgate has {n} samples")
    bad = ~np.isfinite(y)
    if bad.any():
        raise MagcalError(
            f"the scalar magnetometer has {int(bad.sum())} missing or non-finite value(s) (first at row "
            f"{int(np.argmax(bad))}): fill or cut them before the compensation"
        )
    return y


@dataclass
class TLCompensation:
    """Fitted Tolles-Lawson coefficients and what the fit saw.

    Attributes
    ----------
    terms : tuple of str
        The term groups (:data:`magcal.model.tolles_lawson.TERM_GROUPS`).
    coefficients : numpy.ndarray, shape (q,)
        In the order of :attr:`labels`: permanent in nT, induced in nT per ``scale_nT``, eddy in nT per
        (``scale_nT`` nT per sample).
    sample_rate_hz : float
    passband_hz : (float, float)
    order : int
        Butterworth order per edge.
    trim : int
        Samples dropped at each end of the band-passed fit.
    ridge : float
    scale_nT : float
    conditioning : Conditioning
        Of the band-passed, trimmed design as fitted.
    residual_bp_nT : numpy.ndarray, shape (N - 2 trim,)
        The band-passed scalar minus the band-passed design times the coefficients, over the fitted samples.
    compensated_nT : numpy.ndarray, shape (N,)
        The calibration flight's scalar minus the platform field.
    use_scalar_total : bool
        The direction cosines divide by the scalar's reading (MagNav's "modified" TL), else by the fluxgate's
        magnitude.
    """

    terms: tuple[str, ...]
    coefficients: np.ndarray
    sample_rate_hz: float
    passband_hz: tuple[float, float] = DEFAULT_PASSBAND_HZ
    order: int = 4
    trim: int = 20
    ridge: float = 0.0
    scale_nT: float = DEFAULT_SCALE_nT
    conditioning: Conditioning | None = None
    residual_bp_nT: np.ndarray = field(default_factory=lambda: np.zeros(0))
    compensated_nT: np.ndarray = field(default_factory=lambda: np.zeros(0))
    use_scalar_total: bool = False

    @property
    def labels(self) -> list[str]:
        """The coefficients' names (:func:`magcal.model.tolles_lawson.term_labels`)."""
        return term_labels(self.terms)

    @property
    def residual_std_nT(self) -> float:
        """Standard deviation of the band-passed residual over the fitted samples (nT)."""
        return float(np.std(self.residual_bp_nT)) if self.residual_bp_nT.size else float("nan")

    def coefficient(self, label: str) -> float:
        """One coefficient by its label (``permanent_x``, ``induced_xy``, ``eddy_zx`` ...)."""
        try:
            return float(self.coefficients[self.labels.index(label)])
        except ValueError:
            raise MagcalError(f"no coefficient {label!r}: the fit has " + ", ".join(self.labels)) from None

    def tl18(self) -> np.ndarray:
        """TL's 18 coefficients in MagNav.jl's order (permanent 3, induced 6, eddy 9); a term the fit did not
        have is 0 (``induced5``'s ``u_z B_z``, ``eddy8``'s ``u_z dB_z``)."""
        extra = set(self.terms) - {"permanent", "induced", "induced5", "induced3", "eddy", "eddy8", "eddy3"}
        if extra:
            raise MagcalError(
                "TL-18 holds the permanent, induced and eddy terms only; this fit also has " + ", ".join(sorted(extra))
            )
        out = np.zeros(18)
        names = term_labels(DEFAULT_TERMS)
        for label, value in zip(self.labels, self.coefficients):
            out[names.index(label)] = value
        return out

    def platform_field_nT(self, flux_nT, scalar_nT=None) -> np.ndarray:
        """The platform's scalar signature ``A c`` (nT, N) along a line's fluxgate vector (N, 3); ``scalar_nT``
        only when the fit divided by the scalar's reading."""
        total = None
        if self.use_scalar_total:
            if scalar_nT is None:
                raise MagcalError("this compensation divides by the scalar's reading: give scalar_nT")
            total = np.asarray(scalar_nT, dtype=float)
        return design_matrix(flux_nT, self.terms, total, self.scale_nT) @ self.coefficients

    def compensate(self, scalar_nT, flux_nT) -> np.ndarray:
        """A line's scalar (N,) minus the platform field along its fluxgate vector (N, 3), nT."""
        flux = np.asarray(flux_nT, dtype=float)
        y = _checked_scalar(scalar_nT, flux.shape[0] if flux.ndim == 2 else -1)
        return y - self.platform_field_nT(flux, y)

    def to_dict(self, signals: bool = True) -> dict:
        """A JSON-ready document; ``signals`` keeps the residual and the compensated flight (lists of nT)."""
        out = {
            "kind": "tolles_lawson",
            "terms": list(self.terms),
            "labels": self.labels,
            "coefficients": self.coefficients,
            "sample_rate_hz": self.sample_rate_hz,
            "passband_hz": list(self.passband_hz),
            "order": self.order,
            "trim": self.trim,
            "ridge": self.ridge,
            "scale_nT": self.scale_nT,
            "use_scalar_total": self.use_scalar_total,
            "residual_std_nT": self.residual_std_nT,
            "conditioning": self.conditioning.to_dict() if self.conditioning is not None else None,
        }
        if signals:
            out["residual_bp_nT"] = self.residual_bp_nT
            out["compensated_nT"] = self.compensated_nT
        return jsonable(out)

    def to_json(self, signals: bool = True) -> str:
        return json.dumps(self.to_dict(signals))

    @classmethod
    def from_dict(cls, d: dict) -> TLCompensation:
        """The compensation a :meth:`to_dict` document holds (its labels checked against its terms)."""
        if d.get("kind") != "tolles_lawson":
            raise MagcalError("not a Tolles-Lawson compensation document (its 'kind' is not 'tolles_lawson')")
        terms = check_terms(d["terms"])
        coefficients = np.asarray(d["coefficients"], dtype=float)
        if "labels" in d and list(d["labels"]) != term_labels(terms):
            raise MagcalError("the document's labels do not match its terms: it was edited or is damaged")
        if coefficients.shape != (len(term_labels(terms)),):
            raise MagcalError(f"{coefficients.size} coefficients for {len(term_labels(terms))} terms")
        cond = d.get("conditioning")
        return cls(
            terms=terms,
            coefficients=coefficients,
            sample_rate_hz=float(d["sample_rate_hz"]),
            passband_hz=(float(d["passband_hz"][0]), float(d["passband_hz"][1])),
            order=int(d["order"]),
            trim=int(d["trim"]),
            ridge=float(d["ridge"]),
            scale_nT=float(d["scale_nT"]),
            conditioning=Conditioning.from_dict(cond) if cond else None,
            residual_bp_nT=np.asarray(d.get("residual_bp_nT", []), dtype=float),
            compensated_nT=np.asarray(d.get("compensated_nT", []), dtype=float),
            use_scalar_total=bool(d.get("use_scalar_total", False)),
        )

    @classmethod
    def from_json(cls, text: str) -> TLCompensation:
        return cls.from_dict(json.loads(text))


def solve_ridge(design, target, ridge: float = 0.0) -> np.ndarray:
    """Least squares ``design c = target`` (design (n, q), target (n,), or (n, k) for k targets at once), with
    ``ridge`` added to the normal matrix's diagonal (``(D^T D + ridge I) c = D^T t``, solved as an augmented least
    squares)."""
    if ridge < 0 or not np.isfinite(ridge):
        raise MagcalError(f"the ridge must be a number >= 0, got {ridge!r}")
    if ridge > 0:
        q = design.shape[1]
        design = np.vstack([design, np.sqrt(ridge) * np.eye(q)])
        target = np.concatenate([target, np.zeros((q,) + np.shape(target)[1:])])
    return np.linalg.lstsq(design, target, rcond=None)[0]


def fit_tolles_lawson(
    flux_nT,
    scalar_nT,
    *,
    sample_rate_hz: float | None = None,
    time_s=None,
    terms=DEFAULT_TERMS,
    ridge: float = 0.0,
    passband_hz=DEFAULT_PASSBAND_HZ,
    order: int = 4,
    trim: int = 20,
    scale_nT: float = DEFAULT_SCALE_nT,
    use_scalar_total: bool = False,
    mask=None,
) -> TLCompensation:
    """Fit Tolles-Lawson coefficients on a compensation flight.

    Parameters
    ----------
    flux_nT : array_like, shape (N, 3)
        The fluxgate's vector in the body frame (nT), evenly sampled.
    scalar_nT : array_like, shape (N,)
        The scalar magnetometer, uncompensated (nT).
    sample_rate_hz : float, optional
        Samples per second; else from ``time_s``.
    time_s : array_like, shape (N,), optional
        The samples' times (s), evenly spaced.
    terms : sequence of str
        Term groups (default TL's 18: ``permanent, induced, eddy``).
    ridge : float
        Added to the band-passed normal matrix's diagonal (MagNav's ``lambda``; 0 is plain least squares).
    passband_hz : (float, float)
        The band-pass's edges (Hz), default 0.1-0.9.
    order : int
        Butterworth order per edge.
    trim : int
        Samples dropped at each end after the band-pass.
    scale_nT : float
        The induced and eddy columns' divisor (nT).
    use_scalar_total : bool
        Divide the direction cosines by the scalar's reading instead of the fluxgate's magnitude.
    mask : array_like of bool, shape (N,), optional
        Samples the fit uses (after the band-pass over the whole flight), e.g. the maneuvers only.

    Returns
    -------
    TLCompensation
    """
    flux = np.asarray(flux_nT, dtype=float)
    n = flux.shape[0] if flux.ndim == 2 else -1
    y = _checked_scalar(scalar_nT, n)
    rate = _rate(sample_rate_hz, time_s)
    terms = check_terms(terms)
    design = design_matrix(flux, terms, y if use_scalar_total else None, scale_nT)
    if n <= 2 * trim + design.shape[1]:
        raise MagcalError(f"{n} samples are too few for {design.shape[1]} terms after trimming {trim} at each end")
    design_bp = bandpass_columns(design, rate, passband_hz, order)
    y_bp = bandpass(y, rate, passband_hz, order)
    kept = np.zeros(n, dtype=bool)
    kept[trim : n - trim] = True
    if mask is not None:
        kept &= np.asarray(mask, dtype=bool)
    if kept.sum() <= design.shape[1]:
        raise MagcalError(f"only {int(kept.sum())} samples are kept for {design.shape[1]} terms: widen the mask")
    coefficients = solve_ridge(design_bp[kept], y_bp[kept], float(ridge))
    return TLCompensation(
        terms=terms,
        coefficients=coefficients,
        sample_rate_hz=rate,
        passband_hz=(float(passband_hz[0]), float(passband_hz[1])),
        order=int(order),
        trim=int(trim),
        ridge=float(ridge),
        scale_nT=float(scale_nT),
        conditioning=conditioning(design_bp[kept]),
        residual_bp_nT=y_bp[kept] - design_bp[kept] @ coefficients,
        compensated_nT=y - design @ coefficients,
        use_scalar_total=bool(use_scalar_total),
    )
