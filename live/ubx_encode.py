"""UBX encoders for the emulator: GnssEpoch → RXM-RAWX, ephemerides → RXM-SFRBX, IMU → ESF-RAW.

The inverse of :mod:`live.ubx_gnss` / :mod:`live.ubx_imu`, message construction and framing by
pyubx2 (``UBXMessage(...).serialize()``). What a receiver would report that a recording
does not hold is synthesised so that decoding gives the recording back:

- RAWX lock time: the time since the start of the satellite's phase arc (capped at 64.5 s);
  an arc starts (lock time 0) at every LLI bit 0; a phase that appears without it counts as
  locked for long already (64.5 s);
  RINEX LLI bit 1 (half-cycle unresolved) ↔ halfCyc = 0. C/N0 is an integer dB-Hz, Doppler a
  float32: those two round; pseudorange and phase are float64 and pass exactly.
- SFRBX: LNAV subframes 1-3 (+ subframe 4 page 18 with the Klobuchar α/β) for GPS/QZSS,
  I/NAV word types 1-5 for Galileo (:mod:`live.navmsg`).
- ESF-RAW: pyubx2 builds this variable-length message only from a payload, packed by
  :func:`live.ubx_imu.esf_raw_payload`.

:func:`receiver_messages` orders one receiver's messages as a u-blox receiver sends them, so
that the decoders' assumptions hold: at each epoch first the ESF-RAW batch of the IMU samples
up to and including the epoch (the decoder dates its newest sample at the epoch, see
:mod:`live.ubx_imu`: exact when the IMU samples fall on the epochs, as in the recordings),
then RXM-RAWX; every ``sfrbx_period_s`` (30 s, the LNAV frame period) the SFRBX of the
ephemerides in use come first, right after the previous epoch (``SFRBX_LEAD_S`` before
the first one): an epoch's
ephemerides are known when it is decoded (as for a receiver tracking for a while), and the
RAWX is not held up behind them (its arrival times the camera, see ``live.source``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

from pyubx2 import GET, UBXMessage

from estimator.ephemeris import is_beidou_geo, select_ephemeris
from estimator.frames import SECONDS_PER_WEEK, week_tow_from_gpst
from estimator.records import GnssEpoch, ImuData, KeplerEphemeris, NavigationData

from .navmsg import inav_words, lnav_subframes
from .ubx_gnss import GLONASS_FREQ_ID_OFFSET, UBX_GNSS_IDS
from .ubx_imu import STTAG_TICK_S, esf_raw_payload

__all__ = ["RawxEncoder", "sfrbx_messages", "esf_raw_message", "receiver_messages"]

_LOCKTIME_MAX_MS = 64500


class RawxEncoder:
    """GnssEpochs of one receiver → RXM-RAWX message bytes (keeps the phase arcs)."""

    def __init__(self, glonass_slots: dict[str, int] | None = None, leap_seconds: int = 18):
        self.glonass_slots = dict(glonass_slots or {})
        self.leap_seconds = leap_seconds
        self._arc_start: dict[str, float] = {}

    def _locktime_ms(self, sat: str, t: float, slip: bool) -> int:
        if slip:
            self._arc_start[sat] = t
        elif sat not in self._arc_start:
            self._arc_start[sat] = -math.inf  # no slip flagged: locked for long already
        age = t - self._arc_start[sat]
        return int(min(_LOCKTIME_MAX_MS, round(age * 1000.0))) if math.isfinite(age) \
            else _LOCKTIME_MAX_MS

    def encode(self, epoch: GnssEpoch) -> bytes:
        week, tow = week_tow_from_gpst(epoch.time)
        fields: dict[str, object] = {"rcvTow": tow, "week": week, "leapS": self.leap_seconds,
                                     "leapSec": 1, "numMeas": len(epoch.satellites)}
        for k, sat in enumerate(sorted(epoch.satellites), start=1):
            o = epoch.satellites[sat]
            system = sat[0]
            if system not in UBX_GNSS_IDS:
                raise ValueError(f"{sat}: system {system} has no UBX encoding here")
            has_phase = math.isfinite(o.carrier_phase)
            if has_phase:
                lock = self._locktime_ms(sat, epoch.time, bool(o.lli & 1))
            else:
                self._arc_start.pop(sat, None)
                lock = 0
            sig = 1 if system == "C" and is_beidou_geo(sat) else 0  # B1I D2 on GEOs
            freq_id = 0
            if system == "R":
                if sat not in self.glonass_slots:
                    raise ValueError(f"{sat}: GLONASS frequency number unknown")
                freq_id = self.glonass_slots[sat] + GLONASS_FREQ_ID_OFFSET
            cno = 0 if not math.isfinite(o.snr) else min(255, max(0, round(o.snr)))
            n = f"{k:02d}"
            fields.update({
                f"prMes_{n}": o.pseudorange if math.isfinite(o.pseudorange) else 0.0,
                f"cpMes_{n}": o.carrier_phase if has_phase else 0.0,
                f"doMes_{n}": o.doppler, f"gnssId_{n}": UBX_GNSS_IDS[system],
                f"svId_{n}": int(sat[1:]), f"sigId_{n}": sig, f"freqId_{n}": freq_id,
                f"locktime_{n}": lock, f"cno_{n}": cno,
                f"prValid_{n}": int(math.isfinite(o.pseudorange)), f"cpValid_{n}": int(has_phase),
                f"halfCyc_{n}": int(has_phase and not o.lli & 2), f"subHalfCyc_{n}": 0,
            })
        return UBXMessage("RXM", "RXM-RAWX", GET, **fields).serialize()


def sfrbx_messages(eph: KeplerEphemeris, t: float, *,
                   iono: tuple[Sequence[float], Sequence[float]] | None = None) -> list[bytes]:
    """RXM-SFRBX messages broadcasting ``eph``, sent from gpst ``t`` on (GPS/QZSS LNAV
    subframes 1-3, + page 18 with ``iono`` = (alpha, beta); Galileo I/NAV words 1-5)."""
    system = eph.sat[0]
    tow = (t % SECONDS_PER_WEEK) // 6 * 6
    if system in "GJ":
        words, sig = lnav_subframes(eph, tow, iono=iono), 0
    elif system == "E":
        words, sig = inav_words(eph, tow), 1  # E1-B
    else:
        raise ValueError(f"{eph.sat}: only GPS/QZSS LNAV and Galileo I/NAV are encoded")
    return [UBXMessage("RXM", "RXM-SFRBX", GET, gnssId=UBX_GNSS_IDS[system],
                       svId=int(eph.sat[1:]), sigId=sig, numWords=len(w), version=2,
                       **{f"dwrd_{i:02d}": x for i, x in enumerate(w, start=1)}).serialize()
            for w in words]


def esf_raw_message(tags: Sequence[int], gyro: Sequence[Sequence[float]],
                    accel: Sequence[Sequence[float]]) -> bytes:
    """UBX-ESF-RAW bytes of IMU samples (rad/s, m/s²) at sensor time tags ``tags``."""
    return UBXMessage("ESF", "ESF-RAW", GET,
                      payload=esf_raw_payload(tags, gyro, accel)).serialize()


SFRBX_LEAD_S = 0.5  # the subframes of an epoch's ephemerides are sent this long before it
_ESF_BATCH = 10  # samples per ESF-RAW message (as a u-blox receiver at 100 Hz sends them)


def receiver_messages(epochs: Sequence[GnssEpoch], nav: NavigationData, *,
                      imu: ImuData | None = None, glonass_slots: dict[str, int] | None = None,
                      leap_seconds: int = 18, sfrbx_period_s: float = 30.0
                      ) -> Iterator[tuple[float, bytes]]:
    """(gpst due, message bytes) of one receiver's UBX stream, in sending order.

    ``epochs``: the receiver's observation epochs; ``nav``: the ephemerides broadcast (GPS,
    QZSS LNAV and Galileo I/NAV of the satellites observed; other systems are not encoded);
    ``imu``: samples sent as ESF-RAW in the same stream (a u-blox sensor-fusion receiver).
    """
    rawx = RawxEncoder(glonass_slots, leap_seconds)
    # what is broadcast: LNAV records, and the I/NAV ones of Galileo (not F/NAV: E5a only)
    broadcast = NavigationData(ephemerides={
        sat: [e for e in records if isinstance(e, KeplerEphemeris)
              and (sat[0] != "E" or e.data_source & 1)]
        for sat, records in nav.ephemerides.items() if sat[0] in "GJE"})
    iono = ((nav.iono_alpha, nav.iono_beta) if nav.iono_alpha is not None
            and nav.iono_beta is not None else None)
    k_imu = 0
    tag0 = epochs[0].time if epochs else 0.0
    last_broadcast = -math.inf
    last_due: float | None = None
    for epoch in epochs:
        t = epoch.time
        if t - last_broadcast >= sfrbx_period_s - 1e-6:
            # right after the previous epoch (the stream stays in time order)
            sfrbx_due = t - SFRBX_LEAD_S if last_due is None else last_due
            last_broadcast = t
            for sat in sorted(epoch.satellites):
                eph = select_ephemeris(broadcast, sat, t)
                if isinstance(eph, KeplerEphemeris):
                    for msg in sfrbx_messages(eph, t - 1.0, iono=iono if sat[0] == "G"
                                              else None):
                        yield sfrbx_due, msg
        if imu is not None:
            end = k_imu
            while end < len(imu.time) and imu.time[end] <= t + 1e-9:
                end += 1
            for a in range(k_imu, end, _ESF_BATCH):
                b = min(a + _ESF_BATCH, end)
                tags = [round((float(x) - tag0) / STTAG_TICK_S) for x in imu.time[a:b]]
                yield float(imu.time[b - 1]), esf_raw_message(tags, imu.gyro[a:b],
                                                              imu.accel[a:b])
            k_imu = end
        yield t, rawx.encode(epoch)
        last_due = t
