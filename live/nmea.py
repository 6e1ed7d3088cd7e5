"""NMEA 0183 sentences for the bridge: heading, rate of turn, course/speed, position, time, alerts.

Generated with pynmeagps from a :class:`BridgeState` (what the fused estimate gives the
bridge) and :class:`Alert` records (berthing and integrity alarms):

========  ==================================================================================
HDT       true heading (deg); an empty field when the heading is not valid
THS       true heading and mode indicator: A autonomous, E estimated (dead reckoning),
          S simulator (replay/emulator), V not valid
ROT       rate of turn (deg/min, negative = bow turning to port), A valid / V not valid
VTG       course over ground (true, deg; empty below 0.05 m/s), speed (knots, km/h), mode
GGA       UTC time, latitude, longitude, quality (0 invalid, 1 GNSS, 4 RTK fixed, 5 RTK
          float, 6 dead reckoning, 8 simulator), satellites, HDOP, altitude + geoid separation
ZDA       UTC date and time, local zone 00:00
ALR       alarm: number, condition (A threshold exceeded / V not), acknowledged (A) or not (V)
ALF       alert (IEC 61924-2 bridge alert management): category B, priority (A alarm, W
          warning, C caution), state (V active-unacknowledged, A active-acknowledged,
          U rectified-unacknowledged, N normal), alert id, instance, revision counter, text
========  ==================================================================================

Times are converted from gpst to UTC with the leap seconds given (GPS − UTC, 18 s since
2017). Heights: without a geoid model GGA carries the ellipsoidal height as altitude with a
geoid separation of ``geoid_separation_m`` (0 unless configured), so that altitude +
separation is the ellipsoidal height as the standard defines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime

from pynmeagps import GET, NMEAMessage

from estimator.frames import datetime_from_gpst

__all__ = ["MODES", "BridgeState", "Alert", "SentenceMaker"]

# mode of the fused state -> (THS / VTG mode indicator, GGA quality)
MODES = {
    "rtk-fixed": ("A", 4),
    "rtk-float": ("A", 5),
    "gnss": ("A", 1),
    "dead-reckoning": ("E", 6),
    "simulated": ("S", 8),
    "invalid": ("V", 0),
}
MS_TO_KNOTS = 3600.0 / 1852.0
_PRIORITY = {"alarm": "A", "warning": "W", "caution": "C", "emergency": "E"}


@dataclass(frozen=True)
class BridgeState:
    """What the bridge is told at one instant (any object with these attributes will do)."""

    time: float  # gpst s
    llh_deg: tuple[float, float, float]  # latitude, longitude (deg), ellipsoidal height (m)
    velocity_ned: tuple[float, float, float]  # m/s
    euler: tuple[float, float, float]  # roll, pitch, yaw (rad); yaw = true heading
    rate_of_turn: float  # rad/s about the vertical, positive turning to starboard
    mode: str = "gnss"  # a key of MODES; "invalid" when the integrity layer distrusts it
    satellites: int = 0
    hdop: float | None = None


@dataclass(frozen=True)
class Alert:
    """A berthing or integrity alert as the bridge alert management sees it."""

    alert_id: int  # 1..999
    text: str  # short description (ALF allows 16 characters here; longer is cut)
    priority: str = "warning"  # alarm / warning / caution / emergency
    active: bool = True
    acknowledged: bool = False
    changed: float = 0.0  # gpst of the last change of state
    instance: int = 1
    revision: int = 1


def _num(x: float, digits: int) -> float | str:
    """A field's number, or empty when it is not finite: a NaN goes out as "no data", never
    as the text ``nan`` a bridge display might show or choke on."""
    return round(x, digits) if math.isfinite(x) else ""


def _utc(t_gpst: float, leap_seconds: int) -> datetime:
    return datetime_from_gpst(t_gpst - leap_seconds)


class SentenceMaker:
    """Sentences as bytes (``$...*hh\\r\\n``) from states and alerts."""

    def __init__(self, *, heading_talker: str = "HE", position_talker: str = "GN",
                 alert_talker: str = "II", leap_seconds: int = 18,
                 geoid_separation_m: float = 0.0):
        self.heading_talker = heading_talker
        self.position_talker = position_talker
        self.alert_talker = alert_talker
        self.leap_seconds = leap_seconds
        self.geoid_separation_m = geoid_separation_m
        self._alf_sequence = 0

    def _mode(self, state: BridgeState) -> tuple[str, int]:
        if state.mode not in MODES:
            raise ValueError(f"unknown mode {state.mode!r} (one of {sorted(MODES)})")
        return MODES[state.mode]

    def heading(self, state: BridgeState) -> list[bytes]:
        """HDT, THS and ROT; their fields empty and flagged ``V`` unless the state is valid."""
        indicator, _ = self._mode(state)
        yaw, rate = state.euler[2], state.rate_of_turn
        if not (math.isfinite(yaw) and math.isfinite(rate)):
            indicator = "V"
        valid = indicator != "V"
        hdg = round(math.degrees(yaw) % 360.0, 2) % 360.0 if valid else ""
        rot = round(math.degrees(rate) * 60.0, 1) if valid else ""
        t = self.heading_talker
        return [
            NMEAMessage(t, "HDT", GET, headingT=hdg, headingTu="T").serialize(),
            NMEAMessage(t, "THS", GET, headt=hdg, mi=indicator).serialize(),
            NMEAMessage(t, "ROT", GET, rot=rot, valid="A" if valid else "V").serialize(),
        ]

    def course_speed(self, state: BridgeState) -> bytes:
        """VTG; course and speed empty (mode ``N``) unless the state is valid."""
        indicator, _ = self._mode(state)
        vn, ve, _ = state.velocity_ned
        speed = math.hypot(vn, ve)
        if indicator == "V" or not math.isfinite(speed):
            return NMEAMessage(self.position_talker, "VTG", GET, cogt="", cogtUnit="T",
                               cogm="", cogmUnit="M", sogn="", sognUnit="N", sogk="",
                               sogkUnit="K", posMode="N").serialize()
        cog = round(math.degrees(math.atan2(ve, vn)) % 360.0, 1) % 360.0 \
            if speed >= 0.05 else ""
        return NMEAMessage(self.position_talker, "VTG", GET, cogt=cog, cogtUnit="T", cogm="",
                           cogmUnit="M", sogn=round(speed * MS_TO_KNOTS, 2), sognUnit="N",
                           sogk=round(speed * 3.6, 2), sogkUnit="K",
                           posMode=indicator).serialize()

    def position(self, state: BridgeState) -> bytes:
        """GGA; position empty (quality 0) unless the state is valid, as a receiver without
        a fix sends it."""
        _, quality = self._mode(state)
        lat, lon, h = state.llh_deg
        if not all(math.isfinite(x) for x in (lat, lon, h)):
            quality = 0
        valid = quality != 0
        utc = _utc(state.time, self.leap_seconds)
        hdop = _num(state.hdop, 1) if state.hdop is not None else ""
        return NMEAMessage(
            self.position_talker, "GGA", GET, hpnmeamode=True, time=utc.time(),
            lat=lat if valid else "", NS="N" if not valid or lat >= 0 else "S",
            lon=lon if valid else "", EW="E" if not valid or lon >= 0 else "W",
            quality=quality, numSV=state.satellites, HDOP=hdop,
            alt=round(h - self.geoid_separation_m, 2) if valid else "", altUnit="M",
            sep=round(self.geoid_separation_m, 2), sepUnit="M", diffAge="",
            diffStation="").serialize()

    def time(self, t_gpst: float) -> bytes:
        utc = _utc(t_gpst, self.leap_seconds)
        return NMEAMessage(self.position_talker, "ZDA", GET, time=utc.time(), day=utc.day,
                           month=utc.month, year=utc.year, ltzh="00", ltzn="00").serialize()

    def alert(self, alert: Alert) -> list[bytes]:
        """ALR and ALF of one alert."""
        if not 1 <= alert.alert_id <= 999:
            raise ValueError(f"alert id {alert.alert_id} is not 1..999")
        if alert.priority not in _PRIORITY:
            raise ValueError(f"alert priority {alert.priority!r} not in {sorted(_PRIORITY)}")
        changed = _utc(alert.changed, self.leap_seconds).time()
        text = "".join(c for c in alert.text.upper() if 32 <= ord(c) < 127
                       and c not in "$*,!\\^~")
        if alert.active:
            state = "A" if alert.acknowledged else "V"
        else:
            state = "N" if alert.acknowledged else "U"
        self._alf_sequence = (self._alf_sequence + 1) % 10
        t = self.alert_talker
        return [
            NMEAMessage(t, "ALR", GET, timealarmchange=changed, alarmnum=f"{alert.alert_id:03d}",
                        alarmcond="A" if alert.active else "V",
                        alarmstate="A" if alert.acknowledged else "V",
                        alarmtext=text).serialize(),
            NMEAMessage(t, "ALF", GET, numSen=1, senNum=1, seqmid=self._alf_sequence,
                        timelastchange=changed, alertcat="B",
                        alertpriority=_PRIORITY[alert.priority], alertstate=state, mfrcode="",
                        alertid=f"{alert.alert_id:03d}", alertinst=alert.instance,
                        revisionctr=alert.revision, escalationctr=0,
                        alerttxt=text[:16]).serialize(),
        ]
