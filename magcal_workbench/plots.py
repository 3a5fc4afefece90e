"""Evidence plots for the Model tab and the full-size view: what the residual looks like against time,
temperature, field direction (power per spherical-harmonic degree) and sensor.

Only plotting: the numbers come from the controller's residuals and the engine's diagnosis
(:func:`magcal.diagnosis.diagnose`, whose ``evidence`` holds the plot data). :func:`evidence_panels` gathers them
once; :func:`evidence_figure` draws them with plotly (the panel, interactive) and :func:`evidence_image` with
matplotlib (the full-size view, and PNG/SVG files for teaching), so both show the same data.
"""

from __future__ import annotations

import io

import numpy as np

SENSOR_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd")
MAX_POINTS = 1500
WINDOW_COLOUR = "#f5b041"
FLOOR_COLOUR = "#d62728"


def _decimate(n: int, kept: np.ndarray, max_points: int = MAX_POINTS) -> np.ndarray:
    idx = np.flatnonzero(kept)
    if idx.size > max_points:
        idx = idx[np.linspace(0, idx.size - 1, max_points).astype(int)]
    return idx


def _evidence(diagnosis) -> dict:
    ev = getattr(diagnosis, "evidence", None) if diagnosis is not None else None
    return ev if isinstance(ev, dict) else {}


def evidence_panels(ctrl, window_s=None, max_points: int = MAX_POINTS, before_rms_nT=None) -> list[dict] | None:
    """The evidence plots' data, one dict per panel, or None before any fit.

    Each panel: ``title``, ``x_label``, ``y_label`` (nT), ``traces`` (dicts with ``kind`` ``markers`` / ``line``
    / ``bar`` / ``diamonds``, ``x``, ``y``, ``sensor`` (0-based or None), ``name``), ``hline`` (the noise floor,
    nT, or None), ``band`` (the time window ``(t0, t1)`` s, or None), ``note`` (text shown when the panel is
    empty). ``before_rms_nT``: the RMS per sensor before the last fit (model against model), drawn beside the
    current bars. Before a diagnosis the time and temperature panels show the current residuals; after it, the
    diagnosis's own evidence (its residuals of the diagnosed fit, their running mean in time, power per degree per
    sensor, and the inter-sensor figures). Without a temperature channel its panel is left out (an empty panel
    reads as a fault).
    """
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


def _colour(trace, n_bars=0):
    if trace["sensor"] is not None:
        return SENSOR_COLOURS[trace["sensor"] % 4]
    return list(SENSOR_COLOURS[:n_bars]) if trace["kind"] == "bar" else "black"


def evidence_figure(ctrl, window_s=None, before_rms_nT=None):
    """The panels of :func:`evidence_panels` as one plotly figure (a column of panels), or None before any fit.

    ``window_s``: ``(t0, t1)`` of the time scrubber's window (s), shaded on the time panel.
    """
    panels = evidence_panels(ctrl, window_s, before_rms_nT=before_rms_nT)
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


def evidence_matplotlib(ctrl, window_s=None, title: str | None = None, before_rms_nT=None):
    """The panels of :func:`evidence_panels` as a matplotlib figure (2 x 2 grid, full size), or None."""
    panels = evidence_panels(ctrl, window_s, max_points=20_000, before_rms_nT=before_rms_nT)
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
        if p["title"].startswith("residual vs t") or p["hline"]:
            ax.legend(loc="upper left" if p["hline"] else "best", fontsize=8, markerscale=3 if not p["hline"] else 1)
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return fig


def evidence_image(ctrl, fmt: str = "svg", window_s=None, title: str | None = None, before_rms_nT=None) -> bytes | None:
    """The full-size evidence as an image file's bytes (``svg`` or ``png``), or None before any fit."""
    if fmt not in ("svg", "png"):
        raise ValueError(f"format {fmt!r}: svg or png")
    fig = evidence_matplotlib(ctrl, window_s, title, before_rms_nT)
    if fig is None:
        return None
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=110)
    return buf.getvalue()
