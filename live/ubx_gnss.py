"""GNSS from a u-blox receiver's UBX stream: RXM-RAWX → GnssEpoch, RXM-SFRBX → ephemerides.

Field parsing is pyubx2's; the framing is ``ubx_frames``' (a fake header's length must not
swallow the good messages after it); this module maps the fields onto the project's
records with the conventions of the RINEX path (``recordings.rinex.l1_epochs``):

- time tag: gpst = week · 604800 + rcvTow (the receiver's own time tag, GPS scale, as a
  RINEX converter writes it); epochs before the receiver knows the week (week 0) are skipped;
- signals: GPS and QZSS L1 C/A, Galileo E1 (E1-C preferred to E1-B), BeiDou B1I (D1 or D2),
  GLONASS L1OF, i.e. what ``l1_epochs`` reads (C1C/C2I...); other signals and SBAS are left
  out; satellite ids are the RINEX ones (G05, E11, C21, J02, R17);
- pseudorange (m) when prValid, carrier phase (cycles) when cpValid, Doppler (Hz) and C/N0
  (dB-Hz): u-blox reports them in the RINEX sign convention already (phase grows with the
  range, Doppler positive when approaching), so they pass unchanged;
- loss of lock, RINEX LLI: bit 0 (slip possible) when the lock time went back, is shorter
  than the time since the satellite's previous epoch (lost in between), the half-cycle
  correction changed (subHalfCyc toggled: the phase moved by half a cycle), or the receiver
  reset its clock (clkReset); bit 1 (half-cycle ambiguity) while halfCyc is not yet
  resolved. A satellite's first phase is flagged when its lock began after the receiver's
  previous epoch (a newly acquired signal, as receivers and RTKLIB flag it); at the first
  epoch of the stream only a lock time of 0 is.

Ephemerides: GPS/QZSS LNAV subframes 1-3 (+ subframe 4 page 18 for the Klobuchar α/β) and
Galileo I/NAV word types 1-5 become ``KeplerEphemeris`` records (:mod:`live.navmsg`) in a
``NavigationData`` that grows as they arrive (:class:`EphemerisAssembler`, which may start
from a RINEX navigation file). BeiDou and GLONASS subframes are not decoded: seed them from a
RINEX navigation file if those systems are to be used.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from pyubx2 import VALNONE, UBXMessage, UBXReader
from pyubx2.ubxhelpers import calc_checksum

from engine.messages import ImuMessage
from estimator.frames import gpst_from_week_tow
from estimator.records import GnssEpoch, KeplerEphemeris, NavigationData, SatObservation

from .navmsg import (
    GalileoWord,
    LnavSubframe,
    NavMessageError,
    decode_inav_page,
    decode_lnav_subframe,
    inav_ephemeris,
    klobuchar_from_page18,
    lnav_ephemeris,
)
from .streams import ByteStream
from .ubx_imu import EsfRawDecoder

__all__ = [
    "UBX_SYSTEMS",
    "UBX_GNSS_IDS",
    "KEPT_SIGNALS",
    "rinex_sat_id",
    "RawxDecoder",
    "EphemerisAssembler",
    "UbxGnssSource",
]

# u-blox gnssId -> RINEX system letter (SBAS 1 and IMES 4 are not used)
UBX_SYSTEMS = {0: "G", 2: "E", 3: "C", 5: "J", 6: "R"}
UBX_GNSS_IDS = {v: k for k, v in UBX_SYSTEMS.items()}
# u-blox sigId of the kept L1-band signal per system, by preference (see module docstring)
KEPT_SIGNALS = {"G": (0,), "J": (0,), "E": (0, 1), "C": (0, 1), "R": (0,)}
GLONASS_FREQ_ID_OFFSET = 7  # freqId 0..13 = frequency number -7..6
_LOCKTIME_MAX_MS = 64500  # the receiver caps lockTime there
_LOCK_TOLERANCE_MS = 50  # lock-time reports are rounded; an epoch gap is at least 50 ms


def rinex_sat_id(gnss_id: int, sv_id: int) -> str | None:
    """RINEX satellite id of a u-blox (gnssId, svId); None for systems not used."""
    system = UBX_SYSTEMS.get(gnss_id)
    if system is None or not 1 <= sv_id <= 99:
        return None
    return f"{system}{sv_id:02d}"


@dataclass
class _Lock:
    time: float  # gpst of the last epoch the signal's phase was seen
    locktime_ms: int
    sub_half: int


UBX_SYNC = b"\xb5\x62"
# The payload lengths the messages read here can have ((class, id) → check); any other
# message up to OTHER_MAX_LENGTH. Line noise that looks like a header claimed 16 KB, and the
# reader swallowed that much of the good messages after it: a receiver cut off for up to
# 90 s (a user trial).
_LENGTHS = {
    (0x02, 0x15): lambda n: n >= 16 and (n - 16) % 32 == 0 and n <= 16 + 32 * 255,  # RAWX
    (0x02, 0x13): lambda n: n >= 8 and (n - 8) % 4 == 0 and n <= 8 + 4 * 16,  # SFRBX
    (0x10, 0x03): lambda n: n >= 4 and (n - 4) % 8 == 0 and n <= 4 + 8 * 256,  # ESF-RAW
    (0x01, 0x20): lambda n: n == 16,  # NAV-TIMEGPS
}
OTHER_MAX_LENGTH = 2048  # (NAV-SAT with 120 satellites: 1448)


def ubx_frames(stream: ByteStream, on_error: Callable[[Exception], None]) -> Iterator[bytes]:
    """Whole UBX messages (sync to checksum) of a byte stream. A header whose length its
    message cannot have (``_LENGTHS``), or a message whose checksum fails, is noise: the scan
    goes on from the byte after its sync, so that the good messages it overlapped are found
    (``on_error`` is told of each). Bytes between messages (NMEA, garbage) are skipped."""
    buf = bytearray()

    def fill(n: int) -> bool:
        while len(buf) < n:
            chunk = stream.read(n - len(buf))
            if not chunk:
                return False
            buf.extend(chunk)
        return True

    while True:
        k = buf.find(UBX_SYNC)
        if k < 0:
            del buf[:max(len(buf) - 1, 0)]  # (a last 0xB5 may begin a sync)
            if not fill(len(buf) + 1):
                return
            continue
        del buf[:k]
        if not fill(6):
            return
        cls, mid, n = buf[2], buf[3], buf[4] | buf[5] << 8
        ok = _LENGTHS.get((cls, mid), lambda n: n <= OTHER_MAX_LENGTH)(n)
        if ok:
            if not fill(8 + n):
                return
            ok = calc_checksum(bytes(buf[2:6 + n])) == bytes(buf[6 + n:8 + n])
            if ok:
                frame = bytes(buf[:8 + n])
                del buf[:8 + n]
                yield frame
                continue
            on_error(ValueError(f"UBX 0x{cls:02x} 0x{mid:02x}: checksum failed"))
        else:
            on_error(ValueError(f"UBX 0x{cls:02x} 0x{mid:02x}: length {n} impossible"))
        del buf[:1]  # noise: scan again from the byte after its sync


class RawxDecoder:
    """RXM-RAWX messages of one receiver → :class:`GnssEpoch` (keeps the lock history)."""

    def __init__(self) -> None:
        self._locks: dict[str, _Lock] = {}
        self.glonass_slots: dict[str, int] = {}  # "R03" -> frequency number, as seen
        self.leap_seconds: int | None = None  # GPS - UTC when the receiver knows it
        self.skipped_no_time = 0  # epochs before the receiver knew the GPS week
        self.not_finite = 0  # measurements with an infinite or NaN value (left out)
        self._last_time: float | None = None

    def decode(self, msg: UBXMessage) -> GnssEpoch | None:
        """The epoch of a parsed RXM-RAWX message (None before the week is known)."""
        if msg.week == 0:
            self.skipped_no_time += 1
            return None
        t = gpst_from_week_tow(msg.week, msg.rcvTow)
        if msg.leapSec:
            self.leap_seconds = int(msg.leapS)
        clock_reset = bool(msg.clkReset)
        chosen: dict[str, tuple[int, int]] = {}  # sat -> (preference rank, measurement index)
        for i in range(1, msg.numMeas + 1):
            sat = rinex_sat_id(getattr(msg, f"gnssId_{i:02d}"), getattr(msg, f"svId_{i:02d}"))
            if sat is None:
                continue
            kept = KEPT_SIGNALS[sat[0]]
            sig = getattr(msg, f"sigId_{i:02d}")
            if sig not in kept:
                continue
            rank = kept.index(sig)
            if sat not in chosen or rank < chosen[sat][0]:
                chosen[sat] = (rank, i)

        sats: dict[str, SatObservation] = {}
        for sat, (_, i) in sorted(chosen.items()):
            g = lambda name, i=i: getattr(msg, f"{name}_{i:02d}")
            if sat[0] == "R":
                self.glonass_slots[sat] = int(g("freqId")) - GLONASS_FREQ_ID_OFFSET
            if not all(math.isfinite(float(g(name))) for name in ("prMes", "cpMes", "doMes")):
                self.not_finite += 1  # a corrupt message that still checks out: left out
                continue
            pr = float(g("prMes")) if g("prValid") else math.nan
            phase = math.nan
            lli = 0
            if g("cpValid"):
                phase = float(g("cpMes"))
                lli = self._lli(sat, t, int(g("locktime")), int(g("subHalfCyc")), clock_reset)
                if not g("halfCyc"):
                    lli |= 2
            else:
                self._locks.pop(sat, None)  # no phase: the next one starts a new arc
            if math.isnan(pr) and math.isnan(phase):
                continue
            sats[sat] = SatObservation(pseudorange=pr, carrier_phase=phase,
                                       doppler=float(g("doMes")), snr=float(g("cno")), lli=lli)
        self._last_time = t
        return GnssEpoch(time=t, satellites=sats, flag=0)

    def _lli(self, sat: str, t: float, locktime_ms: int, sub_half: int, clock_reset: bool) -> int:
        prev = self._locks.get(sat)
        self._locks[sat] = _Lock(t, locktime_ms, sub_half)
        if prev is None:
            # a new arc: flagged when the lock began after this receiver's previous epoch
            since_ms = 1.0 if self._last_time is None else (t - self._last_time) * 1000.0
            return 1 if locktime_ms < since_ms else 0
        elapsed_ms = (t - prev.time) * 1000.0
        expected = min(prev.locktime_ms + elapsed_ms, _LOCKTIME_MAX_MS)
        slip = (locktime_ms + _LOCK_TOLERANCE_MS < expected or sub_half != prev.sub_half
                or clock_reset)
        return 1 if slip else 0


class EphemerisAssembler:
    """Broadcast subframes/pages → a growing :class:`NavigationData`.

    Subframes are kept per satellite and issue (IODC/IODE, IODnav), so that a record is only
    formed from parts of one issue. ``rejected`` counts the parts that failed a check by
    reason (parity, CRC...): a corrupted subframe from the air is normal and never fatal.
    """

    def __init__(self, seed: NavigationData | None = None):
        self.nav = seed if seed is not None else NavigationData()
        self.rejected: Counter[str] = Counter()
        self.ignored: Counter[str] = Counter()  # systems/signals not decoded
        self._lnav: dict[str, dict[tuple[int, int], LnavSubframe]] = {}
        self._inav: dict[str, dict[tuple[int, int], GalileoWord]] = {}
        self._inav_w5: dict[str, GalileoWord] = {}

    # -- records

    def _add(self, eph: KeplerEphemeris) -> KeplerEphemeris | None:
        """Add a record; None when the same one is already there (re-broadcast)."""
        records = self.nav.ephemerides.setdefault(eph.sat, [])
        if eph in records:
            return None
        # the same issue with changed contents (e.g. health) replaces the older record
        records[:] = [r for r in records if not (isinstance(r, KeplerEphemeris)
                                                 and r.toe == eph.toe and r.iode == eph.iode
                                                 and r.data_source == eph.data_source)]
        records.append(eph)
        records.sort(key=lambda r: r.toe)
        return eph

    # -- GPS / QZSS LNAV

    def add_lnav(self, sat: str, words: list[int], time_hint: float) -> KeplerEphemeris | None:
        """One subframe (ten u-blox words) of ``sat``; the new record it completes, if any."""
        try:
            sf = decode_lnav_subframe(words)
        except NavMessageError as exc:
            self.rejected[str(exc)] += 1
            return None
        if sf.subframe_id == 4:
            iono = klobuchar_from_page18(sf)
            if iono is not None and sat[0] == "G":
                self.nav.iono_alpha, self.nav.iono_beta = iono  # type: ignore[assignment]
                if self.nav.leap_seconds is None:
                    self.nav.leap_seconds = int(sf.fields["delta_t_ls"])
            return None
        if sf.subframe_id == 5:
            return None
        issue = int(sf.fields["iodc"]) & 0xFF if sf.subframe_id == 1 else int(sf.fields["iode"])
        parts = self._lnav.setdefault(sat, {})
        parts[(sf.subframe_id, issue)] = sf
        sfs = [parts.get((k, issue)) for k in (1, 2, 3)]
        if any(s is None for s in sfs):
            return None
        try:
            eph = lnav_ephemeris(sat, sfs[0], sfs[1], sfs[2], time_hint)  # type: ignore[arg-type]
        except NavMessageError as exc:
            self.rejected[str(exc)] += 1
            return None
        return self._add(eph)

    # -- Galileo I/NAV

    def add_inav(self, sat: str, words: list[int], time_hint: float) -> KeplerEphemeris | None:
        """One nominal page pair (eight u-blox words) of ``sat``; the new record, if any."""
        try:
            word = decode_inav_page(words)
        except NavMessageError as exc:
            self.rejected[str(exc)] += 1
            return None
        if word.word_type == 5:
            self._inav_w5[sat] = word
        elif 1 <= word.word_type <= 4:
            self._inav.setdefault(sat, {})[(word.word_type,
                                            int(word.fields["iodnav"]))] = word
        else:
            return None
        w5 = self._inav_w5.get(sat)
        parts = self._inav.get(sat, {})
        for issue in {iod for (_, iod) in parts}:
            ws = {k: parts.get((k, issue)) for k in (1, 2, 3, 4)}
            if w5 is None or any(w is None for w in ws.values()):
                continue
            eph = self._add(inav_ephemeris(sat, {**ws, 5: w5}, time_hint))  # type: ignore[dict-item]
            if eph is not None:
                return eph
        return None

    # -- UBX

    def add_sfrbx(self, msg: UBXMessage, time_hint: float | None) -> KeplerEphemeris | None:
        """A parsed RXM-SFRBX message; ``time_hint`` (gpst, e.g. the receiver's last epoch)
        resolves the week of toe/toc. Without a hint nothing can be dated: ignored."""
        sat = rinex_sat_id(msg.gnssId, msg.svId)
        words = [getattr(msg, f"dwrd_{i:02d}") for i in range(1, msg.numWords + 1)]
        sig = getattr(msg, "sigId", 0)
        if time_hint is None:
            self.ignored["no time yet"] += 1
            return None
        if sat is not None and sat[0] in "GJ" and sig == 0 and len(words) == 10:
            return self.add_lnav(sat, words, time_hint)
        if sat is not None and sat[0] == "E" and sig == 1 and len(words) == 8:
            return self.add_inav(sat, words, time_hint)
        self.ignored[f"gnssId {msg.gnssId} sigId {sig}"] += 1
        return None


class UbxGnssSource:
    """One receiver's UBX byte stream → GNSS epochs (and IMU samples, given an IMU decoder).

    Iterating yields :class:`GnssEpoch` for each RXM-RAWX, and :class:`ImuMessage` samples of
    ESF-RAW when ``imu`` (a :class:`live.ubx_imu.EsfRawDecoder`) is given; RXM-SFRBX feeds
    ``assembler`` (shared by the receivers of one installation). The iteration ends at the end
    of the stream; a stream that stops raises :class:`live.streams.StreamStalled`. Messages
    with a bad checksum or unparsable payload are counted in ``bad_messages``.
    """

    def __init__(self, stream: ByteStream, *, assembler: EphemerisAssembler | None = None,
                 imu: EsfRawDecoder | None = None, name: str = "receiver"):
        self.stream = stream
        self.assembler = assembler if assembler is not None else EphemerisAssembler()
        self.imu = imu
        self.name = name
        self.rawx = RawxDecoder()
        self.bad_messages = 0
        self.last_error: str | None = None
        self.last_epoch_time: float | None = None

    def _error(self, err: Exception) -> None:
        self.bad_messages += 1
        self.last_error = f"{self.name}: {err}"

    @property
    def rejected_total(self) -> int:
        """Messages rejected so far (noise, bad checksum, unparsable), and measurements with
        an infinite or NaN value."""
        return self.bad_messages + self.rawx.not_finite

    @property
    def last_rejection(self) -> str | None:
        return self.last_error

    def __iter__(self) -> Iterator[GnssEpoch | ImuMessage]:
        for raw in ubx_frames(self.stream, self._error):
            try:
                msg = UBXReader.parse(raw, validate=VALNONE)  # (checked by ubx_frames)
            except Exception as exc:  # noqa: BLE001 - pyubx2's errors vary by version
                self._error(exc)
                continue
            ident = msg.identity
            if ident == "RXM-RAWX":
                epoch = self.rawx.decode(msg)
                if epoch is None:
                    continue
                self.last_epoch_time = epoch.time
                if self.rawx.leap_seconds is not None and self.assembler.nav.leap_seconds is None:
                    self.assembler.nav.leap_seconds = self.rawx.leap_seconds
                if self.imu is not None:
                    self.imu.navigation_epoch(epoch.time)
                yield epoch
            elif ident == "RXM-SFRBX":
                self.assembler.add_sfrbx(msg, self.last_epoch_time)
            elif ident == "ESF-RAW" and self.imu is not None:
                yield from self.imu.decode(msg)
            elif (ident == "NAV-TIMEGPS" and self.imu is not None and msg.towValid
                  and msg.weekValid):
                t = gpst_from_week_tow(msg.week, msg.iTOW * 1e-3 + msg.fTOW * 1e-9)
                self.imu.navigation_epoch(t)
