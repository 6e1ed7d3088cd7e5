"""Error-state EKF (estimator/ekf.py) and the fusion engine (estimator/pipeline.py).

a) the measurement Jacobians against finite differences of the measurement models;
b) a simulated small-boat run (motion + MEMS IMU + four-receiver GNSS of ``recordings.sim``):
   NEES consistency and the accuracy of INS + CPP, the satellite-blocking scenarios of thesis
   tables 19 and 21 (tight vs loose coupling with 3 satellites, common vs separate clocks);
c) the VO measurement models with VO outputs made from the truth (wrong scale, drifting
   world), and a short end-to-end run with rendered frames through the real VO.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pytest

from estimator.ekf import ErrorStateEkf
from estimator.frames import (
    dcm_to_rotvec,
    ecef_to_ned,
    euler_to_dcm,
    ned_to_ecef,
    rotvec_to_dcm,
)
from estimator.ins import Ins, InsState, gravity_level
from estimator.pipeline import Fusion, FusionOptions
from estimator.records import ImuCalibration
from estimator.vo import VoOutput, umeyama_alignment
from recordings.faults import iono_storm
from recordings.sim.scenarios import SMALL_BOAT
from recordings.sim.scene import camera_calibration
from recordings.sim.simulate import SensorRun, simulate_sensors

DURATION_S = 65.0
BLOCK_AFTER_S = 30.0  # thesis: 30 s with every satellite, then the blocking scenario
SEED = 3
SCENARIO = SMALL_BOAT
TABLE21 = {0: ["G05"], 1: ["G18"], 2: ["G24"], 3: ["G20"]}  # one satellite per receiver
THREE_SATS = ["G05", "G18", "G24"]  # spread in azimuth (62°, 313°, 197°)


class Sim(SensorRun):
    def truth(self, t_gpst: float):
        return self.motion.state(t_gpst - SCENARIO.start_gpst)


@pytest.fixture(scope="module")
def sim() -> Sim:
    run = simulate_sensors(SCENARIO, SEED, DURATION_S)
    return Sim(**vars(run))


@dataclass
class Sample:
    t: float  # s since the scenario start
    dp: np.ndarray  # position error (relative to the world origin), m
    dv: np.ndarray
    de: np.ndarray  # attitude error, rad (small angle in L)
    P_r: np.ndarray  # against the world: the filter's and the drift it does not model
    P_v: np.ndarray
    P_e: np.ndarray
    P_drift: np.ndarray


def run(sim: Sim, options: FusionOptions, vo_feed=None, every: int = 10):
    """Drive the fusion with the simulated messages in time order; sample the errors."""
    f = Fusion(sim.calibration, sim.nav, options)
    out: list[Sample] = []
    p0 = None
    for k, t in sim.feed(f):
        if vo_feed is not None and k % 10 == 0:
            vo_feed(f, t)
        if f.ekf is None or k % every:
            continue
        if p0 is None:
            p0 = sim.truth(f.origin_time).position_ned[0]
        s = f.state()
        tr = sim.truth(s.time)
        ix, P = f.ekf.ix, f.ekf.P
        out.append(Sample(
            t=s.time - SCENARIO.start_gpst, dp=s.position_ned - (tr.position_ned[0] - p0),
            dv=s.velocity_ned - tr.velocity_ned[0],
            de=dcm_to_rotvec(s.C_body_to_level @ tr.C_body_to_level[0].T),
            P_r=s.position_cov + s.position_drift_cov, P_v=P[ix.V, ix.V].copy(), P_e=s.attitude_cov,
            P_drift=s.position_drift_cov))
    return f, out


def horizontal_stats(samples: list[Sample], t_from: float = BLOCK_AFTER_S):
    h = np.array([s.dp[:2] for s in samples if s.t >= t_from])
    std = float(np.sqrt(np.mean(np.sum((h - h.mean(axis=0)) ** 2, axis=1))))
    return std, float(np.max(np.linalg.norm(h, axis=1)))


def nees(samples: list[Sample], err: str, cov: str, t_from: float) -> float:
    vals = [getattr(s, err) @ np.linalg.solve(getattr(s, cov), getattr(s, err))
            for s in samples if s.t >= t_from]
    return float(np.mean(vals))


# ------------------------------------------------------------------- measurement Jacobians


def test_measurement_jacobians_match_finite_differences():
    """y = measured − predicted = H x with x = estimate − truth: perturbing the nominal state
    by δ must change every innovation by H δ."""
    origin = np.array([np.radians(34.72), np.radians(135.33), 37.0])
    C = euler_to_dcm(0.03, -0.02, 0.7)
    ins = Ins(origin, ImuCalibration(), InsState(0.0, np.array([1.0, 2.0, 0.1]),
                                                 np.array([1.0, 0.5, 0.0]), C))
    antennas = SMALL_BOAT.antennas_body()
    cam = camera_calibration(SMALL_BOAT)
    ekf = ErrorStateEkf(ins, antennas, camera_to_body=cam.C_camera_to_body,
                        camera_lever_body=cam.lever_arm_body)
    gyro, accel = np.array([0.01, -0.02, 0.15]), np.array([0.3, 0.1, -9.8])
    for k in range(1, 101):  # 1 s of turning: the clone (previous epoch) differs from now
        ekf.propagate(0.01 * k, gyro, accel)
    ekf.delays = np.array([0.01, -0.03, 0.02])
    C_wc = (C @ cam.C_camera_to_body).T
    ekf.start_vo_segment(0, C_wc, np.array([0.2, 0.1, 1.0]), 3.0, 1.0)
    ix = ekf.ix
    u = np.array([0.3, -0.5, -0.81])
    u /= np.linalg.norm(u)
    # A VO attitude that agrees with the prediction (innovations are small in operation).
    C_wc_now = (ekf.nominal.C_body_to_level @ cam.C_camera_to_body).T @ ekf.vo.C_world_to_level
    p_w = np.array([0.5, -0.2, 2.0])

    def innovations() -> np.ndarray:
        eta = [ekf.eta_model(a, u, 1.0)[0] for a in range(4)]
        sd = [ekf.sd_model(i, j, -u)[0] for i, j in ((0, 1), (0, 3), (2, 1))]
        y_th, _, y_d, _ = ekf.vo_innovation(C_wc_now, p_w)
        return -np.array([*eta, *sd, *(-y_th), *(-y_d)])  # measured fixed: y = −predicted

    def perturb(delta: np.ndarray) -> None:
        ekf.ins.correct(d_position=-delta[ix.R], d_attitude=-delta[ix.E])
        ekf.nominal = ekf.ins.state
        ekf.delays = ekf.delays + delta[ix.D]
        ekf.clock_drift = ekf.clock_drift + delta[ix.Z]
        vo = ekf.vo
        vo.C_world_to_level = rotvec_to_dcm(delta[ix.TH]) @ vo.C_world_to_level
        vo.scale += float(delta[ix.S][0])
        vo.origin_ned = vo.origin_ned + delta[ix.DV]
        ekf._clone_position = ekf._clone_position + delta[ix.R0]
        ekf._clone_attitude = rotvec_to_dcm(delta[ix.E0]) @ ekf._clone_attitude

    H = np.array([*(ekf.eta_model(a, u, 1.0)[1] for a in range(4)),
                  *(ekf.sd_model(i, j, -u)[1] for i, j in ((0, 1), (0, 3), (2, 1))),
                  *ekf.vo_innovation(C_wc_now, p_w)[1], *ekf.vo_innovation(C_wc_now, p_w)[3]])
    y0 = innovations()
    rng = np.random.default_rng(1)
    delta = np.zeros(ix.n)
    for block, scale in ((ix.R, 0.01), (ix.E, 1e-4), (ix.D, 0.01), (ix.Z, 0.01),
                         (ix.TH, 1e-4), (ix.S, 0.01), (ix.DV, 0.01), (ix.R0, 0.01),
                         (ix.E0, 1e-4)):
        delta[block] = rng.normal(0.0, scale, block.stop - block.start)
    perturb(delta)
    dy = innovations() - y0
    np.testing.assert_allclose(dy, H @ delta, atol=2e-6)
    # the bias columns stay empty: biases enter through the propagation only
    assert not np.any(H[:, ix.BG]) and not np.any(H[:, ix.BA])


def test_a_vo_held_off_the_attitude_corrects_its_own_states_only():
    """While the single differences hold the heading, a VO update must not pull the
    attitude, the gyro bias or the clone's attitude (a VO yaw drifting within its model
    dragged the fused heading 0.5° off on an unseen seed, and its clicks' distances with it):
    those states and their covariance stay, Θ takes the disagreement. The same update
    without the hold does move the attitude, and the Joseph-form update with nothing held is
    filterpy's optimal one."""
    import copy

    origin = np.array([np.radians(34.72), np.radians(135.33), 37.0])
    C = euler_to_dcm(0.03, -0.02, 0.7)
    ins = Ins(origin, ImuCalibration(), InsState(0.0, np.zeros(3), np.array([1.0, 0.5, 0.0]),
                                                 C))
    cam = camera_calibration(SMALL_BOAT)
    ekf = ErrorStateEkf(ins, SMALL_BOAT.antennas_body(), camera_to_body=cam.C_camera_to_body,
                        camera_lever_body=cam.lever_arm_body)
    gyro, accel = np.array([0.01, -0.02, 0.15]), np.array([0.3, 0.1, -9.8])
    for k in range(1, 101):
        ekf.propagate(0.01 * k, gyro, accel)
    C_wc = (ekf.nominal.C_body_to_level @ cam.C_camera_to_body).T
    ekf.start_vo_segment(0, C_wc, np.zeros(3), 3.0, 0.3)
    for k in range(101, 301):  # 2 s: Θ's random walk opens up beside the attitude
        ekf.propagate(0.01 * k, gyro, accel)
    ekf.flush()
    ix = ekf.ix
    # the VO's camera 0.3° off in yaw from the fused one, its position where the EKF has it
    C_vo = (rotvec_to_dcm(np.radians([0.0, 0.0, 0.3])) @ ekf.nominal.C_body_to_level
            @ cam.C_camera_to_body).T @ ekf.vo.C_world_to_level
    p_w = ekf.vo.C_world_to_level.T @ (ekf.camera_position() - ekf.vo.origin_ned) / ekf.vo.scale

    free, held = copy.deepcopy(ekf), copy.deepcopy(ekf)
    free.update_vo(C_vo, p_w)
    held.update_vo(C_vo, p_w, hold_attitude=True)
    yaw = lambda e: dcm_to_rotvec(e.nominal.C_body_to_level @ ekf.nominal.C_body_to_level.T)[2]  # noqa: E731
    assert abs(np.degrees(yaw(free))) > 0.01  # the VO pulls the attitude when not held
    assert abs(yaw(held)) < 1e-12
    np.testing.assert_array_equal(held.nominal.gyro_bias, ekf.nominal.gyro_bias)
    assert np.any(free.nominal.gyro_bias != ekf.nominal.gyro_bias)
    np.testing.assert_allclose(held._clone_attitude, ekf._clone_attitude, atol=1e-15)
    for block in (ix.E, ix.BG, ix.E0):
        np.testing.assert_allclose(held.P[block, block], ekf.P[block, block], rtol=1e-12)
    # Θ took the disagreement: the VO world turned towards the measurement
    th = dcm_to_rotvec(held.vo.C_world_to_level @ ekf.vo.C_world_to_level.T)[2]
    assert np.degrees(th) < -0.05
    assert np.linalg.eigvalsh(held.P).min() > -1e-15 * np.abs(held.P).max()
    np.testing.assert_allclose(held.P, held.P.T, rtol=0, atol=1e-18)

    # nothing held: the Joseph-form update is the optimal one
    y, H, _, _ = ekf.vo_innovation(C_vo, p_w)
    R = np.eye(3) * ekf.cfg.vo_attitude_sigma**2
    a, b = copy.deepcopy(ekf), copy.deepcopy(ekf)
    a._schmidt_update(y, H, R, H @ a.P @ H.T + R, hold=())
    b.kf.update(y.reshape(-1, 1), R=R, H=H)
    np.testing.assert_allclose(a.kf.x, b.kf.x, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-7, atol=1e-16)


# ------------------------------------------------------------------ INS + CPP on the boat


def test_an_unmeasured_bias_keeps_its_turn_on_uncertainty():
    """The IMU biases are turn-on constants plus a slow instability: with nothing measuring
    them, their σ must not shrink. As Gauss–Markov error states (F = −1/τ, τ 300 s) the
    accelerometer bias σ fell from 0.25 to 0.17 m/s² in 114 s with no information, and a
    large ship's tilt, tied to it, was trusted 4-5σ off."""
    origin = np.array([np.radians(34.72), np.radians(135.33), 37.0])
    ins = Ins(origin, ImuCalibration(), InsState(0.0, np.zeros(3), np.zeros(3), np.eye(3)))
    ekf = ErrorStateEkf(ins, SMALL_BOAT.antennas_body())
    ix = ekf.ix
    before = np.sqrt(np.diag(ekf.P))
    g = -gravity_level(np.zeros(3), origin)  # at rest, level: the specific force is −g
    for k in range(1, 12001):  # 120 s
        ekf.propagate(0.01 * k, np.zeros(3), g)
    after = np.sqrt(np.diag(ekf.covariance(slice(0, ix.n))))
    for block in (ix.BG, ix.BA):
        assert np.all(after[block] >= before[block]), (block, before[block], after[block])


def test_the_time_update_by_blocks_is_the_dense_one():
    """``flush`` propagates P by blocks (the INS block's Φ, a diagonal elsewhere): it must be
    Φ P Φᵀ + ½ (Φ Q_c Φᵀ + Q_c) Δt of the dense Φ, for a P with every block filled (a VO
    segment, correlations everywhere) and the rounding asymmetry the updates leave in it, and
    carry the carrier-phase noise cross-covariance as Φ M."""
    import math

    from estimator.ins import error_state_transition

    origin = np.array([np.radians(34.72), np.radians(135.33), 37.0])
    C = euler_to_dcm(0.03, -0.02, 0.7)
    for common_clock in (True, False):
        ins = Ins(origin, ImuCalibration(), InsState(0.0, np.zeros(3), np.array([2.0, 0.5, 0.0]),
                                                     C))
        ekf = ErrorStateEkf(ins, SMALL_BOAT.antennas_body(), common_clock=common_clock)
        ekf.start_vo_segment(0, C.T, np.array([0.2, 0.1, 1.0]), 3.0, 1.0)
        ix, n = ekf.ix, ekf.ix.n
        rng = np.random.default_rng(5)
        A = rng.normal(size=(n, n)) * rng.uniform(0.01, 3.0, n)
        P = A @ A.T
        P[3, 20] *= 1.0 + 1e-12  # the asymmetry of a Joseph update's rounding
        ekf.kf.P = P.copy()
        ekf._noise_M = rng.normal(size=(n, 9))
        M = ekf._noise_M.copy()
        gyro, accel = np.array([0.01, -0.02, 0.15]), np.array([0.3, 0.1, -9.8])
        for k in range(1, 5):  # under covariance_interval_s: accumulated, not flushed
            ekf.propagate(0.01 * k, gyro, accel)
        dt, f_mean = ekf._acc_dt, ekf._acc_f / ekf._acc_dt
        cfg = ekf.cfg
        Phi = np.eye(n)
        Phi[ix.INS, ix.INS] = error_state_transition(
            dt, ekf.nominal.C_body_to_level, f_mean, origin, math.inf, math.inf,
            ins.gyro_correction, ins.accel_correction, ekf._gamma)
        q = np.zeros(n)
        q[ix.V], q[ix.E] = cfg.accel_vrw**2, cfg.gyro_arw**2
        q[ix.BG] = 2.0 * cfg.gyro_bias_sigma**2 / cfg.gyro_bias_tau
        q[ix.BA] = 2.0 * cfg.accel_bias_sigma**2 / cfg.accel_bias_tau
        speed = float(np.linalg.norm(ekf.nominal.velocity_ned))
        for block, tau, psd in (
                (ix.D, cfg.delay_tau, 2.0 * cfg.delay_sigma**2 / cfg.delay_tau),
                (ix.Z, cfg.clock_drift_tau, cfg.clock_drift_psd),
                (ix.TH, cfg.vo_attitude_tau, cfg.vo_attitude_psd + cfg.vo_attitude_per_m * speed),
                (ix.S, cfg.vo_scale_tau,
                 (cfg.vo_scale_psd + cfg.vo_scale_per_m * speed) * ekf.vo.scale**2),
                (ix.DV, cfg.vo_drift_tau, cfg.vo_drift_psd + cfg.vo_drift_per_m * speed)):
            k = np.arange(block.start, block.stop)
            Phi[k, k] = 1.0 - dt / tau
            q[block] = psd
        Ps = 0.5 * (P + P.T)
        expected = Phi @ Ps @ Phi.T + 0.5 * (Phi @ np.diag(q) @ Phi.T + np.diag(q)) * dt
        ekf.flush()
        scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
        assert np.max(np.abs(ekf.P - expected) / scale) < 1e-13
        assert np.max(np.abs(ekf.P - ekf.P.T) / scale) < 1e-15  # symmetric to rounding
        np.testing.assert_allclose(ekf._noise_M, Phi @ M, rtol=1e-13, atol=1e-14)


def test_ins_cpp_consistency_and_accuracy(sim):
    """All satellites: NEES of position, velocity and attitude within chi-square bounds;
    horizontal error σ ≤ 5 cm (thesis table 17: 4.8 cm), heading error σ ≤ 0.2° (table 20:
    0.05–0.23° for a 10 cm array)."""
    f, samples = run(sim, FusionOptions(use_vo=False))
    st = f.status()
    assert st.phase == "fused" and st.compass_fixed and st.satellites >= 9
    assert f.origin_time - SCENARIO.start_gpst <= 3.0  # compass fix within a few epochs
    value = nees(samples, "dv", "P_v", 20.0) / 3.0
    assert 0.2 < value < 3.0, value
    # The attitude σ errs on the safe side here: tilt NEES/dof ~0.24 (the biases' random walk
    # keeps the turn-on σ, which a large ship needs: there it was 4σ overconfident), heading
    # ~0.06 (its σ ~2× wide: a known weakness, the check only says it is not absurd).
    late = [s for s in samples if s.t >= 20.0]
    tilt = np.mean([s.de[:2] @ np.linalg.solve(s.P_e[:2, :2], s.de[:2]) for s in late]) / 2
    heading = np.mean([s.de[2] ** 2 / s.P_e[2, 2] for s in late])
    assert 0.1 < tilt < 3.0 and 0.02 < heading < 3.0, (tilt, heading)
    std, _ = horizontal_stats(samples, 20.0)
    assert std <= 0.05
    yaw = np.degrees([s.de[2] for s in samples if s.t >= 20.0])
    assert np.sqrt(np.mean(np.square(yaw))) <= 0.2 and np.max(np.abs(yaw)) < 0.4
    assert np.max(np.abs(np.degrees([s.de[:2] for s in samples if s.t >= 20.0]))) < 0.1
    # Nothing to reject in clean data (cycle slips are caught before the EKF).
    stats = f.ekf.stats
    assert stats["eta"].rejected <= 0.002 * stats["eta"].accepted
    assert stats["zeta"].rejected <= 0.002 * stats["zeta"].accepted
    assert 0.3 < stats["eta"].mean_nis_per_dof < 2.0
    timing = f.timing()
    assert timing["imu"] < 1.0 and timing["gnss"] < 100.0  # ms per call (≥ 2× real time)


def test_position_covariance_is_consistent(sim):
    """The position's σ against the world covers its error: the filter takes each epoch's
    TDCP rate error as white, but with the simulated atmosphere departing from the correction
    models the integrated carrier phase drifts more than that admits (NEES/dof was ~4.9 with
    the filter's covariance alone); the reported drift (``cpp.CorrelatedDrift``, the world
    origin's) holds the rest."""
    f, samples = run(sim, FusionOptions(use_vo=False))
    value = nees(samples, "dp", "P_r", 20.0) / 3.0
    assert 0.3 < value < 3.0, ("dp", value)
    alone = np.mean([s.dp @ np.linalg.solve(s.P_r - s.P_drift, s.dp) for s in samples
                     if s.t >= 20.0]) / 3.0
    assert alone > 3.0, alone  # what the drift adds is needed


def test_an_active_atmosphere_widens_the_drift_it_drives(monkeypatch):
    """A small boat's seed (187, of a user trial) whose atmosphere is far more active than the
    quiet day the drift model was fitted on: its trajectory drifted 0.16 m in 70 s while the
    position's σ said 0.03 m (NEES/dof 12.9) and the HPL 0.18 m. The epochs' TDCP scatter
    (3.8 mm/s RMS, 0.1-1.0 on quiet seeds) measures the activity, and the drift's σ and its
    overbound in the HPL grow with it (``cpp.AtmosphereActivity``). As the server runs it:
    with the recording's sea-surface height."""
    from estimator.cpp import AtmosphereActivity
    from evaluation.consistency import position_consistency

    found = position_consistency("small-boat", 187, duration_s=80.0)
    assert found["activity_end"] > 1.8, found
    assert found["nees"] < 3.5 and found["max_error_to_hpl"] < 0.7, found
    monkeypatch.setattr(AtmosphereActivity, "scale", property(lambda _self: 1.0))
    quiet = position_consistency("small-boat", 187, duration_s=80.0)  # the quiet day's model
    assert quiet["nees"] > 6.0 and quiet["max_error_to_hpl"] > 0.85, quiet


def test_two_receivers_left_start_from_the_course_and_stay_honest(sim):
    """Receivers 3 and 4 silent throughout: no compass fix (it needs three), so the INS starts
    from the tilt and the course over ground, and one baseline's single differences cannot
    tell a turn about itself — the attitude check stands aside instead of failing on a
    singular fit (it did: the engine died). The heading converges, always inside its
    protection level."""
    two = Sim(**{**vars(sim), "epochs": [eps if i < 2 else [None] * len(eps)
                                          for i, eps in enumerate(sim.epochs)]})
    f = Fusion(two.calibration, two.nav, FusionOptions(use_vo=False))
    rows = []
    for k, _t in two.feed(f):
        if f.ekf is None or k % 50:
            continue
        s = f.state()
        tr = two.truth(s.time)
        heading = abs(np.degrees(dcm_to_rotvec(s.C_body_to_level @ tr.C_body_to_level[0].T)[2]))
        rows.append((heading, s.status.integrity.heading_pl_deg))
    assert f.origin_time is not None and "course" in f.alignment.message
    assert not f.compass.fixed
    assert f.ekf.stats["zeta"].accepted > 0  # the one baseline's single differences
    heading, pl = np.array(rows).T
    assert np.all(heading <= pl), rows  # (the 1° alert limit is reached after ~35 s)
    assert heading[-1] < 1.0 and pl[-1] < 0.1 * pl[0], (rows[0], rows[-1])


def _storm_run(sim, options: FusionOptions):
    """INS + carrier phase under an ionosphere twice the broadcast model's (``iono-storm``):
    (the fusion, the world origin's error NED, [(t, horizontal error, HPL, the HPL without
    the origin's term, trusted)] every half second)."""
    storm = iono_storm(sim.nav, np.radians(SCENARIO.origin_llh_deg[:2]).tolist()
                       + [SCENARIO.origin_llh_deg[2]], 1.0)
    stormy = Sim(**{**vars(sim), "epochs": [[storm(i, ep) for ep in eps]
                                            for i, eps in enumerate(sim.epochs)]})
    f = Fusion(stormy.calibration, stormy.nav, options)
    k2, p0, rows = f.monitor.cfg.k(2), None, []
    for k, t in stormy.feed(f):
        if f.ekf is None or k % 50:
            continue
        if p0 is None:
            p0 = stormy.truth(f.origin_time).position_ned[0]
        s = f.state()
        ig = s.status.integrity
        h = float(np.hypot(*(s.position_ned - (stormy.truth(s.time).position_ned[0] - p0))[:2]))
        P = s.position_cov[:2, :2]
        without = ig.hpl_m - k2 * (np.sqrt(np.linalg.eigvalsh(
            P + f.monitor.origin_drift_cov()[:2, :2])[-1]) - np.sqrt(np.linalg.eigvalsh(P)[-1]))
        rows.append((t - SCENARIO.start_gpst, h, ig.hpl_m, without, ig.trusted))
    site = np.array([*np.radians(SCENARIO.origin_llh_deg[:2]), SCENARIO.origin_llh_deg[2]])
    origin_error = ecef_to_ned(ned_to_ecef(np.zeros(3), f.origin.llh), site) - p0
    t, h, hpl, without, trusted = (np.array(c) for c in zip(*rows, strict=True))
    return f, origin_error, t, h, hpl, without, trusted.astype(bool)


def test_a_standalone_fix_metres_off_stays_inside_the_protection_level(sim):
    """An ionosphere twice the broadcast model's puts the standalone fix — the world origin,
    where the carrier phase's satellite geometry is computed — metres off, and the trajectory
    drifts ~0.1 mm/s per metre of it for as long as it runs (``cpp.origin_sensitivity``).
    Every trusted state's horizontal error must stay inside its protection level, and it is
    the origin's term that keeps it there: without it the error ends beyond the level."""
    _f, origin_error, t, h, hpl, without, trusted = _storm_run(sim, FusionOptions(use_vo=False))
    assert np.linalg.norm(origin_error) > 5.0, origin_error  # the storm did its damage
    # honest, and still available (the heading's level is within its limit from ~20 s)
    assert trusted[t >= BLOCK_AFTER_S].all()
    assert np.all(h[trusted] <= hpl[trusted])
    assert h[-1] > 1.2 * without[-1], (h[-1], without[-1], hpl[-1])


def test_the_sea_surface_pins_the_origin_height(sim):
    """The same storm with the sea surface's height known to 1 m (0.7 m off here, as a tide
    table not applied would leave it): the world origin's height is taken from it, the
    drift it drove and the protection level both shrink. A height given above mean sea level
    instead of the ellipsoid (37 m off) is refused, and said so."""
    height = SCENARIO.origin_llh_deg[2] + 0.7
    base = dict(use_vo=False, body_origin_height_m=-SCENARIO.reference_point_down_m)
    f0, e0, _t, h0, hpl0, _w, _tr = _storm_run(sim, FusionOptions(**base))
    f1, e1, _t, h1, hpl1, _w, trusted = _storm_run(
        sim, FusionOptions(**base, sea_surface=(height, 1.0)))
    assert abs(e0[2]) > 5.0 and abs(e1[2]) < 1.5, (e0, e1)
    assert np.all(h1[trusted] <= hpl1[trusted])
    assert hpl1[-1] < 0.6 * hpl0[-1] and h1[-1] < h0[-1], (hpl0[-1], hpl1[-1], h0[-1], h1[-1])
    assert not [a for a in f1.alerts() if a.kind == "sea-surface"]
    f2, e2, _t, h2, hpl2, _w, trusted2 = _storm_run(
        sim, FusionOptions(**base, sea_surface=(height - 37.0, 1.0)))
    np.testing.assert_allclose(e2, e0)
    refused = [a.message for a in f2.alerts() if a.kind == "sea-surface"]
    assert refused and "above the ellipsoid" in refused[0], f2.alerts()
    # ... and the disagreement (26 m: either could be wrong) widens the origin's height
    assert hpl2[-1] > 2.0 * hpl0[-1] and np.all(h2[trusted2] <= hpl2[trusted2])


def test_common_clock_beats_separate_clocks(sim):
    """Thesis table 21: four satellites, each seen by one receiver only. One clock-drift state
    for the common clock keeps the trajectory (0.063 m σ in the thesis), four separate ones
    cannot solve velocity + 4 drifts from 4 rows (1.44 m σ)."""
    common = FusionOptions(use_vo=False, per_receiver_sats=TABLE21, keep_after_s=BLOCK_AFTER_S)
    separate = dataclasses.replace(common, common_clock=False)
    f_c, s_c = run(sim, common)
    f_s, s_s = run(sim, separate)
    std_c, max_c = horizontal_stats(s_c)
    std_s, max_s = horizontal_stats(s_s)
    assert f_c.status().satellites == 4
    assert std_c < 0.1 and max_c < 0.3
    assert std_s > 5.0 * std_c and max_s > 0.5


def test_tight_coupling_with_three_satellites(sim):
    """Thesis tables 18–19: with 3 satellites the loosely coupled velocity does not exist
    (4 unknowns per receiver), the tightly coupled η with the common clock still helps."""
    tight = FusionOptions(use_vo=False, satellites_keep=THREE_SATS, keep_after_s=BLOCK_AFTER_S)
    loose = dataclasses.replace(tight, tightly_coupled=False)
    f_t, s_t = run(sim, tight)
    f_l, s_l = run(sim, loose)
    std_t, _ = horizontal_stats(s_t)
    std_l, _ = horizontal_stats(s_l)
    assert f_t.status().satellites == 3 and f_l.status().satellites == 0
    assert f_l.status().phase == "degraded"
    assert std_t < 0.5 and std_l > 3.0 * std_t
    # The single differences still hold the heading with 3 satellites.
    yaw = np.degrees([s.de[2] for s in s_t if s.t >= BLOCK_AFTER_S])
    assert np.sqrt(np.mean(np.square(yaw))) < 0.3


def test_a_satellites_antennas_share_its_tdcp_rate_error():
    """The TDCP's unmodelled rate (atmosphere, signal) is the satellite's: four antennas 10 cm
    apart seeing one satellite learn about as much as one antenna when that rate dominates,
    not four times as much; their own phase noise still averages over the four."""
    import copy

    from estimator.ekf import EkfConfig, EtaInput

    origin = np.array([np.radians(34.72), np.radians(135.33), 37.0])
    ins = Ins(origin, ImuCalibration(), InsState(0.0, np.zeros(3), np.array([1.0, 0.5, 0.0]),
                                                 euler_to_dcm(0.0, 0.0, 0.7)))
    # the clock drift known and steady: one satellite's rows inform the displacement
    ekf = ErrorStateEkf(ins, SMALL_BOAT.antennas_body(), initial_sigmas={"clock_drift": 1e-5},
                        config=EkfConfig(clock_drift_psd=1e-12))
    for k in range(1, 101):  # 1 s since the clone: the rows' interval
        ekf.propagate(0.01 * k, np.zeros(3), np.array([0.0, 0.0, -9.8]))
    u = np.array([0.3, -0.5, -0.81])
    u /= np.linalg.norm(u)
    ix = ekf.ix

    def information(antennas: list[int], rate_sigma: float) -> float:
        e = copy.deepcopy(ekf)
        before = u @ e.covariance(ix.R) @ u  # the clone: the displacement is R − R0
        rows = [EtaInput(antenna=a, sat="G05", u_ned=u, measured=e.eta_model(a, u, 1.0)[0],
                         sigma=0.002, interval=1.0) for a in antennas]
        e.update_carrier_phase(rows, [], rate_sigma=rate_sigma)
        return 1.0 / (u @ e.covariance(ix.R) @ u) - 1.0 / before

    assert information([0, 1, 2, 3], 0.02) < 1.2 * information([0], 0.02)
    assert information([0, 1, 2, 3], 1e-6) > 1.4 * information([0], 1e-6)


# --------------------------------------------------------------------------- VO models


def test_vo_models_estimate_scale_and_remove_drift(sim):
    """VO outputs made from the truth in a world that is scaled wrongly and keeps drifting
    (rotation, scale and origin): the EKF finds the scale within 1 % and maps the VO
    trajectory and structure back onto the truth while the raw drift grows to ~0.4 m."""
    cam = sim.calibration.camera
    t_vo = 25.0
    S0, scale_rate = 4.0, 2e-4  # metres per VO unit, and its drift (1/s)
    drift_rate = np.array([0.008, -0.008, 0.002])  # m/s of the VO origin
    rot_rate = np.radians([0.003, -0.003, 0.008])  # rad/s of the VO world
    st = sim.motion.state(t_vo)
    C_w_l = st.C_body_to_level[0] @ cam.C_camera_to_body
    o0 = sim.motion.point_position_ned(t_vo, cam.lever_arm_body)
    rng = np.random.default_rng(2)
    end = sim.motion.state(DURATION_S).position_ned[0]
    pts = end + np.column_stack([rng.uniform(5, 30, 100), rng.uniform(-20, 20, 100),
                                 rng.uniform(-3, 0.5, 100)])
    log = []

    def world(tau: float):
        return (rotvec_to_dcm(rot_rate * tau) @ C_w_l, S0 * (1 + scale_rate * tau),
                o0 + drift_rate * tau)

    def feed(f: Fusion, t: float) -> None:
        rel = t - SCENARIO.start_gpst
        if rel < t_vo:
            return
        C_eff, S_eff, o_eff = world(rel - t_vo)
        r_cam = sim.motion.point_position_ned(rel, cam.lever_arm_body)
        C_b_l = sim.motion.state(rel).C_body_to_level[0]
        p_w = C_eff.T @ (r_cam - o_eff) / S_eff + rng.normal(0, 0.002, 3)
        C_wc = (C_b_l @ cam.C_camera_to_body).T @ C_eff @ rotvec_to_dcm(
            rng.normal(0, np.radians(0.05), 3))
        f.process_vo(VoOutput(
            time=t, status="tracking", segment=0, C_world_to_camera=C_wc,
            camera_position_world=p_w, n_tracked=100, n_inliers=100, is_keyframe=False,
            points_world=(pts - o_eff) @ C_eff / S_eff, point_ids=np.arange(100),
            observations=(np.zeros(0, np.int64), np.zeros((0, 2)))))
        if f.ekf is not None and f.ekf.vo is not None:
            log.append((rel, S_eff, f.ekf.vo.scale, r_cam, f.ekf.vo_to_level(p_w[None])[0]))

    f, samples = run(sim, FusionOptions(use_vo=True), vo_feed=feed)
    p0 = sim.truth(f.origin_time).position_ned[0]
    rel, S_true, S_est, r_cam, mapped = log[-1]
    assert abs(S_est / S_true - 1.0) < 0.01
    st = f.status()
    assert st.scale == pytest.approx(S_est) and st.vo_status == "tracking"
    raw_drift = np.linalg.norm(drift_rate) * (rel - t_vo)
    assert raw_drift > 0.4
    cam_err = [np.linalg.norm(m - (r - p0)) for t, _, _, r, m in log if t > t_vo + 10.0]
    # The mapping turns with the fused heading, which the VO does not correct while the
    # single differences hold it (a few hundredths of a degree: cm over the ~40 m travelled):
    # 4.7 cm RMS when the VO still pulled the heading, 5.4 cm since.
    assert np.sqrt(np.mean(np.square(cam_err))) < 0.06
    X, sigma, ids = f.structure()
    assert len(ids) == 100 and np.all(sigma > 0)
    err = np.linalg.norm(X - (pts[ids] - p0), axis=1)
    assert np.median(err) < 0.15 and np.median(err) < np.median(sigma)
    # The VO updates did not disturb the INS + CPP solution.
    assert horizontal_stats(samples, 20.0)[0] < 0.05
    assert f.ekf.stats["vo_position"].rejected == 0 and f.ekf.stats["vo_attitude"].rejected == 0


# ------------------------------------------------------------------------ end to end


def test_end_to_end_with_rendered_frames(sim):
    """Five seconds of rendered video through the real VO: the fusion maps the VO world, its
    scale agrees with the truth and the structure points sit at the true depth of the pixels
    they were seen at."""
    from recordings.sim.scene import PortScene

    cam = sim.calibration.camera
    scene = PortScene.build(SCENARIO, SEED)
    f = Fusion(sim.calibration, sim.nav, FusionOptions(use_vo=True))
    outputs: dict[float, VoOutput] = {}
    process = f.vo.process

    def spy(t: float, image: np.ndarray, prepared: object = None,
            following: object = None) -> VoOutput:
        outputs[t] = process(t, image, prepared, following)  # the raw VO outputs, for scoring
        return outputs[t]

    f.vo.process = spy
    rng = np.random.default_rng(4)
    imu, epochs = sim.imu, sim.epochs
    # A gentle turn towards the pier. 10 s: on seed 3's port (mirrored in the water since each
    # seed draws its look) the VO initialises only after 5.4 s (4.0 s without the
    # reflections), so the scale needs the longer run (it was 5 s on the former single look).
    t_first, t_last = 40.0, 50.0
    truth: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    ke = 0
    for k, t in enumerate(imu.time):
        rel = t - SCENARIO.start_gpst
        if rel > t_last + 1e-9:
            break
        f.process_imu(t, imu.gyro[k], imu.accel[k])
        while ke < len(epochs[0]) and epochs[0][ke].time <= t + 1e-9:
            f.process_gnss(epochs[0][ke].time, [epochs[i][ke] for i in range(4)])
            ke += 1
        if k % 10 or rel < t_first - 1e-9:
            continue
        C_l_c = (sim.motion.state(rel).C_body_to_level[0] @ cam.C_camera_to_body).T
        r_cam = sim.motion.point_position_ned(rel, cam.lever_arm_body)
        image, depth = scene.render(C_l_c, r_cam, rel, cam, rng, return_depth=True)
        state = f.process_frame(t, image)
        assert state is not None and state.time == pytest.approx(t)
        truth[t] = (C_l_c, r_cam, depth)
    st = f.status()
    assert st.vo_status == "tracking" and st.scale is not None and f.ekf.vo is not None
    seg = f.ekf.vo.segment
    track = [(o.camera_position_world, truth[t][1]) for t, o in outputs.items()
             if o.status == "tracking" and o.segment == seg]
    assert len(track) > 15
    # Scale of the VO world from the truth: similarity of the VO trajectory onto the truth
    # (its rotation is ill-determined on a nearly straight track, its scale is not).
    s_true, _, _ = umeyama_alignment(np.array([p for p, _ in track]),
                                     np.array([r for _, r in track]))
    assert st.scale == pytest.approx(s_true, rel=0.05)
    p0 = sim.truth(f.origin_time).position_ned[0]
    t_end = max(outputs)
    out = outputs[t_end]
    C_l_c, r_cam, depth = truth[t_end]
    mapped = f.ekf.vo_to_level(out.camera_position_world[None])[0] + p0
    assert np.linalg.norm(mapped - r_cam) < 0.1
    # Structure: the fused points seen in the last frame lie at the rendered depth of their
    # pixels (what is left is the VO's triangulation error along the viewing direction).
    X, sigma, ids = f.structure()
    index = {int(i): k for k, i in enumerate(ids)}
    depth_err = []
    for pid, (u, v) in zip(*out.observations, strict=True):
        z_true = float(depth[int(round(v)), int(round(u))])
        if int(pid) in index and np.isfinite(z_true):
            z_fused = C_l_c[2] @ (X[index[int(pid)]] + p0 - r_cam)
            depth_err.append(abs(z_fused / z_true - 1.0))
    assert len(depth_err) > 30 and np.median(depth_err) < 0.2
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    stats = f.ekf.stats
    assert stats["vo_position"].accepted > 20 and stats["vo_position"].rejected == 0
    assert stats["vo_attitude"].rejected == 0
