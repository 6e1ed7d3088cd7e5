"""Start-up and alignment of the fusion (thesis 5.1.1: the INS block's initialisation,
fig. 19).

Before the INS runs, IMU samples are buffered and the GNSS compass (``compass.GnssCompass``) is
fed every epoch with the accelerometer tilt until it fixes its integers. At the epoch after the
first fix the INS starts at the PREVIOUS epoch (the world origin) from the compass attitude, the
SPP position and the TDCP velocity of the interval. Without a compass fix after
``ALIGN_TIMEOUT_S`` (and moving), the INS starts from the accelerometer tilt and the course over
ground, with a wide attitude σ (``aligning``).
"""

from __future__ import annotations

import math
import time as _time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .compass import GnssCompass, tilt_from_specific_force
from .cpp import eta_observations, tight_velocity
from .frames import euler_to_dcm
from .gnss_epochs import GnssFront
from .records import GnssEpoch

ALIGN_TIMEOUT_S = 20.0  # without a compass fix, start from tilt + course after this long
IMU_BUFFER_S = 2.5  # raw IMU kept before the INS starts (replayed from the previous epoch)
COURSE_MIN_SPEED = 0.5  # m/s: the course over ground gives a heading only above this
COURSE_ATTITUDE_SIGMA = math.radians(10.0)  # attitude σ of a start from tilt + course


@dataclass
class InsStart:
    """How the INS starts: at ``time`` (the previous epoch: the world origin)."""

    time: float
    C_body_to_level: np.ndarray
    velocity_centre_ned: np.ndarray  # antenna-array centre, TDCP over the interval
    clock_drift_mps: float
    spp_ecef: np.ndarray  # the antenna-array centre at ``time``
    spp_covariance: np.ndarray  # ... its error covariance (ECEF, m²)
    attitude_sigma: float | None  # None: a compass fix; else tilt + course, this σ (rad)


class Alignment:
    """The start-up stage: IMU buffer, GNSS compass and the decision to start the INS."""

    def __init__(self, compass: GnssCompass, antennas_body: np.ndarray, G: np.ndarray,
                 A: np.ndarray, phase_sigma_m: float, common_clock: bool) -> None:
        self.compass = compass
        self.antennas = antennas_body
        self._G, self._A = G, A  # gyro, accelerometer calibration matrices
        self.phase_sigma_m = phase_sigma_m
        self.common_clock = common_clock
        self.imu: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self._prev_fix: np.ndarray | None = None  # compass attitude at the last epoch
        self._prev_spp: tuple[np.ndarray, np.ndarray] | None = None  # position, covariance
        self.message = "waiting for GNSS"

    def buffer_imu(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        self.imu.append((t, gyro, accel))
        while self.imu and self.imu[0][0] < t - IMU_BUFFER_S:
            self.imu.popleft()

    def tilt(self) -> tuple[float, float] | None:
        """Roll and pitch from the mean specific force of the last second of samples."""
        if not self.imu:
            return None
        f = np.mean([s[2] for s in list(self.imu)[-100:]], axis=0)
        return tilt_from_specific_force(self._A @ f)

    def samples_from(self, t_start: float, past: float) -> list[tuple[float, np.ndarray,
                                                                     np.ndarray]]:
        """The buffered samples from ``t_start`` on (replayed into the new INS)."""
        return [s for s in self.imu if s[0] >= t_start - past]

    def step(self, t: float, epochs: list[GnssEpoch | None], front: GnssFront,
             timed: Callable[[str, float], None]) -> InsStart | None:
        """One epoch before the INS runs: compass, SPP and TDCP velocity; an ``InsStart``
        when the INS can start (the epoch itself is then applied once the INS reaches it)."""
        front.standalone(epochs, joint=True)
        t0 = _time.perf_counter()
        sol = self.compass.update(epochs, self.tilt())
        timed("compass", _time.perf_counter() - t0)
        centre = front.spp_ecef
        geo = front.geometry(t, epochs, centre) if centre is not None else None
        v_interval = None
        if geo is not None and front.prev_geo is not None:
            rows = eta_observations(front.prev, epochs, front.prev_geo, geo,
                                    phase_sigma_m=self.phase_sigma_m,
                                    common_clock=self.common_clock).rows
            C = sol.C_body_to_level if sol.fixed else None
            levers = self.antennas - self.antennas.mean(axis=0)
            omega = self._G @ self.imu[-1][1] if self.imu else None
            tv = tight_velocity(rows, lever_arms_body=levers, C_body_to_level=C,
                                omega_body=omega if C is not None else None)
            if tv is not None:
                v_interval = (tv.velocity_ned, tv.clock_drift_mps)
        start = self._decide(t, sol.fixed, v_interval, front)
        if sol.fixed:
            self._prev_fix = sol.C_body_to_level
        else:
            self._prev_fix = None
            if start is None:
                self.message = f"compass: {sol.message or 'not fixed'}"
        self._prev_spp = None if front.spp_ecef is None or front.spp_covariance is None \
            else (front.spp_ecef, front.spp_covariance)
        if start is None:
            front.advance(epochs, geo)
        return start

    def _decide(self, t: float, fixed: bool, v_interval: tuple[np.ndarray, float] | None,
                front: GnssFront) -> InsStart | None:
        ready = v_interval is not None and front.prev_geo is not None \
            and self._prev_spp is not None
        if not ready:
            return None
        assert v_interval is not None and front.prev_geo is not None \
            and self._prev_spp is not None
        t_prev = front.prev_geo.time
        if fixed and self._prev_fix is not None:
            self.message = "INS started from the GNSS compass fix"
            return InsStart(t_prev, self._prev_fix, v_interval[0], v_interval[1],
                            *self._prev_spp, attitude_sigma=None)
        if t - (front.t_first or t) > ALIGN_TIMEOUT_S \
                and np.hypot(*v_interval[0][:2]) > COURSE_MIN_SPEED:
            tilt = self.tilt() or (0.0, 0.0)
            yaw = math.atan2(v_interval[0][1], v_interval[0][0])
            self.message = "no compass fix: INS started from tilt and course over ground"
            return InsStart(t_prev, euler_to_dcm(tilt[0], tilt[1], yaw), v_interval[0],
                            v_interval[1], *self._prev_spp,
                            attitude_sigma=COURSE_ATTITUDE_SIGMA)
        return None
