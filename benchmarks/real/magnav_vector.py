"""A real aircraft (issue 29): vector calibration of a cabin fluxgate of the MagNav challenge's survey aircraft
from its INS attitude and IGRF, calibrated on one compensation segment and applied to segments flown later,
beside the total-field fit.

The data (not in this repository; the licence - the Air Force Acceptable Use Agreement of MagNav.jl's
``readmes/DATA_SHARING_AGREEMENT.md`` - allows non-profit research use and forbids redistribution): the SGL 2020
training flights, ``Flt1006_train.h5`` (6 July 2020; compensation boxes at 5182 m, line 1006.04; at 3048 m, 1006.06;
at 400 m over Eastern Ontario, 1006.08). MagNav.jl downloads them as the lazy artifact ``sgl_2020_train``
(``Artifacts.toml``: ``sgl_2020_train_v3.tar.gz``, sha256 9197872972a6f61dc755911e20324d0596e31e36eddd74cb02fdc6c883dc9e7b);
the DOI is 10.5281/zenodo.4271803. Put the file at ``benchmarks/real/data/Flt1006_train.h5`` (git-ignored)::

    pip install h5py
    python benchmarks/real/magnav_vector.py                       # Flux D, calibrate on 1006.04, test 1006.06, .08
    python benchmarks/real/magnav_vector.py --flux b --cal 1006.06 --test 1006.04 1006.08

What the file holds (``readmes/sgl_2020_fields_readme.txt``), at 10 Hz: the fluxgates ``flux_{a,b,c,d}_{x,y,z}``
(nT; A, C and D in the cabin, B at the base of the tail stinger), the INS attitude ``ins_roll, ins_pitch, ins_yaw``
(deg; "yaw clockwise from north, then pitch up, then roll to starboard": the aerospace ZYX convention magcal
reads), the position ``lat, lon`` (deg) and ``utm_z`` (m above the WGS-84 ellipsoid), ``year``, ``doy``, ``tt`` (s
past midnight UTC), ``line`` (the segment) and ``mag_1_c`` (the tail stinger's professionally compensated scalar
field, nT: it holds the crustal anomaly and the daily variation that IGRF lacks).

Printed per test segment: the world (north-east-down) components' RMS per component against IGRF (the vector fit;
the floor is the INS attitude error times the field plus IGRF's error - the anomaly - which the components
cannot get below), and |B| against ``mag_1_c`` and against IGRF for the raw fluxgate, the vector fit and the
total-field fit (magcal's ML fit with ``mag_1_c`` as the per-sample reference).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import sys
import warnings
from pathlib import Path

import numpy as np

from magcal.checks.reference import resolve_vector_reference
from magcal.data.dataset import Dataset
from magcal.fitting.pipeline import calibrate
from magcal.fitting.vector import fit_vector

HERE = Path(__file__).resolve().parent
DEFAULT_FILE = HERE / "data" / "Flt1006_train.h5"


def read_segments(path, lines, flux="d", current=None):
    """One :class:`~magcal.data.dataset.Dataset` per line number (e.g. ``1006.04``) of a MagNav HDF5 file.

    Readings: ``flux_<flux>_{x,y,z}`` (nT); ``time_s`` = ``tt``; ``ref_total_nT`` = ``mag_1_c``; extra columns
    ``roll_deg, pitch_deg, yaw_deg`` (INS), ``lat, lon, alt_m`` (``utm_z``, WGS-84 height) and, with ``current``
    (a field name such as ``cur_strb``), ``current_A``. The date goes to ``metadata['date']``.
    """
    import h5py

    out = {}
    with h5py.File(path, "r") as h5:

        def col(name):
            if name not in h5:
                raise SystemExit(f"{path}: no field {name!r} (see readmes/sgl_2020_fields_readme.txt)")
            return np.asarray(h5[name][()], dtype=float).ravel()

        line = col("line")
        year, doy = int(col("year")[0]), int(col("doy")[0])
        date = (_dt.date(year, 1, 1) + _dt.timedelta(days=doy - 1)).isoformat()
        cols = {
            "x": col(f"flux_{flux}_x"),
            "y": col(f"flux_{flux}_y"),
            "z": col(f"flux_{flux}_z"),
            "tt": col("tt"),
            "mag_1_c": col("mag_1_c"),
            "roll_deg": col("ins_roll"),
            "pitch_deg": col("ins_pitch"),
            "yaw_deg": col("ins_yaw"),
            "lat": col("lat"),
            "lon": col("lon"),
            "alt_m": col("utm_z"),
        }
        if current:
            cols["current_A"] = col(current)
    for value in lines:
        keep = np.isclose(line, float(value), atol=1e-4)
        keep &= np.all([np.isfinite(v) for v in cols.values()], axis=0)
        if keep.sum() < 100:
            raise SystemExit(f"{path}: line {value} has {int(keep.sum())} usable samples; give another --cal/--test")
        c = {k: v[keep] for k, v in cols.items()}
        extra = {k: c[k] for k in ("roll_deg", "pitch_deg", "yaw_deg", "lat", "lon", "alt_m")}
        if current:
            extra["current_A"] = c["current_A"]
        out[value] = Dataset(
            readings_nT=np.column_stack([c["x"], c["y"], c["z"]])[None],
            time_s=c["tt"],
            ref_total_nT=c["mag_1_c"],
            extra=extra,
            metadata={"date": date, "line": str(value), "flux": flux},
            source=f"{Path(path).name} line {value}",
        )
    return out


def study(segments, cal_line, test_lines, terms=None):
    """Fit both calibrations on ``cal_line`` and score them on ``test_lines``; returns a dict of figures."""
    cal = segments[cal_line]
    date = cal.metadata["date"]
    ref = resolve_vector_reference(cal, reference="igrf", date=date)
    vec = fit_vector(cal, ref, terms=terms, reference_total_nT=cal.ref_total_nT)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scalar = calibrate(cal.replace(reference_total_nT=None))
    out = {
        "calibration": {
            "line": cal_line,
            "n": cal.n_samples,
            "vector": vec.to_dict(),
            "scalar_rms_nT": float(scalar.rms_nT),
            "scalar_warnings": list(scalar.remarks) + [str(w.message) for w in caught],
            "tilt_deg": [float(np.ptp(cal.extra["roll_deg"])), float(np.ptp(cal.extra["pitch_deg"]))],
        },
        "tests": {},
    }
    for line in [cal_line] + list(test_lines):
        ds = segments[line]
        igrf = resolve_vector_reference(ds, reference="igrf", date=date).ned_nT
        f_igrf = np.linalg.norm(igrf, axis=1)
        world = vec.calibration.world(ds)[0]
        f_vec = np.linalg.norm(world, axis=1)
        f_sc = np.linalg.norm(scalar.calibration.correct(ds)[0], axis=1)
        f_raw = np.linalg.norm(ds.readings_nT[0], axis=1)

        def rms(v):
            return float(np.sqrt(np.mean(np.asarray(v, dtype=float) ** 2)))

        out["tests"][line] = {
            "n": ds.n_samples,
            "world_rms_nT": rms(world - igrf),
            "world_rms_ned_nT": np.sqrt(np.mean((world - igrf) ** 2, axis=0)).tolist(),
            "F_vs_mag1c": {
                "raw": rms(f_raw - ds.ref_total_nT),
                "vector": rms(f_vec - ds.ref_total_nT),
                "scalar": rms(f_sc - ds.ref_total_nT),
            },
            "F_vs_igrf": {"raw": rms(f_raw - f_igrf), "vector": rms(f_vec - f_igrf), "scalar": rms(f_sc - f_igrf)},
            "mag1c_minus_igrf_rms_nT": rms(ds.ref_total_nT - f_igrf),
        }
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--file", default=str(DEFAULT_FILE))
    parser.add_argument("--flux", default="d", choices=("a", "b", "c", "d"))
    parser.add_argument("--cal", default="1006.04")
    parser.add_argument("--test", nargs="+", default=["1006.06", "1006.08"])
    parser.add_argument("--current", default=None, help="a current field (e.g. cur_strb) for the current term")
    args = parser.parse_args(argv)
    if not Path(args.file).exists():
        print(f"{args.file}: not found; see this script's docstring for how to obtain it", file=sys.stderr)
        return 2
    segments = read_segments(args.file, [args.cal] + args.test, args.flux, args.current)
    r = study(segments, args.cal, args.test)
    c = r["calibration"]
    print(
        f"Flux {args.flux.upper()}, calibrated on line {c['line']} ({c['n']} samples, roll span {c['tilt_deg'][0]:.0f} "
        f"deg, pitch span {c['tilt_deg'][1]:.0f} deg)"
    )
    s = c["vector"]["sensors"][0]
    print(
        f"  vector fit: mounting {s['mounting_right_angle']}, {s['mounting_angle_off_deg']:.2f} deg off; in-sample "
        f"vector RMS {s['rms_vector_nT']:.1f} nT, total field {s['rms_total_field_nT']:.1f} nT; attitude+model "
        f"error {s['attitude_noise_deg']:.3f} deg"
    )
    print(f"  total-field fit: in-sample RMS {c['scalar_rms_nT']:.1f} nT; warnings: {len(c['scalar_warnings'])}")
    print(
        "line       N   world RMS vs IGRF (N, E, D)       |B| vs mag_1_c: raw / vector / scalar   |B| vs IGRF: "
        "raw / vector / scalar   mag_1_c - IGRF"
    )
    for line, t in r["tests"].items():
        n, e, d = t["world_rms_ned_nT"]
        fm, fi = t["F_vs_mag1c"], t["F_vs_igrf"]
        print(
            f"{line:8s} {t['n']:6d}  {t['world_rms_nT']:7.1f} ({n:.0f}, {e:.0f}, {d:.0f})        "
            f"{fm['raw']:8.1f} / {fm['vector']:6.1f} / {fm['scalar']:6.1f}       "
            f"{fi['raw']:8.1f} / {fi['vector']:6.1f} / {fi['scalar']:6.1f}     {t['mag1c_minus_igrf_rms_nT']:6.1f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
