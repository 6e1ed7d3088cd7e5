"""Strapdown INS (estimator.ins) against analytic motions and the simulated scenarios."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.frames import dcm_to_rotvec, earth_rate_level, euler_to_dcm, rot_z, rotvec_to_dcm
from estimator.ins import (
    IDX_A,
    IDX_E,
    IDX_R,
    IDX_V,
    IDX_W,
    Ins,
    InsState,
    RateSmoother,
    calibration_matrices,
    error_state_matrix,
    error_state_transition,
    gravity_gradient_level,
    gravity_level,
)
from estimator.records import ImuCalibration
from recordings.sim.imu import ImuErrorModel, simulate_imu
from recordings.sim.motion import ShipMotion
from recordings.sim.scenarios import SCENARIOS

ORIGIN = np.array([np.radians(34.7205), np.radians(135.3330), 37.0])
W_IE = earth_rate_level(ORIGIN[0])
RATE = 100.0


def att_error_deg(C_est: np.ndarray, C_true: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(dcm_to_rotvec(C_est @ C_true.T))))


def run(ins: Ins, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> list[InsState]:
    return [ins.propagate(t[k], gyro[k], accel[k]) for k in range(len(t))]


# ------------------------------------------------------------------------ analytic motions


def static_imu(C: np.ndarray, r: np.ndarray, n: int):
    """Ideal samples of an IMU at rest on the Earth at r with attitude C."""
    gyro = np.tile(C.T @ W_IE, (n, 1))
    accel = np.tile(-C.T @ gravity_level(r, ORIGIN), (n, 1))
    return gyro, accel


def test_gravity_model():
    g = gravity_level(np.zeros(3), ORIGIN)
    assert g[:2] == pytest.approx([0.0, 0.0], abs=1e-12) and 9.79 < g[2] < 9.80
    # 100 m north the local vertical leans ~1.6e-5 rad towards the south in the origin's axes.
    g_n = gravity_level(np.array([100.0, 0.0, 0.0]), ORIGIN)
    assert g_n[0] / g_n[2] == pytest.approx(-100.0 / 6.36e6, rel=0.02)
    Gam = gravity_gradient_level(ORIGIN)
    np.testing.assert_allclose(np.diag(Gam) / (g[2] / 6.37e6), [-1, -1, 2], rtol=0.02)
    pts = np.array([[10.0, -20.0, -3.0], [-50.0, 40.0, 1.0]])
    np.testing.assert_allclose(gravity_level(pts, ORIGIN)[1], gravity_level(pts[1], ORIGIN))


def test_static_stays_put_and_accel_bias_drifts_quadratically():
    C = euler_to_dcm(0.02, -0.01, 1.0)
    r0 = np.array([-30.0, 10.0, -1.0])
    n = int(60 * RATE) + 1
    t = np.arange(n) / RATE
    gyro, accel = static_imu(C, r0, n)
    ins = Ins(ORIGIN, ImuCalibration(), InsState(0.0, r0, np.zeros(3), C))
    s = run(ins, t, gyro, accel)[-1]
    assert np.linalg.norm(s.position_ned - r0) < 1e-3
    assert np.linalg.norm(s.velocity_ned) < 1e-4
    assert att_error_deg(s.C_body_to_level, C) < 1e-6

    bias = np.array([0.03, -0.02, 0.01])  # m/s², not known to the INS
    ins = Ins(ORIGIN, ImuCalibration(), InsState(0.0, r0, np.zeros(3), C))
    s = run(ins, t, gyro, accel + bias)[-1]
    expected = 0.5 * (C @ bias) * t[-1] ** 2
    np.testing.assert_allclose(s.position_ned - r0, expected, rtol=0.02, atol=0.05)


def turn_imu(V: float, rate: float, psi0: float, r0: np.ndarray, t: np.ndarray):
    """Level constant turn at constant speed: true trajectory and ideal IMU samples."""
    psi = psi0 + rate * t
    radius = V / rate
    pos = r0 + radius * np.column_stack(
        [np.sin(psi) - np.sin(psi0), np.cos(psi0) - np.cos(psi), 0 * t])
    vel = V * np.column_stack([np.cos(psi), np.sin(psi), 0 * t])
    acc = V * rate * np.column_stack([-np.sin(psi), np.cos(psi), 0 * t])
    C = np.array([rot_z(p) for p in psi])
    C_lb = np.transpose(C, (0, 2, 1))
    f_level = acc - gravity_level(pos, ORIGIN) + 2 * np.cross(W_IE, vel)
    gyro = np.array([0.0, 0.0, rate]) + C_lb @ W_IE
    accel = np.einsum("nij,nj->ni", C_lb, f_level)
    return pos, vel, C, gyro, accel


def test_constant_turn_closes_the_circle():
    V, rate = 1.0, np.radians(10.0)
    period = 2 * np.pi / rate
    t = np.arange(int(round(period * RATE)) + 1) / RATE
    r0 = np.array([-40.0, 0.0, -0.6])
    pos, vel, C, gyro, accel = turn_imu(V, rate, 0.3, r0, t)
    ins = Ins(ORIGIN, ImuCalibration(), InsState(0.0, r0, vel[0], C[0]))
    states = run(ins, t, gyro, accel)
    err = np.array([s.position_ned for s in states]) - pos
    assert np.abs(err).max() < 2e-3
    assert np.linalg.norm(states[-1].position_ned - r0) < 2e-3  # back where it started
    assert np.linalg.norm(states[-1].velocity_ned - vel[0]) < 1e-4
    assert att_error_deg(states[-1].C_body_to_level, C[0]) < 1e-4


# ----------------------------------------------------------------------- scenarios


def scenario_origin(sc) -> np.ndarray:
    return np.array([np.radians(sc.origin_llh_deg[0]), np.radians(sc.origin_llh_deg[1]),
                     sc.origin_llh_deg[2]])


@pytest.fixture(scope="module", params=sorted(SCENARIOS))
def scenario_motion(request):
    sc = SCENARIOS[request.param]
    return sc, ShipMotion(sc, seed=11)


def follow(sc, motion, imu, cal, t_start: float, seconds: float = 10.0, bias_known=None):
    """Run the INS from the true state at t_start over ``seconds``; return the final errors
    (position m, velocity m/s, attitude deg) and the truth at the end."""
    k0 = int(round(t_start * RATE))
    k1 = k0 + int(round(seconds * RATE))
    st = motion.state(imu.time[[k0, k1]] - imu.time[0])
    gyro, accel = imu.gyro[k0:k1 + 1].copy(), imu.accel[k0:k1 + 1].copy()
    gb = ab = np.zeros(3)
    if bias_known is not None:
        # The INS holds the true bias at the start; the slow Gauss–Markov change is removed
        # from the samples, so the bias is known throughout.
        gb, ab = bias_known["gyro_bias"][k0], bias_known["accel_bias"][k0]
        gyro -= bias_known["gyro_bias"][k0:k1 + 1] - gb
        accel -= bias_known["accel_bias"][k0:k1 + 1] - ab
    init = InsState(imu.time[k0], st.position_ned[0], st.velocity_ned[0],
                    st.C_body_to_level[0], gb, ab)
    ins = Ins(scenario_origin(sc), cal, init)
    s = run(ins, imu.time[k0:k1 + 1], gyro, accel)[-1]
    return (s.position_ned - st.position_ned[1], s.velocity_ned - st.velocity_ned[1],
            att_error_deg(s.C_body_to_level, st.C_body_to_level[1]), st)


@pytest.mark.parametrize("t_start", [5.0, 25.0])
def test_perfect_imu_follows_the_reference(scenario_motion, t_start):
    sc, motion = scenario_motion
    imu, cal, _ = simulate_imu(motion, sc, 11, sc.start_gpst, errors=ImuErrorModel.none())
    dr, dv, de, _ = follow(sc, motion, imu, cal, t_start)
    assert np.linalg.norm(dr) < 0.01
    assert np.linalg.norm(dv) < 0.002
    assert de < 0.01


def test_calibrated_mems_with_known_biases_follows_the_reference(scenario_motion):
    sc, motion = scenario_motion
    # Deterministic errors only, all known (calibration + bias history): exact again.
    exact = dataclasses.replace(ImuErrorModel(), gyro_arw=0.0, accel_vrw=0.0,
                                gyro_scale_factor_residual=0.0, gyro_misalignment_residual=0.0,
                                accel_scale_factor_residual=0.0, accel_misalignment_residual=0.0)
    imu, cal, truth = simulate_imu(motion, sc, 11, sc.start_gpst, errors=exact)
    assert np.abs(truth["accel_bias"]).max() > 1e-3  # the errors are really there
    dr, dv, de, _ = follow(sc, motion, imu, cal, 20.0, bias_known=truth)
    assert np.linalg.norm(dr) < 0.01 and de < 0.01

    # With the MEMS white noise on top, the drift is at the random-walk level: 10 s of
    # 0.05 m/s/√h VRW and 0.15 deg/√h ARW give a few cm (1 sigma) and ~0.01 deg.
    noisy = dataclasses.replace(exact, gyro_arw=ImuErrorModel().gyro_arw,
                                accel_vrw=ImuErrorModel().accel_vrw)
    imu, cal, truth = simulate_imu(motion, sc, 11, sc.start_gpst, errors=noisy)
    dr, dv, de, _ = follow(sc, motion, imu, cal, 20.0, bias_known=truth)
    assert np.linalg.norm(dr) < 0.15 and de < 0.05


def predicted_errors(sc, st, gyro_err: np.ndarray, accel_err: np.ndarray, dt: float):
    """Linear error model driven by the calibrated-sensor errors (rate, specific force)."""
    x = np.zeros(9)
    origin = scenario_origin(sc)
    Gam = gravity_gradient_level(origin)
    f_level = st.accel_ned - gravity_level(st.position_ned, origin) + 2 * np.cross(
        W_IE, st.velocity_ned)
    for k in range(len(gyro_err) - 1):
        C = st.C_body_to_level[k]
        F = error_state_matrix(C, f_level[k], origin, gravity_gradient=Gam)[:9, :9]
        u = np.concatenate([np.zeros(3), C @ accel_err[k], C @ gyro_err[k]])
        x = x + (F @ x + u) * dt
    return x


def test_unknown_biases_drift_as_the_error_model_predicts(scenario_motion):
    sc, motion = scenario_motion
    model = dataclasses.replace(ImuErrorModel(), gyro_arw=0.0, accel_vrw=0.0)
    imu, cal, truth = simulate_imu(motion, sc, 11, sc.start_gpst, errors=model)
    seconds, t_start = 10.0, 20.0
    dr, dv, de, _ = follow(sc, motion, imu, cal, t_start, seconds)
    k0 = int(round(t_start * RATE))
    k1 = k0 + int(round(seconds * RATE))
    G, A = calibration_matrices(cal)
    gyro_err = imu.gyro[k0:k1 + 1] @ G.T - truth["gyro_true"][k0:k1 + 1]
    accel_err = imu.accel[k0:k1 + 1] @ A.T - truth["accel_true"][k0:k1 + 1]
    st = motion.state(imu.time[k0:k1 + 1] - imu.time[0])
    x = predicted_errors(sc, st, gyro_err, accel_err, 1.0 / RATE)
    # 20 mg and 0.07 deg/s give metres in 10 s; the linear model predicts them to a few %.
    assert np.linalg.norm(dr) > 0.5
    np.testing.assert_allclose(dr, x[IDX_R], rtol=0.05, atol=0.05 * np.linalg.norm(x[IDX_R]))
    np.testing.assert_allclose(dv, x[IDX_V], atol=0.05 * np.linalg.norm(x[IDX_V]))
    assert de == pytest.approx(np.degrees(np.linalg.norm(x[IDX_E])), rel=0.05)


# ------------------------------------------------------------------- error model, feedback


def test_error_state_transition_matches_the_nonlinear_ins():
    """Perturb every error state, run the INS and the linear model side by side."""
    V, rate = 1.0, np.radians(8.0)
    seconds = 5.0
    t = np.arange(int(seconds * RATE) + 1) / RATE
    r0 = np.array([-40.0, 0.0, -0.6])
    pos, vel, C, gyro, accel = turn_imu(V, rate, 0.3, r0, t)
    x0 = np.concatenate([[0.1, -0.2, 0.05], [0.01, 0.02, -0.01], [1e-3, -2e-3, 3e-3],
                         [2e-4, -1e-4, 3e-4], [0.01, -0.02, 0.015]])
    init = InsState(0.0, r0 + x0[IDX_R], vel[0] + x0[IDX_V], rotvec_to_dcm(x0[IDX_E]) @ C[0],
                    x0[IDX_W], x0[IDX_A])  # the true biases are zero
    ins = Ins(ORIGIN, ImuCalibration(), init)
    states = run(ins, t, gyro, accel)
    x = x0.copy()
    Gam = gravity_gradient_level(ORIGIN)
    for k in range(len(t) - 1):
        f_level = C[k] @ accel[k]
        x = error_state_transition(1.0 / RATE, C[k], f_level, ORIGIN, 1e12, 1e12,
                                   gravity_gradient=Gam) @ x
    s = states[-1]
    np.testing.assert_allclose(s.position_ned - pos[-1], x[IDX_R], rtol=0.02, atol=2e-3)
    np.testing.assert_allclose(s.velocity_ned - vel[-1], x[IDX_V], rtol=0.02, atol=1e-3)
    np.testing.assert_allclose(dcm_to_rotvec(s.C_body_to_level @ C[-1].T), x[IDX_E],
                               rtol=0.02, atol=2e-5)
    # Feedback with the predicted errors brings the INS back onto the truth.
    ins.correct(x[IDX_R], x[IDX_V], x[IDX_E], x[IDX_W], x[IDX_A])
    s = ins.state
    assert np.linalg.norm(s.position_ned - pos[-1]) < 0.01
    assert np.linalg.norm(s.velocity_ned - vel[-1]) < 0.003
    assert att_error_deg(s.C_body_to_level, C[-1]) < 0.01
    np.testing.assert_allclose(s.gyro_bias, 0.0, atol=1e-12)
    np.testing.assert_allclose(ins.omega_body, gyro[-1], atol=1e-12)  # recalibrated sample
    np.testing.assert_allclose(ins.specific_force_level, s.C_body_to_level @ accel[-1])


def test_gauss_markov_blocks_and_calibration():
    F = error_state_matrix(np.eye(3), np.array([0, 0, -9.8]), ORIGIN, 100.0, 200.0)
    np.testing.assert_allclose(F[IDX_W, IDX_W], -np.eye(3) / 100.0)
    np.testing.assert_allclose(F[IDX_A, IDX_A], -np.eye(3) / 200.0)
    Phi = error_state_transition(0.01, np.eye(3), np.array([0, 0, -9.8]), ORIGIN, 100.0, 200.0)
    np.testing.assert_allclose(np.diag(Phi[IDX_W, IDX_W]), 1 - 0.01 / 100.0, atol=1e-8)
    # The INS inverts ImuCalibration: raw = M diag(1+s) true + bias.
    M = np.eye(3) + np.array([[0, 1e-3, -2e-3], [3e-3, 0, 1e-3], [-1e-3, 2e-3, 0]])
    cal = ImuCalibration(gyro_scale_factor=np.array([1e-3, -2e-3, 3e-3]), gyro_misalignment=M,
                         accel_scale_factor=np.array([-3e-3, 1e-3, 2e-3]), accel_misalignment=M.T)
    b_g, b_a = np.array([1e-3, 2e-3, -1e-3]), np.array([0.1, -0.2, 0.3])
    ins = Ins(ORIGIN, cal, InsState(0.0, np.zeros(3), np.zeros(3), np.eye(3), b_g, b_a))
    w, f = np.array([0.1, -0.2, 0.3]), np.array([1.0, 2.0, -9.0])
    raw_w = M @ np.diag(1 + cal.gyro_scale_factor) @ w + b_g
    raw_f = M.T @ np.diag(1 + cal.accel_scale_factor) @ f + b_a
    w_hat, f_hat = ins.calibrate(raw_w, raw_f)
    np.testing.assert_allclose(w_hat, w, atol=1e-14)
    np.testing.assert_allclose(f_hat, f, atol=1e-13)
    with pytest.raises(ValueError):
        ins.propagate(0.0, raw_w, raw_f)
        ins.propagate(-1.0, raw_w, raw_f)


@pytest.mark.parametrize("ship", ["large ship turning slowly", "small boat in a chop"])
def test_the_rate_shown_is_smoothed_as_much_as_the_motion_allows(ship: str) -> None:
    """``RateSmoother``: a MEMS gyro's sample noise (0.2°/√h at 100 Hz: 0.033°/s) on a
    large ship's 160 m lever is 9 cm/s at the bow, so its slow turn is smoothed to a tenth of
    that; a small boat yawing ±2°/s with the waves every 3 s must not lag behind (half a
    second of smoothing would put it 0.4°/s behind). Its σ covers its error either way."""
    arw = np.radians(0.2) / 60.0
    fs = 100.0
    t = np.arange(0.0, 60.0, 1.0 / fs)
    if ship.startswith("large"):
        true = np.radians(0.05) * np.sin(2 * np.pi * t / 120.0)  # a 0.05°/s turn building up
    else:
        true = np.radians(2.0) * np.sin(2 * np.pi * t / 3.0)
    rng = np.random.default_rng(7)
    raw = true + rng.normal(0.0, arw * np.sqrt(fs), t.size)
    sm = RateSmoother(arw)
    out, sig = np.zeros(t.size), np.zeros(t.size)
    for k in range(t.size):
        sm.update(np.array([0.0, 0.0, raw[k]]), 1.0 / fs if k else 0.0)
        out[k], sig[k] = sm.out[2], sm.sigma
    after = t > 10.0
    err, raw_err = (out - true)[after], (raw - true)[after]
    rms = float(np.sqrt(np.mean(err**2)))
    raw_rms = float(np.sqrt(np.mean(raw_err**2)))
    if ship.startswith("large"):
        assert rms < 0.2 * raw_rms, (rms, raw_rms)
    else:
        assert rms < 1.2 * raw_rms, (rms, raw_rms)  # as good as the samples, not 0.4°/s late
    assert np.mean(np.abs(err) <= 2.0 * sig[after]) > 0.9


def test_rotvec_to_dcm_is_scipys_rotation_from_tiny_to_large_angles() -> None:
    """``rotvec_to_dcm`` (Rodrigues in Python floats) against scipy's rotation, and back."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    for size in (0.0, 1e-13, 1e-9, 1e-4, 0.1, 1.0, 3.0):
        for _ in range(50):
            v = rng.normal(size=3)
            v *= size * rng.uniform(0.5, 1.0) / np.linalg.norm(v)
            C = rotvec_to_dcm(v)
            np.testing.assert_allclose(C, Rotation.from_rotvec(v).as_matrix(), rtol=0,
                                       atol=1e-15)
            np.testing.assert_allclose(C @ C.T, np.eye(3), rtol=0, atol=1e-15)
            if size >= 1e-9:
                np.testing.assert_allclose(dcm_to_rotvec(C), v, rtol=1e-9, atol=1e-15)
