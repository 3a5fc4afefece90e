"""The figure of a compensation (``magcal calibrate --mode compensation --figure PATH``, a PNG).

Three rows:

1. the band-passed scalar before the compensation along the flight, the maneuvers shaded and each named above it
   (its heading, and R, P or Y for a roll, a pitch or a yaw);
2. the band-passed scalar after it, on its own scale (tens of pT where the one before swings by tens of nT), the
   maneuvers shaded alike;
3. the FOM table as the report gives it: per heading (rows) and maneuver (columns) the peak-to-peak before and
   after (nT), the sums per heading and the FOM; beside it the peak-to-peak per maneuver before and after on a
   logarithmic scale.
"""

from __future__ import annotations

import os

import numpy as np

from magcal.core.errors import MagcalError
from magcal.model.tolles_lawson import bandpass

__all__ = ["write_compensation_figure"]

#: The maneuvers' kinds, their letters above the shading and their colours.
KINDS = {"roll": ("R", "C1"), "pitch": ("P", "C2"), "yaw": ("Y", "C4")}


def _shade(ax, t, maneuvers, label: bool) -> None:
    """Shade each maneuver's span (and name it above the axes when ``label``)."""
    for m in maneuvers:
        letter, colour = KINDS.get(m.kind, (m.kind[:1].upper(), "C7"))
        t0, t1 = t[m.start], t[min(m.stop, len(t) - 1)]
        ax.axvspan(t0, t1, color=colour, alpha=0.12, lw=0)
        if label:
            ax.text(
                0.5 * (t0 + t1), 1.01, f"{m.heading_deg:.0f}{letter}", transform=ax.get_xaxis_transform(),
                ha="center", va="bottom", fontsize=7, color=colour,
            )  # fmt: skip


def _table_rows(fom):
    """The FOM table's cells: a row per heading (before -> after per kind, the heading's sum), then the totals."""
    headings = list(dict.fromkeys(round(m.heading_deg) for m in fom.after.maneuvers))
    kinds = [k for k in KINDS if any(m.kind == k for m in fom.after.maneuvers)]
    cell = {
        (round(m.heading_deg), m.kind): (b, a)
        for m, b, a in zip(fom.after.maneuvers, fom.before.peak_to_peak_nT, fom.after.peak_to_peak_nT)
    }
    rows = []
    for h in headings:
        pairs = [cell.get((h, k)) for k in kinds]
        before = sum(p[0] for p in pairs if p)
        after = sum(p[1] for p in pairs if p)
        rows.append([f"{h} deg"] + [f"{p[0]:.2f} / {p[1]:.3f}" if p else "-" for p in pairs])
        rows[-1].append(f"{before:.2f} / {after:.3f}")
    totals = [sum(cell[(h, k)][j] for h in headings if (h, k) in cell) for k in kinds for j in (0, 1)]
    rows.append(["all"] + [f"{totals[2 * i]:.2f} / {totals[2 * i + 1]:.3f}" for i in range(len(kinds))])
    rows[-1].append(f"{fom.before.fom_nT:.2f} / {fom.after.fom_nT:.3f}")
    return ["heading"] + kinds + ["sum"], rows


def write_compensation_figure(result, path) -> str:
    """Draw ``result`` (a :class:`magcal.fitting.compensation.CompensationResult` with its FOM) to ``path`` (PNG);
    returns the path."""
    try:
        import matplotlib
    except ImportError:
        raise MagcalError(
            'the figure needs matplotlib: pip install "magcal-workbench[figures]" (or leave --figure out)'
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.transforms import Bbox

    if result.fom is None or result.record is None:
        raise MagcalError("--figure: the compensation has no FOM table to draw (no maneuvers found)")
    record, comp, fom = result.record, result.calibration, result.fom
    rate = record.sample_rate_hz
    t = record.time_s if record.time_s is not None else np.arange(record.n_samples) / rate
    band = f"band-passed {comp.tl.passband_hz[0]:g}-{comp.tl.passband_hz[1]:g} Hz"
    before = bandpass(record.scalar_nT, rate, comp.tl.passband_hz)
    after = bandpass(comp.tl.compensated_nT, rate, comp.tl.passband_hz)
    trim = comp.tl.trim if 2 * comp.tl.trim < t.size else 0
    shown = slice(trim, t.size - trim)  # the band-pass's edges are not the platform's
    fig = plt.figure(figsize=(12, 10))
    grid = fig.add_gridspec(3, 2, height_ratios=[2.2, 2.2, 2.4], width_ratios=[1.0, 1.25], hspace=0.45, wspace=0.08)
    top = fig.add_subplot(grid[0, :])
    middle = fig.add_subplot(grid[1, :], sharex=top)
    top.plot(t[shown], before[shown], lw=0.7, color="0.35")
    _shade(top, t, fom.after.maneuvers, label=True)
    top.set_ylabel("before (nT)")
    top.set_title(f"uncompensated scalar {comp.scalar_column!r}, {band}", fontsize=10, pad=14, loc="left")
    middle.plot(t[shown], after[shown], lw=0.7, color="C0")
    _shade(middle, t, fom.after.maneuvers, label=False)
    middle.set_ylabel("after (nT)")
    middle.set_xlabel("time (s)")
    terms = ", ".join(["Tolles-Lawson", *comp.effects])
    middle.set_title(f"compensated ({terms}), {band}: its own scale", fontsize=10, loc="left")
    fig.suptitle(
        f"FOM {fom.before.fom_nT:.2f} nT before, {fom.after.fom_nT:.3f} nT after; improvement ratio "
        f"{fom.improvement_ratio:.0f}",
        fontsize=12,
    )
    bars = fig.add_subplot(grid[2, 0])
    labels = [f"{m.heading_deg:.0f}{KINDS.get(m.kind, (m.kind[:1].upper(),))[0]}" for m in fom.after.maneuvers]
    x = np.arange(len(labels))
    bars.bar(x - 0.2, fom.before.peak_to_peak_nT, 0.4, color="0.6", label="before")
    bars.bar(x + 0.2, fom.after.peak_to_peak_nT, 0.4, color="C0", label="after")
    bars.set_yscale("log")
    bars.set_xticks(x, labels, fontsize=8, rotation=45)
    bars.set_ylabel("peak-to-peak (nT)")
    bars.set_title("per maneuver", fontsize=10, loc="left")
    bars.legend(fontsize=8, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=2, frameon=False)
    table_ax = fig.add_subplot(grid[2, 1])
    table_ax.axis("off")
    header, rows = _table_rows(fom)
    widths = [0.13] + [0.87 / (len(header) - 1)] * (len(header) - 1)
    table = table_ax.table(
        cellText=rows, colLabels=header, colWidths=widths, bbox=Bbox.from_bounds(0.0, 0.0, 1.0, 0.92), cellLoc="center"
    )
    table.auto_set_font_size(False)
    table.set_fontsize(8.5)
    for (row, col), c in table.get_celld().items():
        if row == 0 or col == 0:
            c.set_text_props(fontweight="bold")
        if row == len(rows) or col == len(header) - 1:
            c.set_facecolor("0.92")
    table_ax.set_title("FOM table: peak-to-peak before / after (nT)", fontsize=10, loc="left")
    path = os.fspath(path)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
