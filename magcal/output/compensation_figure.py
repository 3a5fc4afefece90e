"""The figure of a compensation: the band-passed scalar before and after along the flight with the maneuvers
marked, and the FOM table's peak-to-peak values per maneuver before and after (``magcal calibrate --mode
compensation --figure PATH``, a PNG)."""

from __future__ import annotations

import os

import numpy as np

from magcal.core.errors import MagcalError
from magcal.model.tolles_lawson import bandpass

__all__ = ["write_compensation_figure"]


def write_compensation_figure(result, path) -> str:
    """Draw ``result`` (a :class:`magcal.fitting.compensation.CompensationResult` with its FOM) to ``path`` (PNG);
    returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if result.fom is None or result.record is None:
        raise MagcalError("--figure: the compensation has no FOM table to draw (no maneuvers found)")
    record, comp, fom = result.record, result.calibration, result.fom
    rate = record.sample_rate_hz
    t = record.time_s if record.time_s is not None else np.arange(record.n_samples) / rate
    before = bandpass(record.scalar_nT, rate, comp.tl.passband_hz)
    after = bandpass(comp.tl.compensated_nT, rate, comp.tl.passband_hz)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 7), gridspec_kw={"height_ratios": [3, 2]})
    top.plot(t, before, lw=0.7, color="0.6", label="uncompensated")
    top.plot(t, after, lw=0.8, color="C0", label=f"compensated ({', '.join(['TL', *comp.effects])})")
    for m in fom.after.maneuvers:
        top.axvspan(t[m.start], t[min(m.stop, len(t) - 1)], color="C1", alpha=0.08)
    top.set_xlabel("time (s)")
    top.set_ylabel(f"band-passed {comp.tl.passband_hz[0]:g}-{comp.tl.passband_hz[1]:g} Hz (nT)")
    top.set_title(
        f"FOM {fom.before.fom_nT:.2f} -> {fom.after.fom_nT:.3f} nT, improvement ratio {fom.improvement_ratio:.1f}"
    )
    top.legend(loc="upper right", fontsize=8)
    labels = [f"{m.heading_deg:.0f} {m.kind}" for m in fom.after.maneuvers]
    x = np.arange(len(labels))
    bottom.bar(x - 0.2, fom.before.peak_to_peak_nT, 0.4, color="0.6", label="before")
    bottom.bar(x + 0.2, fom.after.peak_to_peak_nT, 0.4, color="C0", label="after")
    bottom.set_yscale("log")
    bottom.set_xticks(x, labels, rotation=45, fontsize=8)
    bottom.set_ylabel("peak-to-peak (nT)")
    bottom.legend(fontsize=8)
    fig.tight_layout()
    path = os.fspath(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
