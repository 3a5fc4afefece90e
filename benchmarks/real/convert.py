"""Convert the raw real recordings (see ``fetch.py``) into magcal CSV files in nT.

One function per recording; each reads from ``data/raw/`` and writes ``data/<name>.csv`` with ``# key: value``
header lines saying where the data came from, the sensor, the unit conversion and the sample rate. The local
field is not given as ``reference_total_nT`` (a bench is rarely at the IGRF value); the IGRF value of the
likely site is kept as the information key ``igrf_total_nT``.

Usage::

    python benchmarks/real/fetch.py --mirror /work/.mirror     # or without --mirror to download
    python benchmarks/real/convert.py --all                    # or: convert.py qmc_filtered ads_rm3100 ...
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from magcal.data.io import write_csv

HERE = Path(__file__).resolve().parent
RAW_DIR = HERE / "data" / "raw"
OUT_DIR = HERE / "data"

#: nT per gauss.
NT_PER_GAUSS = 1e5

#: QMC5883L sensitivity (datasheet): 12000 LSB/G at +-2 G, 3000 LSB/G at +-8 G. The recordings' fitted field is
#: 1071 counts: 8.9 uT with 12000 LSB/G (below the weakest geomagnetic field anywhere, ~22 uT), 35.7 uT with
#: 3000 LSB/G (IGRF at Mendoza 23.0 uT). See FINDINGS.md for the argument; 3000 LSB/G is used.
QMC_LSB_NT = NT_PER_GAUSS / 3000.0
#: ICM-20948 (AK09916 magnetometer): 0.15 uT per LSB.
ICM20948_LSB_NT = 150.0
#: RM3100 at the default cycle count 200: 75 counts per uT.
RM3100_LSB_NT = 1000.0 / 75.0
#: HMC5883L at the default gain (+-1.3 G): 1090 LSB/G.
HMC5883L_LSB_NT = NT_PER_GAUSS / 1090.0


def _write(name: str, columns: dict, metadata: dict, out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.csv"
    write_csv(path, columns, metadata={**metadata, "units": "nT"})
    return path


def _vector_columns(readings_nT: np.ndarray) -> dict:
    return {"x": readings_nT[:, 0], "y": readings_nT[:, 1], "z": readings_nT[:, 2]}


# ---- tomisuarez2/MagnetometerCalibration (QMC5883L) -----------------------------------------------------------


def read_qmc_counts(path: Path) -> tuple[float, float, np.ndarray]:
    """``(rate_Hz, still_s, counts)`` of a QMC logger file: ``Fs,50.00`` / ``Initialization time,60`` /
    ``mx,my,mz`` then integer rows."""
    with open(path, encoding="utf-8") as fh:
        rate = float(fh.readline().split(",")[1])
        still = float(fh.readline().split(",")[1])
        header = fh.readline().strip()
        if header.replace(" ", "") != "mx,my,mz":
            raise ValueError(f"{path}: line 3: expected the header 'mx,my,mz', found {header!r}")
        counts = np.loadtxt(fh, delimiter=",", ndmin=2)
    return rate, still, counts


def convert_qmc(which: str, raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR, lsb_nT: float = QMC_LSB_NT) -> Path:
    """``qmc_filtered`` / ``qmc_noisy``: QMC5883L raw counts x ``lsb_nT``; ``t`` = index / 50 Hz (nominal)."""
    rate, still, counts = read_qmc_counts(raw_dir / f"qmc_{which}_raw_data.csv")
    t = np.arange(len(counts)) / rate
    meta = {
        "source": f"github.com/tomisuarez2/MagnetometerCalibration 'calibration data/{which}_raw_data.csv'",
        "licence": "MIT (c) 2025 Tomas Suarez",
        "sensor": "QMC5883L (GY-63 board) on an Arduino UNO, OSR 512, hand-turned; Universidad Nacional de Cuyo",
        "conversion": f"raw counts x {lsb_nT:.6g} nT (3000 LSB/G, +-8 G); the sketch asks for +-2 G = 12000 LSB/G "
        "but the fitted field would then be 8.9 uT; see FINDINGS.md",
        "lsb_nT": f"{lsb_nT:.6g}",
        "rate_Hz": f"{rate:g}",
        "time": "t = sample index / rate (the file has no time stamps)",
        "still_s": f"{still:g} (the logger's initialization time: sensor still at the start)",
        "igrf_total_nT": "23028 (Mendoza, Argentina, 2025.6; site assumed)",
    }
    return _write(f"qmc_{which}", {"t": t, **_vector_columns(counts * lsb_nT)}, meta, out_dir)


def convert_qmc_filtered(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    return convert_qmc("filtered", raw_dir, out_dir)


def convert_qmc_noisy(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    return convert_qmc("noisy", raw_dir, out_dir)


# ---- apujara22/MagCal_W25_MXL (ADS payload: ICM-20948 + RM3100) ------------------------------------------------


def _rtc_seconds(text: str) -> float:
    """``'mm:ss.s'`` (the RTC time as a spreadsheet kept it: hours lost, 0.1 s) in s."""
    minutes, seconds = text.split(":")
    return int(minutes) * 60 + float(seconds)


def spread_repeats(t: np.ndarray) -> np.ndarray:
    """Strictly increasing times from stamps that repeat: each run of equal stamps is spread evenly up to the next
    distinct stamp (the last run by the median interval)."""
    t = np.asarray(t, dtype=float)
    out = t.copy()
    distinct = np.flatnonzero(np.r_[True, np.diff(t) != 0])
    steps = np.diff(t[distinct])
    step_end = np.median(steps) if steps.size else 1.0
    for k, start in enumerate(distinct):
        stop = distinct[k + 1] if k + 1 < len(distinct) else len(t)
        gap = (t[stop] - t[start]) if stop < len(t) else step_end * (stop - start)
        out[start:stop] = t[start] + gap * np.arange(stop - start) / (stop - start)
    return out


def read_ads(path: Path) -> dict:
    """Columns of ``data_original.csv`` as float arrays (``cur_time`` as RTC seconds, unwrapped over hours)."""
    with open(path, encoding="utf-8-sig", newline="") as fh:
        rows = list(csv.reader(fh))
    header = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if r and any(c.strip() for c in r)]
    cols = {}
    for j, name in enumerate(header):
        if not name:
            continue
        if name == "cur_time":
            rtc = np.array([_rtc_seconds(r[j]) for r in body])
            rtc += 3600.0 * np.cumsum(np.r_[0, np.diff(rtc) < -1800])  # hour roll-over
            cols[name] = rtc
        else:
            cols[name] = np.array([float(r[j]) for r in body])
    return cols


def convert_ads(sensor: str, raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``ads_icm20948`` (imu_m* x 150 nT) / ``ads_rm3100`` (mag_* counts x 13.333 nT) with ``t`` from the RTC and
    ``temp`` = ICM-20948 die temperature."""
    c = read_ads(raw_dir / "ads_data_original.csv")
    if sensor == "icm20948":
        counts, lsb = np.c_[c["imu_mx"], c["imu_my"], c["imu_mz"]], ICM20948_LSB_NT
        what = "ICM-20948 (AK09916) magnetometer, counts x 150 nT (0.15 uT/LSB)"
    elif sensor == "rm3100":
        counts, lsb = np.c_[c["mag_x"], c["mag_y"], c["mag_z"]], RM3100_LSB_NT
        what = "PNI RM3100, counts x 13.333 nT (75 LSB/uT, cycle count 200)"
    else:
        raise ValueError(f"unknown ADS sensor {sensor!r} (icm20948 or rm3100)")
    t_rtc = c["cur_time"] - c["cur_time"][0]
    meta = {
        "source": "github.com/apujara22/MagCal_W25_MXL 'ADSvehicle/preFlightCali/data_original.csv'",
        "licence": "none stated: local development only, do not redistribute",
        "sensor": f"{what}; ADS payload (Raspberry Pi), U. Michigan MXL, pre-flight calibration 2025-02-12, outdoors",
        "conversion": f"counts x {lsb:.6g} nT (checked against the authors' data_original_imu/_pni.csv in uT)",
        "lsb_nT": f"{lsb:.6g}",
        "rate_Hz": "~9.9 (bursts of 10 reads, then sleep to 1 s)",
        "time": "t from the RTC column cur_time (mm:ss.s, 0.1 s); repeated stamps spread evenly to the next; "
        "t_rtc_s = the stamps as logged",
        "temp": "ICM-20948 die temperature (imu_T), degC; enviro_t = BME680 air temperature",
        "igrf_total_nT": "52856 (Ann Arbor, MI, 2025-02-12; site assumed)",
    }
    columns = {
        "t": spread_repeats(t_rtc),
        **_vector_columns(counts * lsb),
        "temp": c["imu_T"],
        "t_rtc_s": t_rtc,
        "enviro_t": c["enviro_t"],
    }
    return _write(f"ads_{sensor}", columns, meta, out_dir)


def convert_ads_icm20948(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    return convert_ads("icm20948", raw_dir, out_dir)


def convert_ads_rm3100(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    return convert_ads("rm3100", raw_dir, out_dir)


#: The authors' flight window (unix s): first and last stamp of ``postFlightCali/data_ADSflight_times.csv``.
ADS_FLIGHT_WINDOW = (1740235658.99726, 1740241184.5163)
#: Columns of the ADS logger's raw files (no header; as in ``data_original.csv``), 0-based.
ADS_COLUMNS = {
    "unix_time": 0,
    "imu_mx": 8,
    "imu_my": 9,
    "imu_mz": 10,
    "imu_T": 11,
    "mag_x": 12,
    "mag_y": 13,
    "mag_z": 14,
    "enviro_t": 16,
    "enviro_p": 17,
}
#: An RM3100 count beyond this on any axis is a read glitch (the flight field is ~4000 counts per axis at most).
ADS_GLITCH_COUNTS = 20000
#: The flight is written at every ADS_FLIGHT_DECIMATION-th sample (~2.4 Hz) to keep the benchmark short.
ADS_FLIGHT_DECIMATION = 4


def read_ads_flight(raw_dir: Path = RAW_DIR) -> tuple[np.ndarray, int]:
    """Rows (unix time, then the columns of :data:`ADS_COLUMNS`) of the flight's raw logger files inside the
    flight window, and the number of malformed lines skipped."""
    from fetch import ADS_FLIGHT_FILES  # the same directory

    rows, skipped = [], 0
    keys = list(ADS_COLUMNS.values())
    for stamp in ADS_FLIGHT_FILES:
        with open(raw_dir / f"ads_flight_{stamp}.csv", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                parts = line.strip().split(",")
                try:
                    rows.append([float(parts[k]) for k in keys])
                except (IndexError, ValueError):
                    skipped += 1
    a = np.asarray(rows, dtype=float)
    a = a[np.argsort(a[:, 0], kind="stable")]
    inside = (a[:, 0] >= ADS_FLIGHT_WINDOW[0]) & (a[:, 0] <= ADS_FLIGHT_WINDOW[1])
    return a[inside], skipped


def convert_ads_flight(sensor: str, raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``ads_flight_rm3100`` / ``ads_flight_icm20948``: the ADS payload's balloon flight (2025-02-22), every 4th
    sample, RM3100 read glitches dropped; ``temp`` = ICM-20948 die temperature, ``pressure_hPa`` and ``air_t``."""
    a, skipped = read_ads_flight(raw_dir)
    c = {name: a[:, j] for j, name in enumerate(ADS_COLUMNS)}
    rm = np.c_[c["mag_x"], c["mag_y"], c["mag_z"]]
    glitch = np.any(np.abs(rm) > ADS_GLITCH_COUNTS, axis=1)
    repeat = np.r_[False, np.diff(c["unix_time"]) <= 0]
    keep = ~glitch & ~repeat
    keep &= (np.cumsum(keep) - 1) % ADS_FLIGHT_DECIMATION == 0
    if sensor == "icm20948":
        counts, lsb = np.c_[c["imu_mx"], c["imu_my"], c["imu_mz"]], ICM20948_LSB_NT
        what = "ICM-20948 (AK09916) magnetometer, counts x 150 nT"
    elif sensor == "rm3100":
        counts, lsb = rm, RM3100_LSB_NT
        what = "PNI RM3100, counts x 13.333 nT (75 LSB/uT)"
    else:
        raise ValueError(f"unknown ADS sensor {sensor!r} (icm20948 or rm3100)")
    t = c["unix_time"][keep]
    meta = {
        "source": "github.com/apujara22/MagCal_W25_MXL 'ADSvehicle/postFlightCali/Telem/data_1740235425.csv' ... "
        "'data_1740241125.csv' (20 files of 5 min)",
        "licence": "none stated: local development only, do not redistribute",
        "sensor": f"{what}; ADS payload (Raspberry Pi) on a high-altitude balloon flight, U. Michigan MXL, "
        "2025-02-22: ground to ~10 hPa (~26 km) and down; the payload swings and spins",
        "conversion": f"counts x {lsb:.6g} nT",
        "lsb_nT": f"{lsb:.6g}",
        "rate_Hz": f"~{9.7 / ADS_FLIGHT_DECIMATION:.2g} (sample numbers 0, {ADS_FLIGHT_DECIMATION}, "
        f"{2 * ADS_FLIGHT_DECIMATION}, ... of the ~9.7 Hz log)",
        "time": "t = logger unix time - 1740235659 s (the authors' flight window, data_ADSflight_times.csv)",
        "dropped": f"{int(glitch.sum())} RM3100 read glitches (|count| > {ADS_GLITCH_COUNTS}), "
        f"{int(repeat.sum())} repeated stamps, {skipped} malformed lines",
        "temp": "ICM-20948 die temperature (imu_T), degC: -32 to +5 degC, not monotonic in time "
        "(cooling through the troposphere, warming in the stratosphere, cooling on descent)",
        "what_for": "flight log, not a calibration rotation: partial attitude coverage; the field changes with "
        "altitude (~-650 nT at 26 km) and position; temperature varies independently of time",
        "igrf_total_nT": "about 53000 at the ground (south-east Michigan; launch site assumed)",
    }
    columns = {
        "t": t - ADS_FLIGHT_WINDOW[0],
        **_vector_columns(counts[keep] * lsb),
        "temp": c["imu_T"][keep],
        "pressure_hPa": c["enviro_p"][keep],
        "air_t": c["enviro_t"][keep],
    }
    return _write(f"ads_flight_{sensor}", columns, meta, out_dir)


def convert_ads_flight_rm3100(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    return convert_ads_flight("rm3100", raw_dir, out_dir)


def convert_ads_flight_icm20948(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    return convert_ads_flight("icm20948", raw_dir, out_dir)


def convert_mxl_test1(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``mxl_test1``: RM3100 on a quadrotor (uT with 1/75 resolution) -> counts -> nT; no usable time stamps."""
    uT = np.loadtxt(raw_dir / "mxl_test1_esti_trunc.csv", delimiter=",", skiprows=1, ndmin=2)
    counts = np.round(uT * 75.0)
    meta = {
        "source": "github.com/apujara22/MagCal_W25_MXL 'Matlab Version/20210423_mag_cali/test1_esti_trunc.csv'",
        "licence": "none stated: local development only, do not redistribute",
        "sensor": "PNI RM3100 on the EstiBone quadrotor, turned by hand (traj0: 360 deg roll, pitch, yaw), "
        "south of MAIR, U. Michigan, 2021-04-23",
        "conversion": f"uT x 75 rounded to counts, x {RM3100_LSB_NT:.6g} nT",
        "lsb_nT": f"{RM3100_LSB_NT:.6g}",
        "rate_Hz": "unknown (the logger's ns time stamps were rounded to 1.47819E+18 by a spreadsheet)",
        "igrf_total_nT": "53271 (Ann Arbor, MI, 2021-04-23)",
    }
    return _write("mxl_test1", _vector_columns(counts * RM3100_LSB_NT), meta, out_dir)


# ---- sunsided/sensor-fusion (HMC5883L + MPU6050) ---------------------------------------------------------------


def _read_mat73(path: Path, name: str) -> np.ndarray:
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise SystemExit("the sensor-fusion files are MATLAB v7.3 (HDF5): pip install h5py") from exc
    with h5py.File(path, "r") as f:
        return np.array(f[name]).T


def convert_sf_fullsphere(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``sf_fullsphere``: HMC5883L in gauss -> nT, host time stamps, MPU6050 temperature interpolated."""
    mag = _read_mat73(raw_dir / "sf_fullsphere_hmc5883l_compass.mat", "compassBuffer")
    temp = _read_mat73(raw_dir / "sf_fullsphere_mpu6050_temperature.mat", "temperatureBuffer")
    t = mag[:, 0]
    readings = np.round(mag[:, 1:4] * 1090.0) * HMC5883L_LSB_NT  # the values are counts / 1090 exactly
    meta = {
        "source": "github.com/sunsided/sensor-fusion 'data/set-2/full-sphere/hmc5883l_compass.mat' "
        "(+ mpu6050_temperature.mat)",
        "licence": "EUPL-1.2 (c) Markus Mayer (sunsided)",
        "sensor": "Honeywell HMC5883L (gain 1090 LSB/G) with an MPU6050 on one board, turned about the centre point "
        "through 9 rotations covering the sphere",
        "conversion": f"gauss x 1e5 (= counts x {HMC5883L_LSB_NT:.6g} nT)",
        "lsb_nT": f"{HMC5883L_LSB_NT:.6g}",
        "rate_Hz": "~77 mean (75 Hz nominal); t = host arrival time stamps, s",
        "temp": "MPU6050 die temperature (100 Hz) interpolated onto the magnetometer times, degC",
        "igrf_total_nT": "about 49000 (central Europe; site not stated)",
    }
    columns = {"t": t, **_vector_columns(readings), "temp": np.interp(t, temp[:, 0], temp[:, 1])}
    return _write("sf_fullsphere", columns, meta, out_dir)


# ---- aleksandrbazhin/ellipsoid_fit_python ------------------------------------------------------------------


#: Assumed LSB of ab_mag_out (not stated by the source): 0.3 uT/LSB (AK8975-class) puts the field at ~52 uT.
AB_ASSUMED_LSB_NT = 300.0


def convert_ab_mag_out(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``ab_mag_out``: 347 integer vectors of unknown sensor; counts x an assumed 300 nT."""
    counts = np.loadtxt(raw_dir / "ab_mag_out.txt", ndmin=2)
    meta = {
        "source": "github.com/aleksandrbazhin/ellipsoid_fit_python 'mag_out.txt'",
        "licence": "MIT (c) 2016 aleksandrbazhin",
        "sensor": "not stated (example input of an ellipsoid-fit tool for magnetometer calibration)",
        "conversion": f"counts x {AB_ASSUMED_LSB_NT:g} nT: ASSUMED (fitted field 174 counts -> 52 uT); "
        "only relative figures (RMS / field) mean anything",
        "lsb_nT": f"{AB_ASSUMED_LSB_NT:g}",
        "rate_Hz": "unknown (no time stamps)",
    }
    return _write("ab_mag_out", _vector_columns(counts * AB_ASSUMED_LSB_NT), meta, out_dir)


# ---- flight-controller logs (PX4 ULog, ArduPilot DataFlash) ---------------------------------------------------
#
# Read with magcal's own log reader (magcal.data.logs: pyulog for .ulg, pymavlink for .bin; `pip install pyulog
# pymavlink`), which gives the field in nT, the log's time in s, the vehicle's attitude as qw..qz and, for
# ArduPilot, the raw field with the logged calibration (COMPASS_OFS*, motor offsets, DIA/ODI/SCALE) undone.
# These are flights or bench logs, not calibration rotations: the attitudes cover part of the sphere at best.


def _read_flight_log(raw_name: str, raw_dir: Path):
    """A :class:`magcal.data.dataset.Dataset` from a raw log, with the reader's warnings collected as strings."""
    import warnings

    try:
        from magcal.data.logs import read_log
    except ImportError as exc:  # pragma: no cover - magcal without its log reader
        raise SystemExit(f"this magcal has no magcal.data.logs reader for flight logs ({exc})") from exc
    path = raw_dir / raw_name
    if not path.exists():
        raise FileNotFoundError(2, "no such file", str(path))
    from magcal.core.errors import DataWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        try:
            ds = read_log(path, name=raw_name)
        except ValueError as exc:  # DatasetError: e.g. pyulog / pymavlink missing
            raise SystemExit(f"{raw_name}: {exc}") from exc
    return ds, [str(w.message) for w in caught if issubclass(w.category, DataWarning)]


def _write_log(name: str, ds, notes: list, metadata: dict, out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.csv"
    meta = {**metadata, "units": "nT"}
    if notes:
        meta["reader_notes"] = " | ".join(n.replace("\n", " ") for n in notes)[:600]
    write_csv(path, ds, metadata=meta)
    return path


def convert_px4_sample(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``px4_sample``: pyulog's test log (PX4 on an AUAV-X2.1, 2016): ``sensor_combined.magnetometer_ga``, the
    field the vehicle had already calibrated (CAL_MAG0 offsets), gauss -> nT, one sample per magnetometer update."""
    ds, notes = _read_flight_log("px4_sample.ulg", raw_dir)
    meta = {
        "source": "github.com/PX4/pyulog 'test/sample.ulg'",
        "licence": "BSD-3-Clause (c) 2016 PX4 Pro Drone Autopilot (pyulog)",
        "sensor": "PX4 on an AUAV-X2.1 autopilot (HMC5883-class external compass assumed, not stated), disarmed, "
        "tilted by hand +-22 deg roll, +-9 deg pitch, 28 deg of yaw in 69 s",
        "conversion": "gauss x 1e5; the field as calibrated by the vehicle (CAL_MAG0_*OFF subtracted, "
        "scales 1.0), not raw",
        "rate_Hz": "~98 (magnetometer updates inside sensor_combined at 248 Hz; repeats dropped)",
        "time": "t = log time stamp + magnetometer_timestamp_relative, s",
        "what_for": "not a calibration rotation: magnitude stability under small tilts, timing, quantization",
    }
    return _write_log("px4_sample", ds, notes, meta, out_dir)


def _ardupilot_meta(path: str, what: str) -> dict:
    return {
        "source": f"github.com/erlerobot/logs '{path}'",
        "licence": "none stated: local development only, do not redistribute",
        "sensor": f"ArduCopter compass 1 (HMC5883L-class on the Erle PXF / Erle-Brain board); {what}",
        "conversion": "MAG milligauss x 100 (the log stores whole milligauss: a 100 nT step); the logged calibration "
        "(OfsX..Z, motor offsets) undone by magcal.data.logs",
        "lsb_nT": "100",
        "time": "t = TimeMS / TimeUS of the MAG messages, s",
        "igrf_total_nT": "about 45000 (Vitoria-Gasteiz, Spain, where Erle Robotics flew; site assumed)",
        "what_for": "flight log, not a calibration rotation: attitude coverage partial, motors and battery current on",
    }


def convert_ap_erlebrain3(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``ap_erlebrain3``: ArduCopter fly test of an Erle-Brain 3 (2016), MAG ~9.4 Hz."""
    ds, notes = _read_flight_log("ap_erlebrain3.bin", raw_dir)
    meta = _ardupilot_meta("pxf/copter/Erle-Brain3.BIN", "fly test, 265 s, yaw through 360 deg, roll/pitch +-40 deg")
    return _write_log("ap_erlebrain3", ds, notes, {**meta, "rate_Hz": "~9.4 (MAG logged at the 10 Hz loop)"}, out_dir)


def convert_ap_pxf_rpi(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``ap_pxf_rpi``: ArduCopter on a PXF v2.0b cape + Raspberry Pi (2015), MAG ~3.8 Hz for 20 min."""
    ds, notes = _read_flight_log("ap_pxf_rpi.bin", raw_dir)
    meta = _ardupilot_meta("pxf/copter/PXFv2.0b+Rpi.BIN", "1231 s, yaw through 360 deg, roll/pitch +-30 deg")
    return _write_log("ap_pxf_rpi", ds, notes, {**meta, "rate_Hz": "~3.8 mean (MAG logged irregularly)"}, out_dir)


def convert_ap_pxf_flip(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``ap_pxf_flip``: ArduCopter PXF v1.4 log (2014-12-15): level flight, then the vehicle turns over."""
    ds, notes = _read_flight_log("ap_pxf_flip.bin", raw_dir)
    meta = _ardupilot_meta(
        "pxf/copter/15-12-2014/16.BIN",
        "152 s of level flight (roll/pitch within +-8 deg, yaw 25-351 deg), then the vehicle "
        "turns over in its last seconds (roll -108, pitch 81 deg)",
    )
    return _write_log("ap_pxf_flip", ds, notes, {**meta, "rate_Hz": "10 (MAG at the 10 Hz loop)"}, out_dir)


# ---- timspi/mag-calib (CaribouLabs IMU + GNSS logger) ------------------------------------------------------------

#: nT per count of the CaribouLabs logger's magnetometer: ASSUMED 150 nT (1.5 mG/LSB: LIS2MDL, or AK09916 0.15 uT);
#: the part is not stated. With it the fitted field is ~45 uT, against IGRF ~44 uT in Israel (CaribouLabs' home;
#: the site is not stated either). 100 nT would give 30 uT (below any geomagnetic field there), 300 nT 91 uT.
CL_ASSUMED_LSB_NT = 150.0
#: Seconds per tick of the logger's ``imu_time``: ASSUMED 10 ns. The logged roll/pitch/yaw turn between rows by
#: 1.5x |gyro| (deg/s) x delta-ticks x 1e-8 s (median over rows turning faster than 50 deg/s): 10 ns ticks with
#: a lagging attitude filter, ~77 Hz, 20.7 s in all. (1 us ticks would make 34 min at 0.77 Hz, 1 ns 2 s.)
CL_TICK_S = 1e-8


def convert_cl_imu_gnss(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``cl_imu_gnss``: CaribouLabs logger, integer counts x an assumed 150 nT; ``temp`` = barometer temperature."""
    with open(raw_dir / "cl_imu_gnss_data.csv", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    names = ("magx", "magy", "magz", "imu_time", "baro_temp_c", "accx", "accy", "accz", "gyrox", "gyroy", "gyroz")
    col = {k: np.array([float(r[k]) for r in rows]) for k in names}
    counts = np.c_[col["magx"], col["magy"], col["magz"]]
    t = (col["imu_time"] - col["imu_time"][0]) * CL_TICK_S
    meta = {
        "source": "github.com/timspi/mag-calib 'raw_data/imu_gnss_data.csv'",
        "licence": "MIT (c) 2025 CaribouLabs.co",
        "sensor": "CaribouLabs IMU + GNSS logger (magnetometer part not stated; no GNSS fix), waved by hand "
        "through the sphere (roll +-180, pitch +-89 deg)",
        "conversion": f"counts x {CL_ASSUMED_LSB_NT:g} nT: ASSUMED (fitted field ~303 counts -> 45 uT; "
        "IGRF ~44 uT in Israel, site not stated)",
        "lsb_nT": f"{CL_ASSUMED_LSB_NT:g}",
        "rate_Hz": "~77 (stamps every 1.30e6 ticks; one gap of 27 rows)",
        "time": f"t = (imu_time - first) x {CL_TICK_S:g} s: the tick ASSUMED 10 ns (attitude vs gyro, see convert.py)",
        "temp": "barometer temperature (baro_temp_c), degC: 24.8 -> 25.8, rising with time (hand warmth)",
        "accel_units": "m/s^2",
        "accelerometer": "accx, accy, accz as ax, ay, az (m/s^2, |a| 9.79 at rest); gyrox.. as gx_rad_s.. (rad/s)",
    }
    columns = {"t": t, **_vector_columns(counts * CL_ASSUMED_LSB_NT), "temp": col["baro_temp_c"]}
    columns.update({a: col[f"acc{a[1]}"] for a in ("ax", "ay", "az")})
    columns.update({f"g{a}_rad_s": col[f"gyro{a}"] for a in "xyz"})
    return _write("cl_imu_gnss", columns, meta, out_dir)


# ---- michaelwro/mag-cal-example (FXOS8700) -----------------------------------------------------------------------


def convert_mw_fxos8700(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``mw_fxos8700``: FXOS8700 in uT (Adafruit driver: 0.1 uT per count) -> nT; ``t`` = index / 10 Hz."""
    uT = np.loadtxt(raw_dir / "mw_mag_readings.txt", ndmin=2)
    readings = np.round(uT * 10.0) * 100.0  # the driver prints counts x 0.1 uT with float noise
    meta = {
        "source": "github.com/michaelwro/mag-cal-example 'examples/mag-readings.txt'",
        "licence": "none stated: local development only, do not redistribute",
        "sensor": "NXP FXOS8700 (Adafruit FXOS8700 + FXAS21002 9-DOF board) on an Arduino Uno, turned by hand "
        "(Michael Wrona, 2021-01-14)",
        "conversion": "uT x 1000 (the Adafruit driver gives counts x 0.1 uT)",
        "lsb_nT": "100",
        "rate_Hz": "10 nominal (the sketch's delay(100) after each read; no time stamps)",
        "time": "t = sample index / 10 Hz",
    }
    t = np.arange(len(readings)) / 10.0
    return _write("mw_fxos8700", {"t": t, **_vector_columns(readings)}, meta, out_dir)


# ---- CK-Explorer/Magnetometer-and-Accelerometer-Calibration (LSM9DS1) ---------------------------------------------

#: LSM9DS1 magnetometer at +-4 G (datasheet): 0.14 mgauss per LSB = 14 nT. Every value of the file is a multiple of
#: 0.00014 G to within 1e-12 (and no other sensitivity of the common parts fits: LIS3MDL 1/6842 G, LSM9DS0 0.16 mG,
#: LIS2MDL 1.5 mG, HMC5883L 1/1090 G all leave residues up to half a step).
LSM9DS1_4G_LSB_NT = 0.14e-3 * NT_PER_GAUSS


def convert_ck_lsm9ds1(raw_dir: Path = RAW_DIR, out_dir: Path = OUT_DIR) -> Path:
    """``ck_lsm9ds1``: LSM9DS1 magnetometer in gauss (0.14 mG steps) -> nT; no time stamps."""
    a = np.loadtxt(raw_dir / "ck_acc_mag_log.csv", delimiter=",", skiprows=1, ndmin=2)
    counts = np.round(a[:, 3:6] / 0.14e-3)
    meta = {
        "source": "github.com/CK-Explorer/Magnetometer-and-Accelerometer-Calibration 'Data Examples/acc_mag_log.csv'",
        "licence": "Apache-2.0 (CK-Explorer)",
        "sensor": "ST LSM9DS1 (decided from the data: every reading a multiple of 0.14 mG, its +-4 G sensitivity), "
        "turned through the sphere with the accelerometer logged beside it",
        "conversion": f"gauss / 0.14e-3 rounded to counts, x {LSM9DS1_4G_LSB_NT:.6g} nT",
        "lsb_nT": f"{LSM9DS1_4G_LSB_NT:.6g}",
        "rate_Hz": "unknown (no time stamps)",
        "igrf_total_nT": "about 40000 (Malaysia, the author's UTC+8 commits; site not stated); the fitted field is "
        "~31 uT",
        "accel_units": "g",
        "accelerometer": "the file's ax, ay, az (g), the LSM9DS1's accelerometer on the same die",
    }
    columns = {**_vector_columns(counts * LSM9DS1_4G_LSB_NT), "ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2]}
    return _write("ck_lsm9ds1", columns, meta, out_dir)


#: Every recording: name -> converter.
CONVERTERS = {
    "qmc_filtered": convert_qmc_filtered,
    "qmc_noisy": convert_qmc_noisy,
    "ads_icm20948": convert_ads_icm20948,
    "ads_rm3100": convert_ads_rm3100,
    "mxl_test1": convert_mxl_test1,
    "sf_fullsphere": convert_sf_fullsphere,
    "ab_mag_out": convert_ab_mag_out,
    "ads_flight_rm3100": convert_ads_flight_rm3100,
    "ads_flight_icm20948": convert_ads_flight_icm20948,
    "px4_sample": convert_px4_sample,
    "ap_erlebrain3": convert_ap_erlebrain3,
    "ap_pxf_rpi": convert_ap_pxf_rpi,
    "ap_pxf_flip": convert_ap_pxf_flip,
    "cl_imu_gnss": convert_cl_imu_gnss,
    "mw_fxos8700": convert_mw_fxos8700,
    "ck_lsm9ds1": convert_ck_lsm9ds1,
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Convert the raw real recordings into magcal CSVs (nT).")
    parser.add_argument("names", nargs="*", help=f"recordings to convert: {', '.join(CONVERTERS)}")
    parser.add_argument("--all", action="store_true", help="convert every recording")
    parser.add_argument("--raw-dir", type=Path, default=RAW_DIR)
    parser.add_argument("--out-dir", type=Path, default=OUT_DIR)
    parser.add_argument(
        "--flight-every",
        type=int,
        default=ADS_FLIGHT_DECIMATION,
        help=f"keep every N-th sample of the ADS flight (default {ADS_FLIGHT_DECIMATION}; 1 = all "
        "53 000 samples at 9.7 Hz, about 2.5 min for benchmarks/real.py on it alone)",
    )
    args = parser.parse_args(argv)
    if args.flight_every < 1:
        parser.error(f"--flight-every must be at least 1, got {args.flight_every}")
    globals()["ADS_FLIGHT_DECIMATION"] = args.flight_every
    names = list(CONVERTERS) if args.all else args.names
    if not names:
        parser.error("name recordings or give --all")
    unknown = [n for n in names if n not in CONVERTERS]
    if unknown:
        parser.error(f"unknown recording(s) {', '.join(unknown)}; known: {', '.join(CONVERTERS)}")
    status = 0
    for name in names:
        try:
            path = CONVERTERS[name](args.raw_dir, args.out_dir)
        except FileNotFoundError as exc:
            print(f"{name}: raw file missing ({exc.filename}); run benchmarks/real/fetch.py first", file=sys.stderr)
            status = 1
            continue
        print(f"{name}: {path}")
    return status


if __name__ == "__main__":
    sys.exit(main())
