"""Evidence plots for the Model tab and the full-size view: what the residual looks like against time,
temperature, field direction (power per spherical-harmonic degree) and sensor.

Only plotting: the numbers come from the controller's residuals and the engine's diagnosis
(:func:`magcal.diagnosis.diagnose`, whose ``evidence`` holds the plot data). :func:`evidence_panels` gathers them
once; :func:`evidence_figure` draws them with plotly (the panel, interactive) and :func:`evidence_image` with
matplotlib (the full-size view, and PNG/SVG files for teaching), so both show the same data.

The cockpit's plots follow: the total field |B| against time (raw and corrected, with the reference,
the excluded samples greyed and the excluded stretches shaded, the range being chosen and the samples taken while
turning fast marked), the error histogram (|B| - reference, before and after calibration) and the figures of the
compact table (% of samples within +-1/2/5 % of the reference, coverage of the sphere). Their data come from
:class:`FieldRecord` (the open file's or a live session's) through pure functions the tests call.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass

import numpy as np

from magcal.checks.coverage import direction_map
from magcal.diagnosis.vector import evidence_channel
from magcal.geometry.shape import FieldShape

SENSOR_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd")
MAX_POINTS = 1500
WINDOW_COLOUR = "#f5b041"
FLOOR_COLOUR = "#d62728"


#: The page's plotly figures are drawn with this configuration (:func:`add_figure`): no mode bar (plotly's
#: toolbar, which shows on hover over the figure's top right and covered the titles there); drag still zooms and
#: a double click zooms out again, the evidence has its own PNG and SVG downloads.
PLOTLY_CONFIG = {"displayModeBar": False, "displaylogo": False}


def add_figure(gui, figure, aspect: float, **kw):
    """``figure`` added to ``gui`` (viser's ``add_plotly``, ``kw`` to it) at ``aspect`` with the page's
    :data:`PLOTLY_CONFIG`: every plotly figure the page draws is added here (viser keeps the configuration with the
    handle, for each figure assigned to it later)."""
    return gui.add_plotly(figure, config=PLOTLY_CONFIG, aspect=aspect, **kw)


def _decimate(n: int, kept: np.ndarray, max_points: int = MAX_POINTS) -> np.ndarray:
    idx = np.flatnonzero(kept)
    if idx.size > max_points:
        idx = idx[np.linspace(0, idx.size - 1, max_points).astype(int)]
    return idx


def envelope_indices(values, max_points: int = MAX_POINTS) -> np.ndarray:
    """Sorted sample indices that draw ``values`` (rows of one time axis, shape ``(k, n)``) in at most
    ``max_points`` points while keeping its extremes: the record is cut into ``max_points // 2`` even stretches of
    time, and each gives the sample that lies highest and the one that lies lowest, over every row, measured from
    the row's own median (a spike of one sensor is kept, whatever the others do). All samples up to
    ``max_points``; the first and last samples always. Non-finite values count as neither extreme.
    """
    v = np.atleast_2d(np.asarray(values, float))
    n = v.shape[1]
    if n <= max_points:
        return np.arange(n)
    med = np.nanmedian(v, axis=1, keepdims=True) if np.isfinite(v).any() else np.zeros((v.shape[0], 1))
    dev = v - med
    hi = np.where(np.isfinite(dev), dev, -np.inf).max(axis=0)
    lo = np.where(np.isfinite(dev), dev, np.inf).min(axis=0)
    n_buckets = max(1, (max_points - 2) // 2)
    edges = np.linspace(0, n, n_buckets + 1).astype(np.int64)
    starts = edges[:-1]
    hi_idx = starts + np.array([np.argmax(hi[a:b]) for a, b in zip(edges[:-1], edges[1:])], np.int64)
    lo_idx = starts + np.array([np.argmin(lo[a:b]) for a, b in zip(edges[:-1], edges[1:])], np.int64)
    return np.unique(np.concatenate([[0, n - 1], hi_idx, lo_idx]))


def _evidence(diagnosis) -> dict:
    ev = getattr(diagnosis, "evidence", None) if diagnosis is not None else None
    return ev if isinstance(ev, dict) else {}


def evidence_panels(
    ctrl, window_s=None, max_points: int = MAX_POINTS, before_rms_nT=None, candidate=None
) -> list[dict] | None:
    """The evidence plots' data, one dict per panel, or None before any fit.

    Each panel: ``title``, ``x_label``, ``y_label`` (nT), ``traces`` (dicts with ``kind`` ``markers`` / ``line``
    / ``bar`` / ``diamonds``, ``x``, ``y``, ``sensor`` (0-based or None), ``name``), ``hline`` (the noise floor,
    nT, or None), ``band`` (the time window ``(t0, t1)`` s, or None), ``note`` (text shown when the panel is
    empty). ``before_rms_nT``: the RMS per sensor before the last fit (model against model), drawn beside the
    current bars. Before a diagnosis the time and temperature panels show the current residuals; after it, the
    diagnosis's own evidence (its residuals of the diagnosed fit, their running mean in time, power per degree per
    sensor, and the inter-sensor figures). Without a temperature channel its panel is left out (an empty panel
    reads as a fault). On a record whose loop works on the vector model (``ctrl.vector_loop()``), the vector
    model's panels instead (:func:`vector_evidence_panels`, against the channel of ``candidate``).
    """
    if ctrl.vector_loop():
        return vector_evidence_panels(ctrl.vector, window_s, max_points, candidate)
    if ctrl.residual_nT is None or ctrl.calibration is None:
        return None
    ds = ctrl.dataset
    ev = _evidence(ctrl.diagnosis)
    ns = ds.n_sensors
    panels = []

    time_ev = ev.get("time")
    if time_ev is not None:
        x_t, r_t, smooth = np.asarray(time_ev["x"]), np.asarray(time_ev["y"]), np.asarray(time_ev["smooth"])
        x_label = time_ev.get("x_label", "time (s)")
    else:
        kept = ctrl.kept
        x_t = ds.time_s[kept] if ds.time_s is not None else np.flatnonzero(kept).astype(float)
        r_t, smooth = ctrl.residual_nT[:, kept], None
        x_label = "time (s)" if ds.time_s is not None else "sample"
    idx = _decimate(len(x_t), np.ones(len(x_t), bool), max_points)
    traces = []
    for s in range(ns):
        traces.append({"kind": "markers", "x": x_t[idx], "y": r_t[s, idx], "sensor": s, "name": f"sensor {s + 1}"})
        if smooth is not None:
            traces.append(
                {"kind": "line", "x": x_t[idx], "y": smooth[s, idx], "sensor": s, "name": f"s{s + 1} running mean"}
            )
    panels.append(
        {
            "title": "residual vs time" if ds.time_s is not None else "residual vs sample",
            "x_label": x_label,
            "traces": traces,
            "band": window_s,
        }
    )

    if ds.temperature_C is not None:
        temp_ev = ev.get("temperature")
        if temp_ev is not None:
            x_c, r_c = np.asarray(temp_ev["x"]), np.asarray(temp_ev["y"])
        else:
            x_c, r_c = ds.temperature_C[ctrl.kept], ctrl.residual_nT[:, ctrl.kept]
        idx = _decimate(len(x_c), np.ones(len(x_c), bool), max_points)
        panels.append(
            {
                "title": "residual vs temperature",
                "x_label": "degC",
                "traces": [
                    {"kind": "markers", "x": x_c[idx], "y": r_c[s, idx], "sensor": s, "name": f"sensor {s + 1}"}
                    for s in range(ns)
                ],
            }
        )

    direction = ev.get("direction") or {}
    per = direction.get("per_sensor") if isinstance(direction, dict) else None
    panels.append(
        {
            "title": "RMS per spherical-harmonic degree",
            "x_label": "degree",
            "traces": [
                {
                    "kind": "bar",
                    "x": np.asarray(sh["degree"]),
                    "y": np.asarray(sh["rms_nT"]),
                    "sensor": s,
                    "name": f"sensor {s + 1}",
                }
                for s, sh in enumerate(per or [])
            ],
            "note": None if per else "press Diagnose",
        }
    )

    labels = [f"s{s + 1}" for s in range(ns)]
    traces = [{"kind": "bar", "x": labels, "y": ctrl.rms_per_sensor_nT(), "sensor": None, "name": "total-field RMS"}]
    if before_rms_nT is not None:
        traces.append(
            {
                "kind": "before",
                "x": labels,
                "y": np.asarray(before_rms_nT, float),
                "sensor": None,
                "name": "before the last fit",
            }
        )
    sensors = ev.get("sensors") or {}
    if sensors and sensors.get("difference_rms_nT") is not None:
        traces.append(
            {
                "kind": "diamonds",
                "x": labels,
                "y": np.asarray(sensors["difference_rms_nT"]),
                "sensor": None,
                "name": "difference from the common mode",
            }
        )
    panels.append(
        {"title": "total-field RMS per sensor", "x_label": "sensor", "traces": traces, "hline": ctrl.floor_nT() or None}
    )
    for p in panels:
        p.setdefault("y_label", "nT")
        p.setdefault("hline", None)
        p.setdefault("band", None)
        p.setdefault("note", None)
    return panels


#: The vector evidence's channels (keys of :attr:`magcal.diagnosis.vector.VectorDiagnosis.evidence`) in words.
CHANNEL_WORDS = {"time_s": "time", "temperature_C": "temperature", "turn_rate_dps": "turn rate"}
#: ... and their axis labels.
CHANNEL_AXES = {"time_s": "time (s)", "temperature_C": "degC", "turn_rate_dps": "turn rate (deg/s)"}
#: Bins of the running mean drawn through a residual against a channel.
MEAN_BINS = 30


def binned_mean(x, y, bins: int = MEAN_BINS) -> tuple[np.ndarray, np.ndarray]:
    """The mean of ``y`` in ``bins`` bins of ``x`` holding equal numbers of samples (finite pairs only): the line
    drawn through a residual against a channel, so that a trend shows through the scatter."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 2 * bins:
        return np.zeros(0), np.zeros(0)
    order = np.argsort(x, kind="stable")
    parts = np.array_split(order, bins)
    return np.array([x[p].mean() for p in parts]), np.array([y[p].mean() for p in parts])


def vector_evidence_panels(vm, window_s=None, max_points: int = MAX_POINTS, candidate=None) -> list[dict] | None:
    """The vector model's evidence plots (:func:`evidence_panels`' panels), or None before a vector fit: the world
    residuals north, east, down and the |B| residual of the kept samples (per sensor, with their mean in bins)
    against the channel the candidate's effect follows (:func:`magcal.diagnosis.vector.evidence_channel`: the
    current or throttle, the temperature, the turn rate, else time; without a candidate, the channel of the effect
    added last), and the world RMS per component and |B| of the fit beside the fit before it, with the world noise
    floor. The data are the engine's: the diagnosis's evidence (:attr:`magcal.diagnosis.vector.VectorDiagnosis.
    evidence`), or before one the same of the current fit (:attr:`magcal_workbench.vectormodel.VectorModel.evidence`).
    """
    ev = vm.plot_evidence()
    if ev is None:
        return None
    ctrl = vm.ctrl
    ds = ctrl.dataset
    label = candidate if candidate not in (None, "", "-") else (vm.effects[-1] if vm.effects else None)
    key = evidence_channel(label, ev) if label else "time_s"
    if key == "current":
        x_all, words = np.asarray(ev["current"]["values"], float), str(ev["current"]["column"])
        axis = "current_A (A)" if words == "current_A" else words
    elif key == "time_s" and ev.get("time_s") is None:
        x_all, words, axis = np.arange(ds.n_samples, dtype=float), "sample", "sample"
    else:
        x_all, words, axis = np.asarray(ev[key], float), CHANNEL_WORDS[key], CHANNEL_AXES[key]
    world = np.asarray(ev["world_residual_nT"], float)
    total = np.asarray(ev["total_residual_nT"], float)
    rows = ctrl.kept & np.all(np.isfinite(world), axis=(0, 2)) & np.isfinite(x_all)
    idx = _decimate(len(x_all), rows, max_points)
    every = np.flatnonzero(rows)
    panels = []
    for comp, name in ((0, "north"), (1, "east"), (2, "down"), (None, "|B|")):
        traces = []
        for s in range(world.shape[0]):
            y = world[s, :, comp] if comp is not None else total[s]
            traces.append({"kind": "markers", "x": x_all[idx], "y": y[idx], "sensor": s, "name": f"sensor {s + 1}"})
            mx, my = binned_mean(x_all[every], y[every])
            if mx.size:
                traces.append({"kind": "line", "x": mx, "y": my, "sensor": s, "name": f"s{s + 1} mean"})
        panels.append(
            {
                "title": f"{name} residual vs {words}",
                "x_label": axis,
                "traces": traces,
                "band": window_s if key == "time_s" else None,
            }
        )
    labels = ["N", "E", "D", "|B|"]
    row = vm.vector_row()
    now = [*(row.world_rms_nT if row.world_rms_nT is not None else [np.nan] * 3), row.total_field_rms_nT]
    traces = [{"kind": "bar", "x": labels, "y": np.array(now, dtype=float), "sensor": None, "name": "RMS"}]
    history = ctrl.state.vector_history
    if len(history) >= 2:
        prev = history[-2]
        traces.append(
            {
                "kind": "before",
                "x": labels,
                "y": np.array([*prev.world_rms_nT, prev.total_rms_nT], dtype=float),
                "sensor": None,
                "name": "before the last fit",
            }
        )
    panels.append(
        {
            "title": "world RMS per component (vector fit)",
            "x_label": "component",
            "traces": traces,
            "hline": vm.floor_nT,
        }
    )
    for p in panels:
        p.setdefault("y_label", "nT")
        p.setdefault("hline", None)
        p.setdefault("band", None)
        p.setdefault("note", None)
    return panels


def _colour(trace, n_bars=0):
    if trace["sensor"] is not None:
        return SENSOR_COLOURS[trace["sensor"] % 4]
    return list(SENSOR_COLOURS[:n_bars]) if trace["kind"] == "bar" else "black"


def evidence_figure(ctrl, window_s=None, before_rms_nT=None, candidate=None):
    """The panels of :func:`evidence_panels` as one plotly figure (a column of panels), or None before any fit.

    ``window_s``: ``(t0, t1)`` of the time scrubber's window (s), shaded on the time panel; ``candidate``: the
    chosen candidate's label (the vector model's panels put its channel on their axis).
    """
    panels = evidence_panels(ctrl, window_s, before_rms_nT=before_rms_nT, candidate=candidate)
    if panels is None:
        return None
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    n = len(panels)
    fig = make_subplots(rows=n, cols=1, subplot_titles=[p["title"] for p in panels], vertical_spacing=0.36 / n)
    shown = set()
    for row, p in enumerate(panels, start=1):
        for tr in p["traces"]:
            s = tr["sensor"]
            group = {"legendgroup": f"s{s}"} if s is not None else {}
            first = s is not None and s not in shown and tr["kind"] == "markers"
            if first:
                shown.add(s)
            if tr["kind"] == "markers":
                fig.add_trace(
                    go.Scattergl(
                        x=tr["x"],
                        y=tr["y"],
                        mode="markers",
                        opacity=0.45,
                        name=tr["name"],
                        marker={"size": 3, "color": _colour(tr)},
                        showlegend=first,
                        **group,
                    ),
                    row=row,
                    col=1,
                )
            elif tr["kind"] == "line":
                fig.add_trace(
                    go.Scattergl(
                        x=tr["x"],
                        y=tr["y"],
                        mode="lines",
                        name=tr["name"],
                        showlegend=False,
                        line={"color": _colour(tr), "width": 2},
                        **group,
                    ),
                    row=row,
                    col=1,
                )
            elif tr["kind"] == "bar":
                fig.add_trace(
                    go.Bar(
                        x=tr["x"],
                        y=tr["y"],
                        name=tr["name"],
                        showlegend=False,
                        marker={"color": _colour(tr, len(tr["x"]))},
                        **group,
                    ),
                    row=row,
                    col=1,
                )
            elif tr["kind"] == "before":
                fig.add_trace(
                    go.Scatter(
                        x=tr["x"],
                        y=tr["y"],
                        mode="markers",
                        name=tr["name"],
                        marker={"symbol": "line-ew-open", "size": 40, "color": "#555555", "line": {"width": 3}},
                    ),
                    row=row,
                    col=1,
                )
            else:
                fig.add_trace(
                    go.Scatter(
                        x=tr["x"],
                        y=tr["y"],
                        mode="markers",
                        name=tr["name"],
                        marker={"symbol": "diamond", "size": 10, "color": "black"},
                    ),
                    row=row,
                    col=1,
                )
        if p["band"] is not None:
            fig.add_vrect(
                x0=float(p["band"][0]),
                x1=float(p["band"][1]),
                fillcolor=WINDOW_COLOUR,
                opacity=0.3,
                line_width=0,
                row=row,
                col=1,
            )
        if p["hline"]:
            fig.add_hline(y=p["hline"], line_dash="dash", line_color=FLOOR_COLOUR, row=row, col=1)
        if p["note"] and not p["traces"]:
            # in paper coordinates: the page's plotly.js reads "x3 domain" references as data coordinates
            y_domain = fig.layout[f"yaxis{row}"].domain
            fig.add_annotation(
                text=p["note"], xref="paper", yref="paper", x=0.5, y=0.5 * (y_domain[0] + y_domain[1]), showarrow=False
            )
        fig.update_xaxes(title_text=p["x_label"], row=row, col=1)
    fig.update_yaxes(title_text="nT")  # every panel is in nT
    # the top margin keeps the first title clear of plotly's toolbar
    fig.update_layout(
        height=275 * n,
        margin={"l": 55, "r": 10, "t": 60, "b": 30},
        legend={"orientation": "h", "y": -0.12},
        template="plotly_white",
        barmode="group",
    )
    return fig


def evidence_matplotlib(ctrl, window_s=None, title: str | None = None, before_rms_nT=None, candidate=None):
    """The panels of :func:`evidence_panels` as a matplotlib figure (2 columns, full size), or None."""
    panels = evidence_panels(ctrl, window_s, max_points=20_000, before_rms_nT=before_rms_nT, candidate=candidate)
    if panels is None:
        return None
    from matplotlib.figure import Figure

    cols = 2
    rows = (len(panels) + 1) // 2
    fig = Figure(figsize=(13.0, 4.2 * rows), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, p in zip(axes, panels):
        bars = [t for t in p["traces"] if t["kind"] == "bar" and t["sensor"] is not None]
        width = 0.8 / max(len(bars), 1)
        for tr in p["traces"]:
            if tr["kind"] == "markers":
                ax.plot(tr["x"], tr["y"], ".", ms=2.5, alpha=0.5, color=_colour(tr), label=tr["name"])
            elif tr["kind"] == "line":
                ax.plot(tr["x"], tr["y"], "-", lw=2, color=_colour(tr))
            elif tr["kind"] == "bar" and tr["sensor"] is not None:  # grouped by sensor
                k = next(i for i, b in enumerate(bars) if b is tr)
                ax.bar(
                    np.asarray(tr["x"], float) + (k - 0.5 * (len(bars) - 1)) * width,
                    np.nan_to_num(np.asarray(tr["y"], float)),
                    width,
                    color=_colour(tr),
                    label=tr["name"],
                )
            elif tr["kind"] == "bar":
                ax.bar(tr["x"], tr["y"], color=_colour(tr, len(tr["x"])))
            elif tr["kind"] == "before":
                ax.plot(tr["x"], tr["y"], "_", ms=40, mew=3, color="#555555", label=tr["name"])
            else:
                ax.plot(tr["x"], tr["y"], "D", color="black", label=tr["name"])
        if p["band"] is not None:
            ax.axvspan(float(p["band"][0]), float(p["band"][1]), color=WINDOW_COLOUR, alpha=0.3, lw=0)
        if p["hline"]:
            ax.axhline(p["hline"], ls="--", color=FLOOR_COLOUR, label=f"noise floor {p['hline']:.3g} nT")
        if p["note"] and not p["traces"]:
            ax.text(0.5, 0.5, p["note"], ha="center", va="center", transform=ax.transAxes, color="0.4")
        ax.set_title(p["title"])
        ax.set_xlabel(p["x_label"])
        ax.set_ylabel(p["y_label"])
        ax.grid(alpha=0.3)
        if p["hline"]:  # room above the bars for the legend
            top = max([float(np.nanmax(np.asarray(t["y"], float))) for t in p["traces"]] + [p["hline"]])
            ax.set_ylim(0, 1.35 * top)
        if p["title"].startswith("residual vs t") or p["hline"] or any(t["kind"] == "before" for t in p["traces"]):
            ax.legend(loc="upper left" if p["hline"] else "best", fontsize=8, markerscale=3 if not p["hline"] else 1)
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return fig


def evidence_image(
    ctrl, fmt: str = "svg", window_s=None, title: str | None = None, before_rms_nT=None, candidate=None
) -> bytes | None:
    """The full-size evidence as an image file's bytes (``svg`` or ``png``), or None before any fit."""
    if fmt not in ("svg", "png"):
        raise ValueError(f"format {fmt!r}: svg or png")
    fig = evidence_matplotlib(ctrl, window_s, title, before_rms_nT, candidate)
    if fig is None:
        return None
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=110)
    return buf.getvalue()


# --- the cockpit: |B| against time, the error histogram, the compact table's figures ---------------------------
#: The bands of the compact table: % of the reference field.
WITHIN_PCT = (1.0, 2.0, 5.0)
RAW_COLOUR = "#ff7f0e"
CORRECTED_COLOUR = "#1f77b4"
REFERENCE_COLOUR = "#2ca02c"
EXCLUDED_COLOUR = "#b0b0b0"
FAST_COLOUR = "#d62728"
#: The range being chosen (region editor) and the excluded stretches, shaded.
RANGE_COLOUR = "#4dabf7"
EXCLUDED_BAND_COLOUR = "#9e9e9e"
#: Shortest run of excluded samples (consecutive in time) drawn as a shaded band; shorter ones show as grey points.
MIN_BAND_SAMPLES = 3
#: Most bands drawn (the longest first).
MAX_BANDS = 30
#: Cells of the coverage figure (as the live view's coverage spheres).
COVERAGE_CELLS = 300
#: Most samples the coverage figure reads (an even stride through a larger record).
COVERAGE_SAMPLES = 20_000


@dataclass
class FieldRecord:
    """What the cockpit's plots and table read, for the open file or a live session.

    Attributes
    ----------
    time_s : numpy.ndarray, shape (N,)
        Sample times, s (the sample number when the data have none).
    raw_nT : numpy.ndarray, shape (n_sensors, N, 3)
        Raw readings, nT.
    corrected_nT : numpy.ndarray or None, shape (n_sensors, N, 3)
        Readings corrected by the current calibration (array frame, nT), or None before a fit.
    reference_nT : numpy.ndarray, shape (N,)
        The reference total field per sample, nT (the fit's, the user's or the file's; else the median |raw|).
    kept : numpy.ndarray of bool, shape (N,)
        The samples the fit uses.
    fast : numpy.ndarray of bool or None, shape (N,)
        Samples taken while turning fast (:func:`magcal_workbench.motion.fast_turning`), None without gyro or
        attitude.
    raw_reference_nT : numpy.ndarray or None, shape (N,)
        What the raw readings are judged against (:func:`raw_reference_nT`): the raw data's own figure, the same
        before and after a fit; None: ``reference_nT``.
    """

    time_s: np.ndarray
    raw_nT: np.ndarray
    corrected_nT: np.ndarray | None
    reference_nT: np.ndarray
    kept: np.ndarray
    fast: np.ndarray | None = None
    raw_reference_nT: np.ndarray | None = None

    @property
    def n_samples(self) -> int:
        return int(self.raw_nT.shape[1])

    @property
    def n_sensors(self) -> int:
        return int(self.raw_nT.shape[0])


def within_fractions(magnitude_nT, reference_nT, pcts=WITHIN_PCT) -> dict:
    """Share (0-1) of the samples whose total field lies within +-p % of the reference, for each ``p`` of
    ``pcts``; NaN when no sample has both a finite magnitude and a positive reference.

    Parameters
    ----------
    magnitude_nT : array_like, shape (..., N)
        |B| per sample, nT (several sensors pooled).
    reference_nT : array_like, broadcastable to ``magnitude_nT``
        The reference total field, nT.
    """
    m = np.asarray(magnitude_nT, float)
    ref = np.broadcast_to(np.asarray(reference_nT, float), m.shape)
    ok = np.isfinite(m) & np.isfinite(ref) & (ref > 0)
    rel_pct = 100.0 * np.abs(m[ok] / ref[ok] - 1.0)
    return {float(p): float(np.mean(rel_pct <= p)) if rel_pct.size else float("nan") for p in pcts}


def excluded_bands(time_s, kept, min_samples: int = MIN_BAND_SAMPLES, max_bands: int = MAX_BANDS) -> list:
    """Stretches of excluded samples, consecutive in time, as ``(t0, t1)`` pairs (s): runs of at least
    ``min_samples``, the ``max_bands`` longest, in time order."""
    t = np.asarray(time_s, float)
    order = np.argsort(t, kind="stable")
    out = ~np.asarray(kept, bool)[order]
    edges = np.diff(np.concatenate([[0], out.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    runs = [(s, e) for s, e in zip(starts, ends) if e - s >= min_samples]
    runs = sorted(sorted(runs, key=lambda r: r[0] - r[1])[:max_bands])
    ts = t[order]
    return [(float(ts[s]), float(ts[e - 1])) for s, e in runs]


def magnitude_series(record: FieldRecord, max_points: int = MAX_POINTS) -> dict:
    """The |B| plot's data, decimated to at most ``max_points`` samples (a min/max envelope that keeps each
    stretch's extremes, :func:`envelope_indices`; every sample still counts in the fit and the table).

    Returns
    -------
    dict
        ``t`` (s), ``raw`` and ``corrected`` (n_sensors, n) |B| in nT (``corrected`` None before a fit),
        ``reference`` (n,) nT, ``kept`` (n,) bool, ``fast`` (n,) bool or None, ``index`` (n,) the samples shown,
        ``bands`` (the excluded stretches, :func:`excluded_bands`, over every sample).
    """
    n = record.n_samples
    t = np.asarray(record.time_s, float)
    if n <= max_points:
        idx = np.arange(n)
        raw = np.linalg.norm(np.asarray(record.raw_nT, float), axis=2)
        corr = None if record.corrected_nT is None else np.linalg.norm(np.asarray(record.corrected_nT, float), axis=2)
    else:  # a min/max envelope: every stretch's highest and lowest sample, of any sensor, is drawn
        raw_all = np.linalg.norm(np.asarray(record.raw_nT, float), axis=2)
        corr_all = None
        if record.corrected_nT is not None:
            corr_all = np.linalg.norm(np.asarray(record.corrected_nT, float), axis=2)
        idx = envelope_indices(raw_all if corr_all is None else np.vstack([raw_all, corr_all]), max_points)
        raw = raw_all[:, idx]
        corr = None if corr_all is None else corr_all[:, idx]
    return {
        "t": t[idx],
        "raw": raw,
        "corrected": corr,
        "reference": np.asarray(record.reference_nT, float)[idx],
        "kept": np.asarray(record.kept, bool)[idx],
        "fast": None if record.fast is None else np.asarray(record.fast, bool)[idx],
        "index": idx,
        "bands": excluded_bands(t, record.kept),
    }


#: Most values the histogram's range (its percentiles) is read from (an even stride); every value is counted.
RANGE_SAMPLES = 200_000


def _histogram(values, bins: int):
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return np.zeros(0), np.zeros(0, int)
    sample = v[np.linspace(0, v.size - 1, RANGE_SAMPLES).astype(int)] if v.size > RANGE_SAMPLES else v
    lo, hi = np.percentile(sample, [0.5, 99.5])
    lo, hi = min(lo, 0.0), max(hi, 0.0)  # zero error is always on the axis
    if hi - lo <= 0:
        lo, hi = lo - 1.0, hi + 1.0
    counts, edges = np.histogram(np.clip(v, lo, hi), bins=bins, range=(lo, hi))
    return edges, counts


def error_histogram(record: FieldRecord, unit: str = "nT", bins: int = 60) -> dict:
    """The error histograms before and after calibration: ``|B| - reference`` of the kept samples (every sensor
    pooled), in nT or in % of the reference.

    Each histogram has its own bins (0.5-99.5 percentile range widened to include 0, the tails piled into the
    end bins): the raw error spans hundreds of nT and the corrected one a few, so shared bins would show the
    corrected one as one bar.

    Returns
    -------
    dict
        ``unit``; ``before`` and ``after`` (None before a fit) each ``{"edges", "counts", "rms", "n"}``
        (``rms`` in ``unit``).
    """
    if unit not in ("nT", "%"):
        raise ValueError(f"unit {unit!r}: nT or %")
    kept = np.asarray(record.kept, bool)
    ref = np.asarray(record.reference_nT, float)[kept]

    def errors(vectors):
        m = np.linalg.norm(np.asarray(vectors, float)[:, kept], axis=2)
        e = m - ref
        return (100.0 * e / ref if unit == "%" else e).ravel()

    out: dict = {"unit": unit, "before": None, "after": None}
    for key, vectors in (("before", record.raw_nT), ("after", record.corrected_nT)):
        if vectors is None or not kept.any():
            continue
        e = errors(vectors)
        edges, counts = _histogram(e, bins)
        finite = e[np.isfinite(e)]
        rms = float(np.sqrt(np.mean(finite**2))) if finite.size else float("nan")
        out[key] = {"edges": edges, "counts": counts, "rms": rms, "n": int(finite.size)}
    return out


def coverage_fraction(record: FieldRecord, cells: int = COVERAGE_CELLS, max_samples: int = COVERAGE_SAMPLES) -> list:
    """Share (0-1) of the sphere of field directions visited by each sensor's kept samples
    (:func:`magcal.checks.coverage.direction_map`): of the corrected readings about the origin after a fit, else
    of the raw readings about their own fitted centre. A larger record is taken at an even stride through time, at
    most ``max_samples`` of its kept samples: a cell counts as visited when a direction lies within 30 deg of it,
    and neighbouring samples of a path are far closer than that."""
    kept = np.asarray(record.kept, bool)
    if kept.sum() > max_samples:
        chosen = np.flatnonzero(kept)
        kept = np.zeros_like(kept)
        kept[chosen[np.linspace(0, chosen.size - 1, max_samples).astype(int)]] = True
    out = []
    for s in range(record.n_sensors):
        if record.corrected_nT is not None:
            shape = FieldShape(centre_nT=np.zeros(3), cinv=np.eye(3), field_nT=float("nan"), source="origin")
            m = direction_map(np.asarray(record.corrected_nT[s])[kept], cells, shape=shape)
        else:
            m = direction_map(np.asarray(record.raw_nT[s])[kept], cells)
        out.append(float(m.fraction))
    return out


def record_key(record: FieldRecord, *extra) -> str:
    """A digest of everything the cockpit's figures read from ``record`` (and of ``extra``, e.g. the range being
    chosen): equal keys, equal figures, so a figure whose data did not change is not rebuilt."""
    h = hashlib.blake2b(digest_size=16)
    arrays = (record.time_s, record.raw_nT, record.corrected_nT, record.reference_nT, record.kept, record.fast)
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.data)
    h.update(repr(extra).encode())
    return h.hexdigest()


def raw_reference_nT(dataset, typed_nT=None) -> np.ndarray:
    """The total field the raw readings are judged against, per sample (nT): the file's ``ref_total`` column,
    else the reference typed in the page (``typed_nT``), else the file's ``# reference_total_nT``, else the median
    |raw| of every sensor. No fit enters it: the raw row of the table and the history's first step are the raw
    data's figure, whatever the fits find."""
    if dataset.ref_total_nT is not None:
        return np.asarray(dataset.ref_total_nT, dtype=float)
    if typed_nT:
        return np.full(dataset.n_samples, float(typed_nT))
    if dataset.reference_total_nT:
        return np.full(dataset.n_samples, float(dataset.reference_total_nT))
    return np.full(dataset.n_samples, float(np.median(np.linalg.norm(dataset.readings_nT, axis=2))))


def table_figures(record: FieldRecord) -> dict:
    """The compact table's data-derived figures: ``within_raw`` / ``within_corrected`` (:func:`within_fractions`
    of the kept samples, every sensor pooled; the latter None before a fit), ``rms_raw_nT`` (RMS of
    ``|raw| - reference``), ``coverage`` (per sensor, :func:`coverage_fraction`), ``n_kept``, ``n_samples``."""
    kept = np.asarray(record.kept, bool)
    ref = np.asarray(record.reference_nT, float)[kept]
    raw_ref = ref if record.raw_reference_nT is None else np.asarray(record.raw_reference_nT, float)[kept]
    raw = np.linalg.norm(np.asarray(record.raw_nT, float)[:, kept], axis=2)
    err = (raw - raw_ref).ravel()
    err = err[np.isfinite(err)]
    corr = None
    if record.corrected_nT is not None:
        corr = np.linalg.norm(np.asarray(record.corrected_nT, float)[:, kept], axis=2)
    return {
        "within_raw": within_fractions(raw, raw_ref),
        "within_corrected": None if corr is None else within_fractions(corr, ref),
        "rms_raw_nT": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        "coverage": coverage_fraction(record) if kept.any() else [float("nan")] * record.n_sensors,
        "n_kept": int(kept.sum()),
        "n_samples": record.n_samples,
    }


def magnitude_figure(record: FieldRecord, pending_s=None, max_points: int = MAX_POINTS):
    """|B| against time (plotly): each sensor's raw and corrected |B| (kept samples in colour, excluded ones
    grey), the reference, the excluded stretches shaded grey, the range being chosen (``pending_s``, ``(t0, t1)``
    s) shaded blue, and the samples taken while turning fast ringed red."""
    import plotly.graph_objects as go

    d = magnitude_series(record, max_points)
    t, kept, ns = d["t"], d["kept"], record.n_sensors
    fig = go.Figure()
    fig.add_trace(
        go.Scattergl(
            x=t, y=d["reference"], mode="lines", line={"color": REFERENCE_COLOUR, "width": 1.5}, name="reference"
        )
    )
    every = " (every sensor)" if ns > 1 else ""
    for key, colour, label in (("raw", RAW_COLOUR, "raw"), ("corrected", CORRECTED_COLOUR, "corrected")):
        values = d[key]
        if values is None:
            continue
        for s in range(ns):
            fig.add_trace(
                go.Scattergl(
                    x=t[kept],
                    y=values[s, kept],
                    mode="markers",
                    marker={"size": 3, "color": colour, "opacity": 0.6},
                    name=label + every,
                    legendgroup=key,
                    showlegend=s == 0,
                )
            )
            if (~kept).any():
                fig.add_trace(
                    go.Scattergl(
                        x=t[~kept],
                        y=values[s, ~kept],
                        mode="markers",
                        marker={"size": 3, "color": EXCLUDED_COLOUR},
                        name="excluded",
                        legendgroup="excluded",
                        showlegend=key == "raw" and s == 0,
                    )
                )
    fast = d["fast"]
    if fast is not None and fast.any():
        shown = d["corrected"] if d["corrected"] is not None else d["raw"]
        fig.add_trace(
            go.Scattergl(
                x=t[fast],
                y=shown[0, fast],
                mode="markers",
                marker={"size": 7, "color": "rgba(0,0,0,0)", "line": {"color": FAST_COLOUR, "width": 1}},
                name="turning fast",
            )
        )
    for t0, t1 in d["bands"]:
        fig.add_vrect(x0=t0, x1=t1, fillcolor=EXCLUDED_BAND_COLOUR, opacity=0.35, line_width=0)
    if pending_s is not None:
        fig.add_vrect(
            x0=float(pending_s[0]), x1=float(pending_s[1]), fillcolor=RANGE_COLOUR, opacity=0.25, line_width=0
        )
    fig.update_layout(
        height=300,
        margin={"l": 60, "r": 10, "t": 30, "b": 35},
        title={"text": "|B| against time", "font": {"size": 13}},
        xaxis_title="time (s)",
        yaxis_title="|B| nT",
        legend={"orientation": "h", "y": -0.3, "font": {"size": 10}},
        template="plotly_white",
    )
    return fig


def histogram_figure(record: FieldRecord, unit: str = "nT"):
    """The error histograms before and after calibration overlaid (plotly), each on its own horizontal axis in
    its colour (raw: bottom, corrected: top), since the raw error spans hundreds of nT and the corrected one a
    few; each axis's title says its RMS (no legend: in the panel's narrow plot it would lie over an axis)."""
    import plotly.graph_objects as go

    h = error_histogram(record, unit)
    rms = {k: "" if h[k] is None else f" (RMS {format_rms(h[k]['rms'], unit)})" for k in ("before", "after")}
    fig = go.Figure()
    axes = {"before": "x", "after": "x2"}
    for key, colour, label in (("before", RAW_COLOUR, "raw"), ("after", CORRECTED_COLOUR, "corrected")):
        part = h[key]
        if part is None or not len(part["counts"]):
            continue
        edges = part["edges"]
        fig.add_trace(
            go.Bar(
                x=0.5 * (edges[:-1] + edges[1:]),
                y=part["counts"],
                width=np.diff(edges),
                marker={"color": colour},
                opacity=0.55,
                name=f"{label} (RMS {format_rms(part['rms'], unit)})",
                xaxis=axes[key],
            )
        )
    fig.update_layout(
        barmode="overlay",
        height=280,
        margin={"l": 50, "r": 10, "t": 75, "b": 45},
        title={"text": f"error |B| - reference ({unit})", "font": {"size": 13}, "y": 0.98},
        xaxis={
            "title": {"text": f"raw, {unit}{rms['before']}", "font": {"color": RAW_COLOUR}},
            "tickfont": {"color": RAW_COLOUR},
        },
        yaxis={"title": {"text": "samples"}},
        showlegend=False,
        template="plotly_white",
    )
    if h["after"] is not None:
        fig.update_layout(
            xaxis2={
                "title": {
                    "text": f"corrected, {unit}{rms['after']}",
                    "font": {"color": CORRECTED_COLOUR},
                    "standoff": 2,
                },
                "tickfont": {"color": CORRECTED_COLOUR},
                "overlaying": "x",
                "side": "top",
                "showgrid": False,
            }
        )
    return fig


def format_rms(value: float, unit: str) -> str:
    """An RMS for a legend: ``3.01 nT``, ``0.006 %``."""
    if not np.isfinite(value):
        return "-"
    return f"{value:.3g} {unit}" if unit == "nT" else f"{value:.2g} %"


#: Room left above and below the data on a log axis (a factor): the points never sit on the frame.
LOG_AXIS_MARGIN = 1.25


def log_axis_scales(data) -> dict:
    """uPlot scales for a history plot (x the step, y on a log axis) whose y axis spans the data, not the decades
    around them: ``data`` as the plot takes it, ``(x, y1, y2, ...)``. uPlot's own range for a log axis snaps to
    whole decades, so figures of 700-1300 nT were drawn on an axis to 10 000. The x axis holds every step with half
    a step either side: a history of one step is a point in the middle, not on the frame's edge."""
    values = np.concatenate([np.asarray(y, float).ravel() for y in data[1:]]) if len(data) > 1 else np.array([])
    values = values[np.isfinite(values) & (values > 0)]
    y: dict = {"distr": 3, "log": 10}
    if values.size:
        y["range"] = [float(values.min()) / LOG_AXIS_MARGIN, float(values.max()) * LOG_AXIS_MARGIN]
    x: dict = {"time": False}
    steps = np.asarray(data[0], float) if len(data) else np.array([])
    steps = steps[np.isfinite(steps)]
    if steps.size:  # the steps are whole numbers: the frame's edges, half a step out, are not steps of their own
        x["range"] = [float(np.ceil(steps.min())) - 0.5, float(np.floor(steps.max())) + 0.5]
    return {"x": x, "y": y}


def one_step_history(x, series, floors):
    """A history plot's data for uPlot when it holds one step: uPlot draws a line between two x values, so the
    floor of a single step would be drawn nowhere. The step stays at ``x = 0``, its figures there alone (infinite
    at the frame's edges: the browser draws no line to and no point at an infinite value, while uPlot draws NaN as
    the log axis's foot), and the floors (``floors``: the indices in ``series`` that are floors) span the frame,
    from half a step before to half a step after (:func:`log_axis_scales` keeps that frame).
    Histories of more steps are returned as they are: ``(x, *series)``."""
    if len(x) != 1:
        return (x, *series)
    out = [np.array([-0.5, 0.0, 0.5])]
    for k, values in enumerate(series):
        v = float(np.asarray(values, dtype=float)[0])
        out.append(np.full(3, v) if k in floors else np.array([np.inf, v, np.inf]))
    return tuple(out)
