"""The effects' physical domains on real records: the BROAD hand-turned IMU with motion-capture attitude.

For each undisturbed BROAD record (01-09, ``benchmarks/real/data/broad_*.csv``, the lab's field vector from the
file's header) the vector fit with each bounded effect alone, twice: with the effect's domain (ours) and with it
removed (the fit before domains: what ``magcal calibrate`` wrote and ``magcal apply`` then refused). Printed per
record and effect: the fitted values, whether the fit held them on a bound (``not physical here``), and whether the
calibration with them goes through save, load and apply. The floor is the domain itself (a loop width >= 0, a
nonlinearity within 5000 ppm, a delay the record can show).

Run: ``python benchmarks/domain_broad.py`` (about a minute per record on the 2-core machine);
``--records 01,02`` for some only.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from magcal.calibration.calibration import Calibration
from magcal.checks.reference import VectorReference
from magcal.core.errors import MagcalError
from magcal.data.io import read_csv
from magcal.fitting.vector import fit_vector
from magcal.model.terms import EFFECTS, Domain, fitted_outside_domain

DATA = HERE / "real" / "data"
RECORDS = [f"{k:02d}" for k in range(1, 10)]
EFFECT_NAMES = ("hysteresis", "nonlinearity_quadratic", "nonlinearity_cubic", "attitude_time_offset")


def lab_field(path) -> np.ndarray:
    """The ``# lab_field_ned_nT: N,E,D`` line of a BROAD record's header."""
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if not line.startswith("#"):
                break
            if line.startswith("# lab_field_ned_nT:"):
                return np.array([float(v) for v in line.split(":", 1)[1].split(",")])
    raise SystemExit(f"{path}: no lab_field_ned_nT line")


def values_text(name, values, field_nT) -> str:
    v = np.ravel(values)
    if name.startswith("nonlinearity"):
        return "(" + ", ".join(f"{1e6 * x / field_nT:,.0f}" for x in v) + ") ppm"
    unit = "ms" if name == "attitude_time_offset" else "nT"
    return "(" + ", ".join(f"{x:.3g}" for x in v) + f") {unit}"


def round_trip(cal, ds) -> str:
    """``ok`` when the calibration saves, loads and applies; else the refusal."""
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "cal.json")
        try:
            cal.save(path)
            back = Calibration.load(path)
            vectors = back.correct(ds, warn=False, force=True)
        except MagcalError as exc:
            return "REFUSED: " + str(exc).split(": ", 2)[-1][:70]
    return "ok" if np.all(np.isfinite(vectors)) else "NaN"


def fit_one(ds, reference, name, free):
    cls = EFFECTS[name]
    original = cls.domain
    if free:  # the fit before domains
        cls.domain = lambda self: Domain.free(len(self.param_names()))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = fit_vector(ds, reference, effects=[name], warn=False)
    finally:
        cls.domain = original
    return fit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--records", default=",".join(RECORDS))
    args = parser.parse_args()
    print(f"{'rec':>3}  {'effect':<24} {'before (no domain)':<34} {'load':<8} {'ours':<34} held on a bound")
    for rec in args.records.split(","):
        path = DATA / f"broad_{rec}.csv"
        if not path.exists():
            print(f"{rec}: {path} missing (benchmarks/real/README.md)")
            continue
        ds = read_csv(path)
        ned = lab_field(path)
        reference = VectorReference(np.tile(ned, (ds.n_samples, 1)), "lab field", "vector")
        field_nT = float(np.linalg.norm(ned))
        for name in EFFECT_NAMES:
            t0 = time.perf_counter()
            old = fit_one(ds, reference, name, free=True)
            new = fit_one(ds, reference, name, free=False)
            label = next(iter(new.calibration.effect_values))
            held = fitted_outside_domain(new.calibration.model, new.calibration.effect_values, pulls=new.bound_pull_z)
            print(
                f"{rec:>3}  {name:<24} {values_text(name, old.calibration.effect_values[label], field_nT):<34} "
                f"{round_trip(old.calibration, ds)[:8]:<8} "
                f"{values_text(name, new.calibration.effect_values[label], field_nT):<34} "
                f"{'yes' if held else 'no'} (load {round_trip(new.calibration, ds)}; {time.perf_counter() - t0:.0f} s)"
            )


if __name__ == "__main__":
    main()
