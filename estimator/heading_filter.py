"""Heading from the calibrated gyro and snapshot headings (thesis fig. 14: the heading held by
the single differences of ONE satellite): a Kalman filter over [heading, yaw-rate bias].

Prediction: the heading integrates the gyro's yaw rate minus the bias estimate over the
interval; the heading's variance grows with the gyro's angle random walk and the bias's with
its random walk. Update: a snapshot heading (e.g. ``compass.attitude_from_single_differences``
with the tilt from the INS) with its variance, gated at ``gate_sigma``.
"""

from __future__ import annotations

import math

import numpy as np

from .frames import wrap_angle

GYRO_ARW = math.radians(0.01)  # rad/√s: heading random walk of a MEMS gyro
GYRO_BIAS_WALK = math.radians(0.001)  # rad/s/√s
GATE_SIGMA = 4.0  # snapshot headings further than this (σ of the innovation) are rejected


class HeadingFilter:
    """[heading (rad), yaw-rate bias (rad/s)] with its covariance."""

    def __init__(self, heading: float, bias: float, heading_sigma: float, bias_sigma: float,
                 arw: float = GYRO_ARW, bias_walk: float = GYRO_BIAS_WALK,
                 gate_sigma: float = GATE_SIGMA) -> None:
        self.x = np.array([heading, bias], float)
        self.P = np.diag([heading_sigma**2, bias_sigma**2])
        self.arw, self.bias_walk, self.gate_sigma = arw, bias_walk, gate_sigma

    @property
    def heading(self) -> float:
        return float(self.x[0])

    def predict(self, yaw_rate: np.ndarray, dt: np.ndarray, interval: float) -> None:
        """Integrate the yaw-rate samples (rad/s, each over its ``dt`` s) of an interval."""
        self.x[0] += float(np.sum((yaw_rate - self.x[1]) * dt))
        F = np.array([[1.0, -interval], [0.0, 1.0]])
        self.P = F @ self.P @ F.T + np.diag([self.arw**2 * interval,
                                             self.bias_walk**2 * interval])

    def update(self, heading: float, variance: float) -> bool:
        """A snapshot heading (rad) with its variance; False when the gate rejects it."""
        nu = float(wrap_angle(np.array(heading - self.x[0])))
        S = self.P[0, 0] + variance
        if nu * nu > self.gate_sigma**2 * S:
            return False
        K = self.P[:, 0] / S
        self.x = self.x + K * nu
        self.P = self.P - np.outer(K, self.P[0, :])
        return True
