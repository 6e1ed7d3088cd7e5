"""Byte streams of live devices: TCP, UDP, serial ports and files, with a stall timeout.

``open_stream(url, stall_timeout_s)`` gives a :class:`ByteStream` whose ``read(n)`` and
``readline()`` block until the data is there, return ``b""`` at the end of the stream (peer
closed, end of file) and raise :class:`StreamStalled` when no byte arrived for
``stall_timeout_s``: a device that stops talking is reported, never waited on forever.
pyubx2's reader takes a ByteStream as its data stream (it needs exactly these two calls).

URLs:
- ``tcp://HOST:PORT``: a TCP client (a receiver's or a serial-to-Ethernet converter's port);
- ``udp://[HOST]:PORT``: datagrams received on PORT (bound to HOST, default all interfaces);
- ``serial:///dev/ttyUSB0?baud=115200``: a serial port (pyserial);
- ``file:///path`` or a plain path: a file read to its end (tests, replays of raw logs).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

__all__ = ["StreamStalled", "ByteStream", "open_stream"]

_POLL_S = 0.05  # how often a blocked read wakes up to check the stall timeout


class StreamStalled(TimeoutError):
    """No data arrived for longer than the stream's stall timeout."""


class ByteStream:
    """Buffered reads over a ``recv(max_bytes)`` function.

    ``recv`` returns the bytes available (at most ``max_bytes``), ``b""`` at the end of the
    stream, or None when nothing arrived within its own short poll interval.
    """

    def __init__(self, recv: Callable[[int], bytes | None], name: str,
                 stall_timeout_s: float = 5.0, close: Callable[[], None] | None = None):
        self._recv = recv
        self._close = close
        self.name = name
        self.stall_timeout_s = stall_timeout_s
        self._buf = bytearray()
        self._eof = False
        self.bytes_read = 0
        self.local_address: tuple[str, int] | None = None  # of a UDP stream's socket

    def _fill(self) -> bool:
        """Wait for more data: False at the end of the stream, StreamStalled on a stall."""
        if self._eof:
            return False
        start = time.monotonic()
        while True:
            chunk = self._recv(65536)
            if chunk is None:
                if time.monotonic() - start > self.stall_timeout_s:
                    raise StreamStalled(f"{self.name}: no data for {self.stall_timeout_s:g} s")
                continue
            if not chunk:
                self._eof = True
                return False
            self._buf += chunk
            self.bytes_read += len(chunk)
            return True

    def read(self, n: int) -> bytes:
        """Exactly ``n`` bytes; fewer only at the end of the stream (``b""`` when none left)."""
        while len(self._buf) < n and self._fill():
            pass
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def readline(self) -> bytes:
        """Bytes up to and including the next ``\\n`` (what is left at the end of the stream)."""
        while True:
            k = self._buf.find(b"\n")
            if k >= 0:
                out = bytes(self._buf[:k + 1])
                del self._buf[:k + 1]
                return out
            if not self._fill():
                out = bytes(self._buf)
                self._buf.clear()
                return out

    def close(self) -> None:
        if self._close is not None:
            self._close()

    def __enter__(self) -> ByteStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _socket_recv(sock: socket.socket, datagrams: bool) -> Callable[[int], bytes | None]:
    sock.settimeout(_POLL_S)

    def recv(n: int) -> bytes | None:
        try:
            data = sock.recv(n)
        except TimeoutError:
            return None
        # an empty datagram is not the end of a UDP "stream"
        return None if datagrams and not data else data

    return recv


def _host_port(netloc: str, url: str) -> tuple[str, int]:
    host, _, port = netloc.rpartition(":")
    if not port.isdigit():
        raise ValueError(f"{url}: no port number")
    return host.strip("[]"), int(port)


def open_stream(url: str, stall_timeout_s: float = 5.0) -> ByteStream:
    """Open a device's byte stream (see the module docstring for the URL forms)."""
    parts = urlsplit(url)
    scheme = parts.scheme if len(parts.scheme) > 1 else "file"  # "C:" is not a scheme
    if scheme == "tcp":
        host, port = _host_port(parts.netloc, url)
        try:
            sock = socket.create_connection((host or "127.0.0.1", port),
                                            timeout=stall_timeout_s)
        except OSError as exc:
            raise ConnectionError(f"{url}: cannot connect: {exc}") from exc
        return ByteStream(_socket_recv(sock, False), url, stall_timeout_s, sock.close)
    if scheme == "udp":
        host, port = _host_port(parts.netloc, url)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host or "0.0.0.0", port))
        stream = ByteStream(_socket_recv(sock, True), url, stall_timeout_s, sock.close)
        stream.local_address = sock.getsockname()[:2]
        return stream
    if scheme == "serial":
        import serial  # pyserial, only needed for serial ports

        query = parse_qs(parts.query)
        baud = int(query.get("baud", ["115200"])[0])
        port = serial.Serial(parts.path, baudrate=baud, timeout=_POLL_S)

        def recv_serial(n: int) -> bytes | None:
            data = port.read(min(n, max(1, port.in_waiting)))
            return data or None  # a serial port has no end: silence is a stall

        return ByteStream(recv_serial, url, stall_timeout_s, port.close)
    if scheme == "file":
        path = Path(parts.path if parts.scheme == "file" else url)
        try:
            fh = path.open("rb")
        except OSError as exc:
            raise FileNotFoundError(f"{path}: cannot open: {exc.strerror or exc}") from exc
        return ByteStream(fh.read, str(path), stall_timeout_s, fh.close)
    raise ValueError(f"{url}: unknown stream kind {scheme!r} (tcp, udp, serial or file)")
