"""A session's history of fused states, one per processed frame, and what the API asks of it:
the pose at a time, the trajectory, the error against the recording's reference.

Times in the API are seconds from the recording start; inside, gpst. The history shares the
session's lock (the replay thread appends, API threads read).
"""

from __future__ import annotations

import bisect
import threading
from typing import Any

import numpy as np

from estimator.frames import ecef_to_ned, geodetic_to_ecef, wrap_angle
from estimator.pipeline import EXTRAPOLATE_S
from recordings.format import Recording

from .errors import Conflict, NotFound, Unprocessable
from .overlay import pose_dict

FRAME_MATCH_S = 0.06  # a frame_time matches a stored frame within this (frames are 0.1 s apart)
CSV_HEADER = ("t,gpst,north,east,down,lat_deg,lon_deg,height,roll_deg,pitch_deg,yaw_deg,"
              "v_north,v_east,v_down,std_north,std_east,std_down,phase")


def is_current(state: Any | None, t: float) -> bool:
    """Whether ``state`` is the fused pose at frame time ``t`` (gpst). The fusion extrapolates
    its state to a frame at most ``EXTRAPOLATE_S``; one further behind is the last it could
    make (no IMU since): shown for that frame it would be a stale pose looking live."""
    return state is not None and t - float(state.time) <= EXTRAPOLATE_S + 1e-6


class History:
    """Fused states in time order (``append``; ``rewind`` after a seek back)."""

    def __init__(self, rec: Recording, lock: threading.RLock) -> None:
        self.rec = rec
        self.lock = lock
        self.start_gpst = float(rec.manifest.start_gpst)
        self.end_gpst = float(max(rec.frame_times[-1], rec.imu.time[-1]))
        self._times: list[float] = []
        self._states: list[Any] = []

    # ------------------------------------------------------------------------ writing

    def append(self, t: float, state: Any) -> None:
        """The state at frame time ``t``; one that is not current there is not a pose of it
        (``is_current``) and is left out."""
        if not is_current(state, t):
            return
        with self.lock:
            self._times.append(t)
            self._states.append(state)
            self.end_gpst = max(self.end_gpst, t)  # a live session's span grows

    def rewind(self, t: float | None) -> None:
        """Forget the states after gpst ``t`` (all when None)."""
        with self.lock:
            keep = 0 if t is None else bisect.bisect_right(self._times, t)
            del self._times[keep:], self._states[keep:]

    # ------------------------------------------------------------------------ queries

    def gpst(self, t: float) -> float:
        """Recording-relative seconds → gpst, checked against the recording span."""
        duration = self.end_gpst - self.start_gpst
        if not 0.0 <= t <= duration + 1e-9:
            raise Unprocessable(f"time {t:g} s is outside the recording (0 … {duration:.3f} s)")
        return self.start_gpst + t

    def latest(self) -> Any | None:
        with self.lock:
            return self._states[-1] if self._states else None

    def state_at(self, t: float) -> Any:
        """The stored state of the last frame at or before recording time ``t`` (s)."""
        g = self.gpst(t)
        with self.lock:
            if not self._times:
                raise Conflict("no fused pose stored yet")
            if g > self._times[-1] + FRAME_MATCH_S:
                raise Conflict(_beyond(t, self._times[-1] - self.start_gpst))
            i = bisect.bisect_right(self._times, g + 1e-9) - 1
            if i < 0:
                raise NotFound(f"no fused pose at or before t = {t:g} s (the first is at "
                               f"{self._times[0] - self.start_gpst:.3f} s)")
            return self._states[i]

    def frame_state(self, t: float) -> Any:
        """The stored state of the frame at recording time ``t`` (within FRAME_MATCH_S)."""
        g = self.gpst(t)
        with self.lock:
            if not self._times:
                raise Conflict("no fused pose stored yet")
            # The stored frame nearest to t: the newest frame itself must match (t + tolerance
            # may lie beyond the history by a rounding error).
            i = bisect.bisect_left(self._times, g - FRAME_MATCH_S)
            if i < len(self._times) and abs(self._times[i] - g) <= FRAME_MATCH_S:
                return self._states[i]
            last = self._times[-1] - self.start_gpst
        if g > self.gpst(last) + FRAME_MATCH_S:
            raise Conflict(_beyond(t, last))
        raise NotFound(f"no fused pose for a frame at t = {t:g} s")

    def at_gpst(self, t: float) -> Any | None:
        """The stored state of the frame at gpst ``t`` (None when there is none)."""
        with self.lock:
            i = bisect.bisect_left(self._times, t - 1e-6)
            if i < len(self._times) and abs(self._times[i] - t) < 1e-6:
                return self._states[i]
        return None

    def states(self) -> list[Any]:
        with self.lock:
            return list(self._states)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(times (N,), body positions (N,3)) of the fused trajectory so far."""
        with self.lock:
            times = np.array(self._times)
            pos = np.array([s.position_ned for s in self._states]).reshape(-1, 3)
        return times, pos

    def trajectory(self) -> dict[str, Any]:
        states = self.states()
        rows = [pose_dict(s, self.start_gpst) for s in states]
        return {
            "count": len(rows),
            "t": [r["t"] for r in rows],
            "position_ned": [r["position_ned"] for r in rows],
            "llh_deg": [r["llh_deg"] for r in rows],
            "velocity_ned": [r["velocity_ned"] for r in rows],
            "euler_deg": [r["euler_deg"] for r in rows],
            "position_std_m": [r["position_std_m"] for r in rows],
            "phase": [str(s.status.phase) for s in states],
        }

    def trajectory_csv(self) -> str:
        lines = [CSV_HEADER]
        for s in self.states():
            p = pose_dict(s, self.start_gpst)
            values = [f"{p['t']:.3f}", f"{p['gpst']:.6f}",
                      *(f"{x:.4f}" for x in p["position_ned"]),
                      f"{p['llh_deg'][0]:.9f}", f"{p['llh_deg'][1]:.9f}",
                      f"{p['llh_deg'][2]:.4f}", *(f"{x:.4f}" for x in p["euler_deg"]),
                      *(f"{x:.4f}" for x in p["velocity_ned"]),
                      *(f"{x:.4f}" for x in p["position_std_m"]), str(s.status.phase)]
            lines.append(",".join(values))
        return "\n".join(lines) + "\n"

    # --------------------------------------------------------------- the recording frame

    def origin_in_recording(self, state: Any) -> np.ndarray:
        """The world origin in the recording's local level (manifest origin), from the fused
        absolute position (``llh_deg``, SPP-anchored) of ``state``."""
        lat, lon, h = (float(x) for x in state.llh_deg)
        absolute = ecef_to_ned(geodetic_to_ecef(np.radians(lat), np.radians(lon), h),
                               self.rec.manifest.origin_llh)
        return absolute - np.asarray(state.position_ned, dtype=float)

    def reference_alignment(self) -> tuple[float, np.ndarray] | None:
        """(time, offset) with reference = world + offset, matched at the first fused pose:
        the engine's trajectory starts from its own origin (no base station), so it is
        compared with the reference from the same starting point, as in the thesis."""
        ref = self.rec.reference
        with self.lock:
            if ref is None or not self._states:
                return None
            first = self._states[0]
        p_ref, _v, _e = ref.interpolate(float(first.time))
        if not np.isfinite(p_ref).all():
            return None
        return float(first.time), p_ref - np.asarray(first.position_ned, dtype=float)

    def report(self, name: str, after_s: float = 0.0) -> dict[str, Any]:
        """Horizontal and heading error of the fused states so far against the reference."""
        ref = self.rec.reference
        if ref is None:
            raise NotFound(f"recording {name!r} has no reference trajectory (its manifest "
                           "names no reference file), so the session cannot be evaluated")
        with self.lock:
            times = np.array(self._times)
            states = list(self._states)
        if len(times) == 0:
            raise Conflict("no fused pose stored yet: nothing to evaluate")
        aligned = self.reference_alignment()
        if aligned is None:
            raise Conflict("the first fused pose is outside the reference span")
        keep = times >= self.start_gpst + after_s
        ref_pos, _v, ref_euler = ref.interpolate(times)
        keep &= np.isfinite(ref_pos).all(axis=1)
        if not keep.any():
            raise Conflict(f"no fused pose after {after_s:g} s inside the reference span yet")
        est_pos = np.array([s.position_ned for s in states]).reshape(-1, 3) + aligned[1]
        abs_pos = np.array([self.origin_in_recording(s) + np.asarray(s.position_ned, float)
                            for s in states]).reshape(-1, 3)
        est_yaw = np.array([float(s.euler[2]) for s in states])
        t_rel = np.round(times[keep] - self.start_gpst, 6)
        counts: dict[str, int] = {}
        for s, k in zip(states, keep, strict=True):
            if k:
                counts[str(s.status.phase)] = counts.get(str(s.status.phase), 0) + 1
        return {
            "recording": name,
            "after_s": after_s,
            "from_s": float(t_rel[0]),
            "to_s": float(t_rel[-1]),
            "samples": int(keep.sum()),
            "phases": counts,
            "aligned_at_s": round(aligned[0] - self.start_gpst, 6),
            "horizontal_error_m": _horizontal(est_pos[keep, :2] - ref_pos[keep, :2], t_rel),
            "absolute_horizontal_error_m": _horizontal(abs_pos[keep, :2] - ref_pos[keep, :2],
                                                       t_rel),
            "vertical_error_m": _stats(est_pos[keep, 2] - ref_pos[keep, 2], t_rel, signed=True),
            "heading_error_deg": _stats(np.degrees(wrap_angle(est_yaw[keep]
                                                              - ref_euler[keep, 2])),
                                        t_rel, signed=True),
        }


def _beyond(t: float, last: float) -> str:
    return (f"no fused pose at t = {t:g} s: the last is at {last:.3f} s (not replayed yet, "
            "or no position since: see the session's integrity)")


def _horizontal(e: np.ndarray, t_rel: np.ndarray) -> dict[str, float]:
    """Statistics of the horizontal distance of the (N, 2) errors ``e``; its std is the 2-D
    error's, sqrt(var_N + var_E), as ``replay --report`` gives it (table 17), not the
    distance's own (a user trial read two different "std" of one run)."""
    out = _stats(np.linalg.norm(e, axis=1), t_rel, signed=False)
    out["std"] = float(np.sqrt(np.var(e[:, 0]) + np.var(e[:, 1])))
    return out


def _stats(e: np.ndarray, t_rel: np.ndarray, signed: bool) -> dict[str, float]:
    a = np.abs(e)
    return {
        "rms": float(np.sqrt(np.mean(e**2))),
        "std": float(np.std(e)),
        "mean": float(np.mean(e)) if signed else float(np.mean(a)),
        "max": float(a.max()),
        "max_at_s": float(t_rel[int(np.argmax(a))]),
    }
