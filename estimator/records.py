"""Plain typed records passed between the blocks (sensor inputs, calibration).

The recording loader (``recordings``) produces these; the estimator consumes them. They hold no
behaviour beyond trivial accessors so that any source (a recorded file, a live receiver) can
produce them. Times are GPS seconds since the GPS epoch (``gpst``, see ``frames``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# ------------------------------------------------------------------------------ GNSS


@dataclass(frozen=True)
class KeplerEphemeris:
    """Broadcast Keplerian ephemeris (GPS LNAV, Galileo I/NAV or F/NAV, QZSS, BeiDou)."""

    sat: str  # RINEX satellite id, e.g. "G05", "E11", "J02"
    toc: float  # clock reference time, gpst s (BeiDou: converted from BDT)
    af0: float  # s
    af1: float  # s/s
    af2: float  # s/s^2
    toe: float  # ephemeris reference time, gpst s
    sqrt_a: float
    e: float
    i0: float
    omega0: float
    omega: float
    m0: float
    delta_n: float
    idot: float
    omega_dot: float
    cuc: float
    cus: float
    crc: float
    crs: float
    cic: float
    cis: float
    iode: int  # IODE (GPS/QZSS), IODnav (Galileo), AODE (BeiDou)
    tgd: float  # group delay, s (Galileo: BGD E5a/E1)
    health: int
    data_source: int = 0  # Galileo: bit field (I/NAV vs F/NAV); else 0


@dataclass(frozen=True)
class GlonassEphemeris:
    sat: str  # "R01" ...
    toe: float  # gpst s (converted from UTC(SU))
    tau_n: float  # -TauN from RINEX is stored as the clock bias, s
    gamma_n: float
    position: tuple[float, float, float]  # PZ-90 ECEF, m
    velocity: tuple[float, float, float]  # m/s
    acceleration: tuple[float, float, float]  # luni-solar, m/s^2
    frequency_number: int
    health: int


@dataclass
class NavigationData:
    """All broadcast ephemerides of a navigation file, per satellite sorted by toe."""

    ephemerides: dict[str, list[KeplerEphemeris | GlonassEphemeris]] = field(default_factory=dict)
    iono_alpha: tuple[float, float, float, float] | None = None  # Klobuchar (GPSA)
    iono_beta: tuple[float, float, float, float] | None = None  # Klobuchar (GPSB)
    leap_seconds: int | None = None

    def satellites(self) -> list[str]:
        return sorted(self.ephemerides)


@dataclass(frozen=True)
class SatObservation:
    """L1 (or E1/B1) observation of one satellite by one receiver at one epoch.

    RINEX conventions: carrier phase in cycles (grows with range), Doppler in Hz (positive
    when approaching, i.e. D = -range_rate / wavelength), NaN for a blank field.
    """

    pseudorange: float  # m
    carrier_phase: float  # cycles
    doppler: float  # Hz
    snr: float  # dB-Hz
    lli: int = 0  # RINEX loss-of-lock indicator: bit 0 = cycle slip possible


@dataclass(frozen=True)
class GnssEpoch:
    """One receiver epoch (receiver time tag, gpst s) of L1 observations by satellite id."""

    time: float
    satellites: dict[str, SatObservation]
    flag: int = 0  # RINEX epoch flag (0 OK, 1 power failure before this epoch)


# ------------------------------------------------------------------------------- IMU


@dataclass
class ImuData:
    """IMU samples: time (N,) gpst s, gyro (N,3) rad/s and accel (N,3) m/s^2 in the body frame."""

    time: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __len__(self) -> int:
        return len(self.time)


# ------------------------------------------------------------------------ calibration


def mean_focal(K: np.ndarray) -> float:
    """Mean focal length (px) of intrinsics ``K``: 0.5 (f_x + f_y)."""
    return 0.5 * (K[0, 0] + K[1, 1])


@dataclass
class CameraCalibration:
    width: int
    height: int
    K: np.ndarray  # 3x3 intrinsics (pixels)
    distortion: np.ndarray  # OpenCV (k1, k2, p1, p2, k3)
    C_camera_to_body: np.ndarray  # 3x3, C_C^B
    lever_arm_body: np.ndarray  # camera centre in the body frame, m

    @property
    def focal_px(self) -> float:
        """The mean focal length (px): pixel noise and ray priors are isotropic in it."""
        return mean_focal(self.K)


@dataclass(frozen=True)
class CameraView:
    """The fused camera pose of one frame: what a view of a designated target is taken in."""

    t: float  # gpst of the frame
    C_level_to_camera: np.ndarray  # (3,3)
    position_ned: np.ndarray  # (3,) camera centre in L, m
    pose_cov: np.ndarray | None = None  # (6,6) [position, attitude] covariance, None: unknown


@dataclass
class ImuCalibration:
    """Known deterministic errors: measured = M @ diag(1 + scale_factor) @ true + bias."""

    gyro_scale_factor: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_misalignment: np.ndarray = field(default_factory=lambda: np.eye(3))
    accel_scale_factor: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_misalignment: np.ndarray = field(default_factory=lambda: np.eye(3))
    lever_arm_body: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class Calibration:
    camera: CameraCalibration
    antennas_body: np.ndarray  # (4,3) antenna phase centres in the body frame, m
    imu: ImuCalibration


@dataclass
class Hull:
    outline_body: np.ndarray  # (N,2) polygon (forward, right) in the body frame, m
    length: float
    beam: float
    # Berth line: two points (north, east) in the reference local-level frame, when known.
    berth_line_ned: np.ndarray | None = None
    # Height of the body origin (IMU) above the waterline, an installation constant: it puts
    # the water plane of the overlay under the ship.
    body_origin_height_m: float | None = None
    # Ellipsoidal height of the sea surface at the berth (geoid height plus the tide), when
    # known, and its σ: the antennas stand a known height above it, which pins the height of
    # the standalone fix the carrier phase's geometry is computed at.
    sea_surface_height_m: float | None = None
    sea_surface_sigma_m: float = 1.0
    # Height of the deck above the waterline, when known: a pixel whose ray meets the hull
    # (this prism over the outline) shows the ship herself, not something to measure.
    freeboard_m: float | None = None

    @property
    def sea_surface(self) -> tuple[float, float] | None:
        """(height, σ) of the sea surface for ``FusionOptions.sea_surface``; None unknown."""
        if self.sea_surface_height_m is None:
            return None
        return float(self.sea_surface_height_m), float(self.sea_surface_sigma_m)
