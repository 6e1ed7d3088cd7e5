"""Recording format: writers → load round trip, summary, and every validation error."""

from __future__ import annotations

import json
import shutil
import threading
import warnings
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from estimator.frames import camera_to_body, gpst_from_datetime
from estimator.records import (
    Calibration,
    CameraCalibration,
    GnssEpoch,
    Hull,
    ImuCalibration,
    ImuData,
    SatObservation,
)
from recordings import format as fmt
from recordings import rinex
from recordings.format import (
    Manifest,
    RecordingError,
    RecordingWarning,
    ReferenceTrajectory,
    VideoWriter,
)

DATA = Path(__file__).resolve().parent / "data"
START = gpst_from_datetime(datetime(2024, 6, 24, 8, 20, 0))
ORIGIN_DEG = (34.7205, 135.333, 37.0)
W, H = 64, 48
N_FRAMES = 20
SATS = ("G05", "G07", "E11")


def _brightness(i: int) -> int:
    return 10 * i + 5  # frame i is a flat image: identifies the frame after lossy coding


def make_gnss(rx: int) -> list[GnssEpoch]:
    epochs = []
    for k in range(3):
        sats = {}
        for j, sat in enumerate(SATS):
            sats[sat] = SatObservation(
                pseudorange=2.2e7 + 1e5 * j + 100.0 * k + 0.25 * rx,
                carrier_phase=1.15e8 + 5e5 * j + 523.125 * k + rx,
                doppler=float("nan") if (sat == "E11" and k == 0) else -1234.5 + 10 * j,
                snr=40.0 + j,
                lli=1 if (sat == "G07" and k == 2) else 0,
            )
        epochs.append(GnssEpoch(time=START + k, satellites=sats))
    return epochs


def make_calibration() -> Calibration:
    camera = CameraCalibration(
        width=W, height=H,
        K=np.array([[50.0, 0.0, 32.5], [0.0, 51.0, 24.25], [0.0, 0.0, 1.0]]),
        distortion=np.array([-0.12, 0.05, 0.0005, -0.0003, 0.0]),
        C_camera_to_body=camera_to_body(0.1, 0.05, 0.01),
        lever_arm_body=np.array([3.0, 0.1, -0.4]),
    )
    imu = ImuCalibration(
        gyro_scale_factor=np.array([1e-3, -2e-3, 5e-4]),
        gyro_misalignment=np.eye(3) + 1e-3 * np.array([[0, 1, -2], [1, 0, 3], [0.5, 1, 0]]),
        accel_scale_factor=np.array([2e-3, 1e-3, -1e-3]),
        accel_misalignment=np.eye(3) + 1e-3 * np.array([[0, -1, 2], [2, 0, 1], [1, 1, 0]]),
        lever_arm_body=np.array([0.01, 0.02, -0.03]),
    )
    h = 0.05
    antennas = np.array([[h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0], [-h, -h, 0.0]])
    return Calibration(camera=camera, antennas_body=antennas + [1.0, 0.0, -1.2], imu=imu)


def make_reference() -> ReferenceTrajectory:
    t = START + np.arange(201) * 0.01
    s = t - START
    pos = np.column_stack([-75 + s, -45 + 0.5 * s, -0.6 + 0.01 * np.sin(s)])
    vel = np.column_stack([np.ones_like(s), 0.5 * np.ones_like(s), 0.01 * np.cos(s)])
    yaw = 170.0 + 10.0 * s  # crosses +180 at s = 1 and is stored wrapped, as a file would be
    euler = np.column_stack([2 * np.sin(s), np.cos(s), (yaw + 180) % 360 - 180])
    lat, lon, h = ORIGIN_DEG
    return ReferenceTrajectory.from_ned(t, pos, vel, euler,
                                        np.array([np.radians(lat), np.radians(lon), h]))


def build_recording(root: Path) -> dict:
    """Write a small complete recording with the writers; return what was written."""
    rng = np.random.default_rng(3)
    cal = make_calibration()
    hull = Hull(outline_body=np.array([[3.5, 0], [1.75, 1.25], [-3.5, 1.25], [-3.5, -1.25],
                                       [1.75, -1.25]]),
                length=7.0, beam=2.5, berth_line_ned=np.array([[0.0, -60.0], [0.0, 60.0]]),
                sea_surface_height_m=37.4, sea_surface_sigma_m=0.8)
    t_imu = START + np.arange(201) * 0.01
    imu = ImuData(time=t_imu, gyro=rng.normal(0, 0.1, (201, 3)),
                  accel=rng.normal(0, 0.2, (201, 3)) + [0, 0, -9.8])
    frame_times = START + np.arange(N_FRAMES) * 0.1
    ref = make_reference()
    points = np.array([[0.0, -10.0, -1.5], [0.0, 12.345678, -1.5], [5.0, 0.0, -8.25]])
    kinds = ["quay-corner", "fender", "bollard"]
    manifest = Manifest(name="test-rec", scenario="small-boat", seed=7, start_gpst=START,
                        duration_s=2.0, origin_llh_deg=ORIGIN_DEG, files=fmt.default_files(4),
                        extra={"note": "unit test"})

    fmt.write_manifest(root, manifest)
    fmt.write_calibration(root, cal)
    fmt.write_hull(root, hull)
    fmt.write_imu(root, imu)
    fmt.write_frame_times(root, frame_times)
    fmt.write_reference(root, ref)
    fmt.write_scene_points(root, points, kinds)
    with VideoWriter(root / "video.mp4", (W, H)) as video:
        for i in range(N_FRAMES):
            video.write(np.full((H, W, 3), _brightness(i), np.uint8))
    gnss = [make_gnss(rx) for rx in range(4)]
    (root / "gnss").mkdir()
    ecef = np.array([-3755000.0, 3697000.0, 3612000.0])
    for i, epochs in enumerate(gnss):
        rinex.write_obs(root / fmt.gnss_obs_file(i + 1), epochs, marker_name=f"ANT{i + 1}",
                        receiver_type="TEST", approx_position_ecef=ecef, interval=1.0)
    shutil.copyfile(DATA / "static.nav", root / fmt.NAV_FILE)
    return dict(manifest=manifest, cal=cal, hull=hull, imu=imu, frame_times=frame_times,
                ref=ref, points=points, kinds=kinds, gnss=gnss, ecef=ecef)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("pristine")
    return root, build_recording(root)


@pytest.fixture(scope="module")
def loaded(pristine: tuple[Path, dict]) -> fmt.Recording:
    return fmt.load(pristine[0])


@pytest.fixture
def rec_dir(pristine: tuple[Path, dict], tmp_path: Path) -> Path:
    """A fresh copy of the good recording that a test may damage."""
    dst = tmp_path / "rec"
    shutil.copytree(pristine[0], dst)
    return dst


def edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def edit_lines(path: Path, change) -> None:
    lines = path.read_text().splitlines()
    change(lines)
    path.write_text("\n".join(lines) + "\n")


def load_error(root: Path) -> str:
    with pytest.raises(RecordingError) as err:
        fmt.load(root)
    return str(err.value)


# ------------------------------------------------------------------------- round trip


def test_round_trip_manifest(loaded: fmt.Recording, pristine) -> None:
    m, want = loaded.manifest, pristine[1]["manifest"]
    assert (m.name, m.scenario, m.seed, m.version) == ("test-rec", "small-boat", 7, 1)
    assert m.start_gpst == want.start_gpst and m.duration_s == 2.0
    assert m.origin_llh_deg == ORIGIN_DEG
    assert m.files == fmt.default_files(4)
    assert m.extra == {"note": "unit test"}
    np.testing.assert_allclose(m.origin_llh, [np.radians(34.7205), np.radians(135.333), 37.0])
    assert loaded.path == pristine[0]
    assert loaded.video_path() == pristine[0] / "video.mp4"


def test_round_trip_calibration_and_hull(loaded: fmt.Recording, pristine) -> None:
    cal, want = loaded.calibration, pristine[1]["cal"]
    assert (cal.camera.width, cal.camera.height) == (W, H)
    for name in ("K", "distortion", "C_camera_to_body", "lever_arm_body"):
        np.testing.assert_array_equal(getattr(cal.camera, name), getattr(want.camera, name))
    np.testing.assert_array_equal(cal.antennas_body, want.antennas_body)
    for name in ("gyro_scale_factor", "gyro_misalignment", "accel_scale_factor",
                 "accel_misalignment", "lever_arm_body"):
        np.testing.assert_array_equal(getattr(cal.imu, name), getattr(want.imu, name))
    hull, want_hull = loaded.hull, pristine[1]["hull"]
    np.testing.assert_array_equal(hull.outline_body, want_hull.outline_body)
    assert (hull.length, hull.beam) == (7.0, 2.5)
    np.testing.assert_array_equal(hull.berth_line_ned, want_hull.berth_line_ned)
    assert hull.sea_surface == (37.4, 0.8)


@pytest.mark.parametrize("field,value,expect", [
    ("sea_surface_height_m", "37", "sea_surface_height_m must be a finite number"),
    ("sea_surface_height_m", 6378137.0, "not a height of the sea above the ellipsoid"),
    ("sea_surface_sigma_m", 0.0, "sea_surface_sigma_m must be positive"),
    ("sea_surface_sigma_m", None, "sea_surface_sigma_m must be a finite number"),
])
def test_bad_sea_surface_is_named(rec_dir: Path, field: str, value, expect: str) -> None:
    edit_json(rec_dir / "hull.json", lambda h: h.update({field: value}))
    with pytest.raises(RecordingError, match=expect) as err:
        fmt.load(rec_dir, load_gnss=False)
    assert "hull.json" in str(err.value)


def test_sea_surface_is_optional(rec_dir: Path) -> None:
    def drop(h: dict) -> None:
        h.pop("sea_surface_height_m")
        h.pop("sea_surface_sigma_m")
    edit_json(rec_dir / "hull.json", drop)
    assert fmt.load(rec_dir, load_gnss=False).hull.sea_surface is None


def test_round_trip_imu_frames_reference_scene(loaded: fmt.Recording, pristine) -> None:
    want = pristine[1]
    np.testing.assert_allclose(loaded.imu.time, want["imu"].time, rtol=0, atol=1e-6)
    np.testing.assert_allclose(loaded.imu.gyro, want["imu"].gyro, rtol=0, atol=1e-9)
    np.testing.assert_allclose(loaded.imu.accel, want["imu"].accel, rtol=0, atol=1e-9)
    np.testing.assert_allclose(loaded.frame_times, want["frame_times"], rtol=0, atol=1e-6)
    ref, wref = loaded.reference, want["ref"]
    assert ref is not None and len(ref) == 201
    np.testing.assert_allclose(ref.time, wref.time, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ref.position_ned, wref.position_ned, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ref.velocity_ned, wref.velocity_ned, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ref.euler_deg, wref.euler_deg, rtol=0, atol=1e-8)
    np.testing.assert_allclose(ref.llh_deg[:, :2], wref.llh_deg[:, :2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(ref.llh_deg[:, 2], wref.llh_deg[:, 2], rtol=0, atol=1e-6)
    # from_ned: the first point is ~87 m south-west of the origin, at its height + 0.6 m
    assert ref.llh_deg[0, 0] < ORIGIN_DEG[0] and ref.llh_deg[0, 1] < ORIGIN_DEG[1]
    assert ref.llh_deg[0, 2] == pytest.approx(ORIGIN_DEG[2] + 0.6, abs=0.01)
    np.testing.assert_allclose(loaded.scene_points, want["points"], rtol=0, atol=1e-6)
    assert loaded.scene_point_kinds == want["kinds"]


def test_round_trip_gnss(loaded: fmt.Recording, pristine) -> None:
    want = pristine[1]["gnss"]
    assert loaded.gnss_loaded and len(loaded.gnss) == 4 and len(loaded.gnss_headers) == 4
    for got_rx, want_rx, header in zip(loaded.gnss, want, loaded.gnss_headers, strict=True):
        assert header.interval == 1.0
        np.testing.assert_allclose(header.approx_position_ecef, pristine[1]["ecef"], atol=1e-3)
        assert [e.time for e in got_rx] == pytest.approx([e.time for e in want_rx], abs=1e-6)
        for got, exp in zip(got_rx, want_rx, strict=True):
            assert sorted(got.satellites) == sorted(exp.satellites)
            for sat, o in exp.satellites.items():
                g = got.satellites[sat]
                assert g.pseudorange == pytest.approx(o.pseudorange, abs=1e-3)
                assert g.carrier_phase == pytest.approx(o.carrier_phase, abs=1e-3)
                assert g.snr == pytest.approx(o.snr, abs=1e-3)
                assert (np.isnan(g.doppler) and np.isnan(o.doppler)) or \
                    g.doppler == pytest.approx(o.doppler, abs=1e-3)
                assert (g.lli & 1) == (o.lli & 1)
    assert loaded.nav.ephemerides and {s[0] for s in loaded.nav.ephemerides} >= {"G", "E"}


def test_video_frames_sequential_seek_and_random(loaded: fmt.Recording) -> None:
    got = list(loaded.frames())
    assert [i for i, _, _ in got] == list(range(N_FRAMES))
    assert [t for _, t, _ in got] == pytest.approx(list(loaded.frame_times))
    for i, _, image in got:
        assert image.shape == (H, W, 3)
        assert abs(image.mean() - _brightness(i)) < 4.5  # lossy mp4v, levels 10 apart
    later = list(loaded.frames(start=15))
    assert [i for i, _, _ in later] == list(range(15, N_FRAMES))
    assert abs(later[0][2].mean() - _brightness(15)) < 4.5
    assert abs(loaded.read_frame(13).mean() - _brightness(13)) < 4.5
    with pytest.raises(IndexError):
        loaded.read_frame(N_FRAMES)
    info = loaded.video_info
    assert (info.width, info.height, info.frame_count, info.fps) == (W, H, N_FRAMES, 10.0)


def test_frames_read_ahead_in_order_stop_cleanly_and_raise_decoder_errors(
        loaded: fmt.Recording) -> None:
    """The video is decoded by a thread ahead of the reader: same frames in the same order,
    no thread left behind when the reader stops early, a decoder error raised to the reader."""
    def readers() -> list[threading.Thread]:
        return [t for t in threading.enumerate() if t.name == "video-read-ahead"]

    frames = loaded.frames()
    first = [next(frames) for _ in range(3)]
    assert [i for i, _, _ in first] == [0, 1, 2] and len(readers()) == 1
    frames.close()
    assert readers() == []

    class Broken:
        def __init__(self) -> None:
            self.calls = 0

        def read(self) -> tuple[bool, np.ndarray]:
            self.calls += 1
            if self.calls == 3:
                raise RuntimeError("decoder fell over")
            return True, np.full((2, 2, 3), self.calls, np.uint8)

    reads = fmt._read_ahead(Broken(), 10)
    assert [int(image[0, 0, 0]) for _, image, _ in (next(reads), next(reads))] == [1, 2]
    with pytest.raises(RuntimeError, match="decoder fell over"):
        next(reads)
    assert readers() == []


def test_prepared_frames_carry_what_the_reading_thread_made_of_them(
        loaded: fmt.Recording) -> None:
    """``prepare`` runs in the reading thread on each decoded image: its result comes with the
    very frame; an error in it reaches the reader, and no thread is left behind."""
    seen: list[str] = []

    def prepare(image: np.ndarray) -> float:
        seen.append(threading.current_thread().name)
        return float(image.mean())

    got = list(loaded.prepared_frames(1, prepare))
    assert [i for i, *_ in got] == list(range(1, N_FRAMES))
    assert all(p == float(image.mean()) for _, _, image, p in got)
    assert set(seen) == {"video-read-ahead"}

    def broken(image: np.ndarray) -> None:
        raise ValueError("cannot prepare")

    with pytest.raises(ValueError, match="cannot prepare"):
        list(loaded.prepared_frames(0, broken))
    assert not [t for t in threading.enumerate() if t.name == "video-read-ahead"]


def test_load_accepts_manifest_path_and_skips_gnss(pristine) -> None:
    rec = fmt.load(str(pristine[0] / "manifest.json"), load_gnss=False)
    assert not rec.gnss_loaded and rec.gnss == [] and rec.gnss_headers == []
    assert rec.nav.ephemerides == {}
    info = fmt.summary(rec)
    assert info["gnss"] == {"loaded": False, "receivers": []}
    assert "not loaded" in fmt.format_summary(info)


def test_summary(loaded: fmt.Recording) -> None:
    info = fmt.summary(loaded)
    json.dumps(info)  # the CLI prints it with --json
    assert info["name"] == "test-rec" and info["scenario"] == "small-boat" and info["seed"] == 7
    assert info["start"]["iso"] == "2024-06-24T08:20:00.000 GPST"
    assert info["start"]["week"] == 2320 and info["start"]["tow"] == pytest.approx(116400.0)
    assert info["video"]["frame_count"] == N_FRAMES and not info["video"]["frame_count_mismatch"]
    assert info["imu"]["rate_hz"] == pytest.approx(100.0) and info["imu"]["count"] == 201
    assert info["imu"]["gaps"] == []
    rx = info["gnss"]["receivers"]
    assert len(rx) == 4
    assert rx[0]["epochs"] == 3 and rx[0]["systems"] == "GE" and rx[0]["cycle_slip_flags"] == 1
    assert rx[0]["satellites_per_epoch"] == {"min": 3, "mean": 3.0, "max": 3}
    nav = info["nav"]["systems"]
    assert set(nav) >= {"G", "E"} and nav["G"]["ephemerides"] >= nav["G"]["satellites"] > 0
    assert info["reference"] == {"present": True, "samples": 201}
    assert info["scene_points"] == 3 and info["warnings"] == []
    text = fmt.format_summary(info)
    lines = text.splitlines()
    assert lines[0].startswith("name") and "test-rec" in lines[0]
    # aligned: every value starts in the same column
    col = {len(line) - len(line[len(line.split("  ")[0]):].lstrip()) for line in lines}
    assert len(col) == 1
    assert "gnss rx4" in text and "2024-06-24T08:20:00.000 GPST" in text
    assert "week 2320" in text


def test_reference_interpolation_unwraps_yaw() -> None:
    ref = make_reference()
    # samples 179.9 deg (s = 0.99) and -180 deg (s = 1.0): half way is 179.95, not ~0 as a
    # naive average of the stored angles gives
    pos, vel, euler = ref.interpolate(START + 0.995)
    assert pos.shape == (3,) and vel.shape == (3,)
    assert np.degrees(euler[2]) == pytest.approx(179.95, abs=1e-4)  # µs of START rounding
    np.testing.assert_allclose(pos, [-75 + 0.995, -45 + 0.4975, -0.6 + 0.01 * np.sin(0.995)],
                               atol=1e-5)
    _, _, e = ref.interpolate(START + 1.5)
    assert np.degrees(e[2]) == pytest.approx(-175.0, abs=1e-6)
    assert np.degrees(e[0]) == pytest.approx(2 * np.sin(1.5), abs=1e-3)
    p, v, eu = ref.interpolate(np.array([START - 1.0, START + 0.5, START + 9.0]))
    assert p.shape == v.shape == eu.shape == (3, 3)
    assert np.isnan(p[0]).all() and np.isnan(eu[2]).all() and np.isfinite(p[1]).all()


def test_default_files_and_manifest_origin() -> None:
    files = fmt.default_files(["a.obs", "b.obs"], reference=False)
    assert files["gnss_obs"] == ["a.obs", "b.obs"] and files["reference"] is None
    m = Manifest("n", None, None, START, 1.0, [1, 2, 3])
    assert m.origin_llh_deg == (1.0, 2.0, 3.0)


def test_real_recording_without_reference(rec_dir: Path) -> None:
    def change(m: dict) -> None:
        m["files"]["reference"] = None
        m["files"]["scene_points"] = None
        m["scenario"] = None
        m["seed"] = None
    edit_json(rec_dir / "manifest.json", change)
    edit_json(rec_dir / "hull.json", lambda h: h.pop("berth_line_ned"))
    edit_json(rec_dir / "calibration.json", lambda c: c.pop("imu"))
    rec = fmt.load(rec_dir, load_gnss=False)
    assert rec.reference is None and rec.scene_points is None and rec.scene_point_kinds is None
    assert rec.hull.berth_line_ned is None
    np.testing.assert_array_equal(rec.calibration.imu.gyro_misalignment, np.eye(3))
    info = fmt.summary(rec)
    assert info["reference"]["present"] is False
    assert "real recording" in fmt.format_summary(info)


def test_imu_with_9000_rows_round_trips(tmp_path: Path) -> None:
    n = 9000
    rng = np.random.default_rng(0)
    imu = ImuData(START + np.arange(n) * 0.01, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))
    fmt.write_imu(tmp_path, imu)
    got, notes = fmt._read_imu(tmp_path / "imu.csv")
    assert len(got) == n and notes == []
    np.testing.assert_allclose(got.time, imu.time, atol=1e-6, rtol=0)


# ------------------------------------------------------------------------- validation


def test_missing_manifest(tmp_path: Path) -> None:
    msg = load_error(tmp_path)
    assert "manifest.json" in msg and "missing" in msg
    assert "not a recording directory" in load_error(tmp_path / "nope")


def test_wrong_format_and_version(rec_dir: Path) -> None:
    edit_json(rec_dir / "manifest.json", lambda m: m.update(format="something-else"))
    msg = load_error(rec_dir)
    assert "manifest.json" in msg and "format" in msg and "something-else" in msg
    edit_json(rec_dir / "manifest.json",
              lambda m: m.update(format="berthing-aid-recording", version=2))
    msg = load_error(rec_dir)
    assert "manifest.json" in msg and "unsupported format version 2" in msg
    edit_json(rec_dir / "manifest.json", lambda m: m.pop("version"))
    msg = load_error(rec_dir)
    assert "manifest.json" in msg and "missing field version" in msg


def test_invalid_json_names_line(rec_dir: Path) -> None:
    (rec_dir / "hull.json").write_text('{\n  "length": 7.0,\n  oops\n}')
    msg = load_error(rec_dir)
    assert "hull.json" in msg and "line 3" in msg and "invalid JSON" in msg


def test_manifest_field_errors(rec_dir: Path) -> None:
    edit_json(rec_dir / "manifest.json", lambda m: m.update(start_gpst="soon"))
    msg = load_error(rec_dir)
    assert "manifest.json" in msg and "start_gpst" in msg
    edit_json(rec_dir / "manifest.json", lambda m: m.update(start_gpst=START))
    edit_json(rec_dir / "manifest.json", lambda m: m["files"].pop("imu"))
    msg = load_error(rec_dir)
    assert "manifest.json" in msg and "missing field files.imu" in msg


def test_missing_file_named_in_manifest(rec_dir: Path) -> None:
    (rec_dir / "imu.csv").unlink()
    msg = load_error(rec_dir)
    assert "manifest.json" in msg and "files.imu" in msg and "imu.csv" in msg
    assert "does not exist" in msg


def test_missing_gnss_file_named_in_manifest(rec_dir: Path) -> None:
    (rec_dir / "gnss" / "rx3.obs").unlink()
    msg = load_error(rec_dir)
    assert "files.gnss_obs[2]" in msg and "gnss/rx3.obs" in msg


def test_missing_calibration_field(rec_dir: Path) -> None:
    edit_json(rec_dir / "calibration.json", lambda c: c["camera"].pop("fx"))
    msg = load_error(rec_dir)
    assert "calibration.json" in msg and "missing field camera.fx" in msg


def test_calibration_bad_values(rec_dir: Path) -> None:
    edit_json(rec_dir / "calibration.json",
              lambda c: c["camera"].update(distortion=[0.1, 0.2, 0.3]))
    msg = load_error(rec_dir)
    assert "calibration.json" in msg and "camera.distortion" in msg
    edit_json(rec_dir / "calibration.json",
              lambda c: c["camera"].update(distortion=[0, 0, 0, 0, 0]))
    edit_json(rec_dir / "calibration.json", lambda c: c["imu"].update(gyro_scale=[0, 0, 0]))
    msg = load_error(rec_dir)
    assert "calibration.json" in msg and "unknown field imu.gyro_scale" in msg


def test_calibration_matrix_not_rotation(rec_dir: Path) -> None:
    def skew_it(c: dict) -> None:
        c["camera"]["C_camera_to_body"][0][0] += 0.1
    edit_json(rec_dir / "calibration.json", skew_it)
    msg = load_error(rec_dir)
    assert "calibration.json" in msg and "camera.C_camera_to_body" in msg
    assert "not a rotation" in msg
    # a reflection is orthogonal but still not a rotation
    edit_json(rec_dir / "calibration.json", lambda c: c["camera"].update(
        C_camera_to_body=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]))
    assert "not a rotation" in load_error(rec_dir)


def _time_column(file: str) -> int:
    return 0 if file == "imu.csv" else 1


@pytest.mark.parametrize("file", ["imu.csv", "frames.csv"])
def test_non_monotonic_time(rec_dir: Path, file: str) -> None:
    col = _time_column(file)

    def swap_times(lines: list[str]) -> None:  # data rows at file lines 6 and 7
        a, b = lines[5].split(","), lines[6].split(",")
        a[col], b[col] = b[col], a[col]
        lines[5], lines[6] = ",".join(a), ",".join(b)
    edit_lines(rec_dir / file, swap_times)
    if file == "imu.csv":  # a logger's clock can step back: loaded, noted, dropped by the engine
        notes = fmt.load(rec_dir, load_gnss=False).warnings
        assert any(file in n and "line 7" in n and "do not increase" in n for n in notes), notes
        return
    msg = load_error(rec_dir)
    assert file in msg and "line 7" in msg and "goes back" in msg


@pytest.mark.parametrize("file", ["imu.csv", "frames.csv"])
def test_duplicate_time(rec_dir: Path, file: str) -> None:
    col = _time_column(file)

    def duplicate(lines: list[str]) -> None:
        fields = lines[9].split(",")
        fields[col] = lines[8].split(",")[col]
        lines[9] = ",".join(fields)
    edit_lines(rec_dir / file, duplicate)
    if file == "imu.csv":
        notes = fmt.load(rec_dir, load_gnss=False).warnings
        assert any(file in n and "line 10" in n and "do not increase" in n for n in notes), notes
        return
    msg = load_error(rec_dir)
    assert file in msg and "line 10" in msg and "duplicates" in msg


def test_frame_numbering(rec_dir: Path) -> None:
    edit_lines(rec_dir / "frames.csv", lambda ls: ls.pop(4))
    msg = load_error(rec_dir)
    assert "frames.csv" in msg and "line 5" in msg and "frame is 4, expected 3" in msg


@pytest.mark.parametrize("value,expect", [("nan", "NaN/inf"), ("inf", "NaN/inf"),
                                          ("-inf", "NaN/inf"), ("abc", "not a number"),
                                          ("", "not a number")])
def test_imu_bad_value(rec_dir: Path, value: str, expect: str) -> None:
    def put(lines: list[str]) -> None:
        fields = lines[12].split(",")
        fields[4] = value
        lines[12] = ",".join(fields)
    edit_lines(rec_dir / "imu.csv", put)
    msg = load_error(rec_dir)
    assert "imu.csv" in msg and "line 13" in msg and "accel_x" in msg and expect in msg


def test_imu_wrong_column_count(rec_dir: Path) -> None:
    edit_lines(rec_dir / "imu.csv", lambda ls: ls.__setitem__(20, ls[20] + ",0.5"))
    msg = load_error(rec_dir)
    assert "imu.csv" in msg and "line 21" in msg and "8 columns, expected 7" in msg
    edit_lines(rec_dir / "imu.csv", lambda ls: ls.__setitem__(20, ",".join(ls[20].split(",")[:6])))
    msg = load_error(rec_dir)
    assert "line 21" in msg and "6 columns, expected 7" in msg


def test_csv_header_checked(rec_dir: Path) -> None:
    edit_lines(rec_dir / "imu.csv", lambda ls: ls.__setitem__(0, "t,gx,gy,gz,ax,ay,az"))
    msg = load_error(rec_dir)
    assert "imu.csv" in msg and "line 1" in msg and "header" in msg


def test_csv_comments_and_blank_lines_keep_line_numbers(rec_dir: Path) -> None:
    def change(lines: list[str]) -> None:
        lines.insert(1, "# exported by a logger")
        lines.insert(3, "")
        fields = lines[10].split(",")
        fields[2] = "nan"
        lines[10] = ",".join(fields)
    edit_lines(rec_dir / "imu.csv", change)
    msg = load_error(rec_dir)
    assert "line 11" in msg and "gyro_y" in msg


def test_times_not_gps_seconds(rec_dir: Path) -> None:
    imu, _ = fmt._read_imu(rec_dir / "imu.csv")
    imu.time = imu.time - 2320 * 604800.0  # time of week instead of GPS seconds
    fmt.write_imu(rec_dir, imu)
    msg = load_error(rec_dir)
    assert "imu.csv" in msg and "outside the recording" in msg


def test_imu_gaps_reported_not_fatal(rec_dir: Path) -> None:
    edit_lines(rec_dir / "imu.csv", lambda ls: ls.__delitem__(slice(50, 100)))  # 0.5 s gap
    rec = fmt.load(rec_dir, load_gnss=False)
    info = fmt.summary(rec)
    gaps = info["imu"]["gaps"]
    assert len(gaps) == 1 and gaps[0]["length_s"] == pytest.approx(0.51)
    assert gaps[0]["start_gpst"] == pytest.approx(START + 0.48)
    assert info["imu"]["count"] == 151 and info["imu"]["rate_hz"] == pytest.approx(100.0)
    assert any("gap" in w for w in info["warnings"])
    assert "1 gap(s), longest 0.510 s" in fmt.format_summary(info)


def test_receivers_vs_antennas(rec_dir: Path) -> None:
    edit_json(rec_dir / "manifest.json", lambda m: m["files"]["gnss_obs"].pop())
    msg = load_error(rec_dir)
    assert "manifest.json" in msg and "3 receivers" in msg and "4 antennas" in msg
    fmt.load(rec_dir, load_gnss=False)  # only checked when the GNSS data is read


@pytest.mark.parametrize("times,expect", [
    ([START, START + 1, START + 1], "epoch 3"),  # RINEX allows it; the estimator cannot
    ([START + 8 * 86400 + k for k in range(3)], "outside the recording"),
])
def test_gnss_epoch_times(rec_dir: Path, times: list[float], expect: str) -> None:
    epochs = [GnssEpoch(time=t, satellites=e.satellites) for t, e in zip(times, make_gnss(0),
                                                                            strict=True)]
    rinex.write_obs(rec_dir / "gnss" / "rx1.obs", epochs, marker_name="ANT1",
                    receiver_type="TEST", approx_position_ecef=np.zeros(3), interval=1.0)
    msg = load_error(rec_dir)
    assert "rx1.obs" in msg and expect in msg


def test_receiver_without_l1_observations(rec_dir: Path) -> None:
    path = rec_dir / "gnss" / "rx3.obs"
    path.write_text(path.read_text().replace("C1C L1C D1C S1C", "C5Q L5Q D5Q S5Q"))
    msg = load_error(rec_dir)
    assert "rx3.obs" in msg and "no L1" in msg and "C5Q" in msg


def test_rinex_error_is_wrapped(rec_dir: Path) -> None:
    (rec_dir / "gnss" / "rx2.obs").write_text("this is not a RINEX file\n")
    with pytest.raises(RecordingError) as err:
        fmt.load(rec_dir)
    assert "rx2.obs" in str(err.value)
    assert isinstance(err.value.__cause__, rinex.RinexError)
    assert str(err.value.__cause__) in str(err.value)  # the RINEX reader's message is kept


def test_truncated_rinex_is_wrapped(rec_dir: Path) -> None:
    path = rec_dir / "gnss" / "rx4.obs"
    text = path.read_text()
    path.write_text(text[: len(text) - 40])  # cut inside the last epoch
    msg = load_error(rec_dir)
    assert "rx4.obs" in msg


def test_bad_nav_file_is_wrapped(rec_dir: Path) -> None:
    (rec_dir / "gnss" / "nav.rnx").write_bytes(b"\x00\xff garbage")
    msg = load_error(rec_dir)
    assert "nav.rnx" in msg


def test_frame_count_mismatch_reported(rec_dir: Path) -> None:
    fmt.write_frame_times(rec_dir, START + np.arange(N_FRAMES + 2) * 0.1)
    rec = fmt.load(rec_dir, load_gnss=False)
    info = fmt.summary(rec)
    assert info["video"]["frame_count_mismatch"]
    assert info["video"]["frame_count"] == N_FRAMES and info["video"]["frame_times"] == 22
    assert any("20 frames" in w and "22" in w for w in rec.warnings)
    assert "MISMATCH" in fmt.format_summary(info)
    with pytest.warns(RecordingWarning, match="ends at frame 20"):
        got = [i for i, _, _ in rec.frames(start=18)]
    assert got == [18, 19]


def test_video_longer_than_frames_csv_stops_at_last_timed_frame(rec_dir: Path) -> None:
    fmt.write_frame_times(rec_dir, START + np.arange(N_FRAMES - 5) * 0.1)
    rec = fmt.load(rec_dir, load_gnss=False)
    assert rec.warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(rec.frames())) == N_FRAMES - 5


def test_unreadable_video(rec_dir: Path) -> None:
    (rec_dir / "video.mp4").write_bytes(b"not a video" * 100)
    msg = load_error(rec_dir)
    assert "video.mp4" in msg and "cannot open" in msg


def test_frames_raises_on_unreadable_video(pristine, tmp_path: Path) -> None:
    rec = fmt.load(pristine[0], load_gnss=False)
    rec.path = tmp_path  # the video vanished after loading
    with pytest.raises(RecordingError, match="video.mp4"):
        rec.frames()
    with pytest.raises(RecordingError, match="video.mp4"):
        rec.read_frame(0)


def test_video_size_must_match_calibration(rec_dir: Path) -> None:
    edit_json(rec_dir / "calibration.json", lambda c: c["camera"].update(width=960))
    msg = load_error(rec_dir)
    assert "video.mp4" in msg and "64x48" in msg and "960x48" in msg


def test_scene_points_errors(rec_dir: Path) -> None:
    edit_lines(rec_dir / "reference" / "scene_points.csv",
               lambda ls: ls.__setitem__(2, "1.0,2.0,x,fender"))
    msg = load_error(rec_dir)
    assert "scene_points.csv" in msg and "line 3" in msg and "down" in msg


def test_reference_errors(rec_dir: Path) -> None:
    edit_lines(rec_dir / "reference" / "trajectory.csv",
               lambda ls: ls.__setitem__(30, ls[30].replace(",", ",nan,", 1).rsplit(",", 1)[0]))
    msg = load_error(rec_dir)
    assert "trajectory.csv" in msg and "line 31" in msg and "north" in msg


# ---------------------------------------------------------------------------- writers


def test_video_writer_errors(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(RecordingError, match="cannot open a video writer"):
        VideoWriter(blocker / "video.mp4", (W, H))  # parent is a file
    with VideoWriter(tmp_path / "v.mp4", (W, H)) as video:
        with pytest.raises(RecordingError, match="frame 0"):
            video.write(np.zeros((H + 2, W, 3), np.uint8))
        video.write(np.zeros((H, W, 3), np.uint8))
        assert video.count == 1


def test_writers_refuse_bad_data(tmp_path: Path) -> None:
    imu = ImuData(np.array([START, np.nan]), np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(RecordingError, match="NaN"):
        fmt.write_imu(tmp_path, imu)
    with pytest.raises(RecordingError, match="kind"):
        fmt.write_scene_points(tmp_path, np.zeros((1, 3)), ["a,b"])
    cal = make_calibration()
    cal.camera.K[0, 1] = 0.5
    with pytest.raises(RecordingError, match="skew"):
        fmt.write_calibration(tmp_path, cal)
    m = Manifest("n", None, None, START, 1.0, ORIGIN_DEG, extra={"version": 3})
    with pytest.raises(RecordingError, match="clash"):
        fmt.write_manifest(tmp_path, m)


def test_video_gaps_reported(rec_dir: Path) -> None:
    """Frames missing (a camera silent for a while, a live feed that stalled) are listed as
    the IMU's and the receivers' gaps are (a user trial: ``info`` did not mention a live
    recording's video gap)."""
    times = fmt.load(rec_dir, load_gnss=False).frame_times

    def later(lines: list[str]) -> None:  # frames 3 on came 0.5 s later (the header first)
        for k in range(4, len(lines)):
            frame, t = lines[k].split(",")
            lines[k] = f"{frame},{float(t) + 0.5:.6f}"

    edit_lines(rec_dir / "frames.csv", later)
    rec = fmt.load(rec_dir, load_gnss=False)
    info = fmt.summary(rec)
    gaps = info["video"]["gaps"]
    assert len(gaps) == 1 and gaps[0]["start_gpst"] == pytest.approx(times[2])
    assert gaps[0]["length_s"] == pytest.approx(times[3] - times[2] + 0.5, abs=1e-3)
    video = next(ln for ln in fmt.format_summary(info).splitlines() if ln.startswith("video"))
    assert "1 gap(s), longest 0.6 s at 0.2 s" in video, video
