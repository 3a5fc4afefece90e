"""Obtain the raw files of the real magnetometer recordings used as development data (issue 10).

Nothing here is shipped with magcal: the raw files go to ``benchmarks/real/data/raw/`` (git-ignored) and
``convert.py`` turns them into magcal CSVs in ``benchmarks/real/data/``. Recordings without a licence
(``licence: none``) may be used locally for development only; never commit or redistribute them.

Each source is a file at a pinned commit of a public GitHub repository. Two ways to get it:

* ``python benchmarks/real/fetch.py`` downloads ``https://raw.githubusercontent.com/<repo>/<commit>/<path>``;
* ``python benchmarks/real/fetch.py --mirror DIR`` reads it from local bare clones instead, looked up as
  ``DIR/<owner>+<name>/repo`` or ``DIR/<name>.git`` (``git clone --bare https://github.com/<repo>``), with
  ``git --git-dir=... show <commit>:<path>`` (falling back to ``HEAD`` when the commit is not in the clone).

Run ``python benchmarks/real/fetch.py --list`` to print the table of sources.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
RAW_DIR = HERE / "data" / "raw"


@dataclass(frozen=True)
class Source:
    """One raw file of a public recording."""

    local_name: str
    repo: str
    commit: str
    path: str
    licence: str
    what: str

    @property
    def url(self) -> str:
        return f"https://raw.githubusercontent.com/{self.repo}/{self.commit}/{urllib.parse.quote(self.path)}"


QMC = ("tomisuarez2/MagnetometerCalibration", "eb93f820ffc06155579b7d86928795915eef714a")
MXL = ("apujara22/MagCal_W25_MXL", "b3117ac0dfe91d7350227bccf4c11768a845444a")
SF = ("sunsided/sensor-fusion", "f16045a9d1d4f9037a183f436fe3c098a38ad99d")
AB = ("aleksandrbazhin/ellipsoid_fit_python", "bfab4ce68244529640496f466a4374ef15748275")
PYULOG = ("PX4/pyulog", "3cf17793f14709713ab297d3743314c658874068")
ERLE = ("erlerobot/logs", "3f7d4a0d17f2485f7fa5cb7124fc2a5b13d6c688")
CARIBOU = ("timspi/mag-calib", "c155daa72a19b42452b58ffc7cfbd6be211fd16e")
CKX = ("CK-Explorer/Magnetometer-and-Accelerometer-Calibration", "61ac7669f1cbba2e5ce77763a40ebc123d95ac60")
WRONA = ("michaelwro/mag-cal-example", "226e2e608473b1912320518366d30cdd404c5796")
PFC = ("PyFlightCoach/FlightData", "801c43a7b2243b690c2c775cd6eda7cf47f8cfb3")
DKLA = ("dronekit/dronekit-la-testdata", "62408712e9af63311fa6760b4a6d29b3455e04af")

#: The ADS payload's flight (2025-02-22, U. Michigan MXL): the logger's 5-min files that span the authors' flight
#: window (``ADSvehicle/postFlightCali/data_ADSflight_times.csv``: unix 1740235659 to 1740241185).
ADS_FLIGHT_FILES = tuple(range(1740235425, 1740241126, 300))

SOURCES = (
    Source(
        "qmc_filtered_raw_data.csv",
        *QMC,
        "calibration data/filtered_raw_data.csv",
        "MIT",
        "QMC5883L on GY-63 + Arduino, hand-turned, 50 Hz, raw counts, first 60 s still",
    ),
    Source(
        "qmc_noisy_raw_data.csv",
        *QMC,
        "calibration data/noisy_raw_data.csv",
        "MIT",
        "same set-up, second recording ('noisy')",
    ),
    Source(
        "ads_data_original.csv",
        *MXL,
        "ADSvehicle/preFlightCali/data_original.csv",
        "none (local only)",
        "ADS payload pre-flight: ICM-20948 (counts x 0.15 uT) + RM3100 (counts / 75 uT), ~10 Hz, outdoors",
    ),
    Source(
        "mxl_test1_esti_trunc.csv",
        *MXL,
        "Matlab Version/20210423_mag_cali/test1_esti_trunc.csv",
        "none (local only)",
        "RM3100 on a quadrotor turned by hand outdoors (Ann Arbor, 2021-04-23), uT",
    ),
    Source(
        "sf_fullsphere_hmc5883l_compass.mat",
        *SF,
        "data/set-2/full-sphere/hmc5883l_compass.mat",
        "EUPL-1.2",
        "HMC5883L full-sphere rotation, gauss, host time stamps, ~77 Hz (MATLAB v7.3)",
    ),
    Source(
        "sf_fullsphere_mpu6050_temperature.mat",
        *SF,
        "data/set-2/full-sphere/mpu6050_temperature.mat",
        "EUPL-1.2",
        "MPU6050 die temperature of the same board, 100 Hz",
    ),
    Source(
        "ab_mag_out.txt",
        *AB,
        "mag_out.txt",
        "MIT",
        "example input of an ellipsoid-fit tool: 347 raw integer vectors, sensor and unit not stated",
    ),
    *(
        Source(
            f"ads_flight_{stamp}.csv",
            *MXL,
            f"ADSvehicle/postFlightCali/Telem/data_{stamp}.csv",
            "none (local only)",
            "ADS payload balloon flight, raw logger file (5 min): ICM-20948 + RM3100 counts, die and air temperature, "
            "pressure, ~9.7 Hz",
        )
        for stamp in ADS_FLIGHT_FILES
    ),
    Source(
        "px4_sample.ulg",
        *PYULOG,
        "test/sample.ulg",
        "BSD-3-Clause",
        "PX4 ULog test file of pyulog: AUAV-X2.1, disarmed, hand-tilted +-22 deg for 69 s; sensor_combined "
        "magnetometer_ga (already calibrated by the vehicle), ~98 Hz",
    ),
    Source(
        "ap_erlebrain3.bin",
        *ERLE,
        "pxf/copter/Erle-Brain3.BIN",
        "none (local only)",
        "ArduCopter DataFlash log, Erle-Brain 3 fly test (2016): MAG ~9.4 Hz for 265 s, yaw through 360 deg, "
        "roll/pitch +-40 deg",
    ),
    Source(
        "ap_pxf_rpi.bin",
        *ERLE,
        "pxf/copter/PXFv2.0b+Rpi.BIN",
        "none (local only)",
        "ArduCopter DataFlash log, PXF v2.0b on a Raspberry Pi (2015): MAG ~3.8 Hz for 1231 s, yaw through "
        "360 deg, roll/pitch +-30 deg",
    ),
    Source(
        "ap_pxf_flip.bin",
        *ERLE,
        "pxf/copter/15-12-2014/16.BIN",
        "none (local only)",
        "ArduCopter DataFlash log, Erle-Copter PXF v1.4 (2014-12-15): MAG 10 Hz for 152 s, level flight "
        "(roll/pitch within +-8 deg, yaw 25-351 deg), then the vehicle turns over at the end (roll -108, pitch 81)",
    ),
    Source(
        "ap_erle_218.bin",
        *ERLE,
        "pxf/copter/5-12-2014/218.BIN",
        "none (local only)",
        "ArduCopter 3.2 DataFlash log, Erle-Copter PXF (2014-12-05, Vitoria-Gasteiz): MAG 10 Hz for 335 s with "
        "ATT and GPS (3D fix), yaw through 360 deg many times, roll/pitch mostly within +-15 deg; the same compass "
        "offsets as ap_pxf_flip and ap_erle_37 (the same vehicle, flown 10 and 17 days later)",
    ),
    Source(
        "ap_erle_37.bin",
        *ERLE,
        "pxf/copter/22-12-2014/37.BIN",
        "none (local only)",
        "ArduCopter 3.2 DataFlash log, the same Erle-Copter (2014-12-22): MAG 5 Hz for 180 s with ATT and GPS; "
        "upside down for about 70 s in the middle",
    ),
    Source(
        "pfc_center_0003.bin",
        *PFC,
        "test/data/script_tests/center_0003.bin",
        "LGPL-3.0",
        "ArduPlane 4.x DataFlash log of an F3A aerobatic model aircraft carried on its flying field to mark the "
        "box centre (2025-01-03, near Bristol, UK): MAG 10 Hz for 49 s, ATT, GPS; yaw through 263 deg, level",
    ),
    Source(
        "pfc_pilot_0004.bin",
        *PFC,
        "test/data/script_tests/pilot_0004.BIN",
        "LGPL-3.0",
        "the same aircraft's next log (2025-01-03), carried to the pilot's position: MAG 10 Hz for 99 s, yaw "
        "through 321 deg, roll -2..12, pitch -22..8 deg",
    ),
    Source(
        "dk_log171.bin",
        *DKLA,
        "log171.bin",
        "CC-BY-SA-3.0",
        "ArduCopter 3.3-dev DataFlash log (2015-11, the CMAC field near Canberra) with three compasses (MAG, MAG2, "
        "MAG3: an external HMC5883 at COMPASS_ORIENT 38, an internal LSM303D, an internal HMC5983 not used for yaw "
        "and not calibrated), ATT, GPS, CURR (0.5-27 A) and CTUN throttle; 242 s: on the ground, then hovering "
        "flight; no motor compensation (COMPASS_MOTCT 0)",
    ),
    Source(
        "cl_imu_gnss_data.csv",
        *CARIBOU,
        "raw_data/imu_gnss_data.csv",
        "MIT",
        "CaribouLabs IMU + GNSS logger (part not stated): 1252 rows of integer magnetometer counts with the "
        "logger's tick stamps, accelerometer, gyro, attitude, barometer temperature; waved through the sphere",
    ),
    Source(
        "mw_mag_readings.txt",
        *WRONA,
        "examples/mag-readings.txt",
        "none (local only)",
        "NXP FXOS8700 (Adafruit FXOS8700 + FXAS21002 board) on an Arduino, uT (0.1 uT steps), 10 Hz for ~32 s, "
        "turned by hand; no time stamps",
    ),
    Source(
        "ck_acc_mag_log.csv",
        *CKX,
        "Data Examples/acc_mag_log.csv",
        "Apache-2.0",
        "12000 rows of accelerometer (g) and magnetometer (gauss) readings turned for calibration; every "
        "magnetometer value a multiple of 0.14 mG (LSM9DS1 at +-4 G); no time stamps",
    ),
)


def _mirror_git_dir(mirror: Path, repo: str) -> Path | None:
    owner, name = repo.split("/")
    for candidate in (mirror / f"{owner}+{name}" / "repo", mirror / f"{name}.git", mirror / name / ".git"):
        if candidate.is_dir():
            return candidate
    return None


def _from_mirror(src: Source, mirror: Path) -> bytes:
    git_dir = _mirror_git_dir(mirror, src.repo)
    if git_dir is None:
        raise FileNotFoundError(f"no clone of {src.repo} under {mirror}")
    for rev in (src.commit, "HEAD"):
        proc = subprocess.run(["git", f"--git-dir={git_dir}", "show", f"{rev}:{src.path}"], capture_output=True)
        if proc.returncode == 0:
            return proc.stdout
    raise FileNotFoundError(f"{src.repo}: {src.path} not in {git_dir}: {proc.stderr.decode().strip()}")


def _download(src: Source) -> bytes:
    with urllib.request.urlopen(src.url, timeout=60) as response:
        return response.read()


def fetch(sources=SOURCES, mirror: Path | None = None, raw_dir: Path = RAW_DIR, force: bool = False) -> list:
    """Write each source's raw file into ``raw_dir``; returns the paths written or already present."""
    raw_dir.mkdir(parents=True, exist_ok=True)
    done = []
    for src in sources:
        target = raw_dir / src.local_name
        if target.exists() and not force:
            done.append(target)
            continue
        data = _from_mirror(src, mirror) if mirror else _download(src)
        if data.startswith(b"version https://git-lfs"):
            raise RuntimeError(f"{src.repo}:{src.path} is a Git LFS pointer, not the data")
        target.write_bytes(data)
        done.append(target)
        print(f"{target.name}: {len(data)} bytes from {src.repo}:{src.path}")
    return done


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mirror", type=Path, help="directory of local bare clones instead of downloading")
    parser.add_argument("--force", action="store_true", help="fetch again even if the raw file exists")
    parser.add_argument("--list", action="store_true", help="print the sources and exit")
    args = parser.parse_args(argv)
    if args.list:
        for s in SOURCES:
            print(f"{s.local_name}\n    {s.repo} @ {s.commit[:10]} : {s.path}\n    licence {s.licence}; {s.what}")
        return 0
    fetch(mirror=args.mirror, force=args.force)
    return 0


if __name__ == "__main__":
    sys.exit(main())
