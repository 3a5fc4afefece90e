"""The network sources: text lines in UDP datagrams (listening on the address) or from a TCP server (connecting
to it), or MAVLink over either (``udp://127.0.0.1:14550``, ``tcp://127.0.0.1:5760?mavlink``). Registered as the
live source ``network`` (schemes ``udp`` and ``tcp``)."""

from __future__ import annotations

import socket

from magcal.data.live.lines import LineSource
from magcal.data.live.mavlink import MAVLINK_OPTIONS, MavlinkSource, attitude_max_dt, mavlink_address, raw_lsb
from magcal.data.live.registry import LINE_OPTIONS, SourceKind, SourceURL, register_source
from magcal.data.live.source import RECONNECT_DEFAULT_S, RECONNECT_RANGE_S, LiveError

#: Connect timeout of a TCP source (s).
TIMEOUT_RANGE_S = (0.01, 60.0)


class UdpLineSource(LineSource):
    """Text lines in UDP datagrams received on ``host:port``."""

    def __init__(self, url, host, port, parser):
        super().__init__(url, parser)
        self._sock = _bind_udp(url, host, port)

    def _receive(self, timeout_s):
        self._sock.settimeout(max(timeout_s, 0.001))
        try:
            data, _ = self._sock.recvfrom(65536)
        except (TimeoutError, BlockingIOError):
            return b""
        except OSError as exc:
            raise LiveError(f"{self.url}: receiving failed ({exc})") from None
        return data if data.endswith((b"\n", b"\r")) else data + b"\n"  # a datagram holds whole lines

    def close(self):
        super().close()
        self._sock.close()


class TcpLineSource(LineSource):
    """Text lines from a TCP server at ``host:port`` (magcal connects to it)."""

    def __init__(self, url, host, port, parser, connect_timeout_s=5.0):
        super().__init__(url, parser)
        try:
            self._sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        except (OSError, UnicodeError, ValueError) as exc:  # UnicodeError: a host name the IDNA codec refuses
            raise LiveError(f"{url}: cannot connect to {host}:{port} ({exc}); is the server running?") from None

    def _receive(self, timeout_s):
        self._sock.settimeout(max(timeout_s, 0.001))
        try:
            data = self._sock.recv(65536)
        except (TimeoutError, BlockingIOError):
            return b""
        except OSError as exc:
            raise LiveError(f"{self.url}: the connection failed ({exc})") from None
        if not data:
            self._eof = True
            return b"\n" if self._buffer else b""
        return data

    def close(self):
        super().close()
        self._sock.close()


def _bind_udp(url, host, port):
    """A UDP socket listening on ``host:port``: IPv4 (a name as ``localhost`` too), or IPv6 for an IPv6 address
    (``udp://[::1]:14550``, ``udp://[::]:14550``)."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((host, port))
    except (OSError, UnicodeError, ValueError) as exc:
        sock.close()
        raise LiveError(
            f"{url}: cannot listen on UDP {host}:{port} ({exc}); is another program using the port?"
        ) from None
    return sock


def open_network(url: SourceURL):
    """A ``udp://HOST:PORT`` or ``tcp://HOST:PORT`` URL's source: text lines (listening on UDP, connecting over
    TCP), or MAVLink with ``?mavlink`` (a TCP connection that closes is connected again)."""
    attitude_dt = attitude_max_dt(url)
    host, port = url.host_port()
    params = url.params
    if url.mavlink:  # UDP is connectionless and needs no reconnecting
        return MavlinkSource(
            url.url,
            mavlink_address(url.url, url.scheme, host, port),
            params.get("message"),
            raw_lsb_nT=raw_lsb(url),
            attitude_max_dt_s=attitude_dt,
            reconnect_s=url.number("reconnect", RECONNECT_DEFAULT_S, float, RECONNECT_RANGE_S),
            connect_timeout_s=url.number("timeout", 5.0, float, TIMEOUT_RANGE_S),
        )
    if params.get("format", "lines").lower() != "lines":
        raise LiveError(f"{url.url}: format={params['format']!r}: use format=lines or mavlink")
    if url.scheme == "udp":
        return UdpLineSource(url.url, host, port, url.line_parser())
    return TcpLineSource(
        url.url, host, port, url.line_parser(), connect_timeout_s=url.number("timeout", 5.0, float, TIMEOUT_RANGE_S)
    )


NETWORK = register_source(
    SourceKind(
        name="network",
        schemes=("udp", "tcp"),
        description="text lines in UDP datagrams (listened for) or from a TCP server (connected to); MAVLink with "
        "?mavlink",
        forms=("udp://HOST:PORT", "tcp://HOST:PORT"),
        example="udp://127.0.0.1:14550?format=lines",
        options=("timeout", "reconnect", *LINE_OPTIONS, *MAVLINK_OPTIONS),
        opener=open_network,
    )
)
