"""Reading a large ArduPilot DataFlash log: NumPy's scan (magcal.data.dataflash_scan) against pymavlink's reader.

Run: ``python benchmarks/dataflash_read.py [--messages 1200000] [--repeats 1]`` (about two minutes at 1.2 million:
pymavlink's reader takes most of it). Writes a synthetic log like a plain flight's (FMT messages, the compass
parameters, then MAG messages of two compasses at 10 ms, with an ATT and an IMU message every tenth: 1.2 million
MAG messages in 47 MB), reads it with ``magcal.data.logs.read_log`` both ways (pymavlink's: the fast path turned
off, as before it existed) and prints the seconds, the peak memory each added, and whether the datasets are
equal (every array, every note).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from magcal.data import logs

FORMATS = {  # name: (type, fields, numpy dtype, columns): as ArduPilot 4 writes them
    "PARM": (64, "QNf", [("TimeUS", "<u8"), ("Name", "S16"), ("Value", "<f4")], "TimeUS,Name,Value"),
    "MAG": (
        65,
        "QBhhhhhhhhhBI",
        [("TimeUS", "<u8"), ("I", "u1")]
        + [(c, "<i2") for c in ("MagX", "MagY", "MagZ", "OfsX", "OfsY", "OfsZ", "MOX", "MOY", "MOZ")]
        + [("Health", "u1"), ("S", "<u4")],
        "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",
    ),
    "ATT": (
        66,
        "QccccCCCCB",
        [("TimeUS", "<u8")]
        + [(c, "<i2") for c in ("DesRoll", "Roll", "DesPitch", "Pitch")]
        + [(c, "<u2") for c in ("DesYaw", "Yaw", "ErrRP", "ErrYaw")]
        + [("AEKF", "u1")],
        "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF",
    ),
    "IMU": (
        67,
        "QBffffffIIfBBHH",
        [("TimeUS", "<u8"), ("I", "u1")]
        + [(c, "<f4") for c in ("GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ")]
        + [("EG", "<u4"), ("EA", "<u4"), ("T", "<f4"), ("GH", "u1"), ("AH", "u1"), ("GHz", "<u2"), ("AHz", "<u2")],
        "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz",
    ),
}


def _records(name, n):
    type_id, _, fields, _ = FORMATS[name]
    rec = np.zeros(n, dtype=[("h1", "u1"), ("h2", "u1"), ("type", "u1")] + fields)
    rec["h1"], rec["h2"], rec["type"] = 0xA3, 0x95, type_id
    return rec


def write_log(path, n_mag, seed=1):
    """A log of ``n_mag`` MAG messages (two compasses), with ATT and IMU messages every tenth compass sample."""
    rng = np.random.default_rng(seed)
    out = bytearray()
    fmt = np.zeros(
        1 + len(FORMATS), dtype=[("h", "S3"), ("t", "u1"), ("l", "u1"), ("n", "S4"), ("f", "S16"), ("c", "S64")]
    )
    fmt[0] = (b"\xa3\x95\x80", 128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
    for k, (name, (type_id, fields, dtype, columns)) in enumerate(FORMATS.items(), 1):
        fmt[k] = (
            b"\xa3\x95\x80",
            type_id,
            3 + np.dtype(dtype).itemsize,
            name.encode(),
            fields.encode(),
            columns.encode(),
        )
    out += fmt.tobytes()
    parm = _records("PARM", 4)
    parm["Name"] = [b"COMPASS_OFS_X", b"COMPASS_DIA_X", b"COMPASS_ODI_Y", b"COMPASS_OFS2_Z"]
    parm["Value"] = [31.0, 1.02, -0.01, 12.0]
    out += parm.tobytes()
    steps = n_mag // 20 * 10  # compass pairs, a whole number of tens
    t_us = 1_000_000 + 10_000 * np.arange(steps, dtype=np.uint64)
    mag = _records("MAG", 2 * steps)
    mag["TimeUS"] = np.repeat(t_us, 2) + np.tile([0, 300], steps).astype(np.uint64)
    mag["I"] = np.tile([0, 1], steps)
    heading = np.repeat(np.linspace(0, 40 * np.pi, steps), 2)
    for axis, wave in (("MagX", np.cos(heading)), ("MagY", np.sin(heading)), ("MagZ", 0.8 + 0 * heading)):
        mag[axis] = np.round(450 * wave + rng.normal(0, 2, 2 * steps))
    mag["OfsX"], mag["OfsZ"], mag["MOX"], mag["Health"] = 31, np.tile([0, 12], steps), 2, 1
    every = np.arange(0, steps, 10)
    att, imu = _records("ATT", len(every)), _records("IMU", len(every))
    att["TimeUS"], imu["TimeUS"] = t_us[every], t_us[every] - 5000
    att["Roll"], att["Pitch"] = rng.integers(-900, 900, len(every)), rng.integers(-900, 900, len(every))
    att["Yaw"] = (np.degrees(heading[2 * every]) * 100 % 36000).astype(np.uint16)
    imu["AccZ"], imu["T"] = -9.81, 31.5
    # in time order: a compass pair, then (every tenth pair) the attitude and the IMU
    pairs = np.frombuffer(mag.tobytes(), np.uint8).reshape(steps // 10, 10 * 2 * mag.dtype.itemsize)
    extra = np.concatenate([np.frombuffer(r.tobytes(), np.uint8).reshape(len(every), -1) for r in (att, imu)], axis=1)
    first = 2 * mag.dtype.itemsize
    out += np.concatenate([pairs[:, :first], extra, pairs[:, first:]], axis=1).tobytes()
    Path(path).write_bytes(bytes(out))
    return 2 * steps, len(every)


def peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def read(path, fast: bool):
    saved = logs._gather_fast
    if not fast:
        logs._gather_fast = lambda *a, **k: None
    try:
        before = peak_mb()
        t0 = time.perf_counter()
        ds = logs.read_log(path, warn=False, timeout_s=1e6)  # pymavlink's hour, not refused
        return ds, time.perf_counter() - t0, max(peak_mb() - before, 0.0)
    finally:
        logs._gather_fast = saved


def same(a, b) -> bool:
    arrays = ("readings_nT", "time_s", "temperature_C")
    if a.notes != b.notes or set(a.extra) != set(b.extra) or a.metadata != b.metadata:
        return False
    pairs = [(getattr(a, k), getattr(b, k)) for k in arrays] + [(a.extra[k], b.extra[k]) for k in a.extra]
    return all(np.array_equal(x, y, equal_nan=True) for x, y in pairs if x is not None or y is not None)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=1_200_000, help="MAG messages in the log")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--readers", default="numpy,pymavlink", help="which to time: numpy, pymavlink or both")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "large.bin"
        t0 = time.perf_counter()
        n_mag, n_att = write_log(path, args.messages)
        print(
            f"log: {n_mag:,} MAG, {n_att:,} ATT and IMU messages, {path.stat().st_size / 1e6:.1f} MB "
            f"(written in {time.perf_counter() - t0:.1f} s)"
        )
        print(f"{'reader':<34}{'seconds':>10}{'peak MB':>10}")
        results = {}
        for fast, label in ((True, "NumPy scan (dataflash_scan)"), (False, "pymavlink DFReader (before)")):
            if ("numpy" if fast else "pymavlink") not in args.readers.split(","):
                continue
            for _ in range(args.repeats):
                ds, seconds, peak = read(path, fast)
                results[fast] = ds
                print(f"{label:<34}{seconds:>10.2f}{peak:>10.0f}")
        if len(results) == 2:
            print(
                f"same dataset both ways: {same(results[True], results[False])} "
                f"({results[True].n_sensors} compasses x {results[True].n_samples:,} samples)"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
