"""The vector diagnosis's advice on every real record with attitude: judged or not, and what it does to the next
part of the record and to the next flight, per world component.

For each record: ``diagnose_vector`` (what ``magcal diagnose FILE [--also NEXT]`` runs) gives a verdict and its advice
(the effects to add). The advice is then checked as a user would meet it:

* **next part**: the base model and the advice fitted on the first 70 % of the fitted samples, applied to the last
  30 % as ``magcal apply`` applies them (record-only terms dropped); RMS of the north, east, down and |B| residuals
  of every sensor, base -> advice, and the largest rise of one component (must not exceed 10 %);
* **next flight**: the same vehicle's or instrument's next record (``--also``), both fitted on the whole record;
* **applies**: the advice fitted on the whole record leaves every sensor determined and gives finite world
  components on the next flight.

The records (each one that is present; the raw logs and the mirror's files are optional):

* flight-controller logs in ``data/``: ``px4_sample`` (98 Hz, no GPS), ``ap_erlebrain3``, ``ap_pxf_rpi`` (no GPS)
  and ``ap_pxf_flip`` (GPS: IGRF along the track on the log's date); without a GPS the field vector is the median
  of the firmware's own corrected field turned into north-east-down (``s1x_logged..``, or the readings where the
  firmware already corrected them), an estimate outside the vector fit;
* the raw logs read by ``vector_logs.py`` (``data/raw/``): the Erle-Copter's flight 218 (next: flight 16) and the
  F3A aircraft's logs 3 and 4 (each the other's next flight);
* PX4's ``sample_px4_events.ulg`` (pyulog's test log in ``/work/.mirror/PX4+pyulog``): sensor_mag at 1 Hz;
* MagNav.jl's ``test_data_traj.mat`` (a 100-s simulated trajectory at 1 Hz, IGRF along it);
* the same at 1 Hz: ``px4_sample``, flight 218 and BROAD's trial 02 (its first 70 s) with one sample a second, as a
  compass logged by PX4's default profile would leave them;
* BROAD motion-capture trials ``data/broad_NN.csv`` (``broad.py``): the lab field of the header line as
  ``--reference-vector``; the next flight is the next trial of the same group (undisturbed, tapped, magnet near the
  path, magnet attached, office); every ``--every``-th sample (default 4: 18 Hz).

Usage::

    python benchmarks/real/advice_table.py                    # every record present (about 20 minutes)
    python benchmarks/real/advice_table.py --only broad_28 px4
    PYTHONPATH=/path/to/an/older/checkout python benchmarks/real/advice_table.py   # the same table, older code
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magcal.checks.reference import resolve_vector_reference
from magcal.core.errors import CalibrationError, MagcalError
from magcal.data.attitude import attitude_rows
from magcal.data.io import read_csv
from magcal.diagnosis.vector import LATER_FRACTION, Flight, diagnose_vector
from magcal.fitting.vector import fit_vector

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"
RAW = DATA / "raw"
MIRROR = Path("/work/.mirror")

#: The largest rise of one world component of the next part or flight the advice may cause.
MAX_RISE = 0.10

#: BROAD's groups of trials (the next flight of a trial is the next trial of its group).
BROAD_GROUPS = ((1, 23), (24, 27), (28, 31), (32, 36), (37, 39))

COMPONENTS = ("N", "E", "D", "\\|B\\|")  # |B| escaped: the table is markdown


@dataclass
class Record:
    """A record, its field vector and its next flight (or None)."""

    name: str
    dataset: object
    reference: object
    next_name: str | None = None
    next_dataset: object = None
    next_reference: object = None


# ---- readers ---------------------------------------------------------------------------------------------------


def _quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kwargs)


def _estimated_field(ds):
    """The median of the firmware's corrected field (``s1x_logged..`` or the readings) turned into NED, nT."""
    found = attitude_rows(ds)
    assert found is not None
    rotation, have = found
    logged = [f"s1{a}_logged" for a in "xyz"]
    body = (
        np.column_stack([ds.extra[c] for c in logged])
        if all(c in ds.extra for c in logged)
        else np.asarray(ds.readings_nT[0])
    )
    world = rotation[have].apply(body[have])
    return ",".join(f"{v:.1f}" for v in np.nanmedian(world, axis=0))


def _csv_record(name):
    ds = _quiet(read_csv, DATA / f"{name}.csv")
    if "lat" in ds.extra:
        ds = ds.subset(np.flatnonzero(_level(ds)))
        return Record(name, ds, resolve_vector_reference(ds, "igrf"))
    return Record(name + " (field estimated)", ds, resolve_vector_reference(ds, vector=_estimated_field(ds)))


def _level(ds, max_tilt_deg=60.0):
    """Samples within ``max_tilt_deg`` of level (a copter's log may end upside down after a turnover)."""
    keep = np.ones(ds.n_samples, bool)
    for c in ("att_roll_deg", "att_pitch_deg"):
        if c in ds.extra:
            keep &= np.abs(np.asarray(ds.extra[c])) <= max_tilt_deg
    return keep


def _raw(name):
    sys.path.insert(0, str(HERE))
    from vector_logs import Part, read_part

    ds, _ = _quiet(read_part, Part(name, 0.0, 1.0, name), RAW)
    return ds, resolve_vector_reference(ds, "igrf")


def _raw_pair(name, next_name):
    ds, ref = _raw(name)
    nxt, nref = _raw(next_name)
    return Record(name, ds, ref, next_name, nxt, nref)


def _mirror_file(repo, path, tmp):
    out = tmp / Path(path).name
    blob = subprocess.run(
        ["git", "-C", str(MIRROR / repo / "repo"), "show", f"HEAD:{path}"], capture_output=True, check=False
    )
    if blob.returncode != 0:
        return None
    out.write_bytes(blob.stdout)
    return out


def _px4_events(tmp):
    from magcal.data.logs import read_log

    path = _mirror_file("PX4+pyulog", "test/sample_px4_events.ulg", tmp)
    if path is None:
        return None
    ds = _quiet(read_log, path, warn=False)
    return Record("px4 sample_px4_events (1 Hz)", ds, resolve_vector_reference(ds, "igrf"))


def _magnav_traj(tmp):
    from scipy.io import loadmat

    from magcal.data.dataset import Dataset

    path = _mirror_file("MIT-AI-Accelerator+MagNav.jl", "test/test_data/test_data_traj.mat", tmp)
    if path is None:
        return None
    m = loadmat(path)["traj"][0, 0]

    def col(k):
        return np.asarray(m[k], dtype=float).ravel()

    from scipy.spatial.transform import Rotation

    cnb = np.asarray(m["Cnb"], dtype=float).transpose(2, 0, 1)  # body -> navigation (NED), per sample
    q = Rotation.from_matrix(cnb).as_quat()
    ds = Dataset(
        readings_nT=np.column_stack([col("flux_a_x"), col("flux_a_y"), col("flux_a_z")])[None],
        time_s=col("tt"),
        attitude_wxyz=np.column_stack([q[:, 3], q[:, :3]]),
        extra={"lat": col("lat"), "lon": col("lon"), "alt_m": col("alt")},
        metadata={"date": "2020-06-20"},
        source="MagNav.jl test_data_traj.mat",
    )
    return Record("magnav test_data_traj (1 Hz)", ds, resolve_vector_reference(ds, "igrf"))


def _broad_field(path):
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("# lab_field_ned_nT:"):
                return line.split(":", 1)[1].strip()
            if not line.startswith("#"):
                break
    raise SystemExit(f"{path}: no lab_field_ned_nT line (run benchmarks/real/broad.py)")


def _broad(number, every):
    path = DATA / f"broad_{number:02d}.csv"
    ds = _quiet(read_csv, path)
    ds = ds.subset(np.arange(0, ds.n_samples, every))
    return ds, resolve_vector_reference(ds, vector=_broad_field(path))


def _broad_records(every, only):
    present = sorted(int(p.stem.split("_")[1]) for p in DATA.glob("broad_*.csv"))
    out = []
    for lo, hi in BROAD_GROUPS:
        group = [k for k in present if lo <= k <= hi]
        for i, k in enumerate(group):
            if only and not any(f"broad_{k:02d}".startswith(o) or o == "broad" for o in only):
                continue
            ds, ref = _broad(k, every)
            rec = Record(f"broad_{k:02d}", ds, ref)
            if len(group) > 1:
                nk = group[(i + 1) % len(group)]
                rec.next_name = f"broad_{nk:02d}"
                rec.next_dataset, rec.next_reference = _broad(nk, every)
            out.append(rec)
    return out


def _at_1hz(rec: Record, seconds=None) -> Record:
    """The record as a compass logged at 1 Hz (PX4's default for sensor_mag) would leave it: one sample a second,
    the first ``seconds`` only when given."""
    t = np.asarray(rec.dataset.time_s, dtype=float)
    keep = np.flatnonzero(np.diff(np.floor(t - t[0]), prepend=-1.0) > 0)
    if seconds is not None:
        keep = keep[t[keep] - t[0] < seconds]
    ds = rec.dataset.subset(keep)
    ref = resolve_vector_reference(ds, vector=",".join(f"{v:.1f}" for v in np.asarray(rec.reference.ned_nT)[0]))
    if not np.allclose(np.ptp(np.asarray(rec.reference.ned_nT), axis=0), 0.0):
        ref = resolve_vector_reference(ds, "igrf")
    name = rec.name.split(" (")[0]
    return Record(f"{name} at 1 Hz" + (f", first {seconds:.0f} s" if seconds else ""), ds, ref)


def records(only, every, tmp) -> list:
    """Every record present (``only``: names starting with one of these)."""

    def wanted(name):
        return not only or any(name.startswith(o) for o in only)

    out = []
    for name in ("px4_sample", "ap_erlebrain3", "ap_pxf_rpi", "ap_pxf_flip"):
        if wanted(name) and (DATA / f"{name}.csv").exists():
            out.append(_csv_record(name))
    for name, nxt in (
        ("ap_erle_218.bin", "ap_pxf_flip.bin"),
        ("pfc_center_0003.bin", "pfc_pilot_0004.bin"),
        ("pfc_pilot_0004.bin", "pfc_center_0003.bin"),
    ):
        if wanted(name) and (RAW / name).exists() and (RAW / nxt).exists():
            try:
                out.append(_raw_pair(name, nxt))
            except (SystemExit, MagcalError, ImportError) as exc:
                print(f"{name}: left out ({exc})", file=sys.stderr)
    if wanted("px4"):
        out += [r for r in (_px4_events(tmp),) if r is not None]
    if wanted("magnav"):
        out += [r for r in (_magnav_traj(tmp),) if r is not None]
    if not only or any(o.startswith("broad") for o in only):
        out += _broad_records(every, [o for o in only if o.startswith("broad")])
    slow = [r for r in out if r.name.startswith(("px4_sample", "ap_erle_218", "broad_02"))]
    out += [_at_1hz(r, 70.0 if r.name.startswith("broad") else None) for r in slow]  # a compass logged at 1 Hz
    return out


# ---- the check of the advice -------------------------------------------------------------------------------------


def _components(cal, ds, ref, where):
    """RMS (n_sensors, 4) of the north, east, down and |B| residuals of ``cal`` applied to ``ds`` (record-only terms
    dropped) on the samples ``where``, nT."""
    world = cal.world(ds, record_terms="drop")
    ned = np.asarray(ref.ned_nT, dtype=float)
    err = world - ned[None]
    total = np.linalg.norm(world, axis=2) - np.linalg.norm(ned, axis=1)[None]
    parts = np.concatenate([err, total[:, :, None]], axis=2)[:, where]
    return np.sqrt(np.nanmean(parts**2, axis=1))


def _fit(ds, ref, effects, mask=None):
    return _quiet(fit_vector, ds, ref, effects=list(effects), mask=mask, warn=False)


def check(rec: Record) -> dict:
    """The diagnosis of a record and what its advice does to the next part and the next flight."""
    t0 = time.perf_counter()
    also = []
    if rec.next_dataset is not None:
        also = [Flight(rec.next_dataset, rec.next_reference, rec.next_name)]
    d = _quiet(diagnose_vector, rec.dataset, rec.reference, also=also)
    row = {
        "record": rec.name,
        "n": int(d.base.n),
        "verdict": d.verdict,
        "advice": list(d.explained_by),
        "skipped": d.validation.get("skipped"),
        "summary": d.summary,
        "seconds": 0.0,
    }
    if d.explained_by:
        fitted = np.asarray(d.result.fitted, dtype=bool)
        idx = np.flatnonzero(fitted)
        later = np.zeros_like(fitted)
        later[idx[-int(round(LATER_FRACTION * len(idx))) :]] = True
        train = fitted & ~later
        base = _fit(rec.dataset, rec.reference, d.effects, train).calibration
        advice = _fit(rec.dataset, rec.reference, d.effects + d.explained_by, train).calibration
        row["next_part"] = (
            _components(base, rec.dataset, rec.reference, later),
            _components(advice, rec.dataset, rec.reference, later),
        )
        whole = _fit(rec.dataset, rec.reference, d.effects + d.explained_by)
        row["applies"] = all(s.determined for s in whole.sensors)
        if rec.next_dataset is not None:
            every = np.ones(rec.next_dataset.n_samples, bool)
            base_all = _fit(rec.dataset, rec.reference, d.effects).calibration
            after = _components(whole.calibration, rec.next_dataset, rec.next_reference, every)
            row["next_flight"] = (_components(base_all, rec.next_dataset, rec.next_reference, every), after)
            row["applies"] = row["applies"] and bool(np.all(np.isfinite(after)))
    row["seconds"] = time.perf_counter() - t0
    return row


def _rise(pair) -> float:
    before, after = pair
    return float(np.max(after / before - 1.0))


def _fmt(pair) -> str:
    before, after = pair
    cells = []
    for s in range(before.shape[0]):
        cells.append(
            " ".join(f"{c} {b:.4g}->{a:.4g}" for c, b, a in zip(COMPONENTS, before[s], after[s]))
            + (f" (s{s + 1})" if before.shape[0] > 1 else "")
        )
    return "; ".join(cells) + f"; max rise {100 * _rise(pair):+.1f} %"


def report(rows) -> str:
    lines = [
        "| record | samples | verdict | advice | next part (base -> advice, nT) | next flight (base -> advice, nT) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['record']} | {r['n']} | {r['verdict']} | {', '.join(r['advice']) or '-'} | "
            f"{_fmt(r['next_part']) if 'next_part' in r else '-'} | "
            f"{_fmt(r['next_flight']) if 'next_flight' in r else '-'} |"
        )
    advised = [r for r in rows if r["advice"]]
    unjudged = [r for r in rows if r["verdict"] == "not_judged"]
    lines += [f"{r['record']}: the base fit refused ({r['summary']})" for r in rows if r["verdict"] == "no fit"]
    lines += [
        "",
        f"records: {len(rows)}; advised: {len(advised)}; not judged: {len(unjudged)}",
        f"advice where the judgement was skipped: {sum(1 for r in rows if r['advice'] and r['skipped'])}",
        "advice that does not apply: " + (", ".join(r["record"] for r in advised if not r.get("applies")) or "none"),
        f"advice raising a component of the next part or flight by more than {100 * MAX_RISE:.0f} %: "
        + (
            ", ".join(
                r["record"]
                for r in advised
                if any(_rise(r[k]) > MAX_RISE for k in ("next_part", "next_flight") if k in r)
            )
            or "none"
        ),
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="*", default=[], help="records whose names start with these")
    parser.add_argument("--every", type=int, default=4, help="BROAD: every k-th sample (default 4)")
    parser.add_argument("--verdicts", action="store_true", help="print each record's summary too")
    args = parser.parse_args(argv)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        recs = records(args.only, args.every, Path(tmp))
    rows = []
    for rec in recs:
        try:
            rows.append(check(rec))
        except (MagcalError, CalibrationError) as exc:  # the base fit refused: nothing to diagnose
            rows.append({"record": rec.name, "n": rec.dataset.n_samples, "verdict": "no fit", "advice": []})
            rows[-1].update(skipped=str(exc), summary=str(exc), seconds=0.0)
        r = rows[-1]
        print(f"{r['record']}: {r['verdict']} {r['advice']} ({r['seconds']:.0f} s)", file=sys.stderr, flush=True)
        if args.verdicts:
            print(f"  {r['summary']}", file=sys.stderr, flush=True)
    out = io.StringIO()
    out.write(report(rows) + "\n")
    sys.stdout.write(out.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
