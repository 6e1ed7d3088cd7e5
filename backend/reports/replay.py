"""``berthing-aid replay RECORDING --report``: the thesis' experiments (SPEC section 5) on a
recording with a reference trajectory.

The VO runs ONCE over the video; its outputs are cached and fed to every fusion run through
``Fusion.process_vo`` (the runs without VO skip the frames). Each run replays the IMU samples,
the GNSS epochs and the cached VO in time order (IMU first at equal time tags, as
``backend.replay`` does) and samples ``Fusion.state(at=t)`` at every frame time.

Scoring. The fusion's world frame is its own start point (SPP-anchored), so every run is
aligned to the reference by ONE translation: the reference position at the fusion's origin
time (``Fusion.origin_time``). No rotation is fitted: a heading error shows as a growing
position error. The evaluation window starts ``init_s`` (30 s) after the first GNSS epoch.
σ of a horizontal error is ``sqrt(var_N + var_E)`` over the window (the thesis' "standard
deviation converted to the horizontal distance"; a constant offset is not in σ, it is in the
max and in the RMS that is printed beside it). The estimator never sees the reference.

Table 17 (methods):
- INS+VO+CPP: ``FusionOptions()``.
- INS, INS+VO: the thesis' protocol — carrier phase (and compass) for the ``init_s`` of the
  initialisation, which estimates the biases, the attitude and the VO scale, then no satellite
  at all (``satellites_keep=[]``): the INS (with or without VO) alone over the window. The
  literal ``use_cpp=False`` runs (no carrier phase after the ~1 s start-up, so nothing is
  estimated) are reported too, under ``methods_without_cpp_after_startup``.
- VO: the cached VO trajectory alone, mapped into L ONCE at the window start with the INS+VO+CPP
  run's camera pose and VO scale there (``C_W^L = C_B^L·C_C^B·C_W^C`` and the scale then
  frozen); it ends when the VO loses its world (a new segment cannot be tied to the old one).

Tables 18–20 (satellite subsets): the satellites tracked with carrier phase by all four
receivers throughout (GPS first, as the thesis; Galileo/QZSS fill up if fewer than 5 GPS) are
ranked by geometry; the best 5, and for 4…1 the best subset of those 5, are kept after
``init_s`` (``satellites_keep``), plus none. Geometry = the horizontal DOP of the carrier-phase
velocity with one common clock drift, rows weighted like the EKF's (σ ∝ 1/sin elevation), the
vertical velocity held by the INS (unit-weight prior) and a weak prior on every unknown so that
1–2 satellites still rank, averaged over the window. Each subset runs loosely (per-receiver
TDCP velocities) and tightly (η rows) coupled; velocity, trajectory and heading σ over the
window.

Table 21: the best four satellites, each kept by ONE receiver only (``per_receiver_sats``),
one common clock-drift state vs one per receiver.

Fig. 14 (heading from one satellite): the pipeline cannot restrict baselines, so the heading is
computed here from the single differences of ONE satellite on ONE baseline (each of the six) or
on all six, with ``estimator.compass.attitude_from_single_differences`` in a small Kalman filter
[heading, yaw-rate bias] driven by the calibrated gyro: integers and inter-receiver delays from
a ``GnssCompass`` run on all satellites up to the window start and then frozen, roll/pitch and
the initial heading/gyro bias from the INS+VO+CPP run (the estimator's own values), the
snapshot heading gated at 4σ. A cycle slip on the satellite ends its updates. The pipeline's own
heading with that satellite alone (all baselines, EKF) is listed beside it.

Structure: ``Fusion.structure()`` at the end of INS+VO+CPP against the true scene points
(shifted by the same translation): nearest true point, matched when within
``max(1 m, 5 % of the range)`` (the scene points are a sparse set of strong corners, a feature
elsewhere on a surface has no true counterpart); median and 90th percentile of the matched
distances by range band from the camera at the end. Because the true points are sparse (about a
metre apart along the quay), the quay is also scored as a line: the horizontal distance of the
points within ``QUAY_BAND_M`` of the quay edge (the polyline through the scene points of kind
"quay") to that edge — bollards and deck features just behind the edge count as error.
"""

from __future__ import annotations

import argparse
import inspect
import itertools
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

INIT_S = 30.0  # thesis: 30 s of initialisation with carrier phase, then the window
SUBSET_SIZES = (5, 4, 3, 2, 1, 0)
BANDS_M = ((0.0, 10.0), (10.0, 30.0), (30.0, 60.0), (60.0, math.inf))
MATCH_GATE_M = 1.0  # a structure point is matched to a true point within max(this, ...
MATCH_GATE_FRACTION = 0.05  # ... this fraction of its range from the camera)
QUAY_BAND_M = 3.0  # structure points this close (horizontally) to the quay edge are quay points
HEADING_GATE_SIGMA = 4.0  # fig. 14 filter: snapshot headings further than this are rejected
GYRO_ARW = math.radians(0.01)  # rad/√s: heading random walk of the fig. 14 filter
GYRO_BIAS_WALK = math.radians(0.001)  # rad/s/√s
TILT_SIGMA = math.radians(0.2)  # roll/pitch prior of the snapshot (from the INS)
PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))  # estimator.cpp.BASELINE_PAIRS


class _Progress:
    """One line per run on stderr (stdout carries the report)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.count = 0

    def __call__(self, text: str) -> None:
        if self.enabled:
            self.count += 1
            print(f"replay [{self.count:2d}] {text}", file=sys.stderr, flush=True)


@dataclass
class _Track:
    """States of one fusion run sampled at the frame times (NaN before the INS starts)."""

    label: str
    time: np.ndarray  # (N,) gpst
    position: np.ndarray  # (N,3) body origin, NED in the fusion's world frame
    velocity: np.ndarray  # (N,3)
    euler: np.ndarray  # (N,3) rad
    C: np.ndarray  # (N,3,3) body → level
    scale: np.ndarray  # (N,) VO scale (m per VO unit), NaN when not tracking
    origin_time: float | None
    wall_s: float
    timing_ms: dict[str, float]
    structure: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    structure_raw: np.ndarray | None = None  # unrefined points, when the pipeline refines


# ------------------------------------------------------------------------------ replay


class _Replay:
    """The recording cut to the evaluated span, the VO outputs and the fusion runs."""

    def __init__(self, rec: Any, end_s: float | None, progress: _Progress) -> None:
        from engine.messages import group_gnss

        self.rec = rec
        self.progress = progress
        self.ref = rec.reference
        self.start = float(rec.manifest.start_gpst)
        self.end = self.start + (float(rec.manifest.duration_s) if end_s is None else end_s)
        imu = rec.imu
        keep = imu.time <= self.end + 1e-9
        self.imu_t, self.gyro, self.accel = imu.time[keep], imu.gyro[keep], imu.accel[keep]
        self.gnss = [m for m in group_gnss(rec) if m.t <= self.end + 1e-9]
        if len(self.gnss) < 3:
            raise ValueError(f"{rec.manifest.name}: fewer than 3 GNSS epochs to replay")
        self.first_gnss = self.gnss[0].t
        self.vo: list[Any] = []
        self.vo_ms = self.decode_ms = math.nan
        self.runs: dict[str, _Track] = {}

    @property
    def duration(self) -> float:
        return self.end - self.start

    def run_vo(self) -> None:
        """The VO once over the video: cached outputs and its cost per frame."""
        from estimator.vo import VisualOdometry

        vo = VisualOdometry(self.rec.calibration.camera)
        t_vo = t_dec = 0.0
        tic = time.perf_counter()
        for _, t, image in self.rec.frames():
            if t > self.end + 1e-9:
                break
            t1 = time.perf_counter()
            t_dec += t1 - tic
            self.vo.append(vo.process(t, image))
            tic = time.perf_counter()
            t_vo += tic - t1
        if not self.vo:
            raise ValueError(f"{self.rec.manifest.name}: no video frame to replay")
        n = len(self.vo)
        self.vo_ms, self.decode_ms = 1e3 * t_vo / n, 1e3 * t_dec / n
        tracking = sum(o.status == "tracking" for o in self.vo)
        self.progress(f"VO over {n} frames: {t_vo + t_dec:.1f} s ({self.vo_ms:.1f} ms/frame VO, "
                      f"{self.decode_ms:.1f} ms decoding), tracking {100 * tracking / n:.0f} %, "
                      f"{len({o.segment for o in self.vo})} segment(s)")
        self.sample_t = np.array([o.time for o in self.vo])
        # IMU before GNSS before the frame at equal time tags (backend.replay's order).
        events = [(float(t), 0, i) for i, t in enumerate(self.imu_t)]
        events += [(m.t, 1, i) for i, m in enumerate(self.gnss)]
        events += [(float(t), 2, i) for i, t in enumerate(self.sample_t)]
        events.sort()
        self.events = events

    def fuse(self, label: str, options: Any, structure: bool = False) -> _Track:
        """One fusion run with ``options`` (cached by label)."""
        from estimator.pipeline import Fusion

        if label in self.runs:
            return self.runs[label]
        rec = self.rec
        f = Fusion(rec.calibration, rec.nav, options)
        n = len(self.sample_t)
        pos, vel, eul = (np.full((n, 3), np.nan) for _ in range(3))
        C = np.full((n, 3, 3), np.nan)
        scale = np.full(n, np.nan)
        use_vo = options.use_vo
        tic = time.perf_counter()
        for t, kind, i in self.events:
            if kind == 0:
                f.process_imu(t, self.gyro[i], self.accel[i])
            elif kind == 1:
                f.process_gnss(t, list(self.gnss[i].epochs))
            else:
                if use_vo:
                    f.process_vo(self.vo[i])
                s = f.state(at=t)
                if s is not None:
                    pos[i], vel[i], eul[i], C[i] = (s.position_ned, s.velocity_ned, s.euler,
                                                    s.C_body_to_level)
                    if s.status.scale is not None:
                        scale[i] = s.status.scale
        wall = time.perf_counter() - tic
        track = _Track(label=label, time=self.sample_t, position=pos, velocity=vel, euler=eul,
                       C=C, scale=scale, origin_time=f.origin_time, wall_s=wall,
                       timing_ms=f.timing(), structure=f.structure() if structure else None)
        if structure and "refined" in inspect.signature(f.structure).parameters:
            track.structure_raw = f.structure(refined=False)[0]
        self.runs[label] = track
        started = "never started" if f.origin_time is None else \
            f"origin at +{f.origin_time - self.start:.1f} s"
        self.progress(f"{label}: {wall:.1f} s ({self.duration / max(wall, 1e-9):.1f}x real "
                      f"time), {started}")
        return track


# ----------------------------------------------------------------------------- scoring


def _finite(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _hstd(e: np.ndarray) -> float:
    """σ converted to the horizontal distance: sqrt(var_N + var_E)."""
    return float(np.sqrt(np.var(e[:, 0]) + np.var(e[:, 1])))


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass
class _Errors:
    time: np.ndarray  # all samples (s since the recording start)
    position: np.ndarray  # (N,3) aligned position error, NaN when unknown
    velocity: np.ndarray
    heading: np.ndarray  # rad
    window: np.ndarray  # (N,) bool: inside the window and scored


def _errors(rp: _Replay, track: _Track, t0: float) -> _Errors | None:
    """Errors of a run against the reference, aligned by the translation at its origin."""
    if track.origin_time is None:
        return None
    ref_pos, ref_vel, ref_eul = rp.ref.interpolate(track.time)
    origin = rp.ref.interpolate(track.origin_time)[0]
    e_pos = track.position - (ref_pos - origin)
    e_vel = track.velocity - ref_vel
    e_hdg = _wrap(track.euler[:, 2] - ref_eul[:, 2])
    ok = np.isfinite(e_pos).all(axis=1) & np.isfinite(e_hdg)
    return _Errors(time=track.time - rp.start, position=e_pos, velocity=e_vel, heading=e_hdg,
                   window=ok & (track.time >= t0 - 1e-6))


def _scores(err: _Errors | None, n_window: int) -> dict[str, Any]:
    empty = {"horizontal_std_m": None, "horizontal_max_m": None, "horizontal_rms_m": None,
             "velocity_std_mps": None, "heading_std_deg": None, "heading_rms_deg": None,
             "heading_max_deg": None, "coverage": 0.0}
    if err is None or not err.window.any():
        return empty
    w = err.window
    e, v, h = err.position[w], err.velocity[w], err.heading[w]
    horiz = np.hypot(e[:, 0], e[:, 1])
    vok = np.isfinite(v).all(axis=1)
    return {
        "horizontal_std_m": _hstd(e),
        "horizontal_max_m": float(horiz.max()),
        "horizontal_rms_m": float(np.sqrt(np.mean(horiz**2))),
        "velocity_std_mps": _hstd(v[vok]) if vok.any() else None,
        "heading_std_deg": float(np.degrees(np.std(h))),
        "heading_rms_deg": float(np.degrees(np.sqrt(np.mean(h**2)))),
        "heading_max_deg": float(np.degrees(np.abs(h).max())),
        "coverage": float(w.sum() / max(n_window, 1)),
    }


def _vo_alone(rp: _Replay, main: _Track, t0: float) -> tuple[_Track, dict[str, Any]]:
    """The VO trajectory mapped into L once at the window start (pose and scale of the
    INS+VO+CPP run there), then left alone."""
    from estimator.frames import dcm_to_euler

    cam = rp.rec.calibration.camera
    C_cb, lever = np.asarray(cam.C_camera_to_body, float), np.asarray(cam.lever_arm_body, float)
    n = len(main.time)
    pos, eul = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    k0 = next((k for k in range(n) if main.time[k] >= t0 - 1e-6 and rp.vo[k].status == "tracking"
               and np.isfinite(main.scale[k]) and np.isfinite(main.position[k]).all()), None)
    info: dict[str, Any] = {"anchored_at_s": None, "scale": None, "segment": None}
    if k0 is not None:
        o0 = rp.vo[k0]
        s = float(main.scale[k0])
        C_wl = main.C[k0] @ C_cb @ o0.C_world_to_camera  # C_W^L = C_B^L·C_C^B·C_W^C
        p_cam0 = main.position[k0] + main.C[k0] @ lever
        p_w0 = np.asarray(o0.camera_position_world, float)
        for k in range(k0, n):
            o = rp.vo[k]
            if o.status != "tracking" or o.segment != o0.segment:
                if o.segment != o0.segment:
                    break  # a new VO world: VO alone cannot tie it to the old one
                continue
            C_bl = C_wl @ o.C_world_to_camera.T @ C_cb.T  # C_B^L = C_W^L·C_C^W·C_B^C
            p_cam = p_cam0 + s * C_wl @ (np.asarray(o.camera_position_world, float) - p_w0)
            pos[k] = p_cam - C_bl @ lever
            eul[k] = dcm_to_euler(C_bl)
        info = {"anchored_at_s": float(main.time[k0] - rp.start), "scale": s,
                "segment": int(o0.segment)}
    track = _Track(label="VO", time=main.time, position=pos, velocity=np.full((n, 3), np.nan),
                   euler=eul, C=np.full((n, 3, 3), np.nan), scale=np.full(n, np.nan),
                   origin_time=main.origin_time, wall_s=0.0, timing_ms={})
    return track, info


# ------------------------------------------------------------------ satellite subsets


def _tracked(rp: _Replay) -> list[str]:
    """Satellites with carrier phase at all four receivers in every epoch replayed."""
    sats: set[str] | None = None
    for m in rp.gnss:
        here = set()
        eps = list(m.epochs)
        if len(eps) < 4 or any(e is None for e in eps):
            continue
        for s in eps[0].satellites:
            if all(s in e.satellites and math.isfinite(e.satellites[s].carrier_phase)
                   for e in eps):
                here.add(s)
        sats = here if sats is None else sats & here
    return sorted(sats or ())


def _geometry(rp: _Replay, sats: list[str], t0: float
              ) -> tuple[dict[str, dict[str, float]], dict[float, dict[str, np.ndarray]]]:
    """Elevation/azimuth (deg, averaged) and line of sight (NED) at epochs of the window,
    seen from the site (the manifest origin: metres do not matter for the geometry)."""
    from estimator.cpp import epoch_geometry
    from estimator.frames import ned_to_ecef

    site = ned_to_ecef(np.zeros(3), rp.rec.manifest.origin_llh)
    times = [m.t for m in rp.gnss if m.t >= t0 - 1e-6] or [rp.gnss[-1].t]
    times = times[:: max(1, len(times) // 6)]
    los: dict[float, dict[str, np.ndarray]] = {}
    elaz: dict[str, list[tuple[float, float]]] = {s: [] for s in sats}
    for t in times:
        geo = epoch_geometry(rp.rec.nav, sats, t, site, 0.0, 10.0)
        los[t] = {s: geo.los_ned(s) for s in geo.satellites}
        for s, g in geo.satellites.items():
            elaz[s].append((math.degrees(g.elevation), math.degrees(g.azimuth)))
    info = {s: {"elevation_deg": float(np.mean([a[0] for a in v])),
                "azimuth_deg": float(v[0][1])} for s, v in elaz.items() if v}
    return info, los


def _velocity_dop(los: dict[float, dict[str, np.ndarray]], subset: Sequence[str]) -> float:
    """Horizontal DOP of the carrier-phase velocity (v, one clock drift), rows weighted as the
    EKF weighs them (σ ∝ 1/sin elevation), the vertical held by the INS (unit weight) and a
    weak prior (1e-3) on everything, averaged over the epochs."""
    values = []
    for per in los.values():
        if any(s not in per for s in subset):
            return math.inf
        N = np.diag([1e-3, 1e-3, 1.0 + 1e-3, 1e-3])
        for s in subset:
            h = np.append(-per[s], 1.0)
            N += max(-per[s][2], 0.1) ** 2 * np.outer(h, h)  # sin(elevation) = −e_down
        Q = np.linalg.inv(N)
        values.append(math.sqrt(Q[0, 0] + Q[1, 1]))
    return float(np.mean(values)) if values else math.inf


def _choose_subsets(rp: _Replay, t0: float
                    ) -> tuple[dict[int, list[str]], dict[str, dict[str, float]],
                               dict[int, float]]:
    """The best 5 satellites and, for 4…1, the best subsets of those 5 (and 0: none)."""
    from estimator.cpp import SAME_CARRIER_SYSTEMS

    tracked = [s for s in _tracked(rp) if s[0] in SAME_CARRIER_SYSTEMS]
    info, los = _geometry(rp, tracked, t0)
    tracked = [s for s in tracked if s in info]
    gps = [s for s in tracked if s[0] == "G"]
    pool = gps if len(gps) >= 5 else gps + [s for s in tracked if s[0] != "G"]
    best5 = min(itertools.combinations(pool, min(5, len(pool))),
                key=lambda c: (_velocity_dop(los, c), c), default=())
    chosen: dict[int, list[str]] = {}
    dops: dict[int, float] = {}
    for n in range(len(best5), -1, -1):
        if n == 0:
            chosen[0], dops[0] = [], math.inf
            continue
        # Ties (1–2 satellites barely observe the horizontal) go to the higher satellites.
        combo = min(itertools.combinations(best5, n),
                    key=lambda c: (round(_velocity_dop(los, c), 6),
                                   -sum(info[s]["elevation_deg"] for s in c)))
        chosen[n] = sorted(combo)
        dops[n] = _velocity_dop(los, combo)
    return chosen, info, dops


# --------------------------------------------------------------------- fig. 14 heading


class _OneSatelliteHeading:
    """Fig. 14: heading from the single differences of ONE satellite on chosen baselines,
    in a [heading, yaw-rate bias] Kalman filter driven by the calibrated gyro."""

    def __init__(self, rp: _Replay, main: _Track, t0: float, sats: list[str]) -> None:
        from estimator.compass import GnssCompass
        from estimator.cpp import epoch_geometry
        from estimator.ins import calibration_matrices

        rec = rp.rec
        self.rp, self.main, self.t0 = rp, main, t0
        self.antennas = np.asarray(rec.calibration.antennas_body, float)
        self.ok = np.flatnonzero(np.isfinite(main.euler).all(axis=1))
        self.fix = None
        if not len(self.ok) or main.origin_time is None:
            self.reason = "the INS+VO+CPP run never started"
            return
        # Integers and delays: a compass on ALL satellites until the window start, then frozen.
        compass = GnssCompass(rec.nav, self.antennas)
        for m in rp.gnss:
            if m.t > t0 + 1e-6:
                break
            roll, pitch = self.tilt(m.t)
            sol = compass.update(list(m.epochs), (roll, pitch))
            self.fix = sol if sol.fixed and sol.delays_m is not None else None
        if self.fix is None or compass.position is None:
            self.reason = "the GNSS compass holds no fix with delays at the window start"
            return
        # Yaw rate from the calibrated gyro (roll/pitch of the INS); its bias against the fused
        # heading change over the second half of the initialisation (at most 20 s): the first
        # seconds hold the convergence of the fused heading itself.
        G, _ = calibration_matrices(rec.calibration.imu)
        w = rp.gyro @ G.T
        eul = self.attitudes(rp.imu_t)
        self.yaw_rate = (w[:, 1] * np.sin(eul[:, 0]) + w[:, 2] * np.cos(eul[:, 0])) / np.maximum(
            np.cos(eul[:, 1]), 1e-6)
        self.dt = np.diff(rp.imu_t, prepend=rp.imu_t[0])
        t_a = max(0.5 * (main.origin_time + t0), t0 - 20.0)
        span = (rp.imu_t > t_a) & (rp.imu_t <= t0)
        yaw = np.unwrap(main.euler[self.ok, 2])
        turn = np.interp(t0, main.time[self.ok], yaw) - np.interp(t_a, main.time[self.ok], yaw)
        self.bias0 = float((np.sum(self.yaw_rate[span] * self.dt[span]) - turn)
                           / max(t0 - t_a, 1e-3))
        self.window = [m for m in rp.gnss if m.t > t0 + 1e-6]
        self.geos = {m.t: epoch_geometry(rec.nav, sats, m.t, compass.position,
                                         compass.clock_bias_s, 0.0) for m in self.window}
        self.ref_yaw = rp.ref.interpolate(np.array([m.t for m in self.window]))[2][:, 2]

    def attitudes(self, t: np.ndarray) -> np.ndarray:
        """Roll, pitch, yaw of the INS+VO+CPP run at times ``t`` (nearest sample)."""
        tt = self.main.time[self.ok]
        k = np.clip(np.searchsorted(tt, t), 1, len(tt) - 1)
        k -= (np.abs(tt[k - 1] - t) < np.abs(tt[k] - t)).astype(int)
        return self.main.euler[self.ok][k]

    def tilt(self, t: float) -> tuple[float, float]:
        e = self.attitudes(np.array([t]))[0]
        return float(e[0]), float(e[1])

    def run(self, sat: str, pairs: Sequence[tuple[int, int]]
            ) -> tuple[np.ndarray, np.ndarray, int]:
        """Filtered and snapshot heading errors (rad) over the window epochs, and the number of
        accepted updates. A slip of the satellite at a receiver in use ends the updates (the
        frozen integer is no longer valid)."""
        from estimator.compass import attitude_from_single_differences
        from estimator.cpp import DEFAULT_PHASE_SIGMA_M, detect_cycle_slips
        from estimator.frames import euler_to_dcm
        from estimator.records import GnssEpoch

        fix, rp = self.fix, self.rp
        assert fix is not None
        x = np.array([float(self.attitudes(np.array([self.t0]))[0][2]), self.bias0])
        P = np.diag([math.radians(0.1) ** 2, math.radians(0.01) ** 2])
        receivers = {i for p in pairs for i in p}
        t_prev, prev, slipped, used = self.t0, None, False, 0
        filtered, snapshot = [], []
        for k, m in enumerate(self.window):
            sel = (rp.imu_t > t_prev) & (rp.imu_t <= m.t)
            dt = m.t - t_prev
            x[0] += float(np.sum((self.yaw_rate[sel] - x[1]) * self.dt[sel]))
            F = np.array([[1.0, -dt], [0.0, 1.0]])
            P = F @ P @ F.T + np.diag([GYRO_ARW**2 * dt, GYRO_BIAS_WALK**2 * dt])
            t_prev = m.t
            eps = [None if e is None else GnssEpoch(
                e.time, {s: o for s, o in e.satellites.items() if s == sat}, e.flag)
                for e in m.epochs]
            if prev is not None and any(i in receivers for i, _ in detect_cycle_slips(prev, eps)):
                slipped = True
            prev = eps
            geo = self.geos[m.t]
            snap = math.nan
            if not slipped and sat in geo.satellites:
                lam = geo.wavelengths[sat]
                zetas: dict[tuple[int, int], dict[str, float]] = {}
                for i, j in pairs:
                    a, b = eps[i], eps[j]
                    if a is None or b is None or sat not in a.satellites \
                            or sat not in b.satellites:
                        continue
                    sd = a.satellites[sat].carrier_phase - b.satellites[sat].carrier_phase
                    # ζ_ij = λΦ_ij − D_ij − λN_ij (SPEC section 4)
                    zetas[(i, j)] = {sat: lam * sd - fix.delays_m[(i, j)]
                                     - lam * fix.integers[(i, j)][sat]}
                roll, pitch = self.tilt(m.t)
                sigma = DEFAULT_PHASE_SIGMA_M / max(math.sin(geo.satellites[sat].elevation), 0.1)
                att = attitude_from_single_differences(
                    zetas, {sat: geo.los_ned(sat)}, self.antennas,
                    euler_to_dcm(roll, pitch, x[0]), tilt=(roll, pitch),
                    tilt_sigma_rad=TILT_SIGMA, sigma_u={sat: sigma}) if zetas else None
                if att is not None and math.isfinite(att.covariance[2, 2]):
                    snap = float(att.euler[2])
                    nu = float(_wrap(np.array(snap - x[0])))
                    S = P[0, 0] + float(att.covariance[2, 2])
                    if nu * nu <= HEADING_GATE_SIGMA**2 * S:
                        K = P[:, 0] / S
                        x = x + K * nu
                        P = P - np.outer(K, P[0, :])
                        used += 1
            filtered.append(x[0] - self.ref_yaw[k])
            snapshot.append(snap - self.ref_yaw[k])
        return _wrap(np.array(filtered)), _wrap(np.array(snapshot)), used

    def report(self, sats: list[str], pipeline: dict[str, _Track]) -> dict[str, Any]:
        method = ("single differences of one satellite (integers and inter-receiver delays of "
                  "a GnssCompass on all satellites, frozen at the window start) + calibrated "
                  "gyro in a [heading, gyro bias] Kalman filter (4σ gate); roll/pitch, initial "
                  "heading and gyro bias from the INS+VO+CPP run. snapshot = the single-epoch "
                  "heading from the single differences (tilt from the INS, started from the "
                  "filter's prediction), no gyro")
        out: dict[str, Any] = {"method": method, "satellites": []}
        if self.fix is None:
            out["reason"] = self.reason
            return out
        configs = [("all six", PAIRS)] + [(f"{i}-{j}", ((i, j),)) for i, j in PAIRS]
        for sat in sats:
            g0 = self.geos[self.window[0].t].satellites.get(sat) if self.window else None
            entry: dict[str, Any] = {
                "sat": sat, "elevation_deg": None if g0 is None else math.degrees(g0.elevation),
                "heading_std_deg": {}, "heading_max_deg": {}, "snapshot_std_deg": {},
                "updates": {}}
            for name, pairs in configs:
                pairs = tuple(p for p in pairs if sat in self.fix.integers.get(p, {}))
                filt = snap = np.zeros(0)
                used = 0
                if pairs and self.window:
                    filt, snap, used = self.run(sat, pairs)
                snap = snap[np.isfinite(snap)]
                entry["heading_std_deg"][name] = float(np.degrees(np.std(filt))) \
                    if len(filt) else None
                entry["heading_max_deg"][name] = float(np.degrees(np.abs(filt).max())) \
                    if len(filt) else None
                entry["snapshot_std_deg"][name] = float(np.degrees(np.std(snap))) \
                    if len(snap) else None
                entry["updates"][name] = used
            run = pipeline.get(sat)
            entry["pipeline_all_baselines_std_deg"] = None if run is None else \
                _scores(_errors(self.rp, run, self.t0), 1)["heading_std_deg"]
            out["satellites"].append(entry)
        for key in ("heading_std_deg", "snapshot_std_deg"):
            singles = [v for e in out["satellites"] for k, v in e[key].items()
                       if k != "all six" and v is not None]
            sixes = [e[key]["all six"] for e in out["satellites"]
                     if e[key].get("all six") is not None]
            out[f"worst_single_baseline_{key}"] = max(singles) if singles else None
            out[f"worst_all_six_{key}"] = max(sixes) if sixes else None
        return out


# --------------------------------------------------------------------------- structure


def _structure(rp: _Replay, main: _Track) -> dict[str, Any]:
    out: dict[str, Any] = {"points": 0, "matched": 0, "median_m": None, "p90_m": None,
                           "gate": f"max({MATCH_GATE_M:g} m, {100 * MATCH_GATE_FRACTION:g} % of "
                                   "the range)", "within_30m": None, "bands": []}
    true = rp.rec.scene_points
    if main.structure is None or true is None or len(true) == 0 or main.origin_time is None:
        out["reason"] = "no structure or no true scene points"
        return out
    pts = main.structure[0]
    ok = np.flatnonzero(np.isfinite(main.position).all(axis=1))
    if len(pts) == 0 or len(ok) == 0:
        out["reason"] = "no structure points"
        return out
    k = ok[-1]
    cam = main.position[k] + main.C[k] @ np.asarray(rp.rec.calibration.camera.lever_arm_body)
    origin = rp.ref.interpolate(main.origin_time)[0]
    true_w = np.asarray(true, float) - origin  # the same translation as the trajectories
    quay = _quay_line(rp, origin)
    scores, d = _point_scores(pts, true_w, cam, quay)
    out.update(scores)
    out["camera_end_ned"] = cam.tolist()
    if main.structure_raw is not None and len(main.structure_raw):
        # The same points before the pipeline's landmark refinement, for comparison.
        raw, _ = _point_scores(main.structure_raw, true_w, cam, quay)
        out["unrefined"] = {k: raw[k] for k in ("median_m", "p90_m", "within_30m",
                                                "quay_edge")}
    out["_arrays"] = (pts, d, cam, quay)  # for the plots; dropped from the JSON
    return out


def _point_scores(pts: np.ndarray, true: np.ndarray, cam: np.ndarray,
                  quay: np.ndarray | None) -> tuple[dict[str, Any], np.ndarray]:
    """Nearest-true-point statistics by range band and the quay-edge distances."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(true).query(pts)
    rng = np.linalg.norm(pts - cam, axis=1)
    matched = d <= np.maximum(MATCH_GATE_M, MATCH_GATE_FRACTION * rng)

    def stats(sel: np.ndarray) -> dict[str, Any]:
        m = sel & matched
        return {"points": int(sel.sum()), "matched": int(m.sum()),
                "median_m": float(np.median(d[m])) if m.any() else None,
                "p90_m": float(np.percentile(d[m], 90)) if m.any() else None}

    out: dict[str, Any] = stats(np.ones(len(pts), bool))
    out["within_30m"] = stats(rng < 30.0)
    out["bands"] = [{"range_m": [lo, None if math.isinf(hi) else hi],
                     **stats((rng >= lo) & (rng < hi))} for lo, hi in BANDS_M]
    out["quay_edge"] = None
    if quay is not None:
        dq = _distance_to_polyline(pts[:, :2], quay[:, :2])
        near = dq <= QUAY_BAND_M

        def qstats(sel: np.ndarray) -> dict[str, Any]:
            return {"points": int(sel.sum()),
                    "median_m": float(np.median(dq[sel])) if sel.any() else None,
                    "p90_m": float(np.percentile(dq[sel], 90)) if sel.any() else None}

        out["quay_edge"] = {"band_m": QUAY_BAND_M, "all": qstats(near),
                            "within_30m": qstats(near & (rng < 30.0))}
    return out, d


def _quay_line(rp: _Replay, origin: np.ndarray) -> np.ndarray | None:
    """The quay edge in the fusion's frame: the scene points of kind "quay" in order along
    their main direction (a straight or gently curved quay), None without them."""
    true, kinds = rp.rec.scene_points, rp.rec.scene_point_kinds
    if true is None or not kinds:
        return None
    q = np.asarray(true, float)[np.array(kinds) == "quay"] - origin
    if len(q) < 2:
        return None
    d = q[:, :2] - q[:, :2].mean(axis=0)
    axis = np.linalg.svd(d, full_matrices=False)[2][0]
    return q[np.argsort(d @ axis)]


def _distance_to_polyline(p: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of 2-D points (N,2) to a polyline (M,2)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    L2 = np.maximum(np.sum(ab**2, axis=1), 1e-12)
    t = np.clip(np.einsum("nmk,mk->nm", p[:, None, :] - a[None], ab) / L2, 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(p[:, None, :] - closest, axis=2), axis=1)


# ------------------------------------------------------------------------------ report


def replay_report_for(rec: Any, *, init_s: float = INIT_S, end_s: float | None = None,
                      subset_sizes: Sequence[int] = SUBSET_SIZES, clock_drift: bool = True,
                      single_satellites: int = 5, without_cpp: bool = True,
                      plots_dir: str | Path | None = None, progress: bool = True,
                      tracking: bool = True) -> dict[str, Any]:
    """The thesis' experiments on a loaded recording with a reference (see the module
    docstring). ``end_s``: replay only the first seconds; ``subset_sizes`` (tables 18–20),
    ``clock_drift`` (table 21), ``single_satellites`` (how many of the best five for fig. 14)
    and ``without_cpp`` (the literal ``use_cpp=False`` runs) trim the work for a quick run (the
    keys stay, empty); ``tracking`` adds the designated-target and landmark evaluations
    (``backend.reports.tracking``: seed 002 fig. 7, seed 000 fig. 10)."""
    from estimator.pipeline import FusionOptions

    if rec.reference is None:
        raise ValueError(f"{rec.manifest.name}: no reference trajectory to score against "
                         "(the report needs reference/trajectory.csv)")
    show = _Progress(progress)
    rp = _Replay(rec, end_s, show)
    t0 = rp.first_gnss + init_s
    if t0 >= rp.end - 1.0:
        raise ValueError(f"{rec.manifest.name}: {rp.duration:g} s replayed leaves no window "
                         f"after the {init_s:g} s initialisation")
    rp.run_vo()
    n_window = int(np.sum(rp.sample_t >= t0 - 1e-6))

    # The runs scored on the trajectory only skip the port-structure refinement (a consumer of
    # the fused poses, not an input of the EKF) when this pipeline has it: ~1 ms per frame.
    lean = {"landmarks": None} if "landmarks" in {f.name for f in fields(FusionOptions)} else {}

    def keep(**kw: Any) -> Any:
        return FusionOptions(keep_after_s=init_s, **lean, **kw)

    # The full pipeline; the water plane lets the landmark refinement drop reflections.
    full = FusionOptions(keep_after_s=init_s,
                         body_origin_height_m=rec.hull.body_origin_height_m)
    main = rp.fuse("INS+VO+CPP", full, structure=True)
    if main.origin_time is None:
        raise ValueError(f"{rec.manifest.name}: the fusion never started (no GNSS compass fix "
                         "and no course over ground)")
    runs = {"INS": rp.fuse("INS", keep(use_vo=False, satellites_keep=[])),
            "INS+VO": rp.fuse("INS+VO", keep(satellites_keep=[]))}
    vo_track, vo_info = _vo_alone(rp, main, t0)
    runs["VO"] = vo_track
    runs["INS+VO+CPP"] = main
    errors = {name: _errors(rp, tr, t0) for name, tr in runs.items()}
    methods = {name: _scores(errors[name], n_window)
               for name in ("INS", "VO", "INS+VO", "INS+VO+CPP")}
    methods["VO"].update(vo_info)
    report: dict[str, Any] = {
        "recording": getattr(rec.manifest, "name", "?"),
        "duration_s": rp.duration,
        "init_s": init_s,
        "window_s": [t0 - rp.start, rp.end - rp.start],
        "origin_time_s": main.origin_time - rp.start,
        "alignment": "translation only, by the reference position at the fusion's origin time",
        "methods": methods,
    }
    if without_cpp:
        lit = {"INS": rp.fuse("INS (use_cpp=False)",
                              FusionOptions(use_vo=False, use_cpp=False, **lean)),
               "INS+VO": rp.fuse("INS+VO (use_cpp=False)",
                                 FusionOptions(use_cpp=False, **lean))}
        report["methods_without_cpp_after_startup"] = {
            k: _scores(_errors(rp, tr, t0), n_window) for k, tr in lit.items()}
        for k, tr in lit.items():
            errors[f"{k} (no CPP after start-up)"] = _errors(rp, tr, t0)

    chosen, info, dops = _choose_subsets(rp, t0)
    subsets = []
    for n in subset_sizes:
        if n not in chosen:
            continue
        sats = chosen[n]
        entry: dict[str, Any] = {"n_satellites": n, "satellites": sats,
                                 "geometry_hdop": _finite(dops[n])}
        for mode, tight in (("loose", False), ("tight", True)):
            tr = rp.fuse(f"{n} sat {mode} {','.join(sats)}",
                         keep(satellites_keep=sats, tightly_coupled=tight))
            sc = _scores(_errors(rp, tr, t0), n_window)
            entry[mode] = {k: sc[k] for k in ("velocity_std_mps", "horizontal_std_m",
                                              "heading_std_deg", "horizontal_max_m",
                                              "heading_rms_deg")}
        subsets.append(entry)
    report["satellite_subsets"] = subsets
    report["satellites_tracked"] = {s: info[s] for s in sorted(info)}

    report["clock_drift"] = {}
    four = chosen.get(4)
    if clock_drift and four:
        sats = sorted(four, key=lambda s: -info[s]["elevation_deg"])
        per = {i: [s] for i, s in enumerate(sats)}
        cd: dict[str, Any] = {"satellite_per_receiver": {str(i): s for i, s in enumerate(sats)}}
        for name, common in (("common", True), ("separate", False)):
            tr = rp.fuse(f"one satellite per receiver, {name} clock drift",
                         keep(per_receiver_sats=per, common_clock=common))
            errors[f"per-receiver sats, {name} clock"] = err = _errors(rp, tr, t0)
            sc = _scores(err, n_window)
            cd[name] = {k: sc[k] for k in ("horizontal_std_m", "horizontal_max_m",
                                           "velocity_std_mps", "heading_std_deg",
                                           "heading_rms_deg")}
        report["clock_drift"] = cd

    report["single_satellite_heading"] = {}
    five = chosen[max(chosen)][:max(single_satellites, 0)]
    if five:
        pipeline = {s: rp.fuse(f"1 sat tight {s}", keep(satellites_keep=[s])) for s in five}
        report["single_satellite_heading"] = _OneSatelliteHeading(rp, main, t0, five).report(
            five, pipeline)

    report["structure"] = _structure(rp, main)
    if tracking:
        from backend.reports.tracking import (
            DEFAULT_CLICK_TIMES_S,
            REANCHOR_FRAMES,
            default_clicks,
            evaluate_landmarks,
            evaluate_tracking,
            run_fusion,
        )

        # The evaluation's default click times (45-78 s) when the replay reaches them, else
        # three times spread over the scored window.
        times = [t for t in DEFAULT_CLICK_TIMES_S if t < rp.duration - 5.0]
        times = times or list(np.linspace(init_s, rp.duration - 5.0, 3))
        clicks = [c for c in default_clicks(rec, times_s=times) if c.frame < len(rp.vo)]
        show("tracking and landmark evaluation")
        run = run_fusion(rec, vo_outputs=rp.vo, snapshot_frames=[c.frame for c in clicks],
                         snapshot_every=REANCHOR_FRAMES, options=full, end_s=end_s)
        report["tracking"] = evaluate_tracking(rec, run, clicks, end_s=end_s)
        report["landmarks"] = evaluate_landmarks(rec, run)
    fusion_s = main.wall_s
    vo_s = (rp.vo_ms + rp.decode_ms) * len(rp.vo) / 1e3
    report["realtime_factor"] = rp.duration / max(fusion_s + vo_s, 1e-9)
    timing = {k: float(v) for k, v in main.timing_ms.items()}
    timing["vo"] = rp.vo_ms
    timing["decode"] = rp.decode_ms
    timing["fusion_per_frame"] = 1e3 * fusion_s / len(rp.vo)
    report["timing_ms"] = timing

    if plots_dir is not None:
        report["plots"] = _plots(Path(plots_dir), rp, runs, errors, report)
    report["structure"].pop("_arrays", None)
    return report


def replay_report(recording_path: str | Path, **options: Any) -> dict[str, Any]:
    """Load a recording (``recordings.format.load``) and run :func:`replay_report_for`."""
    from recordings.format import load

    return replay_report_for(load(recording_path), **options)


# ------------------------------------------------------------------------------- plots


def _plots(out: Path, rp: _Replay, runs: dict[str, _Track], errors: dict[str, Any],
           report: dict[str, Any]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    main = runs["INS+VO+CPP"]
    origin = rp.ref.interpolate(main.origin_time)[0]
    t0 = report["window_s"][0]
    palette = iter(["tab:orange", "tab:green", "tab:purple", "tab:blue", "tab:red", "tab:brown",
                    "tab:pink", "tab:gray", "tab:olive", "tab:cyan"])
    colours = {name: next(palette) for name in errors}  # the four methods come first
    true = rp.rec.scene_points
    quay = _quay_line(rp, origin)
    written = []

    # Trajectories from above.
    fig, ax = plt.subplots(figsize=(8, 8))
    ref_pos = rp.ref.interpolate(main.time)[0] - origin
    ax.plot(ref_pos[:, 1], ref_pos[:, 0], "k-", lw=3, alpha=0.35, label="reference")
    for name, tr in runs.items():
        ax.plot(tr.position[:, 1], tr.position[:, 0], "-", color=colours.get(name), lw=1.2,
                label=name)
    if quay is not None:
        ax.plot(quay[:, 1], quay[:, 0], "-", color="saddlebrown", lw=2, label="quay (scene pts)")
    k0 = int(np.searchsorted(main.time - rp.start, t0))
    if k0 < len(ref_pos):
        ax.plot(ref_pos[k0, 1], ref_pos[k0, 0], "ko", ms=6, label=f"window start (+{t0:g} s)")
    lim = ref_pos[np.isfinite(ref_pos).all(axis=1)]
    pad = 15.0
    ax.set_xlim(lim[:, 1].min() - pad, lim[:, 1].max() + pad)
    ax.set_ylim(lim[:, 0].min() - pad, max(lim[:, 0].max(), -np.inf if quay is None
                                           else quay[:, 0].max()) + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"{report['recording']}: trajectories (aligned at the fusion origin)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    written.append(_save(fig, out / "trajectories.png"))

    # Horizontal error over time.
    fig, ax = plt.subplots(figsize=(10, 5))
    for name, err in errors.items():
        if err is None:
            continue
        h = np.hypot(err.position[:, 0], err.position[:, 1])
        ax.semilogy(err.time, np.maximum(h, 1e-4), label=name, color=colours[name], lw=1)
    ax.axvline(t0, color="k", ls="--", lw=0.8)
    ax.set_xlabel("time since the recording start (s)")
    ax.set_ylabel("horizontal error (m)")
    ax.set_title("horizontal error of the body origin (window after the dashed line)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    written.append(_save(fig, out / "horizontal_error.png"))

    # Heading error over time.
    fig, ax = plt.subplots(figsize=(10, 5))
    for name, err in errors.items():
        if err is None or not np.isfinite(err.heading).any():
            continue
        ax.plot(err.time, np.degrees(err.heading), label=name, color=colours[name], lw=1)
    ax.axvline(t0, color="k", ls="--", lw=0.8)
    ax.set_xlabel("time since the recording start (s)")
    ax.set_ylabel("heading error (deg)")
    ax.set_ylim(-1.2, 1.2)
    ax.set_title("heading error (clipped to ±1.2°)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    written.append(_save(fig, out / "heading_error.png"))

    # Port structure from above.
    arrays = report["structure"].get("_arrays")
    if arrays is not None:
        pts, d, cam, _ = arrays
        fig, axes = plt.subplots(1, 2, figsize=(15, 7))
        for ax, span in zip(axes, (None, 30.0), strict=True):
            if true is not None:
                tt = true - origin
                ax.scatter(tt[:, 1], tt[:, 0], s=6, c="red", marker="x", lw=0.6,
                           label="true scene points")
            if quay is not None:
                ax.plot(quay[:, 1], quay[:, 0], "-", color="saddlebrown", lw=1.5, label="quay")
            sc = ax.scatter(pts[:, 1], pts[:, 0], s=4, c=np.minimum(d, 5.0), cmap="viridis",
                            label="fused structure (colour: m to nearest true, ≤5)")
            ax.plot(ref_pos[:, 1], ref_pos[:, 0], "k-", lw=1, label="reference track")
            ax.plot(cam[1], cam[0], "k^", ms=8, label="camera at the end")
            ax.set_aspect("equal")
            ax.grid(alpha=0.3)
            ax.set_xlabel("east (m)")
            ax.set_ylabel("north (m)")
            if span is None:
                c = np.median(pts, axis=0)
                r = max(np.percentile(np.abs(pts[:, :2] - c[:2]), 95) * 1.3, 40.0)
                ax.set_xlim(c[1] - r, c[1] + r)
                ax.set_ylim(c[0] - r, c[0] + r)
                ax.set_title("point cloud from above (95 % of the points)")
            else:
                ax.set_xlim(cam[1] - span, cam[1] + span)
                ax.set_ylim(cam[0] - span, cam[0] + span)
                ax.set_title(f"within {span:g} m of the camera at the end")
        fig.colorbar(sc, ax=axes, shrink=0.7, label="distance to the nearest true point (m)")
        axes[0].legend(fontsize=7, loc="lower left")
        written.append(_save(fig, out / "structure.png"))

    # Fig. 14: heading σ from one satellite, per baseline vs all six.
    ss = report.get("single_satellite_heading") or {}
    if ss.get("satellites"):
        sats = ss["satellites"]
        names = list(sats[0]["heading_std_deg"])
        width = 0.8 / len(names)
        fig, axes = plt.subplots(2, 1, figsize=(10, 8), sharex=True)
        for ax, key, title in zip(axes, ("snapshot_std_deg", "heading_std_deg"), (
                "single-epoch heading from the single differences (no gyro)",
                "filtered with the gyro over the window"), strict=True):
            for k, name in enumerate(names):
                vals = [e[key].get(name) for e in sats]
                ax.bar(np.arange(len(vals)) + k * width, [np.nan if v is None else v
                                                          for v in vals], width,
                       label=name if name == "all six" else f"baseline {name}")
            ax.set_yscale("log")
            ax.set_ylabel("heading σ (deg)")
            ax.set_title(f"one satellite, single baselines vs all six (fig. 14): {title}")
            ax.grid(alpha=0.3, axis="y", which="both")
        axes[1].set_xticks(np.arange(len(sats)) + 0.4 - width / 2)
        axes[1].set_xticklabels([f"{e['sat']} ({_f(e['elevation_deg'], '.0f')}°)" for e in sats])
        axes[0].legend(fontsize=7, ncol=4)
        written.append(_save(fig, out / "single_satellite_heading.png"))
    return written


def _save(fig: Any, path: Path) -> str:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return str(path)


# ---------------------------------------------------------------------------- printing


def _f(x: Any, spec: str = ".3f") -> str:
    return "-" if x is None else format(x, spec)


def format_replay_report(report: dict[str, Any]) -> str:
    """The thesis' tables from :func:`replay_report`."""
    w0, w1 = report["window_s"]
    lines = [f"{report['recording']}: {report['duration_s']:g} s, window {w0:g}-{w1:g} s after "
             f"a {report['init_s']:g} s initialisation; {report['alignment']}", "",
             "table 17  horizontal error     std (m)   max (m)   rms (m)  hdg std/rms (deg)"
             " coverage"]

    def row(name: str, m: dict[str, Any]) -> str:
        return (f"  {name:<27} {_f(m['horizontal_std_m'], '7.3f')}  "
                f"{_f(m['horizontal_max_m'], '8.3f')}  {_f(m['horizontal_rms_m'], '8.3f')}  "
                f"{_f(m['heading_std_deg'], '6.3f')}/{_f(m['heading_rms_deg'], '<6.3f')}  "
                f"{100 * m['coverage']:6.0f}%")

    for name, m in report["methods"].items():
        lines.append(row(name, m))
    vo = report["methods"]["VO"]
    if vo.get("anchored_at_s") is not None:
        lines.append(f"  (VO alone: mapped at +{vo['anchored_at_s']:.1f} s with the fused pose and"
                     f" scale {vo['scale']:.4f} m/unit, segment {vo['segment']})")
    lit = report.get("methods_without_cpp_after_startup")
    if lit:
        lines.append("  no carrier phase after the start-up (use_cpp=False):")
        for name, m in lit.items():
            lines.append(row(f"  {name}", m))
    subsets = report.get("satellite_subsets") or []
    if subsets:
        lines += ["", "tables 18-20  satellites kept after the initialisation "
                      "(loose | tight coupling of the velocity)",
                  f"  {'n':>2} {'satellites':<24} {'HDOP':>6}  {'vel σ (m/s)':>15}  "
                  f"{'traj σ (m)':>15}  {'traj max (m)':>15}  {'heading σ (deg)':>15}  "
                  f"{'hdg rms (deg)':>15}"]
        for s in subsets:
            lo, ti = s["loose"], s["tight"]
            lines.append(
                f"  {s['n_satellites']:>2} {','.join(s['satellites']) or '-':<24} "
                f"{_f(s['geometry_hdop'], '6.2f')}  "
                f"{_f(lo['velocity_std_mps'], '7.3f')}|{_f(ti['velocity_std_mps'], '<7.3f')}  "
                f"{_f(lo['horizontal_std_m'], '7.3f')}|{_f(ti['horizontal_std_m'], '<7.3f')}  "
                f"{_f(lo['horizontal_max_m'], '7.3f')}|{_f(ti['horizontal_max_m'], '<7.3f')}  "
                f"{_f(lo['heading_std_deg'], '7.3f')}|{_f(ti['heading_std_deg'], '<7.3f')}  "
                f"{_f(lo['heading_rms_deg'], '7.3f')}|{_f(ti['heading_rms_deg'], '<7.3f')}")
    cd = report.get("clock_drift") or {}
    if cd:
        per = ", ".join(f"rx{int(i) + 1} {s}" for i, s in cd["satellite_per_receiver"].items())
        lines += ["", f"table 21  one satellite per receiver ({per})",
                  "  clock drift     std (m)   max (m)  vel σ (m/s)  hdg σ/rms (deg)"]
        for name in ("separate", "common"):
            m = cd[name]
            lines.append(f"  {name:<12} {_f(m['horizontal_std_m'], '8.3f')}  "
                         f"{_f(m['horizontal_max_m'], '8.3f')}  "
                         f"{_f(m['velocity_std_mps'], '11.3f')}  "
                         f"{_f(m['heading_std_deg'], '9.3f')}/{_f(m['heading_rms_deg'], '.3f')}")
    ss = report.get("single_satellite_heading") or {}
    if ss.get("satellites"):
        names = list(ss["satellites"][0]["heading_std_deg"])
        lines += ["", "fig. 14  heading σ (deg) from ONE satellite, each baseline vs all six: "
                      "SD + gyro filter / single-epoch snapshot; pipeline = the EKF with that "
                      "satellite alone",
                  "  sat  elev  " + " ".join(f"{n:>13}" for n in names) + "  pipeline"]
        for e in ss["satellites"]:
            cells = [f"{_f(e['heading_std_deg'][n], '5.2f')}/"
                     f"{_f(e['snapshot_std_deg'][n], '<6.1f')}" for n in names]
            lines.append(f"  {e['sat']:<4} {_f(e['elevation_deg'], '4.0f')}  "
                         + " ".join(f"{c:>13}" for c in cells)
                         + f"  {_f(e.get('pipeline_all_baselines_std_deg'), '8.3f')}")
    elif ss.get("reason"):
        lines += ["", f"fig. 14: {ss['reason']}"]
    st = report["structure"]
    lines += ["", f"structure: {st['points']} points, {st['matched']} matched to a true scene "
                  f"point within {st['gate']} (the scene points sample outlines sparsely: a "
                  "coarse check; the 3-D error against the rendered surface is under the "
                  "port-structure refinement below)",
              "  range from the camera   points  matched  median (m)  p90 (m)"]
    for b in st["bands"]:
        lo, hi = b["range_m"]
        name = f"{lo:g}-{hi:g} m" if hi is not None else f">{lo:g} m"
        lines.append(f"  {name:<22} {b['points']:7d}  {b['matched']:7d}  "
                     f"{_f(b['median_m'], '10.3f')}  {_f(b['p90_m'], '7.3f')}")
    lines.append(f"  {'all':<22} {st['points']:7d}  {st['matched']:7d}  "
                 f"{_f(st['median_m'], '10.3f')}  {_f(st['p90_m'], '7.3f')}")
    raw = st.get("unrefined")
    if raw:
        rq = (raw.get("quay_edge") or {}).get("within_30m") or {}
        lines.append(f"  before the landmark refinement: all median {_f(raw['median_m'])} m, "
                     f"p90 {_f(raw['p90_m'])} m; within 30 m median "
                     f"{_f(raw['within_30m']['median_m'])} m; quay edge within 30 m median "
                     f"{_f(rq.get('median_m'))} m")
    q = st.get("quay_edge")
    if q:
        for name, b in (("within 30 m", q["within_30m"]), ("all", q["all"])):
            lines.append(f"  quay edge, {name:<11} {b['points']:7d} points within "
                         f"{q['band_m']:g} m of the edge: median {_f(b['median_m'])} m, "
                         f"p90 {_f(b['p90_m'])} m")
    t = report["timing_ms"]
    stages = ", ".join(f"{k} {v:.2f}" for k, v in t.items())
    lines += ["", f"realtime factor {report['realtime_factor']:.2f} (VO + INS+VO+CPP fusion); "
                  f"ms per call/frame: {stages}"]
    if report.get("tracking"):
        from backend.reports.tracking import format_tracking_report

        lines += ["", format_tracking_report(report["tracking"], report.get("landmarks"))]
    if report.get("plots"):
        lines.append("plots: " + ", ".join(report["plots"]))
    return "\n".join(lines)


# -------------------------------------------------------------------------------- CLI


def _json_safe(x: Any) -> Any:
    """Strict JSON: NaN/inf become null."""
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def cmd_replay(args: argparse.Namespace) -> int:
    path = args.recording
    if path is None:
        path = Path(__file__).resolve().parents[2] / "recordings" / "default"
    if not args.report:
        raise ValueError("replay: add --report to run the thesis' experiments (the interactive "
                         "replay is `berthing-aid serve`)")
    report = _json_safe(replay_report(path, init_s=args.init, end_s=args.end,
                                      plots_dir=args.plots, progress=not args.quiet,
                                      tracking=not args.no_tracking))
    print(json.dumps(report, indent=2, allow_nan=False) if args.json
          else format_replay_report(report))
    return 0


def add_replay_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``berthing-aid replay RECORDING --report [--json] [--plots DIR]``."""
    p = sub.add_parser("replay", help="replay a recording through the fusion and reproduce the "
                                      "thesis' tables against its reference")
    p.add_argument("recording", nargs="?", help="recording directory (default: bundled)")
    p.add_argument("--report", action="store_true",
                   help="run the experiments (tables 17-21, fig. 14, structure, timing)")
    p.add_argument("--json", action="store_true", help="JSON instead of the tables")
    p.add_argument("--plots", metavar="DIR", default=None, help="write PNG plots into DIR")
    p.add_argument("--init", type=float, default=INIT_S, metavar="S",
                   help=f"initialisation before the window (default {INIT_S:g} s)")
    p.add_argument("--end", type=float, default=None, metavar="S",
                   help="replay only the first S seconds (default: all)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--no-tracking", action="store_true",
                   help="skip the designated-target and landmark evaluations")
    p.set_defaults(func=cmd_replay)
    return p
