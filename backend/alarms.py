"""A session's alarms: what the officer is alerted to, in the API and in every frame of the
stream. An alarm is raised, may be acknowledged (it then stops sounding but stays listed while
it is active) and clears by itself when its cause has gone.

- **integrity** (severity ``alarm``): the fused pose is no longer trusted after it had been
  (``estimator.integrity``: a fault, or a protection level beyond its alert limit); the message
  is the first reason. It is raised within the frame the engine declares the loss — within a
  second of a fault the engine detects.
- **faults** the engine raised (``Fusion.alerts()``, severity ``warning``: a receiver silent,
  an IMU gap bridged, frames skipped …) stay listed while active.

An integrity or fault alarm that comes back within ``REARM_S`` of clearing for the same cause,
no higher than it was, is the same alarm again (its acknowledgement kept, ``repeats``
counted), not a new one sounding: a protection level hovering at its limit, or IMU spikes
every half second, had the officer acknowledging a dozen alarms in a few seconds for one
cause (a user trial).

- **berthing** (``approach-bow``, ``approach-stern``): the bow or stern closing the berth line
  faster than the approach-speed limit for its distance (``ApproachLimit`` table, tighter as
  the distance shrinks, in the spirit of berthing-velocity guidance): severity ``warning``
  (amber) above the row's warning speed, ``alarm`` (red, sounding) above its alarm speed.
  Only while the fused pose is trusted (the integrity alarm says when it is not). A rise from
  amber to red is a new alarm (it sounds even if the amber one was acknowledged).
"""

from __future__ import annotations

import re
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

from estimator.integrity import CRITICAL


@dataclass(frozen=True)
class ApproachLimit:
    """One row of the approach-speed table: at distances below ``within_m``."""

    within_m: float
    warning_cms: float  # amber above this closing speed (cm/s, as crews give it)
    alarm_cms: float  # red above this


# Default: tighter as the distance shrinks; nothing beyond 50 m (the approach, not the
# berthing). A small craft's or a large ship's own limits are set per session (API, page).
DEFAULT_APPROACH_LIMITS = (
    ApproachLimit(3.0, 10.0, 15.0),
    ApproachLimit(10.0, 20.0, 30.0),
    ApproachLimit(20.0, 40.0, 60.0),
    ApproachLimit(50.0, 80.0, 120.0),
)
CLEAR_FRACTION = 0.9  # an approach alarm clears below this fraction of its limit (no chatter)
REARM_S = 5.0  # an alarm back within this of clearing is the same alarm again
HISTORY_MAX = 1000  # alarms a session lists (a live one runs for hours)
SEVERITY_RANK = {"caution": 0, "warning": 1, "alarm": 2}


def approach_limit(limits: tuple[ApproachLimit, ...], distance_m: float
                   ) -> ApproachLimit | None:
    """The row that applies at ``distance_m`` (the nearest band that contains it); ``limits``
    sorted by ``within_m``, as the book keeps them."""
    for row in limits:
        if distance_m < row.within_m:
            return row
    return None


@dataclass
class AlarmEntry:
    id: str
    kind: str
    severity: str  # "alarm" | "warning" | "caution"
    message: str
    since_s: float
    active: bool = True
    acknowledged: bool = False
    # the worst it was (an alarm easing to a warning stays one: the run's review must see the
    # red it raised, not the amber it ended as), with what it said then and when
    peak_severity: str = ""
    peak_message: str = ""
    peak_s: float = 0.0
    first_message: str = ""  # what it said when raised: the cause, as later words replace it
    cleared_s: float | None = None  # when it last cleared (None: active, or never)
    repeats: int = 0  # times it came back within REARM_S of clearing

    def __post_init__(self) -> None:
        if not self.peak_severity:
            self.peak_severity, self.peak_message, self.peak_s = \
                self.severity, self.message, self.since_s
        self.first_message = self.first_message or self.message

    def as_dict(self) -> dict[str, Any]:
        return {"id": self.id, "kind": self.kind, "severity": self.severity,
                "message": self.message, "since_s": round(self.since_s, 3),
                "active": self.active, "acknowledged": self.acknowledged,
                "peak_severity": self.peak_severity, "peak_message": self.peak_message,
                "peak_s": round(self.peak_s, 3), "first_message": self.first_message,
                "repeats": self.repeats}


class AlarmBook:
    """The alarms of one session (thread-safe)."""

    def __init__(self, start_gpst: float) -> None:
        self.start_gpst = start_gpst
        self._lock = threading.Lock()
        self._alarms: dict[str, AlarmEntry] = {}  # the latest of each kind
        self._history: deque[AlarmEntry] = deque(maxlen=HISTORY_MAX)  # raised, in order
        self._counter = 0
        self._was_trusted = False
        self._seen_alerts = 0
        self.approach_limits: tuple[ApproachLimit, ...] = DEFAULT_APPROACH_LIMITS

    def update(self, state: Any, engine_alerts: list[Any],
               berth: dict[str, float | None] | None = None,
               engine_active: list[Any] = ()) -> None:
        """A new state, the engine's alert history so far, the berth geometry at that
        state (``geometry.berth_metrics``; None without a berth line) and the engine's active
        alerts, whose current words replace those they were raised with (a receiver "silent
        for 1 epoch" while silent for ten)."""
        integrity = getattr(state.status, "integrity", None)
        t = float(state.time) - self.start_gpst
        with self._lock:
            if integrity is not None:
                if integrity.trusted:
                    self._was_trusted = True
                    self._clear("integrity", t)
                elif self._was_trusted:
                    self._raise("integrity", "alarm", t, "Integrity lost: " + (
                        integrity.reasons[0] if integrity.reasons else integrity.mode))
            for alert in engine_alerts[self._seen_alerts:]:
                if alert.active:
                    self._raise(alert.kind, "alarm" if alert.kind in CRITICAL and
                                self._was_trusted else "warning",
                                alert.t - self.start_gpst, alert.message)
                else:
                    self._clear(alert.kind, alert.t - self.start_gpst)
            self._seen_alerts = len(engine_alerts)
            for alert in engine_active:
                entry = self._alarms.get(alert.kind)
                if entry is not None and entry.active and entry.message != alert.message:
                    entry.message = alert.message
                    if entry.severity == entry.peak_severity:
                        entry.peak_message = alert.message
            trusted = integrity is None or integrity.trusted
            for end in ("bow", "stern"):
                self._approach(end, t, berth if trusted else None)

    def _approach(self, end: str, t: float, berth: dict[str, float | None] | None) -> None:
        kind = f"approach-{end}"
        distance = None if berth is None else berth.get(f"{end}_distance_m")
        mps = None if berth is None else berth.get(f"{end}_approach_mps")
        closing = None if mps is None else 100.0 * mps  # cm/s
        row = None if distance is None else approach_limit(self.approach_limits,
                                                           max(distance, 0.0))
        if row is None or closing is None:
            self._clear(kind, t)
            return
        current = self._alarms.get(kind)
        active = current.severity if current is not None and current.active else None
        # hysteresis: an active level holds until the speed is clearly below its limit
        if closing > row.alarm_cms or (active == "alarm" and
                                       closing > CLEAR_FRACTION * row.alarm_cms):
            severity, limit = "alarm", row.alarm_cms
        elif closing > row.warning_cms or (active is not None and
                                           closing > CLEAR_FRACTION * row.warning_cms):
            severity, limit = "warning", row.warning_cms
        else:
            self._clear(kind, t)
            return
        # held by the hysteresis below its limit: say so, or the figures contradict it
        held = "" if closing > limit else f", held until below {CLEAR_FRACTION * limit:.0f}"
        self._raise(kind, severity, t,
                    f"{end.capitalize()} closing the berth at {closing:.0f} cm/s, "
                    f"{_distance_text(distance)} off (limit {limit:g} cm/s within "
                    f"{row.within_m:g} m{held})")

    def set_approach_limits(self, limits: list[ApproachLimit]) -> None:
        with self._lock:
            self.approach_limits = tuple(sorted(limits, key=lambda r: r.within_m))

    def _raise(self, kind: str, severity: str, t: float, message: str) -> None:
        current = self._alarms.get(kind)
        # Back within REARM_S for the same cause, the figures aside (a protection level
        # hovering, a spike again): the same alarm. Another cause is news (a PL at start-up
        # and an IMU gap 4 s later were one alarm "since 1.5 s"), and so is a ship closing too
        # fast again (the approach alarms have their own hysteresis against chatter).
        back = current is not None and not current.active and current.cleared_s is not None \
            and 0.0 <= t - current.cleared_s <= REARM_S and not kind.startswith("approach-") \
            and _cause(current.message) == _cause(message)
        if current is not None and (current.active or back) and \
                SEVERITY_RANK[severity] <= SEVERITY_RANK[current.severity]:
            # still the same alarm (or eased to a lower level, or back at once after
            # clearing): keep its acknowledgement
            if back:
                current.active, current.cleared_s = True, None
                current.repeats += 1
            current.message, current.severity = message, severity
            if severity == current.peak_severity:
                current.peak_message, current.peak_s = message, t  # its latest words at the peak
            return
        if current is not None:
            current.active = False  # a rise to a higher level: the new alarm replaces it
        self._counter += 1
        entry = AlarmEntry(f"A{self._counter}", kind, severity, message, t)
        self._alarms[kind] = entry
        self._history.append(entry)

    def _clear(self, kind: str, t: float) -> None:
        current = self._alarms.get(kind)
        if current is not None and current.active:
            current.active, current.cleared_s = False, t

    def rewind(self) -> None:
        """The replay went back: the alarms are those of the new run."""
        with self._lock:
            self._alarms.clear()
            self._history.clear()
            self._was_trusted = False
            self._seen_alerts = 0

    def active(self) -> list[dict[str, Any]]:
        with self._lock:
            return [a.as_dict() for a in self._alarms.values() if a.active]

    def all(self) -> list[dict[str, Any]]:
        """The alarms raised in this run (the last ``HISTORY_MAX``), in order: a cleared one
        keeps its last message."""
        with self._lock:
            return [a.as_dict() for a in self._history]

    def acknowledge(self, alarm_id: str) -> dict[str, Any] | None:
        """Acknowledge an alarm by id; None when there is no such alarm."""
        with self._lock:
            for a in self._history:
                if a.id == alarm_id:
                    a.acknowledged = True
                    return a.as_dict()
        return None


def _cause(message: str) -> str:
    """A message with its figures left out: what it is about."""
    return re.sub(r"\d+(\.\d+)?", "#", message)


def _distance_text(d: float) -> str:
    """A distance with the digits its range deserves (cm below 5 m, dm below 50 m)."""
    return f"{d:.2f} m" if d < 5 else f"{d:.1f} m" if d < 50 else f"{d:.0f} m"
