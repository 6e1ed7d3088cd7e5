"""A session's alarms: what the officer is alerted to, in the API and in every frame of the
stream. An alarm is raised, may be acknowledged (it then stops sounding but stays listed while
it is active) and clears by itself when its cause has gone.

- **integrity** (severity ``alarm``): the fused pose is no longer trusted after it had been
  (``estimator.integrity``: a fault, or a protection level beyond its alert limit); the message
  is the first reason. It is raised within the frame the engine declares the loss — within a
  second of a fault the engine detects.
- **faults** the engine raised (``Fusion.alerts()``, severity ``warning``: a receiver silent,
  an IMU gap bridged, frames skipped …) stay listed while active.

Berthing alarms (approach speed against distance) join the same list.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from estimator.integrity import CRITICAL


@dataclass
class AlarmEntry:
    id: str
    kind: str
    severity: str  # "alarm" | "warning" | "caution"
    message: str
    since_s: float
    active: bool = True
    acknowledged: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {"id": self.id, "kind": self.kind, "severity": self.severity,
                "message": self.message, "since_s": round(self.since_s, 3),
                "active": self.active, "acknowledged": self.acknowledged}


class AlarmBook:
    """The alarms of one session (thread-safe)."""

    def __init__(self, start_gpst: float) -> None:
        self.start_gpst = start_gpst
        self._lock = threading.Lock()
        self._alarms: dict[str, AlarmEntry] = {}
        self._counter = 0
        self._was_trusted = False
        self._seen_alerts = 0

    def update(self, state: Any, engine_alerts: list[Any]) -> None:
        """A new state and the engine's alert history so far."""
        integrity = getattr(state.status, "integrity", None)
        t = float(state.time) - self.start_gpst
        with self._lock:
            if integrity is not None:
                if integrity.trusted:
                    self._was_trusted = True
                    self._clear("integrity")
                elif self._was_trusted:
                    self._raise("integrity", "alarm", t, "Integrity lost: " + (
                        integrity.reasons[0] if integrity.reasons else integrity.mode))
            for alert in engine_alerts[self._seen_alerts:]:
                if alert.active:
                    self._raise(alert.kind, "alarm" if alert.kind in CRITICAL and
                                self._was_trusted else "warning",
                                alert.t - self.start_gpst, alert.message)
                else:
                    self._clear(alert.kind)
            self._seen_alerts = len(engine_alerts)

    def _raise(self, kind: str, severity: str, t: float, message: str) -> None:
        current = self._alarms.get(kind)
        if current is not None and current.active:
            current.message = message  # still the same alarm: keep its acknowledgement
            return
        self._counter += 1
        self._alarms[kind] = AlarmEntry(f"A{self._counter}", kind, severity, message, t)

    def _clear(self, kind: str) -> None:
        if kind in self._alarms:
            self._alarms[kind].active = False

    def rewind(self) -> None:
        """The replay went back: the alarms are those of the new run."""
        with self._lock:
            self._alarms.clear()
            self._was_trusted = False
            self._seen_alerts = 0

    def active(self) -> list[dict[str, Any]]:
        with self._lock:
            return [a.as_dict() for a in self._alarms.values() if a.active]

    def all(self) -> list[dict[str, Any]]:
        with self._lock:
            return [a.as_dict() for a in self._alarms.values()]

    def acknowledge(self, alarm_id: str) -> dict[str, Any] | None:
        """Acknowledge an alarm by id; None when there is no such alarm."""
        with self._lock:
            for a in self._alarms.values():
                if a.id == alarm_id:
                    a.acknowledged = True
                    return a.as_dict()
        return None
