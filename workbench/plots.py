"""Evidence plots for the Model tab (plotly): what the residual looks like against time, temperature, field
direction (power per spherical-harmonic degree) and sensor.

Only plotting: the numbers come from the controller's residuals and the engine's diagnosis
(:func:`magcal.diagnosis.diagnose`, whose ``evidence`` holds the plot data).
"""

from __future__ import annotations

import numpy as np

SENSOR_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd")
MAX_POINTS = 1500


def _decimate(n: int, kept: np.ndarray) -> np.ndarray:
    idx = np.flatnonzero(kept)
    if idx.size > MAX_POINTS:
        idx = idx[np.linspace(0, idx.size - 1, MAX_POINTS).astype(int)]
    return idx


def _evidence(diagnosis) -> dict:
    ev = getattr(diagnosis, "evidence", None) if diagnosis is not None else None
    return ev if isinstance(ev, dict) else {}


def evidence_figure(ctrl, window_s=None):
    """A 2 x 2 plotly figure (time, temperature, spherical-harmonic degree, sensors), or None before any fit.

    ``window_s``: ``(t0, t1)`` of the time scrubber's window (s), shaded on the time panel.

    Before a diagnosis the time and temperature panels show the current residuals; after it, the diagnosis's own
    evidence (its residuals of the diagnosed fit, their running mean in time, power per degree per sensor, and
    the inter-sensor figures).
    """
    if ctrl.residual_nT is None or ctrl.calibration is None:
        return None
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    ds = ctrl.dataset
    ev = _evidence(ctrl.diagnosis)
    has_temp = ds.temperature_C is not None
    ns = ds.n_sensors
    # one row per panel; without a temperature channel its panel is left out (an empty panel reads as a fault)
    titles = ["residual vs time" if ds.time_s is not None else "residual vs sample"]
    titles += ["residual vs temperature"] if has_temp else []
    titles += ["RMS per spherical-harmonic degree", "total-field RMS per sensor"]
    row_time, row_temp = 1, (2 if has_temp else None)
    row_sh, row_sensors = len(titles) - 1, len(titles)
    fig = make_subplots(rows=len(titles), cols=1, subplot_titles=titles, vertical_spacing=0.36 / len(titles))

    time_ev = ev.get("time")
    if time_ev is not None:
        x_t, r_t, smooth = np.asarray(time_ev["x"]), np.asarray(time_ev["y"]), np.asarray(time_ev["smooth"])
        x_label = time_ev.get("x_label", "time (s)")
    else:
        kept = ctrl.kept
        x_t = ds.time_s[kept] if ds.time_s is not None else np.flatnonzero(kept).astype(float)
        r_t, smooth = ctrl.residual_nT[:, kept], None
        x_label = "time (s)" if ds.time_s is not None else "sample"
    idx = _decimate(len(x_t), np.ones(len(x_t), bool))
    for s in range(ns):
        colour = SENSOR_COLOURS[s % 4]
        fig.add_trace(go.Scattergl(x=x_t[idx], y=r_t[s, idx], mode="markers", opacity=0.45,
                                   marker={"size": 3, "color": colour}, name=f"sensor {s + 1}",
                                   legendgroup=f"s{s}"), row=row_time, col=1)
        if smooth is not None:
            fig.add_trace(go.Scattergl(x=x_t[idx], y=smooth[s, idx], mode="lines", line={"color": colour, "width": 2},
                                       name=f"s{s + 1} running mean", legendgroup=f"s{s}", showlegend=False),
                          row=row_time, col=1)
    if window_s is not None:
        fig.add_vrect(x0=float(window_s[0]), x1=float(window_s[1]), fillcolor="#f5b041", opacity=0.3, line_width=0,
                      row=row_time, col=1)
    temp_ev = ev.get("temperature")
    if has_temp:
        if temp_ev is not None:
            x_c, r_c = np.asarray(temp_ev["x"]), np.asarray(temp_ev["y"])
        else:
            x_c, r_c = ds.temperature_C[ctrl.kept], ctrl.residual_nT[:, ctrl.kept]
        idx = _decimate(len(x_c), np.ones(len(x_c), bool))
        for s in range(ns):
            fig.add_trace(go.Scattergl(x=x_c[idx], y=r_c[s, idx], mode="markers", opacity=0.45,
                                       marker={"size": 3, "color": SENSOR_COLOURS[s % 4]}, name=f"sensor {s + 1}",
                                       legendgroup=f"s{s}", showlegend=False), row=row_temp, col=1)
    direction = ev.get("direction") or {}
    per = direction.get("per_sensor") if isinstance(direction, dict) else None
    if per:
        for s, sh in enumerate(per):
            fig.add_trace(go.Bar(x=np.asarray(sh["degree"]), y=np.asarray(sh["rms_nT"]),
                                 marker={"color": SENSOR_COLOURS[s % 4]}, name=f"sensor {s + 1}",
                                 legendgroup=f"s{s}", showlegend=False), row=row_sh, col=1)
    else:
        # in paper coordinates: the page's plotly.js reads "x3 domain" references as data coordinates
        y_domain = fig.layout[f"yaxis{row_sh}"].domain
        fig.add_annotation(text="press Diagnose", xref="paper", yref="paper", x=0.5,
                           y=0.5 * (y_domain[0] + y_domain[1]), showarrow=False)
    labels = [f"s{s + 1}" for s in range(ns)]
    fig.add_trace(go.Bar(x=labels, y=ctrl.rms_per_sensor_nT(), name="total-field RMS",
                         marker={"color": list(SENSOR_COLOURS[:ns])}, showlegend=False), row=row_sensors, col=1)
    sensors = ev.get("sensors") or {}
    if sensors and sensors.get("difference_rms_nT") is not None:
        fig.add_trace(go.Scatter(x=labels, y=np.asarray(sensors["difference_rms_nT"]), mode="markers",
                                 marker={"symbol": "diamond", "size": 10, "color": "black"},
                                 name="difference from the common mode"), row=row_sensors, col=1)
    floor = ctrl.floor_nT()
    if floor:
        fig.add_hline(y=floor, line_dash="dash", line_color="#d62728", row=row_sensors, col=1)
    fig.update_yaxes(title_text="nT")  # every panel is in nT
    fig.update_xaxes(title_text=x_label, row=row_time, col=1)
    if row_temp is not None:
        fig.update_xaxes(title_text="degC", row=row_temp, col=1)
    fig.update_xaxes(title_text="degree", row=row_sh, col=1)
    # the top margin keeps the first title clear of plotly's toolbar
    fig.update_layout(height=275 * len(titles), margin={"l": 55, "r": 10, "t": 60, "b": 30},
                      legend={"orientation": "h", "y": -0.12}, template="plotly_white", barmode="group")
    return fig
