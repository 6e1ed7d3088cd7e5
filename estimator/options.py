"""Typed configuration and outputs of the fusion engine (``estimator.pipeline.Fusion``), in
their own module so that every stage of the engine can read them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .ekf import EkfConfig
from .integrity import Integrity, IntegrityConfig
from .landmarks import LandmarkParams


@dataclass
class FusionOptions:
    use_vo: bool = True
    use_cpp: bool = True  # carrier phase (η/v, ζ); False: INS (+ VO) after the start-up
    tightly_coupled: bool = True  # η rows (True) or per-receiver loose velocity (False)
    common_clock: bool = True  # one clock-drift state (True) or one per receiver
    satellites_keep: list[str] | None = None  # only these after keep_after_s (tables 18–20)
    keep_after_s: float = 30.0  # s after the first GNSS epoch
    sky_mask_deg: float | None = None  # elevation mask (deg) applied to every epoch
    # Table 21: receiver index (0..3) → the only satellites it keeps after keep_after_s
    # (receivers not listed keep theirs).
    per_receiver_sats: dict[int, list[str]] | None = None
    ekf: EkfConfig | None = None  # tuning of the EKF (defaults when None)
    # Port-structure refinement (``estimator.landmarks``): a landmark EKF per VO point, fed
    # with every view and the fused camera pose; refined points replace the raw ones in
    # ``structure`` once they have ``landmarks.min_views`` views. None: raw points only.
    landmarks: LandmarkParams | None = field(default_factory=LandmarkParams)
    # Height of the body origin above the waterline (hull.json ``body_origin_height_m``, an
    # installation constant): the water plane lies that far below the world origin, and
    # structure points on or below it (reflections, water patterns) are not reported.
    body_origin_height_m: float | None = None
    # (ellipsoidal height, σ) of the sea surface, m (hull.json ``sea_surface_height_m``): with
    # ``body_origin_height_m`` it gives the antennas' height, which the standalone fix that
    # anchors the carrier phase's geometry is corrected with (``spp.height_aided``).
    sea_surface: tuple[float, float] | None = None
    # Length of the hull (hull.json ``length``, m): a step of the gyro's rate of turn beyond
    # what a hull that long can turn is the gyro's (``integrity.YawStepCheck``). None: unknown,
    # not checked.
    hull_length_m: float | None = None
    # Fault detection, protection levels and alert limits (``estimator.integrity``).
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)

    @property
    def elevation_mask_deg(self) -> float:
        return 10.0 if self.sky_mask_deg is None else float(self.sky_mask_deg)


@dataclass
class FusionStatus:
    phase: str  # 'initialising' | 'aligning' | 'fused' | 'degraded'
    compass_fixed: bool
    satellites: int  # distinct satellites in the last carrier-phase velocity update
    vo_status: str  # VO status ('off' without VO)
    scale: float | None
    scale_converged: bool
    message: str
    integrity: Integrity | None = None  # mode, trust, protection levels (None: not assessed)
    # gpst of the picture a frozen camera keeps repeating (``FrameCheck.still_since``; None:
    # the picture is current): nothing may be drawn on it
    picture_since: float | None = None


@dataclass
class FusedState:
    time: float
    position_ned: np.ndarray  # body origin, L at the world origin (start point), m
    llh_deg: np.ndarray  # lat, lon (deg), h (m) of the body origin (SPP-anchored)
    velocity_ned: np.ndarray
    euler: np.ndarray  # roll, pitch, yaw (rad)
    C_body_to_level: np.ndarray
    rate_of_turn: float  # yaw rate, rad/s
    rate_of_turn_sigma: float  # its 1-σ, rad/s
    omega_body: np.ndarray  # body rate w.r.t. L, body axes, rad/s
    position_cov: np.ndarray  # (3,3) m², the filter's
    # (3,3) m², the drift since the INS started that the filter does not model: added for the
    # position against the world (/pose), not for what was measured from the same drifting
    # trajectory (a designated target, the berth line)
    position_drift_cov: np.ndarray
    velocity_cov: np.ndarray  # (3,3) (m/s)²
    attitude_cov: np.ndarray  # (3,3) rad² (small angles in L)
    status: FusionStatus


@dataclass
class WorldOrigin:
    """The world origin: local level L at the body origin where the INS started."""

    llh: np.ndarray  # rad, rad, m
    C_ecef_to_level: np.ndarray
    time: float  # gpst
    # SPP-averaged correction of the origin (m, NED): only the absolute output (llh) uses it.
    offset_ned: np.ndarray = field(default_factory=lambda: np.zeros(3))
    offset_weight: float = 0.0
