"""The Tolles-Lawson model of a platform's field seen by a scalar magnetometer, and its band-pass.

A scalar magnetometer on a platform reads ``|B_e + B_p| ~ |B_e| + u . B_p``, ``u = B_e / |B_e|`` the Earth
field's direction in the body frame (from a fluxgate beside it). Tolles and Lawson write the platform's field as

* permanent: a body-fixed field ``p`` (nT): ``u . p``;
* induced: a field proportional to the Earth field, ``A B_e`` (``A`` dimensionless): ``|B_e| u^T A u``, six
  independent products ``u_i u_j`` (``A``'s symmetric part; its antisymmetric part never shows in ``u . B_p``);
* eddy currents: a field proportional to the body-frame field's rate, ``E dB_e/dt``: ``u^T E dB_e/dt``, nine
  products ``u_i dB_j``.

All are linear in their coefficients: the platform's scalar signature is ``A c`` with the design matrix ``A``
(:func:`design_matrix`) and ``c`` the coefficients. The columns follow MagNav.jl's ``create_TL_A`` (its term order
and scaling), so coefficients fitted here and there are the same numbers:

=================  =====  ==========================================================================
term group         count  columns, in order (``B`` the fluxgate's vector in nT, ``u = B / Bt``)
=================  =====  ==========================================================================
``permanent``      3      ``u_x, u_y, u_z``
``induced``        6      ``u_x B_x, u_x B_y, u_x B_z, u_y B_y, u_y B_z, u_z B_z`` (each ``/ scale``)
``induced5``       5      the six without ``u_z B_z``
``induced3``       3      ``u_x B_x, u_y B_y, u_z B_z``
``eddy``           9      ``u_i dB_j`` for ``i`` then ``j`` in ``x, y, z`` (each ``/ scale``)
``eddy8``          8      the nine without ``u_z dB_z``
``eddy3``          3      ``u_x dB_x, u_y dB_y, u_z dB_z``
``fdm``            3      ``dB_x, dB_y, dB_z`` (not scaled)
``bias``           1      a constant 1
=================  =====  ==========================================================================

The default, ``permanent, induced, eddy``, is TL's 18 terms. ``scale`` is ``scale_nT`` (50 000 nT, MagNav's
``Bt_scale``): it brings the induced and eddy columns near the permanent ones' size, so the permanent
coefficients are in nT, the induced ones in nT per ``scale_nT`` of field and the eddy ones in nT per (``scale_nT``
nT per sample). ``dB`` is the fluxgate's change per *sample* (a central difference, one-sided at the ends), as in
MagNav, so the eddy coefficients depend on the sample rate: times the rate in Hz they are per nT/s.

Degeneracy: ``u_x^2 + u_y^2 + u_z^2 = 1``, so ``u_x B_x + u_y B_y + u_z B_z = Bt / scale``, which the band-pass
nearly removes: the trace of ``A`` is only weakly determined, the reason for the ridge and for ``induced5``. The
maneuvers make the other terms separable, but they stay strongly collinear: :func:`conditioning` states it.

The band-pass (:func:`bandpass`) is a zero-phase Butterworth filter (0.1-0.9 Hz by default, order 4 per edge,
run forwards and backwards): it removes the geology and the diurnal drift below and the noise above, and it is
applied to the design matrix's columns and to the scalar alike before the fit, with ``trim`` samples dropped at
each end where the filter's start-up rings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from magcal.core.errors import MagcalError

#: TL's 18 terms (MagNav.jl's default).
DEFAULT_TERMS = ("permanent", "induced", "eddy")

#: The induced and eddy columns' scale (nT), MagNav's ``Bt_scale``.
DEFAULT_SCALE_nT = 50_000.0

#: The band-pass's default edges (Hz): above the geology and the diurnal drift, below the noise.
DEFAULT_PASSBAND_HZ = (0.1, 0.9)

_AXES = "xyz"
_INDUCED6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_EDDY9 = tuple((i, j) for i in range(3) for j in range(3))

#: Each term group's columns: ("u", i) direction cosine, ("uB", i, j) ``u_i B_j``, ("udB", i, j) ``u_i dB_j``,
#: ("dB", j) the field's change, ("one",) a constant.
TERM_GROUPS: dict[str, tuple[tuple, ...]] = {
    "permanent": tuple(("u", i) for i in range(3)),
    "induced": tuple(("uB", i, j) for i, j in _INDUCED6),
    "induced5": tuple(("uB", i, j) for i, j in _INDUCED6[:5]),
    "induced3": tuple(("uB", i, i) for i in range(3)),
    "eddy": tuple(("udB", i, j) for i, j in _EDDY9),
    "eddy8": tuple(("udB", i, j) for i, j in _EDDY9[:8]),
    "eddy3": tuple(("udB", i, i) for i in range(3)),
    "fdm": tuple(("dB", j) for j in range(3)),
    "bias": (("one",),),
}

__all__ = [
    "DEFAULT_PASSBAND_HZ",
    "DEFAULT_SCALE_nT",
    "DEFAULT_TERMS",
    "TERM_GROUPS",
    "Conditioning",
    "bandpass",
    "bandpass_columns",
    "check_terms",
    "conditioning",
    "design_matrix",
    "per_sample_difference",
    "term_labels",
]


def check_terms(terms) -> tuple[str, ...]:
    """The term groups as a tuple, each checked against :data:`TERM_GROUPS` (a :class:`MagcalError` naming the
    unknown one and the known ones)."""
    terms = (terms,) if isinstance(terms, str) else tuple(terms)
    if not terms:
        raise MagcalError("no Tolles-Lawson terms given: name some of " + ", ".join(TERM_GROUPS))
    for name in terms:
        if name not in TERM_GROUPS:
            raise MagcalError(f"unknown Tolles-Lawson term {name!r}: use some of " + ", ".join(TERM_GROUPS))
    return terms


def _label(column: tuple) -> str:
    kind = column[0]
    if kind == "u":
        return f"permanent_{_AXES[column[1]]}"
    if kind == "uB":
        return f"induced_{_AXES[column[1]]}{_AXES[column[2]]}"
    if kind == "udB":
        return f"eddy_{_AXES[column[1]]}{_AXES[column[2]]}"
    if kind == "dB":
        return f"rate_{_AXES[column[1]]}"
    return "bias"


def term_labels(terms=DEFAULT_TERMS) -> list[str]:
    """The design matrix's column names, in order: ``permanent_x``, ``induced_xy`` (``u_x B_y``), ``eddy_yz``
    (``u_y dB_z``), ``rate_x``, ``bias``."""
    return [_label(column) for name in check_terms(terms) for column in TERM_GROUPS[name]]


def per_sample_difference(values) -> np.ndarray:
    """The change per sample along axis 0: central differences ``(x[k+1] - x[k-1]) / 2`` inside, one-sided
    differences at the two ends (the unit of ``values`` per sample; zeros for fewer than 3 samples)."""
    x = np.asarray(values, dtype=float)
    out = np.zeros_like(x)
    if x.shape[0] < 3:
        return out
    out[1:-1] = (x[2:] - x[:-2]) / 2.0
    out[0] = x[1] - x[0]
    out[-1] = x[-1] - x[-2]
    return out


def _checked_flux(flux_nT) -> np.ndarray:
    flux = np.asarray(flux_nT, dtype=float)
    if flux.ndim != 2 or flux.shape[1] != 3:
        raise MagcalError(f"the fluxgate's vector must be an (N, 3) array in nT, got shape {flux.shape}")
    bad = ~np.isfinite(flux).all(axis=1)
    if bad.any():
        raise MagcalError(
            f"the fluxgate's vector has {int(bad.sum())} row(s) with a missing or non-finite value (first at row "
            f"{int(np.argmax(bad))}): fill or cut them before the compensation"
        )
    return flux


def design_matrix(flux_nT, terms=DEFAULT_TERMS, total_nT=None, scale_nT: float = DEFAULT_SCALE_nT) -> np.ndarray:
    """The Tolles-Lawson design matrix (N, q): the platform's scalar signature is ``design_matrix(...) @ c``.

    Parameters
    ----------
    flux_nT : array_like, shape (N, 3)
        The fluxgate's vector in the body frame, nT, evenly sampled.
    terms : sequence of str
        Term groups of :data:`TERM_GROUPS`, in the order wanted (default TL's 18).
    total_nT : array_like, shape (N,), optional
        The magnitude ``Bt`` the direction cosines divide by (nT): the fluxgate's own magnitude by default, or the
        scalar magnetometer's reading (MagNav's "modified Tolles-Lawson").
    scale_nT : float
        The induced and eddy columns' divisor (nT).

    Returns
    -------
    numpy.ndarray, shape (N, q)
        Columns in the order of :func:`term_labels` (the module's table).
    """
    flux = _checked_flux(flux_nT)
    total = np.linalg.norm(flux, axis=1) if total_nT is None else np.asarray(total_nT, dtype=float)
    if total.shape != (flux.shape[0],):
        raise MagcalError(f"the total field has shape {total.shape}, the fluxgate {flux.shape[0]} samples")
    if np.any(total <= 0):
        raise MagcalError("the total field must be positive (nT) at every sample to give direction cosines")
    cosines = flux / total[:, None]
    rate = per_sample_difference(flux)
    sources = {
        "u": lambda c: cosines[:, c[1]],
        "uB": lambda c: cosines[:, c[1]] * flux[:, c[2]] / scale_nT,
        "udB": lambda c: cosines[:, c[1]] * rate[:, c[2]] / scale_nT,
        "dB": lambda c: rate[:, c[1]],
        "one": lambda c: np.ones(flux.shape[0]),
    }
    columns = [sources[c[0]](c) for name in check_terms(terms) for c in TERM_GROUPS[name]]
    return np.column_stack(columns)


def _sos(sample_rate_hz: float, passband_hz, order: int):
    """Butterworth second-order sections: a band-pass, a low-pass (low edge <= 0) or a high-pass (high edge at
    or above Nyquist); None for neither edge inside (0, Nyquist)."""
    nyquist = sample_rate_hz / 2.0
    low, high = (float(f) if f is not None else 0.0 for f in passband_hz)
    has_low = 0.0 < low < nyquist
    has_high = 0.0 < high < nyquist
    if has_low and has_high:
        if low >= high:
            raise MagcalError(f"the band-pass's low edge {low} Hz must be below its high edge {high} Hz")
        return signal.butter(order, [low, high], btype="bandpass", fs=sample_rate_hz, output="sos")
    if has_high:
        return signal.butter(order, high, btype="lowpass", fs=sample_rate_hz, output="sos")
    if has_low:
        return signal.butter(order, low, btype="highpass", fs=sample_rate_hz, output="sos")
    return None


def bandpass(values, sample_rate_hz: float, passband_hz=DEFAULT_PASSBAND_HZ, order: int = 4) -> np.ndarray:
    """The zero-phase Butterworth band-pass of ``values`` along axis 0 (same unit, same shape).

    Parameters
    ----------
    values : array_like, shape (N,) or (N, k)
        Evenly sampled series.
    sample_rate_hz : float
        Samples per second.
    passband_hz : (float, float)
        The edges (Hz). A low edge <= 0 makes it a low-pass, a high edge at or above Nyquist a high-pass; both
        outside, the values come back unfiltered.
    order : int
        The Butterworth order per edge (run forwards and backwards: twice the attenuation, no phase shift).
    """
    x = np.asarray(values, dtype=float)
    sos = _sos(float(sample_rate_hz), passband_hz, int(order))
    if sos is None:
        return x.copy()
    if x.shape[0] <= 3 * (2 * sos.shape[0] + 1):
        raise MagcalError(
            f"{x.shape[0]} samples are too few for the band-pass at {sample_rate_hz:g} Hz: record a longer flight"
        )
    return signal.sosfiltfilt(sos, x, axis=0)


def bandpass_columns(matrix, sample_rate_hz: float, passband_hz=DEFAULT_PASSBAND_HZ, order: int = 4):
    """:func:`bandpass` on each column of ``matrix`` (N, q), a constant column (a bias) left as it is."""
    m = np.asarray(matrix, dtype=float)
    out = m.copy()
    varying = np.ptp(m, axis=0) > np.finfo(float).eps * np.maximum(1.0, np.abs(m).max(axis=0))
    if varying.any():
        out[:, varying] = bandpass(m[:, varying], sample_rate_hz, passband_hz, order)
    return out


@dataclass(frozen=True)
class Conditioning:
    """How well a (band-passed) design matrix determines its coefficients.

    Attributes
    ----------
    condition_number : float
        Ratio of the largest to the smallest singular value of the design as fitted (its columns in their own
        units).
    condition_number_scaled : float
        The same after each column is scaled to unit norm: what is left is collinearity, not units.
    column_rms : numpy.ndarray, shape (q,)
        Each column's RMS (the column's unit): a coefficient's effect in nT is its value times this.
    weakest_direction : numpy.ndarray, shape (q,)
        The unit combination of the scaled coefficients the data determine least (the last right singular
        vector): what the ridge holds.
    """

    condition_number: float
    condition_number_scaled: float
    column_rms: np.ndarray
    weakest_direction: np.ndarray

    def to_dict(self) -> dict:
        return {
            "condition_number": float(self.condition_number),
            "condition_number_scaled": float(self.condition_number_scaled),
            "column_rms": [float(v) for v in self.column_rms],
            "weakest_direction": [float(v) for v in self.weakest_direction],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Conditioning:
        return cls(
            float(d["condition_number"]),
            float(d["condition_number_scaled"]),
            np.asarray(d["column_rms"], dtype=float),
            np.asarray(d["weakest_direction"], dtype=float),
        )


def conditioning(matrix) -> Conditioning:
    """The :class:`Conditioning` of a design matrix (N, q)."""
    m = np.asarray(matrix, dtype=float)
    singular = np.linalg.svd(m, compute_uv=False)
    rms = np.sqrt(np.mean(m**2, axis=0))
    norms = np.where(rms > 0, rms, 1.0) * np.sqrt(m.shape[0])
    _, s_scaled, vt = np.linalg.svd(m / norms, full_matrices=False)
    return Conditioning(
        condition_number=float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf"),
        condition_number_scaled=float(s_scaled[0] / s_scaled[-1]) if s_scaled[-1] > 0 else float("inf"),
        column_rms=rms,
        weakest_direction=vt[-1],
    )
