"""Vector calibration on real vehicle logs (issue 29): calibrate on one part, apply to a later part or flight.

The data: public ArduPilot DataFlash logs with the compass (``MAG``), the attitude (``ATT``) and the GPS (3D fixes,
for IGRF along the track on the log's own date), fetched by ``fetch.py`` into ``data/raw/`` (git-ignored)::

    python benchmarks/real/fetch.py --mirror /work/.mirror     # or without --mirror to download
    pip install pymavlink ppigrf
    python benchmarks/real/vector_logs.py                      # about a minute

Vehicles (see ``fetch.py`` for the sources):

* **copter**: an Erle-Copter (ArduCopter 3.2, PXF board, internal compass, DCM attitude), flight 218 of 2014-12-05
  near Vitoria-Gasteiz: calibrated on its first 60 %, applied to its last 40 %, and to the same vehicle's flights
  of 2014-12-15 (``ap_pxf_flip``) and 2014-12-22 (``ap_erle_37``; the logs share the compass offsets the firmware
  held). A copter tilts more than an aircraft (here roll/pitch mostly within +-15 deg, up to 50 deg).
* **plane**: an F3A aerobatic model aircraft (ArduPlane 4.x, external compass, EKF3 attitude) carried around its
  flying field near Bristol on 2025-01-03 (logs 3 and 4, 49 s and 99 s, level within +-22 deg): calibrated on one
  log, applied to the other.

Samples with roll or pitch beyond :data:`MAX_TILT_DEG` are left out of every part (the copter logs end upside down
after a turnover). Each part is written as a magcal CSV (``data/vector_logs/``, git-ignored) and everything runs
through the command line as a user would: ``magcal calibrate part.csv --mode vector --reference igrf
--platform-terms none -o vec.json`` (IGRF along the ``lat, lon, alt_m`` columns, on the ``date`` the reader took
from the GPS), ``magcal calibrate part.csv --mode scalar --reference igrf --lat .. --lon ..`` (the total-field fit of
the same samples) and ``magcal apply cal.json test.csv``.

Printed per test part, RMS against IGRF in nT: the north, east and down components and |B| for the raw field (the
compass as the log holds it with the firmware's calibration undone, rotated by the attitude: ArduPilot logs the
compass in the body frame), the vector fit (``s1n_cal, s1e_cal, s1d_cal`` from ``apply``) and the total-field fit
(its corrected vector rotated by the attitude; refused here: a level vehicle's field directions fill a cone).
Then the platform terms (``--platform-terms eddy``, ``current`` - the CTUN throttle - and both) against none, on
the same held-out parts: terms describing one recording must not make the next one worse.

Caveats: the attitude's yaw comes from an estimator that uses this compass (DCM or EKF with the firmware's own
calibration), so heading errors of that calibration are partly in the "truth"; IGRF lacks the crustal field
and the daily variation (tens to hundreds of nT); GPS altitude is above mean sea level (IGRF takes it as above the
ellipsoid: ~50 m, well under 1 nT).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magcal.checks.reference import igrf_total_nT, resolve_vector_reference
from magcal.cli import main as magcal_main
from magcal.data.attitude import attitude
from magcal.data.io import write_csv
from magcal.data.logs import read_log
from magcal.fitting.vector import fit_vector

HERE = Path(__file__).resolve().parent
RAW_DIR = HERE / "data" / "raw"
WORK_DIR = HERE / "data" / "vector_logs"
OUT_JSON = HERE.parent / "out" / "vector_logs.json"

#: Samples tilted further than this (roll or pitch, deg) are left out: a turnover, a crash, a vehicle on its back.
MAX_TILT_DEG = 60.0

#: Platform-term sets compared on the held-out parts (``--platform-terms``).
TERM_SETS = ("none", "eddy", "current", "eddy,current")


@dataclass(frozen=True)
class Part:
    """A stretch of a log: ``start`` to ``stop`` as fractions of its time span."""

    raw: str
    start: float
    stop: float
    label: str


@dataclass(frozen=True)
class Case:
    name: str
    vehicle: str
    cal: Part
    tests: tuple


CASES = (
    Case(
        "copter",
        "Erle-Copter (ArduCopter 3.2, PXF, internal compass, DCM attitude), Vitoria-Gasteiz, Dec 2014",
        Part("ap_erle_218.bin", 0.0, 0.6, "flight 218 (2014-12-05), first 60 %"),
        (
            Part("ap_erle_218.bin", 0.6, 1.0, "flight 218, last 40 %"),
            Part("ap_pxf_flip.bin", 0.0, 1.0, "flight 16 (2014-12-15)"),
            Part("ap_erle_37.bin", 0.0, 1.0, "flight 37 (2014-12-22)"),
        ),
    ),
    Case(
        "copter, reversed",
        "the same copter, calibrated on the last 40 % of flight 218 (its 30-50 deg manoeuvres) instead",
        Part("ap_erle_218.bin", 0.6, 1.0, "flight 218, last 40 %"),
        (
            Part("ap_erle_218.bin", 0.0, 0.6, "flight 218, first 60 %"),
            Part("ap_pxf_flip.bin", 0.0, 1.0, "flight 16 (2014-12-15)"),
            Part("ap_erle_37.bin", 0.0, 1.0, "flight 37 (2014-12-22)"),
        ),
    ),
    Case(
        "plane",
        "F3A model aircraft (ArduPlane 4.x, external compass, EKF3), carried on its field near Bristol, 2025-01-03",
        Part("pfc_center_0003.bin", 0.0, 1.0, "log 3 (49 s)"),
        (Part("pfc_pilot_0004.bin", 0.0, 1.0, "log 4 (99 s, next)"),),
    ),
    Case(
        "plane, reversed",
        "the same aircraft, calibrated on log 4 and applied to log 3",
        Part("pfc_pilot_0004.bin", 0.0, 1.0, "log 4 (99 s)"),
        (Part("pfc_center_0003.bin", 0.0, 1.0, "log 3 (49 s, before)"),),
    ),
)


def _rms(values, axis=None):
    return np.sqrt(np.mean(np.asarray(values, dtype=float) ** 2, axis=axis))


def cli(*argv):
    """``magcal ARGV`` in this process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            rc = magcal_main([str(a) for a in argv])
        except SystemExit as exc:  # argparse refused the arguments
            rc = exc.code if isinstance(exc.code, int) else 2
    here = str(HERE) + "/"  # messages name the files relative to benchmarks/real
    return rc, out.getvalue().replace(here, ""), err.getvalue().replace(here, "")


def read_part(part: Part, raw_dir: Path = RAW_DIR, undo_calibration=True):
    """The dataset of a part of a log (tilts beyond :data:`MAX_TILT_DEG` left out) and the reader's notes; with
    ``undo_calibration=False`` the field as the firmware corrected it."""
    path = raw_dir / part.raw
    if not path.exists():
        raise SystemExit(f"{path}: missing; run benchmarks/real/fetch.py first (see this script's docstring)")
    ds = read_log(path, name=part.raw, undo_calibration=undo_calibration, warn=False)
    notes = ds.notes
    t = ds.time_s
    lo, hi = t[0] + part.start * (t[-1] - t[0]), t[0] + part.stop * (t[-1] - t[0])
    keep = (t >= lo) & (t < hi) if part.stop < 1.0 else (t >= lo)
    keep &= np.abs(ds.extra["att_roll_deg"]) <= MAX_TILT_DEG
    keep &= np.abs(ds.extra["att_pitch_deg"]) <= MAX_TILT_DEG
    if "lat" not in ds.extra:
        raise SystemExit(f"{part.raw}: no GPS fix in the log; IGRF along the track is not possible")
    return ds.subset(np.flatnonzero(keep)), [str(n) for n in notes]


def _write_part(ds, name: str, work: Path) -> Path:
    work.mkdir(parents=True, exist_ok=True)
    path = work / f"{name}.csv"
    write_csv(path, ds, metadata={"units": "nT"})
    return path


def _applied(cal_json: Path, test_csv: Path, out_csv: Path):
    rc, _, err = cli("apply", cal_json, test_csv, "-o", out_csv)
    if rc != 0:
        raise RuntimeError(f"magcal apply {cal_json.name} {test_csv.name}: {err.strip()}")
    with open(out_csv, encoding="utf-8") as fh:
        rows = [line for line in fh if not line.startswith("#")]
    header = rows[0].strip().split(",")
    values = np.loadtxt(rows[1:], delimiter=",", ndmin=2)
    return {name: values[:, k] for k, name in enumerate(header)}


def _scores(world, ned):
    """RMS per north, east, down component and of |B| against IGRF (nT), and the median heading offset (deg) of the
    horizontal field against IGRF's (positive: the measured field points east of IGRF's)."""
    offset = np.degrees(np.arctan2(world[:, 1], world[:, 0]) - np.arctan2(ned[:, 1], ned[:, 0]))
    return {
        "ned_rms_nT": _rms(world - ned, axis=0).tolist(),
        "F_rms_nT": float(_rms(np.linalg.norm(world, axis=1) - np.linalg.norm(ned, axis=1))),
        "heading_offset_deg": float(np.median((offset + 180.0) % 360.0 - 180.0)),
    }


def lag_scan(ds, reference, shifts_s=(-0.2, -0.1, -0.05, 0.0, 0.05, 0.1, 0.2)):
    """In-sample vector residual RMS (nT) of the vector fit with the compass readings shifted in time by each shift
    (s; positive: the reading of ``t + shift`` paired with the attitude of ``t``): the alignment of MAG and ATT."""
    t, y = ds.time_s, np.asarray(ds.readings_nT[0], dtype=float)
    out = {}
    for shift in shifts_s:
        shifted = np.column_stack([np.interp(t + shift, t, y[:, j]) for j in range(3)])
        fit = fit_vector(ds.replace(readings_nT=shifted[None]), reference, terms=[], warn=False)
        out[f"{shift:+.2f}"] = fit.sensors[0].rms_vector_nT
    return out


def declination_setting(raw: Path):
    """``COMPASS_DEC`` (deg) and ``COMPASS_AUTODEC`` of an ArduPilot log (the last values), or None."""
    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(raw))
    found = {}
    with contextlib.redirect_stdout(io.StringIO()):
        while (m := log.recv_match(type=["PARM"])) is not None:
            if m.Name in ("COMPASS_DEC", "COMPASS_AUTODEC"):
                found[m.Name] = float(m.Value)
    if "COMPASS_DEC" not in found:
        return None
    return {"dec_deg": float(np.degrees(found["COMPASS_DEC"])), "autodec": found.get("COMPASS_AUTODEC")}


def study_case(case: Case, raw_dir: Path = RAW_DIR, work: Path = WORK_DIR) -> dict:
    """Calibrate on ``case.cal`` through the command line, apply to each test part, score against IGRF."""
    slug = case.name.replace(",", "").replace(" ", "_")
    cal_ds, cal_notes = read_part(case.cal, raw_dir)
    cal_csv = _write_part(cal_ds, f"{slug}_cal", work)
    out = {
        "vehicle": case.vehicle,
        "calibration_part": case.cal.label,
        "n_cal": cal_ds.n_samples,
        "date": cal_ds.metadata.get("date"),
        "reader_notes": cal_notes,
        "roll_range_deg": [float(np.min(cal_ds.extra["att_roll_deg"])), float(np.max(cal_ds.extra["att_roll_deg"]))],
        "pitch_range_deg": [
            float(np.min(cal_ds.extra["att_pitch_deg"])),
            float(np.max(cal_ds.extra["att_pitch_deg"])),
        ],
        "channels": sorted(k for k in cal_ds.extra if k in ("throttle", "current_A", "lat")),
        "declination": declination_setting(raw_dir / case.cal.raw),
        "lag_scan_rms_nT": lag_scan(cal_ds, resolve_vector_reference(cal_ds, reference="igrf")),
        "vector": {},
        "tests": [],
    }
    cal_files = {}
    for terms in TERM_SETS:
        if "current" in terms and "throttle" not in cal_ds.extra and "current_A" not in cal_ds.extra:
            continue
        target = work / f"{slug}_vector_{terms.replace(',', '+')}.json"
        args = ["calibrate", cal_csv, "--mode", "vector", "--reference", "igrf", "--platform-terms", terms]
        rc, stdout, err = cli(*args, "-o", target, "--json")
        if rc != 0:
            out["vector"][terms] = {"refused": err.strip()}
            continue
        doc = json.loads(stdout)
        s = doc["sensors"][0]
        out["vector"][terms] = {
            "mounting": s["mounting_right_angle"],
            "mounting_off_deg": s["mounting_angle_off_deg"],
            "orientation_margin": s["orientation_margin"],
            "rms_vector_nT": s["rms_vector_nT"],
            "rms_total_field_nT": s["rms_total_field_nT"],
            "attitude_noise_deg": s["attitude_noise_deg"],
            "warnings": doc.get("warnings", []),
            "validation": doc.get("validation"),
            "reference": doc["reference"]["text"],
            "bias_nT": doc["calibration"]["sensors"][0]["bias_nT"],
            "bias_sd_nT": s["bias_sd_nT"],
            "mounting_sd_deg": s["mounting_sd_deg"],
            "sd_widening": s.get("sd_widening"),
            "determined": s.get("determined"),
        }
        cal_files[terms] = target
    lat, lon = float(np.median(cal_ds.extra["lat"])), float(np.median(cal_ds.extra["lon"]))
    alt_km = float(np.median(cal_ds.extra["alt_m"])) / 1000.0
    scalar_json = work / f"{slug}_scalar.json"
    args = ["calibrate", cal_csv, "--mode", "scalar", "--reference", "igrf", "--lat", lat, "--lon", lon]
    rc, stdout, err = cli(*args, "--alt-km", alt_km, "-o", scalar_json, "--json")
    out["scalar"] = (
        {"refused": err.strip().splitlines()[-1] if err.strip() else f"exit {rc}"}
        if rc != 0
        else {"rms_nT": json.loads(stdout).get("rms_nT"), "warnings": json.loads(stdout).get("warnings", [])}
    )
    total_nT, _ = igrf_total_nT(lat, lon, alt_km, cal_ds.metadata.get("date"))
    rc, stdout, err = cli("diagnose", cal_csv, "--reference", f"{total_nT:.1f}", "--json")
    out["diagnose"] = (
        {"refused": err.strip().splitlines()[-1] if err.strip() else f"exit {rc}"}
        if rc != 0
        else {"recommended": json.loads(stdout).get("recommended")}
    )
    for k, part in enumerate(case.tests):
        ds, notes = read_part(part, raw_dir)
        test_csv = _write_part(ds, f"{slug}_test{k}", work)
        ned = resolve_vector_reference(ds, reference="igrf").ned_nT
        rotation = attitude(ds)
        row = {"part": part.label, "n": ds.n_samples, "date": ds.metadata.get("date"), "reader_notes": notes}
        row["raw"] = _scores(rotation.apply(np.array(ds.readings_nT[0])), ned)  # (scipy refuses read-only)
        logged, _ = read_part(part, raw_dir, undo_calibration=False)
        if logged.n_samples == ds.n_samples:  # the firmware's own calibration, as the log holds it
            row["firmware"] = _scores(rotation.apply(np.array(logged.readings_nT[0])), ned)
        igrf_dec = np.degrees(np.arctan2(ned[:, 1], ned[:, 0]))
        row["igrf_declination_deg"] = float(np.median(igrf_dec))
        for terms, cal_json in cal_files.items():
            table = _applied(cal_json, test_csv, work / f"{slug}_test{k}_{terms.replace(',', '+')}.csv")
            world = np.column_stack([table["s1n_cal"], table["s1e_cal"], table["s1d_cal"]])
            row[f"vector[{terms}]"] = _scores(world, ned)
        if "refused" not in out["scalar"]:
            table = _applied(scalar_json, test_csv, work / f"{slug}_test{k}_scalar.csv")
            body = np.column_stack([table["s1x_cal"], table["s1y_cal"], table["s1z_cal"]])
            row["scalar"] = _scores(rotation.apply(body), ned)
        out["tests"].append(row)
    return out


def _fmt(scores):
    n, e, d = scores["ned_rms_nT"]
    return f"{n:6.0f} {e:6.0f} {d:6.0f} {scores['F_rms_nT']:6.0f} {scores['heading_offset_deg']:+6.1f}"


def report(results: dict) -> str:
    lines = []
    for name, r in results.items():
        lines.append(
            f"\n== {name}: {r['vehicle']}\n   calibrated on {r['calibration_part']}: {r['n_cal']} samples, "
            f"date {r['date']}, roll {r['roll_range_deg'][0]:.0f}..{r['roll_range_deg'][1]:.0f} deg, pitch "
            f"{r['pitch_range_deg'][0]:.0f}..{r['pitch_range_deg'][1]:.0f} deg"
        )
        dec = r.get("declination")
        if dec:
            lines.append(f"   the vehicle's COMPASS_DEC {dec['dec_deg']:.2f} deg (AUTODEC {dec['autodec']:g})")
        scan = ", ".join(f"{k} s: {v:.0f}" for k, v in r["lag_scan_rms_nT"].items())
        lines.append(f"   MAG vs ATT alignment, in-sample vector RMS (nT) with the compass shifted by {scan}")
        v = r["vector"].get("none", {})
        if "refused" in v:
            lines.append(f"   vector fit refused: {v['refused']}")
        elif v:
            lines.append(
                f"   vector fit: mounting {v['mounting']}, {v['mounting_off_deg']:.1f} deg off (next right angle "
                f"{v['orientation_margin']:.2f}x worse); in-sample vector {v['rms_vector_nT']:.0f} nT per component, "
                f"|B| {v['rms_total_field_nT']:.0f} nT; attitude + model error {v['attitude_noise_deg']:.2f} deg"
            )
            lines.append(
                f"     bias {np.round(v['bias_nT']).astype(int).tolist()} nT, sd "
                f"{np.round(v['bias_sd_nT']).astype(int).tolist()} nT, mounting sd "
                f"{np.round(v['mounting_sd_deg'], 2).tolist()} deg (widened {v['sd_widening']:.1f}x for residuals "
                f"correlated in time); determined: {v['determined']}"
            )
            lines += [f"     note: {w[:300]}" for w in v["warnings"]]
        sc = r["scalar"]
        lines.append(
            "   total-field fit: "
            + (f"refused: {sc['refused'][:250]}" if "refused" in sc else f"RMS {sc['rms_nT']:.0f} nT")
        )
        dg = r["diagnose"]
        lines.append(
            "   diagnose: "
            + (f"refused: {dg['refused'][:120]}" if "refused" in dg else f"recommends {dg['recommended']}")
        )
        lines.append(
            "   test part (RMS vs IGRF, nT; heading = median offset of the horizontal field, deg)\n"
            "   " + " " * 42 + "     N      E      D    |B| heading"
        )
        for t in r["tests"]:
            lines.append(f"   {t['part']:34s} {t['n']:5d}  (IGRF declination {t['igrf_declination_deg']:+.2f} deg)")
            for key, label in (("raw", "raw"), ("firmware", "firmware's calibration"), ("vector[none]", "vector fit")):
                if key in t:
                    lines.append(f"     {label:38s} {_fmt(t[key])}")
            if "scalar" in t:
                lines.append(f"     {'total-field fit':38s} {_fmt(t['scalar'])}")
        terms = [k for k in r["vector"] if k != "none" and "refused" not in r["vector"][k]]
        if terms:
            lines.append("   platform terms, held out (world RMS over N, E, D / |B| RMS, nT):")
            for t in r["tests"]:
                cells = []
                for k in ["none", *terms]:
                    sc_ = t[f"vector[{k}]"]
                    cells.append(f"{k}: {_rms(sc_['ned_rms_nT']):.0f} / {sc_['F_rms_nT']:.0f}")
                lines.append(f"     {t['part']:34s} " + "; ".join(cells))
            val = r["vector"][terms[-1]].get("validation")
            if val:
                rows = "; ".join(
                    f"{', '.join(x['terms']) or 'none'}: {x['held_vector_nT']:.0f} / {x['held_total_nT']:.0f}"
                    for x in val["rows"]
                )
                lines.append(f"     magcal calibrate's own held-out blocks of the calibration part: {rows}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--raw-dir", type=Path, default=RAW_DIR)
    parser.add_argument("--json", type=Path, default=OUT_JSON, help=f"figures written here (default {OUT_JSON})")
    parser.add_argument("cases", nargs="*", help=f"cases to run (default all: {', '.join(c.name for c in CASES)})")
    args = parser.parse_args(argv)
    chosen = [c for c in CASES if not args.cases or c.name in args.cases]
    results = {c.name: study_case(c, args.raw_dir) for c in chosen}
    print(report(results))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
