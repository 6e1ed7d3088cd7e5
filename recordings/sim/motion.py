"""True ship motion of a scenario: a smooth berthing manoeuvre plus wave-induced motion.

Everything the simulator derives from the truth (IMU samples, carrier phase, video) comes from
this one model, so position, velocity, acceleration, attitude and angular rate are made
mutually exact:

- Heading ``psi(t)``: C2 piecewise quintic through the keyframe headings (rates at keyframes by
  the Fritsch–Butland rule, zero rate where the heading reverses, zero second derivative at
  every keyframe), so yaw rate and yaw acceleration are analytic and continuous.
- Surge ``u(t)`` and sway ``s(t)`` (speed along and across the heading): cubic B-splines (C2)
  whose coefficients are the smoothest (least jerk) with the least sway that carry the ship
  EXACTLY from each keyframe position to the next along the keyframe headings. Sway is what the
  current/wind (or tugs, for the large ship) add to the motion through the water.
- Horizontal velocity ``v = R(psi) [u, s]`` and acceleration are analytic; the horizontal path
  is their integral (3-point Gauss–Legendre on 10 ms nodes, O(h^7)) held as a C2 quintic
  Hermite through (position, velocity, acceleration) at the nodes; its mismatch with the
  analytic velocity is below 1e-10 m/s.
- Waves: roll, pitch and heave are each a sum of three sinusoids (periods 0.72, 1.0 and 1.35
  times ``wave_period_s``, random phases from the seed) scaled so that the scenario's amplitude
  is that of an equivalent single sinusoid (RMS = amplitude / sqrt 2).
- The ship rotates about its centre of motion on the waterline (the keyframe reference point,
  heaving with the sea); the body origin (IMU) is fixed to the hull ``reference_point_down_m``
  above the waterline and at ``-motion_centre_body`` (forward, right) from that centre (directly
  above it by default), so a roll also sways the IMU (and far more a mast-top antenna) and a
  turn swings an IMU far from amidships round the centre.

Frame: the scenario's local-level frame, NED at ``origin_llh_deg``, fixed to the Earth (it
rotates with the Earth; see ``estimator.ins`` for the mechanization in it). Times are seconds
since the scenario start; the model is defined on [-PAD_S, duration + PAD_S] so that callers
can look slightly outside the scenario (receiver clock offsets, finite differences).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline, PPoly

from .scenarios import Scenario

PAD_S = 10.0  # the motion continues smoothly this long before the start and after the end
NODE_DT_S = 0.01  # spacing of the integrated-path nodes
SPEED_KNOT_SPACING_S = 5.0  # B-spline knot spacing of surge and sway
WAVE_PERIOD_FACTORS = (0.72, 1.0, 1.35)
WAVE_WEIGHTS = (0.5, 1.0, 0.6)

# Least-squares weights of the surge/sway design, scaled for manoeuvres on a ~10 s time scale:
# roughness ∫(u'')² + ∫(s'')² and effort ∫(u')² + ∫(s')² against sideways speed ∫s² (sway kept
# small unless the keyframes demand it), and a calm start/end in the padding (more ∫(u')²).
_W_ROUGH = 2000.0
_W_ACCEL = 20.0
_W_SWAY = 1.0
_W_PAD = 1000.0
_W_TINY = 1e-9


@dataclass
class TrueState:
    """True state of the ship (body origin = IMU) at N times, all arrays over N."""

    t: np.ndarray  # (N,) seconds since scenario start
    position_ned: np.ndarray  # (N,3) body origin in the scenario local-level frame, m
    velocity_ned: np.ndarray  # (N,3) m/s
    accel_ned: np.ndarray  # (N,3) kinematic acceleration in NED, m/s^2
    euler: np.ndarray  # (N,3) roll, pitch, yaw, rad (yaw in (-pi, pi] like dcm_to_euler)
    C_body_to_level: np.ndarray  # (N,3,3)
    omega_body: np.ndarray  # (N,3) rate of body w.r.t. local level, body axes, rad/s
    alpha_body: np.ndarray  # (N,3) its time derivative, rad/s^2


# ----------------------------------------------------------------------------- helpers


def _quintic_hermite(x: np.ndarray, y: np.ndarray, dy: np.ndarray, ddy: np.ndarray) -> PPoly:
    """C2 piecewise quintic matching value, 1st and 2nd derivative at the breakpoints ``x``.

    ``y``, ``dy``, ``ddy`` have shape (len(x), ...) (trailing dims are independent curves)."""
    h = np.diff(x).reshape((-1,) + (1,) * (y.ndim - 1))
    c0, c1, c2 = y[:-1], h * dy[:-1], 0.5 * h**2 * ddy[:-1]
    Y = y[1:] - (c0 + c1 + c2)
    D = h * dy[1:] - (c1 + 2 * c2)
    A = h**2 * ddy[1:] - 2 * c2
    c3 = 10 * Y - 4 * D + 0.5 * A
    c4 = -15 * Y + 7 * D - A
    c5 = 6 * Y - 3 * D + 0.5 * A
    # PPoly wants descending powers of (t - x_i): rescale from s = (t - x_i)/h.
    coeffs = [c5 / h**5, c4 / h**4, c3 / h**3, c2 / h**2, c1 / h, c0]
    return PPoly(np.stack(coeffs), x, extrapolate=False)


def _fritsch_butland_rates(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Shape-preserving slopes: zero at local extrema, a weighted harmonic mean elsewhere."""
    h = np.diff(x)
    delta = np.diff(y) / h
    d = np.zeros_like(y)
    for i in range(1, len(y) - 1):
        a, b = delta[i - 1], delta[i]
        if a * b <= 0.0:
            continue
        w1, w2 = 2 * h[i] + h[i - 1], h[i] + 2 * h[i - 1]
        d[i] = (w1 + w2) / (w1 / a + w2 / b)
    return d


def _gauss_legendre(edges: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes and weights of ``order``-point Gauss–Legendre on each interval of ``edges``."""
    xi, wi = np.polynomial.legendre.leggauss(order)
    a, b = edges[:-1, None], edges[1:, None]
    nodes = 0.5 * (a + b) + 0.5 * (b - a) * xi
    weights = 0.5 * (b - a) * wi
    return nodes, weights


def _dcm_zyx(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Vectorised ``euler_to_dcm``: (N,3,3) C_body_to_level = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    C = np.empty(roll.shape + (3, 3))
    C[..., 0, 0] = cy * cp
    C[..., 0, 1] = cy * sp * sr - sy * cr
    C[..., 0, 2] = cy * sp * cr + sy * sr
    C[..., 1, 0] = sy * cp
    C[..., 1, 1] = sy * sp * sr + cy * cr
    C[..., 1, 2] = sy * sp * cr - cy * sr
    C[..., 2, 0] = -sp
    C[..., 2, 1] = cp * sr
    C[..., 2, 2] = cp * cr
    return C


class _Waves:
    """Sum of sinusoids with analytic first and second derivatives."""

    def __init__(self, amplitude: float, period: float, rng: np.random.Generator) -> None:
        w = np.asarray(WAVE_WEIGHTS, float)
        self.amp = amplitude * w / np.sqrt(np.sum(w**2))
        self.omega = 2 * np.pi / (period * np.asarray(WAVE_PERIOD_FACTORS))
        self.phase = rng.uniform(0.0, 2 * np.pi, len(w))

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        arg = np.outer(t, self.omega) + self.phase
        s, c = np.sin(arg), np.cos(arg)
        return s @ self.amp, c @ (self.amp * self.omega), -(s @ (self.amp * self.omega**2))


# ----------------------------------------------------------------------------- the model


class ShipMotion:
    """True motion of ``scenario``; the seed draws the wave phases (the path is fixed)."""

    def __init__(self, scenario: Scenario, seed: int) -> None:
        self.scenario = scenario
        self.seed = seed
        keys = np.asarray(scenario.path_keyframes, float)
        if keys.ndim != 2 or keys.shape[1] != 4 or len(keys) < 2:
            raise ValueError("path_keyframes must be >= 2 rows of (t, north, east, yaw_deg)")
        if np.any(np.diff(keys[:, 0]) <= 0):
            raise ValueError("path_keyframes times must increase")
        self.t_min = keys[0, 0] - PAD_S
        self.t_max = keys[-1, 0] + PAD_S
        # Body origin (IMU) relative to the centre of motion, body axes.
        fwd, right = scenario.motion_centre_body
        self._lever_origin = np.array([-fwd, -right, scenario.reference_point_down_m])

        # Heading: keyframes plus a steady heading through the padding.
        kt = np.concatenate([[self.t_min], keys[:, 0], [self.t_max]])
        kpsi = np.unwrap(np.radians(keys[:, 3]))
        kpsi = np.concatenate([[kpsi[0]], kpsi, [kpsi[-1]]])
        rate = _fritsch_butland_rates(kt, kpsi)
        self._psi = _quintic_hermite(kt, kpsi, rate, np.zeros_like(kpsi))
        self._psi_d = self._psi.derivative(1)
        self._psi_dd = self._psi.derivative(2)

        self._design_speed(keys)
        self._integrate_path(keys)

        rng = np.random.default_rng(seed)
        self._roll = _Waves(np.radians(scenario.wave_roll_deg), scenario.wave_period_s, rng)
        self._pitch = _Waves(np.radians(scenario.wave_pitch_deg), scenario.wave_period_s, rng)
        self._heave = _Waves(scenario.wave_heave_m, scenario.wave_period_s, rng)

    # -- design --------------------------------------------------------------------------

    def _design_speed(self, keys: np.ndarray) -> None:
        """Surge/sway B-splines: equality constraints = keyframe displacements (exact),
        objective = roughness + sway + calm padding (KKT system, solved once)."""
        k = 3
        span = self.t_max - self.t_min
        n_int = max(int(np.ceil(span / SPEED_KNOT_SPACING_S)), 1)
        inner = np.linspace(self.t_min, self.t_max, n_int + 1)
        knots = np.concatenate([[self.t_min] * k, inner, [self.t_max] * k])
        n = len(knots) - k - 1
        basis = BSpline(knots, np.eye(n), k, extrapolate=False)
        d1, d2 = basis.derivative(1), basis.derivative(2)

        # Objective by exact quadrature over the knot spans.
        x, w = _gauss_legendre(inner, 5)
        x, w = x.ravel(), w.ravel()
        B, B1, B2 = basis(x), d1(x), d2(x)
        pad = ((x < keys[0, 0]) | (x > keys[-1, 0])).astype(float)

        def gram(M: np.ndarray, weight: np.ndarray) -> np.ndarray:
            return (M * weight[:, None]).T @ M

        rough = gram(B2, w)
        effort = gram(B1, w * (_W_ACCEL + _W_PAD * pad))
        H_u = _W_ROUGH * rough + effort + _W_TINY * gram(B, w)
        H_s = _W_ROUGH * rough + effort + _W_SWAY * gram(B, w)
        H = np.block([[H_u, np.zeros((n, n))], [np.zeros((n, n)), H_s]])

        # Displacement constraints, one pair (north, east) per keyframe interval.
        rows, rhs = [], []
        for i in range(len(keys) - 1):
            t0, t1 = keys[i, 0], keys[i + 1, 0]
            edges = np.linspace(t0, t1, max(int(np.ceil((t1 - t0) / 0.1)), 1) + 1)
            xs, ws = _gauss_legendre(edges, 5)
            xs, ws = xs.ravel(), ws.ravel()
            Bs = basis(xs) * ws[:, None]
            psi = self._psi(xs)
            c, s = np.cos(psi)[:, None], np.sin(psi)[:, None]
            rows.append(np.concatenate([(c * Bs).sum(0), (-s * Bs).sum(0)]))
            rows.append(np.concatenate([(s * Bs).sum(0), (c * Bs).sum(0)]))
            rhs.extend([keys[i + 1, 1] - keys[i, 1], keys[i + 1, 2] - keys[i, 2]])
        A = np.array(rows)
        m = len(rhs)
        kkt = np.block([[H, A.T], [A, np.zeros((m, m))]])
        sol = np.linalg.solve(kkt, np.concatenate([np.zeros(2 * n), rhs]))
        self._surge = BSpline(knots, sol[:n], k, extrapolate=False)
        self._sway = BSpline(knots, sol[n : 2 * n], k, extrapolate=False)
        self._surge_d = self._surge.derivative(1)
        self._sway_d = self._sway.derivative(1)

    def _horizontal_velocity(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Analytic horizontal velocity and acceleration (N,2) of the centre of motion."""
        psi, r = self._psi(t), self._psi_d(t)
        u, s = self._surge(t), self._sway(t)
        du, ds = self._surge_d(t), self._sway_d(t)
        c, sn = np.cos(psi), np.sin(psi)
        v = np.stack([c * u - sn * s, sn * u + c * s], axis=-1)
        # d/dt R(psi)[u, s] = R(psi)[u' - r s, s' + r u]
        ax, ay = du - r * s, ds + r * u
        a = np.stack([c * ax - sn * ay, sn * ax + c * ay], axis=-1)
        return v, a

    def _integrate_path(self, keys: np.ndarray) -> None:
        n_before = int(round((keys[0, 0] - self.t_min) / NODE_DT_S))
        n_after = int(round((self.t_max - keys[0, 0]) / NODE_DT_S))
        nodes = keys[0, 0] + NODE_DT_S * np.arange(-n_before, n_after + 1)
        nodes[0], nodes[-1] = self.t_min, self.t_max
        xg, wg = _gauss_legendre(nodes, 3)
        vg, _ = self._horizontal_velocity(xg.ravel())
        steps = (vg.reshape(xg.shape + (2,)) * wg[..., None]).sum(axis=1)
        pos = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
        pos += keys[0, 1:3] - pos[n_before]  # the first keyframe is where the ship starts
        v, a = self._horizontal_velocity(nodes)
        self._path = _quintic_hermite(nodes, pos, v, a)

    # -- evaluation ----------------------------------------------------------------------

    def _times(self, t: np.ndarray | float) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, float))
        if t.ndim != 1:
            raise ValueError("t must be a scalar or a 1-D array")
        if np.any(t < self.t_min - 1e-9) or np.any(t > self.t_max + 1e-9):
            raise ValueError(f"time outside the motion's span [{self.t_min}, {self.t_max}] s")
        return np.clip(t, self.t_min, self.t_max)

    def _attitude(self, t: np.ndarray):
        """Euler angles, C_body_to_level, body rate and its derivative (all analytic)."""
        phi, dphi, ddphi = self._roll(t)
        theta, dtheta, ddtheta = self._pitch(t)
        psi, dpsi, ddpsi = self._psi(t), self._psi_d(t), self._psi_dd(t)
        sf, cf = np.sin(phi), np.cos(phi)
        st, ct = np.sin(theta), np.cos(theta)
        # omega_lb^b from Euler rates (ZYX) and its time derivative.
        omega = np.stack([
            dphi - dpsi * st,
            dtheta * cf + dpsi * sf * ct,
            -dtheta * sf + dpsi * cf * ct,
        ], axis=-1)
        alpha = np.stack([
            ddphi - ddpsi * st - dpsi * dtheta * ct,
            ddtheta * cf - dtheta * dphi * sf + ddpsi * sf * ct
            + dpsi * (dphi * cf * ct - dtheta * sf * st),
            -ddtheta * sf - dtheta * dphi * cf + ddpsi * cf * ct
            - dpsi * (dphi * sf * ct + dtheta * cf * st),
        ], axis=-1)
        euler = np.stack([phi, theta, np.angle(np.exp(1j * psi))], axis=-1)
        return euler, _dcm_zyx(phi, theta, psi), omega, alpha

    def state(self, t: np.ndarray | float) -> TrueState:
        """True state of the body origin (IMU) at ``t`` (s since start; arrays of length N,
        N = 1 for a scalar)."""
        t = self._times(t)
        euler, C, omega, alpha = self._attitude(t)
        heave, dheave, ddheave = self._heave(t)
        v_h, a_h = self._horizontal_velocity(t)
        c = np.column_stack([self._path(t), heave])
        c_dot = np.column_stack([v_h, dheave])
        c_ddot = np.column_stack([a_h, ddheave])
        # Body origin = centre of motion + C l (l: body-fixed, from the waterline up to the IMU).
        l = self._lever_origin
        wxl = np.cross(omega, l)
        body_acc = np.cross(alpha, l) + np.cross(omega, wxl)
        pos = c + C @ l
        vel = c_dot + np.einsum("nij,nj->ni", C, wxl)
        acc = c_ddot + np.einsum("nij,nj->ni", C, body_acc)
        return TrueState(t, pos, vel, acc, euler, C, omega, alpha)

    def point_position_ned(self, t: np.ndarray | float, lever_arm_body: np.ndarray) -> np.ndarray:
        """Position (3,) or (N,3) of a body-fixed point (antenna, camera) at lever arm (body)."""
        scalar = np.ndim(t) == 0
        t = self._times(t)
        # Only what the position needs: the GNSS simulator calls this thousands of times.
        phi, theta = self._roll(t)[0], self._pitch(t)[0]
        C = _dcm_zyx(phi, theta, self._psi(t))
        centre = np.column_stack([self._path(t), self._heave(t)[0]])
        out = centre + C @ (self._lever_origin + np.asarray(lever_arm_body, float))
        return out[0] if scalar else out

    def point_velocity_ned(self, t: np.ndarray | float, lever_arm_body: np.ndarray) -> np.ndarray:
        """Velocity (3,) or (N,3) of a body-fixed point: v + C (omega x l)."""
        scalar = np.ndim(t) == 0
        st = self.state(t)
        wxl = np.cross(st.omega_body, np.asarray(lever_arm_body, float))
        out = st.velocity_ned + np.einsum("nij,nj->ni", st.C_body_to_level, wxl)
        return out[0] if scalar else out

    def surge_sway(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Designed speed along and across the heading of the centre of motion (m/s)."""
        t = self._times(t)
        return self._surge(t), self._sway(t)
