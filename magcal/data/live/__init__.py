"""Live sources: time-stamped magnetometer samples as they arrive, and a recorder that keeps every one on disk.

One interface for every instrument (``docs/export.md`` has the URL forms):

``serial:///dev/ttyUSB0?baud=115200&columns=x,y,z``
    Text lines from a serial port (pyserial), opened again when it disappears (a board reset, a USB
    re-enumeration) for up to ``reconnect`` s (default 30), with nothing received lost (:class:`SerialSource`).
    Also ``&mavlink`` for MAVLink over the port, reopened the same way.
``udp://127.0.0.1:14550?format=lines`` / ``tcp://127.0.0.1:5760``
    Text lines in UDP datagrams (listening on the address) or from a TCP server (connecting to it).
``udp://127.0.0.1:14550?mavlink`` (also ``tcp://...?mavlink``, connected again for up to ``reconnect`` s when closed)
    MAVLink (pymavlink): the magnetometer fields of ``RAW_IMU``, ``SCALED_IMU``, ``SCALED_IMU2``, ``SCALED_IMU3``
    or ``HIGHRES_IMU`` in the units the message definition declares (mgauss, gauss), converted to nT, with the
    temperature where the message sends one, ``ATTITUDE`` merged onto each sample (nearest in time within
    ``attitude_max_dt`` s) and the position of ``GPS_RAW_INT`` / ``GLOBAL_POSITION_INT`` (:class:`MavlinkSource`).
``sim://chi2017?rate=50`` / ``sim://path/to/file.csv?rate=50``
    A simulated instrument playing a preset (:func:`magcal.data.simulation.simulate_timeseries`, deterministic for a
    given ``seed``) or a magcal CSV file in real time: for tests, teaching and demonstrations without hardware.

Text-line options: ``columns`` (comma-separated names of the fields of a line: ``x,y,z`` or ``mx,my,mz`` or
``s1x..s4z``, ``t`` in s (``t_ms``, ``t_us``), ``temp`` in degC, the channels ``roll, pitch, yaw`` (deg), ``gx,
gy, gz`` (deg/s), ``ax, ay, az``, ``lat, lon, alt``, ``_`` for a field to skip; default ``x,y,z``), or
``template`` (the line with its fields in braces: ``x={x} y={y} z={z}``), ``sep`` (the separator; default commas,
semicolons, tabs or spaces), ``units`` (``nT`` default, ``uT``, ``G``, ``mG``, ``counts`` with ``lsb`` in nT per
count), ``prefix`` (only lines starting with it are data, e.g. ``Raw:``), ``checksum`` (``off``: a trailing ``*hh``
is not checked). Framed lines (``|...*``, ``$...*hh``) and bracketed lists (``[x, y, z]`` anywhere in a line) are
read as they come (:mod:`magcal.data.lineformats`). Without a ``t`` column the samples are stamped with the host's
monotonic clock, in s since the source opened.

Channels other than the readings and the temperature (attitude, gyro, accelerometer, position) travel in
:attr:`LiveChunk.channels`, into :meth:`LiveChunk.to_dataset`'s ``extra`` and the recording's columns under the
names :mod:`magcal.data.attitude` and :mod:`magcal.checks.reference` read (``roll_deg``, ``lat``, ...).

:meth:`LiveSource.read` returns a :class:`LiveChunk` of whatever arrived within a timeout (possibly empty);
iterating a source yields non-empty chunks until it ends or is closed. Lines or messages that cannot be read are
counted in :attr:`LiveSource.stats` (with the last reason), never raised; lines that are not data (comments, a
boot banner before the first sample) are counted as skipped. Every wait is bounded, and so is every line's work
(at most :data:`MAX_LINE_BYTES`, a template matched in linear time): a read returns by its timeout whatever
arrives, the lines it did not reach waiting for the next, so ``magcal record --seconds S`` ends after S seconds.

:class:`Recorder` appends the samples to a magcal CSV as they arrive: whole lines only, flushed to disk (``fsync``)
at least every ``flush_interval_s``, so a recording cut by a crash or a kill reopens with
:func:`magcal.read_csv` holding every sample up to the last flush. :class:`LiveSession` runs a source and a
recorder in a thread with pause, resume, stop and listeners (the workbench's live view).

``magcal record URL OUT.csv --seconds 60`` records from the command line (:mod:`magcal.cli.record`).

The modules (every name is also importable from ``magcal.data.live``):

* :mod:`~magcal.data.live.source` -- the interface (:class:`LiveSource`, :class:`LiveChunk`, :class:`SourceStats`,
  :class:`LiveError`), a device's clock across its restarts, a port reopened when lost;
* :mod:`~magcal.data.live.parser` -- :class:`LineParser`: a text line made a sample;
* :mod:`~magcal.data.live.lines` -- a source of text lines from a byte stream;
* :mod:`~magcal.data.live.registry` -- the sources by URL scheme (:data:`LIVE_SOURCES`, entry-point group
  ``magcal.live_sources``) and :func:`open_source`;
* one module per source, each registering itself: :mod:`~magcal.data.live.serialport` (``serial``),
  :mod:`~magcal.data.live.network` (``udp``, ``tcp``), :mod:`~magcal.data.live.simulated` (``sim``); MAVLink over
  either of the first two is :mod:`~magcal.data.live.mavlink`;
* :mod:`~magcal.data.live.recorder` -- :class:`Recorder`, :func:`record`, :class:`LiveSession`.
"""

from __future__ import annotations

# the built-in sources register in the order they are imported: serial, network, sim
# isort: off
from magcal.data.live.source import (
    CLOCK_RESET_S,
    RECONNECT_DEFAULT_S,
    RECONNECT_MAX_INTERVAL_S,
    RECONNECT_RANGE_S,
    LiveChunk,
    LiveError,
    LiveSource,
    SourceStats,
    concatenate_chunks,
)
from magcal.data.live.parser import LineParser
from magcal.data.live.lines import MAX_LINE_BYTES, LineSource, _LineSource
from magcal.data.live.registry import (
    LIVE_SOURCES,
    SourceKind,
    SourceURL,
    load_entry_points,
    open_source,
    register_source,
    schemes,
    source_for,
)
from magcal.data.live.mavlink import (
    MAVLINK_ATTITUDE_BUFFER,
    MAVLINK_ATTITUDE_CHANNELS,
    MAVLINK_FIELD_UNITS_nT,
    MAVLINK_HOLD_S,
    MAVLINK_MESSAGES,
    POSITION_CHANNELS,
    POSITION_MAX_AGE_S,
    MavlinkSource,
    mavlink_address,
)
from magcal.data.live.serialport import BAUD_RANGE, SerialSource, serial_ports
from magcal.data.live.network import TIMEOUT_RANGE_S, TcpLineSource, UdpLineSource
from magcal.data.live.simulated import (
    SIM_MAX_SAMPLES,
    SIM_MAX_SAMPLES_PER_S,
    SIM_MAX_SEED,
    SIM_RATE_RANGE_HZ,
    SIM_SPEED_RANGE,
    SimSource,
)
from magcal.data.live.recorder import LiveSession, Recorder, record

# isort: on

__all__ = [
    "BAUD_RANGE",
    "CLOCK_RESET_S",
    "LIVE_SOURCES",
    "MAVLINK_ATTITUDE_BUFFER",
    "MAVLINK_ATTITUDE_CHANNELS",
    "MAVLINK_FIELD_UNITS_nT",
    "MAVLINK_HOLD_S",
    "MAVLINK_MESSAGES",
    "MAX_LINE_BYTES",
    "POSITION_CHANNELS",
    "POSITION_MAX_AGE_S",
    "RECONNECT_DEFAULT_S",
    "RECONNECT_MAX_INTERVAL_S",
    "RECONNECT_RANGE_S",
    "SIM_MAX_SAMPLES",
    "SIM_MAX_SAMPLES_PER_S",
    "SIM_MAX_SEED",
    "SIM_RATE_RANGE_HZ",
    "SIM_SPEED_RANGE",
    "TIMEOUT_RANGE_S",
    "LineParser",
    "LineSource",
    "LiveChunk",
    "LiveError",
    "LiveSession",
    "LiveSource",
    "MavlinkSource",
    "Recorder",
    "SerialSource",
    "SimSource",
    "SourceKind",
    "SourceStats",
    "SourceURL",
    "TcpLineSource",
    "UdpLineSource",
    "_LineSource",
    "concatenate_chunks",
    "load_entry_points",
    "mavlink_address",
    "open_source",
    "record",
    "register_source",
    "schemes",
    "serial_ports",
    "source_for",
]
