"""True ship motion (recordings.sim.motion) and the MEMS IMU simulator (recordings.sim.imu)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.frames import earth_rate_level, normal_gravity, skew
from estimator.ins import calibration_matrices, gravity_level
from recordings.sim.imu import ImuErrorModel, simulate_imu
from recordings.sim.motion import ShipMotion
from recordings.sim.scenarios import LARGE_SHIP, SCENARIOS, SMALL_BOAT


def origin_of(scenario) -> np.ndarray:
    lat, lon, h = scenario.origin_llh_deg
    return np.array([np.radians(lat), np.radians(lon), h])


def static_scenario(duration: float = 20.0, yaw_deg: float = 30.0):
    """The ship lies still (no path, no waves)."""
    return dataclasses.replace(
        SMALL_BOAT, name="static", duration_s=duration,
        path_keyframes=((0.0, -20.0, 5.0, yaw_deg), (duration, -20.0, 5.0, yaw_deg)),
        wave_roll_deg=0.0, wave_pitch_deg=0.0, wave_heave_m=0.0)


@pytest.fixture(scope="module", params=sorted(SCENARIOS))
def motion(request) -> ShipMotion:
    return ShipMotion(SCENARIOS[request.param], seed=7)


def sample_times(motion: ShipMotion, n: int = 300) -> np.ndarray:
    rng = np.random.default_rng(0)
    return np.sort(rng.uniform(0.0, motion.scenario.duration_s, n))


# ---------------------------------------------------------------------------- motion


def test_velocity_and_acceleration_are_derivatives(motion):
    t, h = sample_times(motion), 1e-4
    a, b, c = motion.state(t - h), motion.state(t), motion.state(t + h)
    v_fd = (c.position_ned - a.position_ned) / (2 * h)
    a_fd = (c.velocity_ned - a.velocity_ned) / (2 * h)
    np.testing.assert_allclose(v_fd, b.velocity_ned, atol=2e-7)
    np.testing.assert_allclose(a_fd, b.accel_ned, atol=2e-7)


def test_angular_rate_matches_attitude_derivative(motion):
    t, h = sample_times(motion), 1e-4
    a, b, c = motion.state(t - h), motion.state(t), motion.state(t + h)
    C_dot = (c.C_body_to_level - a.C_body_to_level) / (2 * h)
    expected = np.array([C @ skew(w) for C, w in zip(b.C_body_to_level, b.omega_body, strict=True)])
    np.testing.assert_allclose(C_dot, expected, atol=1e-8)
    np.testing.assert_allclose((c.omega_body - a.omega_body) / (2 * h), b.alpha_body, atol=1e-7)
    # Euler angles and the DCM agree, DCMs are rotations.
    R = b.C_body_to_level
    np.testing.assert_allclose(R @ np.transpose(R, (0, 2, 1)), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.arctan2(R[:, 1, 0], R[:, 0, 0]),
                               np.angle(np.exp(1j * b.euler[:, 2])), atol=1e-12)


def test_lever_arm_points(motion):
    t, h = sample_times(motion, 50), 1e-4
    lever = np.array([-3.0, 1.5, -10.0])
    p = motion.point_position_ned(t, lever)
    st = motion.state(t)
    np.testing.assert_allclose(p, st.position_ned + st.C_body_to_level @ lever, atol=1e-12)
    v_fd = (motion.point_position_ned(t + h, lever) - motion.point_position_ned(t - h, lever)) / (
        2 * h)
    np.testing.assert_allclose(motion.point_velocity_ned(t, lever), v_fd, atol=2e-7)
    # Scalars in, (3,) out (the GNSS simulator calls it that way).
    assert motion.point_position_ned(1.0, lever).shape == (3,)
    assert motion.state(1.0).position_ned.shape == (1, 3)


def test_keyframes_are_hit_and_motion_is_deterministic(motion):
    sc = motion.scenario
    keys = np.array(sc.path_keyframes)
    # the centre of motion on the waterline (below the IMU unless it is off amidships)
    centre = np.array([*sc.motion_centre_body, -sc.reference_point_down_m])
    for t, n, e, yaw in keys:
        np.testing.assert_allclose(motion.point_position_ned(t, centre)[:2], [n, e], atol=1e-6)
        np.testing.assert_allclose(motion.state(t).euler[0, 2], np.radians(yaw), atol=1e-9)
    same = ShipMotion(sc, seed=7).state(np.linspace(0, sc.duration_s, 11))
    np.testing.assert_array_equal(same.position_ned,
                                  motion.state(np.linspace(0, sc.duration_s, 11)).position_ned)
    other = ShipMotion(sc, seed=8).state(np.linspace(0, sc.duration_s, 11))
    if sc.wave_roll_deg > 0:  # (the static scenario has no waves)
        assert np.abs(other.euler[:, 0] - same.euler[:, 0]).max() > 1e-4  # other wave phases
    with pytest.raises(ValueError):
        motion.state(sc.duration_s + 60.0)


def horizontal_kinematics(motion: ShipMotion, dt: float = 0.05):
    t = np.arange(0.0, motion.scenario.duration_s + 1e-9, dt)
    st = motion.state(t)
    speed = np.linalg.norm(st.velocity_ned[:, :2], axis=1)
    yaw_rate = np.degrees(np.gradient(np.unwrap(st.euler[:, 2]), t))
    return t, st, speed, yaw_rate


def camera_sees_quay(motion: ShipMotion, t: np.ndarray, st) -> np.ndarray:
    sc = motion.scenario
    cam = motion.point_position_ned(t, np.array(sc.camera_lever_arm))
    axis = st.C_body_to_level @ (sc.C_camera_to_body @ np.array([0.0, 0.0, 1.0]))
    azimuth = np.arctan2(axis[:, 1], axis[:, 0])
    quay_e = np.arange(sc.quay_east_range[0], sc.quay_east_range[1] + 1e-9, 1.0)
    bearing = np.arctan2(quay_e[None, :] - cam[:, 1:2], 0.0 - cam[:, 0:1])
    off = np.abs(np.angle(np.exp(1j * (bearing - azimuth[:, None]))))
    return (off < np.radians(sc.camera_hfov_deg / 2)).any(axis=1)


def test_small_boat_character():
    motion = ShipMotion(SMALL_BOAT, seed=1)
    t, st, speed, yaw_rate = horizontal_kinematics(motion)
    assert 0.8 <= speed.max() <= 1.5
    assert 6.0 <= np.abs(yaw_rate).max() <= 12.0
    cam = motion.point_position_ned(SMALL_BOAT.duration_s, np.array(SMALL_BOAT.camera_lever_arm))
    assert 8.0 <= -cam[0] <= 16.0  # final distance of the bow camera to the quay face
    assert speed[-1] < 0.3  # nearly stopped
    assert camera_sees_quay(motion, t, st).mean() > 0.9
    assert np.all(st.position_ned[:, 0] < -5.0)  # never hits the quay


def test_large_ship_character():
    motion = ShipMotion(LARGE_SHIP, seed=1)
    t, st, _, yaw_rate = horizontal_kinematics(motion)
    # The ship's speed is that of the hull centre: the body origin (compass/IMU unit, 60 m aft
    # and 26 m up) also swings with the turns and the roll.
    centre = np.array([*LARGE_SHIP.motion_centre_body, -LARGE_SHIP.reference_point_down_m])
    speed = np.linalg.norm(motion.point_velocity_ned(t, centre)[:, :2], axis=1)
    assert speed.max() <= 0.2
    assert np.linalg.norm(st.velocity_ned[:, :2], axis=1).max() <= 0.6
    assert np.abs(yaw_rate).max() <= 1.5
    assert camera_sees_quay(motion, t, st).mean() > 0.9
    cam = motion.point_position_ned(t, np.array(LARGE_SHIP.camera_lever_arm))
    assert np.all((-cam[:, 0] > 70.0) & (-cam[:, 0] < 130.0))  # quay ~100 m away


# ------------------------------------------------------------------------------- IMU


def test_static_perfect_imu_measures_gravity_and_earth_rate():
    sc = static_scenario()
    motion = ShipMotion(sc, seed=1)
    imu, cal, truth = simulate_imu(motion, sc, 1, 1e9, errors=ImuErrorModel.none())
    assert len(imu) == 2001 and imu.time[0] == 1e9
    np.testing.assert_allclose(np.diff(imu.time), 0.01, atol=1e-6)
    origin = origin_of(sc)
    st = motion.state(0.0)
    C_lb = st.C_body_to_level[0].T
    # Static on the Earth: f = -g, no Coriolis; the gyro sees only the Earth rate.
    g = gravity_level(st.position_ned[0], origin)
    np.testing.assert_allclose(imu.accel.mean(axis=0), -C_lb @ g, atol=1e-12)
    np.testing.assert_allclose(imu.accel[:, 2], -normal_gravity(origin[0], origin[2]), atol=1e-5)
    np.testing.assert_allclose(imu.gyro, np.broadcast_to(C_lb @ earth_rate_level(origin[0]),
                                                         imu.gyro.shape), atol=1e-15)
    np.testing.assert_array_equal(cal.gyro_misalignment, np.eye(3))


def test_error_model_statistics_and_calibration():
    sc = static_scenario(duration=2.0)
    motion = ShipMotion(sc, seed=0)
    model = ImuErrorModel()
    gyro_on, accel_on, sf = [], [], []
    for seed in range(150):
        _, cal, truth = simulate_imu(motion, sc, seed, 0.0)
        gyro_on.append(truth["gyro_bias_turn_on"])
        accel_on.append(truth["accel_bias_turn_on"])
        sf.append(cal.gyro_scale_factor)
    # 450 draws each: the sample sigma is within ~7 % (1 sigma) of the model.
    assert np.std(gyro_on) == pytest.approx(model.gyro_bias_turn_on, rel=0.2)
    assert np.std(accel_on) == pytest.approx(model.accel_bias_turn_on, rel=0.2)
    assert np.std(sf) == pytest.approx(model.gyro_scale_factor, rel=0.2)
    assert abs(np.mean(gyro_on)) < 0.2 * model.gyro_bias_turn_on

    imu, cal, truth = simulate_imu(motion, sc, 3, 0.0)
    G, A = calibration_matrices(cal)
    # White noise at the model density once the (slow) bias is removed.
    gyro_err = (imu.gyro - truth["gyro_bias"]) @ G.T - truth["gyro_true"]
    accel_err = (imu.accel - truth["accel_bias"]) @ A.T - truth["accel_true"]
    assert np.std(gyro_err) == pytest.approx(model.gyro_arw * 10.0, rel=0.1)
    assert np.std(np.diff(accel_err, axis=0)) / np.sqrt(2) == pytest.approx(
        model.accel_vrw * 10.0, rel=0.1)
    # The calibration leaves only the small residual scale factor/misalignment.
    no_noise = dataclasses.replace(model, gyro_arw=0.0, accel_vrw=0.0)
    imu, cal, truth = simulate_imu(motion, sc, 3, 0.0, errors=no_noise)
    _, A = calibration_matrices(cal)
    residual = (imu.accel - truth["accel_bias"]) @ A.T - truth["accel_true"]
    assert 0.0 < np.abs(residual).max() < 6 * model.accel_scale_factor_residual * 9.81


def test_imu_is_deterministic_per_seed():
    sc = dataclasses.replace(SMALL_BOAT, duration_s=5.0)
    motion = ShipMotion(sc, seed=2)
    a, cal_a, _ = simulate_imu(motion, sc, 2, 0.0)
    b, cal_b, _ = simulate_imu(motion, sc, 2, 0.0)
    c, _, _ = simulate_imu(motion, sc, 3, 0.0)
    np.testing.assert_array_equal(a.gyro, b.gyro)
    np.testing.assert_array_equal(a.accel, b.accel)
    np.testing.assert_array_equal(cal_a.accel_misalignment, cal_b.accel_misalignment)
    assert not np.allclose(a.gyro, c.gyro)
