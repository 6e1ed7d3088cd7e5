"""Write a complete simulated recording: motion → IMU, GNSS, video; reference for scoring."""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from estimator.frames import ned_to_ecef
from estimator.records import Calibration, GnssEpoch, Hull, ImuData, NavigationData

from .. import format as fmt
from ..rinex import read_nav, write_obs
from .gnss import GnssErrorModel, GnssTruth, simulate_gnss
from .imu import simulate_imu
from .motion import ShipMotion
from .scenarios import SCENARIOS, Scenario
from .scene import PortScene, camera_calibration
from .variety import seeded

NAV_FILE = Path(__file__).resolve().parent.parent / "data" / "nagoya_2024-06-24.nav"
FRAME_RATE_HZ = 10.0
IMU_RATE_HZ = 100.0


class Progress:
    """Terminal progress per named stage (tqdm on stderr, so stdout stays clean; off when
    stderr is not a terminal, so logs get no carriage-return floods)."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._bars: dict[str, tqdm] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self.enabled:
            return
        bar = self._bars.get(stage)
        if bar is None:
            bar = self._bars[stage] = tqdm(total=total, desc=f"{stage:<6}", unit="step",
                                           disable=None, leave=True)
        bar.update(done - bar.n)
        if done >= total:
            bar.close()


@dataclass
class SensorRun:
    """The non-visual sensors of a simulated berthing, in memory (simulate() writes them; tests
    of the fusion use them directly)."""

    motion: ShipMotion
    calibration: Calibration
    nav: NavigationData
    imu: ImuData
    epochs: list[list[GnssEpoch]]
    imu_truth: dict
    gnss_truth: GnssTruth

    def feed(self, fusion) -> Iterator[tuple[int, float]]:
        """Drive ``fusion`` (``estimator.pipeline.Fusion``) with the IMU samples and the four
        receivers' epochs in time order, as a live feed would; yields (sample index, time)
        after each IMU sample so that callers can add frames or sample errors."""
        imu, epochs = self.imu, self.epochs
        e = 0
        for k, t in enumerate(imu.time):
            fusion.process_imu(t, imu.gyro[k], imu.accel[k])
            while e < len(epochs[0]) and epochs[0][e].time <= t + 1e-9:
                fusion.process_gnss(epochs[0][e].time, [rx[e] for rx in epochs])
                e += 1
            yield k, float(t)


def simulate_sensors(
    scenario: Scenario,
    seed: int,
    duration_s: float,
    gnss_errors: GnssErrorModel | None = None,
    progress: Progress | None = None,
) -> SensorRun:
    """Motion, IMU (100 Hz) and the four receivers' GNSS (1 Hz) over ``duration_s``."""
    start = scenario.start_gpst
    motion = ShipMotion(scenario, seed)
    antennas = scenario.antennas_body()
    imu, imu_cal, imu_truth = simulate_imu(motion, scenario, seed, start, rate_hz=IMU_RATE_HZ)
    keep = imu.time <= start + duration_s + 1e-9
    imu.time, imu.gyro, imu.accel = imu.time[keep], imu.gyro[keep], imu.accel[keep]
    if progress:
        progress("imu", 1, 1)
    nav = read_nav(NAV_FILE)
    epochs, gnss_truth = simulate_gnss(
        scenario, lambda t, i: motion.point_position_ned(t, antennas[i]), nav, start,
        duration_s, seed, errors=gnss_errors,
        progress=(lambda d, n: progress("gnss", d, n)) if progress else None)
    calibration = Calibration(camera=camera_calibration(scenario), antennas_body=antennas,
                              imu=imu_cal)
    return SensorRun(motion, calibration, nav, imu, epochs, imu_truth, gnss_truth)


# The sea surface's ellipsoidal height an installer would enter: a geoid model's (~0.3 m off)
# without the tide of the hour (Osaka Bay: ±0.9 m about mean sea level); stated as σ 1 m.
SEA_SURFACE_SIGMA_M = 1.0


def charted_sea_surface(true_height_m: float, seed: int) -> float:
    """The simulated world's sea-surface height as it would be known, off by a geoid error and
    the tide (its own random stream: the sensors' draws do not move)."""
    rng = np.random.default_rng([seed, 0x5EA])
    return round(float(true_height_m + rng.normal(0.0, 0.3) + rng.uniform(-0.9, 0.9)), 2)


def simulate(
    scenario_name: str,
    seed: int,
    out: str | Path,
    duration_s: float | None = None,
    progress: bool = True,
    gnss_errors: GnssErrorModel | None = None,
    camera_size: tuple[int, int] | None = None,
) -> Path:
    """Simulate ``scenario_name`` with ``seed`` into the directory ``out`` and return it.

    ``camera_size``: (width, height) of the video instead of the scenario's, same field of
    view (e.g. the thesis camera's 1920×1200); the same seed draws the same world."""
    if scenario_name not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario_name!r}; choose one of {sorted(SCENARIOS)}")
    # the seed draws the port, light, water, camera mounting and manoeuvre (variety)
    scenario: Scenario = seeded(SCENARIOS[scenario_name], seed)
    if camera_size is not None:
        w, h = camera_size
        if not (160 <= w <= 4096 and 120 <= h <= 3072):
            raise ValueError(f"camera size {w}x{h} is outside 160x120..4096x3072")
        scenario = dataclasses.replace(scenario, camera_size=(int(w), int(h)))
    duration = float(duration_s if duration_s is not None else scenario.duration_s)
    if not 1.0 <= duration <= scenario.duration_s:
        raise ValueError(
            f"duration must be within 1..{scenario.duration_s:g} s for {scenario_name}")
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"output directory {out} exists and is not empty")
    (out / "gnss").mkdir(parents=True, exist_ok=True)
    (out / "reference").mkdir(exist_ok=True)
    show = Progress(progress)
    start = scenario.start_gpst
    lat, lon, h = scenario.origin_llh_deg
    origin = np.array([np.radians(lat), np.radians(lon), h])

    run = simulate_sensors(scenario, seed, duration, gnss_errors, show)
    motion, imu, epochs = run.motion, run.imu, run.epochs
    camera, antennas = run.calibration.camera, run.calibration.antennas_body
    shutil.copyfile(NAV_FILE, out / "gnss" / "nav.rnx")
    centre = ned_to_ecef(motion.point_position_ned(0.0, antennas.mean(axis=0)), origin)
    obs_files = []
    for i, rx_epochs in enumerate(epochs):
        name = f"gnss/rx{i + 1}.obs"
        write_obs(out / name, rx_epochs, marker_name=f"{scenario.name.upper()}-ANT{i + 1}",
                  receiver_type="BERTHING-AID SIM", approx_position_ecef=centre, interval=1.0,
                  comments=[f"simulated {scenario.name} seed {seed}; one clock for 4 receivers"],
                  run_date=scenario.start)
        obs_files.append(name)

    scene = PortScene.build(scenario, seed)
    rng = np.random.default_rng(seed + 1000)
    n_frames = int(np.floor(duration * FRAME_RATE_HZ + 1e-9)) + 1
    frame_times = start + np.arange(n_frames) / FRAME_RATE_HZ
    with fmt.VideoWriter(out / "video.mp4", (camera.width, camera.height), FRAME_RATE_HZ) as video:
        for k, t in enumerate(frame_times):
            state = motion.state(t - start)
            C_b_l = state.C_body_to_level[0]
            cam_pos = motion.point_position_ned(t - start, camera.lever_arm_body)
            C_level_to_camera = (C_b_l @ camera.C_camera_to_body).T
            video.write(scene.render(C_level_to_camera, cam_pos, t - start, camera, rng))
            show("video", k + 1, n_frames)
    fmt.write_frame_times(out, frame_times)
    fmt.write_imu(out, imu)
    fmt.write_calibration(out, run.calibration)
    berth = np.array([[0.0, scenario.quay_east_range[0]], [0.0, scenario.quay_east_range[1]]])
    fmt.write_hull(out, Hull(scenario.hull_outline(), scenario.hull_length_m, scenario.hull_beam_m,
                             berth, body_origin_height_m=-scenario.reference_point_down_m,
                             sea_surface_height_m=charted_sea_surface(h, seed),
                             sea_surface_sigma_m=SEA_SURFACE_SIGMA_M,
                             freeboard_m=scenario.freeboard_m))

    ref_t = imu.time
    state = motion.state(ref_t - start)
    fmt.write_reference(out, fmt.ReferenceTrajectory.from_ned(
        ref_t, state.position_ned, state.velocity_ned, np.degrees(state.euler), origin))
    points, kinds = scene.scene_points()
    fmt.write_scene_points(out, points, kinds)

    fmt.write_manifest(out, fmt.Manifest(
        name=f"{scenario.name}-seed{seed}", scenario=scenario.name, seed=seed, start_gpst=start,
        duration_s=duration, origin_llh_deg=list(scenario.origin_llh_deg),
        files=fmt.default_files(obs_files)))
    return out
