"""IMU samples from a u-blox sensor-fusion receiver: UBX-ESF-RAW → ImuMessage (gpst).

ESF-RAW carries blocks of (data, sTtag): ``data`` packs a 24-bit two's-complement value and a
6-bit data type; samples of one instant share one sensor time tag. Data types and scales
(u-blox ESF measurement data): 14/13/5 = gyro x/y/z in deg/s · 2^-12, 16/17/18 = accel x/y/z
in m/s² · 2^-10, 12 = gyro temperature (ignored). A sample becomes one
:class:`engine.messages.ImuMessage` (gyro rad/s, accel m/s², in the sensor's axes) when all six
axes are present; incomplete instants are counted in ``incomplete_samples``.

Time: the sensor time tag is a free-running 32-bit counter of the receiver in ticks of
1/25600 s = 39.0625 µs (the real ESF-RAW bytes in the tests advance 256 ticks per 10 ms sample
and 25600 ± 7 ticks between 1 s navigation epochs). It is mapped to gpst by
:class:`SensorClock`, anchored at every navigation epoch on this assumption, which u-blox
does not document and which an installation can correct with ``offset_s``:

    the newest sample of the last ESF-RAW message received before a navigation epoch message
    (RXM-RAWX or NAV-TIMEGPS of epoch T) was taken at T.

The receiver sends the IMU batch that closes an epoch before that epoch's navigation output;
the emulator writes its streams that way. The anchor moves with every epoch (the counter
runs on the sensor's own oscillator); a move of more than ``ANCHOR_JUMP_S`` is counted in
``anchor_jumps`` for the integrity layer. Samples received before the first anchor cannot be
dated and are counted in ``untimed_samples``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

import numpy as np
from pyubx2 import UBXMessage

from engine.messages import ImuMessage

__all__ = [
    "STTAG_TICK_S",
    "ESF_TYPES",
    "SensorClock",
    "EsfRawDecoder",
    "esf_raw_blocks",
    "esf_raw_payload",
]

STTAG_TICK_S = 1.0 / 25600.0  # 39.0625 µs
_COUNTER = 1 << 32
GYRO_SCALE = math.radians(2.0**-12)  # rad/s per LSB
ACCEL_SCALE = 2.0**-10  # m/s² per LSB
# ESF data type -> (quantity, axis)
ESF_TYPES = {14: ("gyro", 0), 13: ("gyro", 1), 5: ("gyro", 2),
             16: ("accel", 0), 17: ("accel", 1), 18: ("accel", 2)}
ANCHOR_JUMP_S = 2e-3


class SensorClock:
    """Maps the 32-bit sensor time tag to gpst through an anchor (tag, gpst) pair."""

    def __init__(self, offset_s: float = 0.0):
        self.offset_s = offset_s
        self._anchor: tuple[int, float] | None = None  # (unwrapped tag, gpst)
        self._last_tag: int | None = None  # unwrapped

    @property
    def anchored(self) -> bool:
        return self._anchor is not None

    def unwrap(self, tag: int) -> int:
        """The counter value made continuous across its 2^32 wrap (every ~46.6 h)."""
        if self._last_tag is None:
            self._last_tag = tag
            return tag
        delta = (tag - self._last_tag) % _COUNTER
        if delta >= _COUNTER // 2:  # slightly older than the newest tag seen
            delta -= _COUNTER
        self._last_tag += delta
        return self._last_tag

    def anchor(self, unwrapped_tag: int, gpst: float) -> float:
        """Set the anchor; returns how far it moves the mapping of that tag (s)."""
        moved = 0.0 if self._anchor is None else gpst - self.to_gpst(unwrapped_tag)
        self._anchor = (unwrapped_tag, gpst - self.offset_s)
        return moved

    def to_gpst(self, unwrapped_tag: int) -> float:
        if self._anchor is None:
            raise RuntimeError("sensor clock not anchored yet")
        tag0, t0 = self._anchor
        return t0 + (unwrapped_tag - tag0) * STTAG_TICK_S + self.offset_s


def _field24(word: int) -> int:
    value = word & 0xFFFFFF
    return value - (1 << 24) if value & 0x800000 else value


def esf_raw_blocks(msg: UBXMessage) -> list[tuple[int, int, int]]:
    """(data type, signed 24-bit value, sensor time tag) of each block of an ESF-RAW."""
    payload = msg.payload
    if (len(payload) - 4) % 8:
        raise ValueError(f"ESF-RAW payload of {len(payload)} bytes is not 4 + 8n")
    out = []
    for k in range(4, len(payload), 8):
        data, tag = struct.unpack_from("<II", payload, k)
        out.append(((data >> 24) & 0x3F, _field24(data), tag))
    return out


class EsfRawDecoder:
    """ESF-RAW messages of one receiver → timed IMU samples (see the module docstring)."""

    def __init__(self, offset_s: float = 0.0):
        self.clock = SensorClock(offset_s)
        self._newest_tag: int | None = None  # unwrapped tag of the newest sample received
        self._last_epoch: float | None = None
        self.incomplete_samples = 0
        self.untimed_samples = 0
        self.anchor_jumps = 0

    def navigation_epoch(self, gpst: float) -> None:
        """A navigation epoch message (RXM-RAWX / NAV-TIMEGPS of epoch ``gpst``) arrived."""
        if self._newest_tag is None or gpst == self._last_epoch:
            return
        self._last_epoch = gpst
        if abs(self.clock.anchor(self._newest_tag, gpst)) > ANCHOR_JUMP_S:
            self.anchor_jumps += 1

    def decode(self, msg: UBXMessage) -> list[ImuMessage]:
        """The complete, dated samples of one parsed ESF-RAW message, in time order."""
        groups: dict[int, dict[str, np.ndarray]] = {}
        order: list[int] = []
        for dtype, value, tag in esf_raw_blocks(msg):
            quantity = ESF_TYPES.get(dtype)
            if quantity is None:
                continue
            utag = self.clock.unwrap(tag)
            if utag not in groups:
                groups[utag] = {"gyro": np.full(3, np.nan), "accel": np.full(3, np.nan)}
                order.append(utag)
            name, axis = quantity
            groups[utag][name][axis] = value * (GYRO_SCALE if name == "gyro" else ACCEL_SCALE)
        out = []
        for utag in sorted(order):
            g = groups[utag]
            self._newest_tag = utag if self._newest_tag is None else max(self._newest_tag, utag)
            if np.isnan(g["gyro"]).any() or np.isnan(g["accel"]).any():
                self.incomplete_samples += 1
                continue
            if not self.clock.anchored:
                self.untimed_samples += 1
                continue
            out.append(ImuMessage(self.clock.to_gpst(utag), g["gyro"], g["accel"]))
        return out


def esf_raw_payload(tags: Sequence[int], gyro: Sequence[Sequence[float]],
                    accel: Sequence[Sequence[float]]) -> bytes:
    """ESF-RAW payload of samples (gyro rad/s, accel m/s²) at sensor time tags ``tags``."""
    out = bytearray(4)  # reserved
    for tag, w, f in zip(tags, gyro, accel, strict=True):
        for dtype, (name, axis) in ESF_TYPES.items():
            value, scale = (w[axis], GYRO_SCALE) if name == "gyro" else (f[axis], ACCEL_SCALE)
            raw = round(value / scale)
            if not -(1 << 23) <= raw < (1 << 23):
                raise ValueError(f"{name} {axis} = {value} does not fit ESF-RAW's 24 bits")
            out += struct.pack("<II", (dtype << 24) | (raw & 0xFFFFFF), tag % _COUNTER)
    return bytes(out)
