"""Convert the BROAD motion-capture trials into magcal CSVs with attitude and position.

BROAD (Laidig, Caruso, Cereatti & Seel 2021, *Data* 6(7) 72; github.com/dlaidig/broad, CC BY 4.0) records a
myon aktos-t IMU turned and carried by hand in a lab, with an eight-camera OptiTrack system giving its orientation
(``opt_quat``, the IMU frame to a world frame East-North-Up) and position (``opt_pos``, m), synchronised and aligned
to the IMU, at 285.7 Hz. Trials 01-23 are undisturbed (rotation, translation, combined; slow, fast, with breaks),
24-27 tapped or vibrated, 28-31 carried past a magnet standing near the path, 32-36 with a magnet attached at
1-5 cm, 37-39 in an office.

Each trial becomes ``data/broad_NN.csv``: ``t`` (s from the start), ``s1x..s1z`` (nT, the IMU's magnetometer: uT x
1000), ``qw..qz`` (the IMU frame to north-east-down: ENU turned into NED, the body frame being the IMU's own),
``pos_n_m, pos_e_m, pos_d_m`` (the marker body's position in the lab, NED, m), ``gx_rad_s..gz_rad_s`` (the
gyroscope), and ``movement`` (1 where the trial's own mask marks the movement phase). The accelerometer is left out:
a record with one makes magcal choose the gravity mode, which is not what these trials are for.

The lab's field is constant but not known: the header line ``lab_field_ned_nT`` gives an estimate made outside the
vector fit (the seed's ellipsoid fit of the readings, the corrected vectors turned into NED with the motion capture
and averaged); it is for ``--reference-vector`` until the record's own fitted field is used.

Usage::

    python benchmarks/real/broad.py                          # every trial present in the mirror, every 4th sample
    python benchmarks/real/broad.py 01 02 28 --every 2       # some trials, 143 Hz
    python benchmarks/real/broad.py --mirror /work/.mirror   # where the bare clone of dlaidig/broad is
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.io import loadmat
from scipy.spatial.transform import Rotation

import magcal
from magcal.data.io import write_csv

HERE = Path(__file__).resolve().parent
OUT_DIR = HERE / "data"
REPO = "dlaidig/broad"
#: ENU -> NED: north = y_enu, east = x_enu, down = -z_enu (a proper rotation).
#: A slow rotation trial whose ellipsoid fit stands in for trials that do not turn enough for their own.
FALLBACK_TRIAL = "02"
ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def _git_dir(mirror: Path) -> Path:
    for candidate in (mirror / "dlaidig+broad" / "repo", mirror / "broad.git", mirror / "broad" / ".git"):
        if candidate.exists():
            return candidate
    raise FileNotFoundError(f"no clone of {REPO} under {mirror}")


def trial_files(git_dir: Path) -> dict:
    """``{number: path}`` of the trials whose MAT (or, failing that, HDF5) file is held by the clone."""
    listing = subprocess.run(
        ["git", "-C", str(git_dir), "ls-tree", "-r", "-l", "HEAD"], capture_output=True, text=True, check=True
    ).stdout
    held: dict = {}
    for line in listing.splitlines():
        meta, path = line.split("\t")
        size = meta.split()[3]
        if not size.isdigit() or not (path.endswith(".mat") or path.endswith(".hdf5")):
            continue
        number = Path(path).name[:2]
        if not number.isdigit():
            continue
        if path.endswith(".mat") or number not in held:
            held[number] = path
    return dict(sorted(held.items()))


def _blob(git_dir: Path, path: str) -> bytes:
    proc = subprocess.run(["git", "-C", str(git_dir), "show", f"HEAD:{path}"], capture_output=True)
    if proc.returncode != 0:
        raise FileNotFoundError(f"{REPO}:{path}: {proc.stderr.decode().strip()}")
    return proc.stdout


def read_trial(git_dir: Path, path: str) -> dict:
    """The trial's arrays: ``imu_mag`` (uT), ``imu_gyr`` (rad/s), ``opt_quat`` (w, x, y, z), ``opt_pos`` (m),
    ``movement`` and ``rate_Hz``."""
    data = _blob(git_dir, path)
    if path.endswith(".mat"):
        mat = loadmat(io.BytesIO(data))
        arrays = {k: np.asarray(mat[k]) for k in ("imu_mag", "imu_gyr", "opt_quat", "opt_pos", "movement")}
        rate = float(np.asarray(mat["sampling_rate"]).ravel()[0])
    else:
        import h5py

        with h5py.File(io.BytesIO(data), "r") as f:
            arrays = {k: np.asarray(f[k]) for k in ("imu_mag", "imu_gyr", "opt_quat", "opt_pos", "movement")}
            rate = float(f.attrs["sampling_rate"])
    arrays["movement"] = arrays["movement"].ravel().astype(bool)
    arrays["rate_Hz"] = rate
    return arrays


def body_to_ned(opt_quat: np.ndarray) -> Rotation:
    """The IMU frame -> NED rotation from BROAD's IMU -> ENU quaternions (scalar first)."""
    enu = Rotation.from_quat(opt_quat[:, [1, 2, 3, 0]])
    return Rotation.from_matrix(ENU_TO_NED) * enu


def lab_field_estimate(readings_nT: np.ndarray, rotation: Rotation, fallback=None) -> tuple[np.ndarray, str]:
    """The lab's field (NED, nT) estimated outside the vector fit, and how: the seed's ellipsoid fit of the trial's
    own readings (or, for a trial that does not turn enough, the ``fallback`` calibration of a rotation trial of the
    same IMU), its corrected vectors turned into NED with the motion capture's attitude and averaged (good to the
    ellipsoid gauge's small rotation)."""
    how = "this trial's ellipsoid fit"
    try:
        calibration = magcal.calibrate(readings_nT, method="ellipsoid").calibration
    except magcal.MagcalError:
        if fallback is None:
            raise
        calibration, how = fallback
    corrected = np.asarray(calibration.correct(readings_nT[None]))[0]
    return np.asarray(np.nanmean(rotation.apply(corrected), axis=0)), how


def convert_trial(number: str, path: str, git_dir: Path, every: int, out_dir: Path, fallback=None) -> Path:
    arrays = read_trial(git_dir, path)
    keep = slice(None, None, every)
    quat = arrays["opt_quat"][keep]
    good = np.all(np.isfinite(quat), axis=1) & (np.linalg.norm(np.nan_to_num(quat), axis=1) > 0.5)
    mag_nT = arrays["imu_mag"][keep] * 1000.0
    rate = arrays["rate_Hz"] / every
    t = np.arange(len(mag_nT)) / rate
    q_ned = np.full((len(t), 4), np.nan)
    rotation = body_to_ned(quat[good])
    xyzw = rotation.as_quat()
    q_ned[good] = xyzw[:, [3, 0, 1, 2]]
    pos = np.full((len(t), 3), np.nan)
    pos[good] = arrays["opt_pos"][keep][good] @ ENU_TO_NED.T
    field, how = lab_field_estimate(mag_nT[good], rotation, fallback)
    gyr = arrays["imu_gyr"][keep]
    columns = {
        "t": t,
        "s1x": mag_nT[:, 0],
        "s1y": mag_nT[:, 1],
        "s1z": mag_nT[:, 2],
        "qw": q_ned[:, 0],
        "qx": q_ned[:, 1],
        "qy": q_ned[:, 2],
        "qz": q_ned[:, 3],
        "pos_n_m": pos[:, 0],
        "pos_e_m": pos[:, 1],
        "pos_d_m": pos[:, 2],
        "gx_rad_s": gyr[:, 0],
        "gy_rad_s": gyr[:, 1],
        "gz_rad_s": gyr[:, 2],
        "movement": arrays["movement"][keep].astype(int),
    }
    meta = {
        "source": f"github.com/{REPO} '{path}'",
        "licence": "CC BY 4.0 (Laidig, Caruso, Cereatti & Seel 2021, BROAD)",
        "sensor": "myon aktos-t IMU magnetometer, turned and carried by hand; OptiTrack attitude and position",
        "conversion": "uT x 1000; opt_quat (IMU -> ENU) turned into IMU -> NED; opt_pos ENU -> NED",
        "rate_Hz": f"{rate:.3f} (every {every} of {arrays['rate_Hz']:.3f} Hz)",
        "lab_field_ned_nT": ",".join(f"{v:.0f}" for v in field),
        "lab_field_note": f"estimate outside the vector fit ({how}, turned into NED, averaged)",
        "units": "nT",
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / f"broad_{number}.csv"
    write_csv(out, columns, metadata=meta, float_format="%.6g")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trials", nargs="*", help="trial numbers (01..39); default every trial in the clone")
    parser.add_argument("--mirror", type=Path, default=Path("/work/.mirror"), help="folder of the bare clone")
    parser.add_argument("--every", type=int, default=4, help="keep every Nth sample (default 4: 71.4 Hz)")
    parser.add_argument("--out-dir", type=Path, default=OUT_DIR)
    args = parser.parse_args(argv)
    git_dir = _git_dir(args.mirror)
    files = trial_files(git_dir)
    wanted = [f"{int(n):02d}" for n in args.trials] or list(files)
    fallback = None
    if FALLBACK_TRIAL in files:
        arrays = read_trial(git_dir, files[FALLBACK_TRIAL])
        calibration = magcal.calibrate(arrays["imu_mag"][:: args.every] * 1000.0, method="ellipsoid").calibration
        fallback = (calibration, f"the ellipsoid fit of trial {FALLBACK_TRIAL}, the same IMU turned")
    for number in wanted:
        if number not in files:
            print(f"broad_{number}: not held by the clone (a large file the snapshot left out)", file=sys.stderr)
            continue
        out = convert_trial(number, files[number], git_dir, args.every, args.out_dir, fallback)
        print(f"broad_{number}: {out} from {files[number]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
