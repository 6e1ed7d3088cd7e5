"""Scenario definitions for the berthing simulator (sensors as in thesis table 15,
``docs/references.md``).

World frame of the simulator = the reference local-level frame (NED) at ``origin_llh``.
The sea surface is the plane down = 0. The quay face is the vertical plane north = 0 between
``quay_east_range``; land (quay apron, buildings, cranes) lies at north > 0, water at north < 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime

import numpy as np

from estimator.frames import camera_to_body, gpst_from_datetime


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    origin_llh_deg: tuple[float, float, float]  # lat, lon (deg), ellipsoidal height of sea surface
    start: datetime  # GPS time of the first sample (inside the shipped nav file's validity)
    duration_s: float
    scene_kind: str  # "marina" or "container-terminal": what the renderer builds
    # Ship path: keyframes (t s, north m, east m, yaw deg) of the ship's centre of motion (on
    # the waterline, at ``motion_centre_body`` from the body origin). ``motion.ShipMotion``
    # passes exactly through them with a C2 heading and the smoothest surge/sway of least
    # sideways speed, and adds wave motion.
    path_keyframes: tuple[tuple[float, float, float, float], ...]
    reference_point_down_m: float  # mean height of the body origin (IMU) above the sea (negative)
    wave_roll_deg: float
    wave_pitch_deg: float
    wave_heave_m: float
    wave_period_s: float
    # Sensors in the body frame (forward, right, down) relative to the body origin (IMU)
    camera_lever_arm: tuple[float, float, float]
    camera_pan_deg: float
    camera_tilt_deg: float  # downward positive
    camera_size: tuple[int, int]  # width, height of the bundled video
    camera_hfov_deg: float
    camera_distortion: tuple[float, float, float, float, float]
    antenna_centre: tuple[float, float, float]
    antenna_side_m: float
    hull_length_m: float
    hull_beam_m: float
    freeboard_m: float  # the deck's height above the waterline (the own hull as rendered)
    quay_east_range: tuple[float, float]
    quay_height_m: float  # quay top above the sea surface
    elevation_mask_deg: float
    # Azimuth/elevation obstruction: (azimuth from, azimuth to, elevation below which masked),
    # degrees, switched on when the antenna is within ``mask_range_m`` of the quay face.
    obstructions: tuple[tuple[float, float, float], ...] = ()
    mask_range_m: float = 0.0
    # (forward, right) of the centre of motion (= the hull centre, amidships on the waterline)
    # from the body origin, m. (0, 0): the body origin (IMU) is amidships above it; a large
    # ship has its IMU inside the GNSS-compass unit (thesis fig. 10), far from amidships.
    motion_centre_body: tuple[float, float] = (0.0, 0.0)
    constellations: tuple[str, ...] = ("G", "E", "J")
    extra: dict = field(default_factory=dict)

    @property
    def start_gpst(self) -> float:
        return gpst_from_datetime(self.start)

    @property
    def C_camera_to_body(self) -> np.ndarray:
        return camera_to_body(np.radians(self.camera_pan_deg), np.radians(self.camera_tilt_deg))

    def antennas_body(self) -> np.ndarray:
        """Four antennas on the corners of a square (thesis fig. 10), numbered 1..4 as
        front-left, front-right, rear-right, rear-left."""
        h = self.antenna_side_m / 2.0
        c = np.array(self.antenna_centre)
        corners = np.array([[h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0], [-h, -h, 0.0]])
        return corners + c

    def hull_outline(self) -> np.ndarray:
        """Hull polygon (forward, right) in the body frame, bow pointed, centred on the centre
        of motion (``motion_centre_body``; the body origin when that is (0, 0))."""
        L, B = self.hull_length_m, self.hull_beam_m
        x_bow, x_stern = 0.5 * L, -0.5 * L
        x_shoulder = 0.5 * L - 0.25 * L
        return np.array([
            [x_bow, 0.0], [x_shoulder, 0.5 * B], [x_stern, 0.5 * B],
            [x_stern, -0.5 * B], [x_shoulder, -0.5 * B],
        ]) + np.array(self.motion_centre_body)


SMALL_BOAT = Scenario(
    name="small-boat",
    description="Thesis sea trial: 7 m boat, bow camera ~1 m above water looking forward, "
    "~1 m/s approach with ~10 deg/s turns over ~90 s, pier ~10 m ahead at the end, open sky.",
    origin_llh_deg=(34.7205, 135.3330, 37.0),  # Nishinomiya marina, Hyogo
    start=datetime(2024, 6, 24, 8, 30, 0),
    duration_s=90.0,
    scene_kind="marina",
    # Approach from the south-west at ~1.1 m/s, an S-turn (starboard ~8 deg/s, port ~10 deg/s),
    # slow down, swing to starboard and stop with the pier ~12 m ahead of the bow camera. The
    # keyframes come from a surge/heading design with a weak current (0.05 m/s to the NE), so
    # the motion model needs only a few cm/s of sway to pass through them.
    path_keyframes=(
        (0.0, -73.2, -46.6, 25.0),
        (10.0, -62.5, -41.3, 25.0),
        (20.0, -54.6, -32.9, 68.0),
        (33.0, -43.6, -24.9, 0.0),
        (47.0, -31.3, -21.0, 32.0),
        (62.0, -21.2, -14.8, 28.0),
        (78.0, -16.0, -11.1, 40.0),
        (90.0, -14.8, -9.9, 40.0),
    ),
    reference_point_down_m=-0.6,
    wave_roll_deg=2.0,
    wave_pitch_deg=1.0,
    wave_heave_m=0.05,
    wave_period_s=3.5,
    camera_lever_arm=(3.0, 0.0, -0.4),  # bow, ~1 m above the sea
    camera_pan_deg=0.0,
    camera_tilt_deg=3.0,
    camera_size=(960, 600),
    camera_hfov_deg=70.3,
    camera_distortion=(-0.12, 0.05, 0.0005, -0.0003, 0.0),
    antenna_centre=(1.0, 0.0, -1.2),
    antenna_side_m=0.10,
    hull_length_m=7.0,
    hull_beam_m=2.5,
    freeboard_m=0.85,
    quay_east_range=(-60.0, 60.0),
    quay_height_m=1.5,
    elevation_mask_deg=10.0,
)

LARGE_SHIP = Scenario(
    name="large-ship",
    description="Large ship coming alongside: bridge camera ~20 m above the sea looking "
    "obliquely down at a container quay ~100 m away, ~0.1 m/s and ~1 deg/s, gantry cranes "
    "masking satellites near the berth.",
    origin_llh_deg=(34.6690, 135.2150, 37.0),  # Kobe container terminal area
    start=datetime(2024, 6, 24, 8, 40, 0),
    duration_s=120.0,
    scene_kind="container-terminal",
    # Heading east along the quay (quay to port), slowing from ~0.12 m/s while tugs push her
    # sideways north towards it (sway up to ~0.08 m/s) and turn her ~10 deg (<= 0.3 deg/s).
    # The keyframes are those of the hull centre (amidships); the body origin is the GNSS
    # compass / IMU unit on the aft mast, 60 m aft of amidships and 26 m above the sea, as in
    # the thesis' hardware where the IMU sits in the compass unit (fig. 10): the trajectory is
    # that of the point the carrier phase measures, so a heading error does not swing it round
    # a 60 m lever arm (0.1 deg of heading = 0.1 m at 60 m).
    path_keyframes=(
        (0.0, -120.0, -32.0, 84.0),
        (30.0, -118.3, -28.6, 88.0),
        (60.0, -116.0, -25.6, 94.0),
        (90.0, -114.1, -23.1, 92.0),
        (120.0, -112.3, -21.8, 91.0),
    ),
    reference_point_down_m=-25.9,  # the compass/IMU unit, ~26 m above the sea
    wave_roll_deg=0.3,
    wave_pitch_deg=0.1,
    wave_heave_m=0.05,
    wave_period_s=9.0,
    camera_lever_arm=(0.0, -10.0, 5.9),  # bridge wing below the mast, ~20 m above the sea
    camera_pan_deg=-75.0,  # looking to port, towards the quay
    camera_tilt_deg=10.0,
    camera_size=(960, 600),
    camera_hfov_deg=70.3,
    camera_distortion=(-0.10, 0.03, 0.0, 0.0, 0.0),
    antenna_centre=(0.0, 0.0, -0.1),  # antennas 10 cm above the IMU, in the same unit
    antenna_side_m=0.10,
    hull_length_m=200.0,
    hull_beam_m=32.0,
    freeboard_m=11.0,
    quay_east_range=(-250.0, 250.0),
    quay_height_m=3.0,
    elevation_mask_deg=10.0,
    obstructions=((300.0, 360.0, 40.0), (0.0, 60.0, 40.0)),
    mask_range_m=150.0,
    motion_centre_body=(60.0, 0.0),  # amidships, 60 m forward of the compass/IMU unit
)

# The simulator's counterpart of a real static receiver pair (benchmarks/calibration.py): the
# small boat's antennas at rest (moored, no waves) for 5 minutes at the time of day of the real
# static data (2024-06-24 08:20 GPST, the same sky), a small cheap video of the still view.
STATIC = replace(
    SMALL_BOAT,
    name="static",
    description="The small boat's four antennas at rest (moored at the pier, no waves) for "
    "5 min: the simulated counterpart of a real static recording, for calibration.",
    start=datetime(2024, 6, 24, 8, 20, 0),
    duration_s=300.0,
    path_keyframes=((0.0, -14.8, -9.9, 40.0), (300.0, -14.8, -9.9, 40.0)),
    wave_roll_deg=0.0,
    wave_pitch_deg=0.0,
    wave_heave_m=0.0,
    camera_size=(320, 200),
)

SCENARIOS: dict[str, Scenario] = {s.name: s for s in (SMALL_BOAT, LARGE_SHIP, STATIC)}
