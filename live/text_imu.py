"""A small text protocol for any IMU: one sample per line, over UDP, a serial line or TCP.

Line format (ASCII, ``\\n`` or ``\\r\\n`` terminated)::

    $IMU,<time_gpst>,<gyro_x>,<gyro_y>,<gyro_z>,<accel_x>,<accel_y>,<accel_z>*<hh>

- ``time_gpst``: GPS seconds since 1980-01-06 00:00:00 (the recordings' time scale), when the
  sample was measured; strictly increasing from line to line;
- gyro in rad/s and accel (specific force) in m/s², body axes (forward, right, down) as
  measured, i.e. with the sensor's own errors (the calibration describes them);
- ``*hh``: optional checksum, two hex digits, the XOR of the characters between ``$`` and
  ``*`` (as NMEA 0183); when present it must match;
- blank lines and lines starting with ``#`` are ignored; over UDP a datagram carries one or
  more whole lines.

Example (as :func:`format_line` writes it)::

    $IMU,1403253000.010000,0.001200000,-0.000300000,0.015000000,0.120000000,-0.030000000,-9.790000000*7E

Every line that is not a valid sample is rejected with a reason (counted in ``rejected`` by
reason, the last kept in ``last_rejection`` with the line number): wrong field count, a
value that is not a number, NaN or infinite, a rate beyond ±35 rad/s or a specific force
beyond ±160 m/s² (far past any navigation-grade or MEMS range: garbage, not motion), a bad
checksum, a time not after the previous sample's (a sample more than ``JUMP_S`` after it
is passed on, but the order moves there only once a later sample follows it: one line far
ahead must not reject the good ones after it).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterator, Sequence

import numpy as np

from engine.messages import ImuMessage

from .streams import ByteStream

__all__ = ["MAX_RATE", "MAX_SPECIFIC_FORCE", "format_line", "TextImuParser", "TextImuSource"]

JUMP_S = 0.5  # a sample this far after the previous one sets the order once one follows it

MAX_RATE = 35.0  # rad/s (2000 deg/s)
MAX_SPECIFIC_FORCE = 160.0  # m/s² (16 g)
_FIELDS = ("time", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")


def _checksum(body: str) -> str:
    value = 0
    for ch in body.encode("ascii"):
        value ^= ch
    return f"{value:02X}"


def format_line(t: float, gyro: Sequence[float], accel: Sequence[float]) -> bytes:
    """One sample as a protocol line (µs time, 1e-9 rad/s and m/s² resolution)."""
    body = "IMU,{:.6f},{:.9f},{:.9f},{:.9f},{:.9f},{:.9f},{:.9f}".format(t, *gyro, *accel)
    return f"${body}*{_checksum(body)}\r\n".encode("ascii")


class TextImuParser:
    """Parses protocol lines one at a time, rejecting (and counting) the bad ones."""

    def __init__(self) -> None:
        self.rejected: Counter[str] = Counter()
        self.last_rejection: str | None = None
        self.accepted = 0
        self.line_number = 0
        self._last_time = -math.inf
        self._jump: float | None = None  # a sample far after the last, not yet followed

    def _reject(self, reason: str) -> None:
        self.rejected[reason] += 1
        self.last_rejection = f"line {self.line_number}: {reason}"

    def parse_line(self, line: bytes | str) -> ImuMessage | None:
        """The sample of a line; None for a blank/comment line or a rejected one."""
        self.line_number += 1
        if isinstance(line, bytes):
            try:
                line = line.decode("ascii")
            except UnicodeDecodeError:
                self._reject("not ASCII")
                return None
        text = line.strip()
        if not text or text.startswith("#"):
            return None
        if not text.startswith("$IMU,"):
            self._reject("does not start with $IMU,")
            return None
        body = text[1:]
        if "*" in body:
            body, _, given = body.partition("*")
            if given.upper() != _checksum(body):
                self._reject("checksum mismatch")
                return None
        parts = body.split(",")[1:]
        if len(parts) != len(_FIELDS):
            self._reject(f"{len(parts)} fields, expected {len(_FIELDS)}")
            return None
        values = []
        for name, part in zip(_FIELDS, parts, strict=True):
            try:
                v = float(part)
            except ValueError:
                self._reject(f"{name} is not a number: {part!r}")
                return None
            if not math.isfinite(v):
                self._reject(f"{name} is {part}")
                return None
            values.append(v)
        t = values[0]
        gyro, accel = np.array(values[1:4]), np.array(values[4:7])
        if np.abs(gyro).max() > MAX_RATE:
            self._reject(f"rotation rate beyond ±{MAX_RATE:g} rad/s")
            return None
        if np.abs(accel).max() > MAX_SPECIFIC_FORCE:
            self._reject(f"specific force beyond ±{MAX_SPECIFIC_FORCE:g} m/s²")
            return None
        if t <= self._last_time:
            self._reject("time not after the previous sample's")
            return None
        if t - self._last_time > JUMP_S and self._jump is None:
            # passed on (the merge judges it against the receivers' clock) but not taken as
            # the order until a later sample follows it: one line 2 s ahead made the next
            # 200 good ones "not after the previous" (a user trial)
            self._jump = t
        else:
            self._last_time, self._jump = t, None
        self.accepted += 1
        return ImuMessage(t, gyro, accel)


class TextImuSource:
    """IMU samples from a byte stream of protocol lines (ends with the stream; a stream
    that stops raises :class:`live.streams.StreamStalled`)."""

    def __init__(self, stream: ByteStream):
        self.stream = stream
        self.parser = TextImuParser()

    @property
    def rejected_total(self) -> int:
        """Lines rejected so far (``TextImuParser.rejected``)."""
        return sum(self.parser.rejected.values())

    @property
    def last_rejection(self) -> str | None:
        return self.parser.last_rejection

    def __iter__(self) -> Iterator[ImuMessage]:
        while True:
            line = self.stream.readline()
            if not line:
                return
            sample = self.parser.parse_line(line)
            if sample is not None:
                yield sample
