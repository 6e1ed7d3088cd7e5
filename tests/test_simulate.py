"""The simulate and info commands, end to end, as a user runs them."""

from __future__ import annotations

import filecmp
import json
from pathlib import Path

import numpy as np
import pytest

from backend.cli import DEFAULT_RECORDING, main
from estimator.frames import euler_to_dcm
from recordings.format import load


@pytest.fixture(scope="module")
def large_ship(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "large"
    assert main(["simulate", "--scenario", "large-ship", "--seed", "5", "--duration", "3",
                 "--out", str(out), "--quiet"]) == 0
    return out


def test_large_ship_recording_loads_and_is_consistent(large_ship: Path) -> None:
    rec = load(large_ship)
    assert rec.manifest.scenario == "large-ship"
    assert len(rec.frame_times) == 31 and len(rec.imu) == 301
    assert len(rec.gnss) == 4 and all(len(rx) == 4 for rx in rec.gnss)
    # Cranes near the berth mask part of the sky: fewer satellites than in open sky.
    assert 5 <= len(rec.gnss[0][0].satellites) < 17
    ref = rec.reference
    assert ref is not None
    speed = np.linalg.norm(ref.velocity_ned[:, :2], axis=1)
    assert speed.max() < 0.25  # a large ship creeps alongside
    # The bridge camera 16-28 m above the sea (each seed draws its height, variety.py).
    C_b_l = euler_to_dcm(*np.radians(ref.euler_deg[0]))
    cam = ref.position_ned[0] + C_b_l @ rec.calibration.camera.lever_arm_body
    assert -28.5 < cam[2] < -15.5
    frame = rec.read_frame(15)
    assert frame.shape == (600, 960, 3) and frame.std() > 20
    # The sea surface's height as an installer knows it: off the world's 37 m by a geoid
    # error and the tide, within what its σ states.
    height, sigma = rec.hull.sea_surface
    assert sigma == 1.0 and 0.0 < abs(height - rec.manifest.origin_llh_deg[2]) < 2.0


def test_simulation_is_deterministic_for_a_seed(large_ship: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    assert main(["simulate", "--scenario", "large-ship", "--seed", "5", "--duration", "3",
                 "--out", str(again), "--quiet"]) == 0
    for name in ["imu.csv", "frames.csv", "gnss/rx1.obs", "gnss/rx4.obs",
                 "reference/trajectory.csv", "calibration.json"]:
        assert filecmp.cmp(large_ship / name, again / name, shallow=False), name


def test_camera_size_renders_the_same_world_at_another_resolution(large_ship: Path,
                                                                   tmp_path: Path) -> None:
    """``--camera-size``: the same seed's world and motion, the video at another size with
    the same field of view (the focal length scales with the width)."""
    small = tmp_path / "small"
    assert main(["simulate", "--scenario", "large-ship", "--seed", "5", "--duration", "3",
                 "--camera-size", "480x300", "--out", str(small), "--quiet"]) == 0
    a, b = load(large_ship), load(small)
    assert b.read_frame(15).shape == (300, 480, 3)
    assert (b.calibration.camera.width, b.calibration.camera.height) == (480, 300)
    np.testing.assert_allclose(b.calibration.camera.K[0, 0], a.calibration.camera.K[0, 0] / 2)
    assert filecmp.cmp(large_ship / "imu.csv", small / "imu.csv", shallow=False)
    # the same picture, downsized: the half-size render matches the full one shrunk
    big = a.read_frame(15).astype(float)
    shrunk = big.reshape(300, 2, 480, 2, 3).mean(axis=(1, 3))
    assert np.abs(shrunk - b.read_frame(15)).mean() < 20


def test_simulate_refuses_bad_arguments(tmp_path: Path, capsys) -> None:
    assert main(["simulate", "--scenario", "tanker", "--out", str(tmp_path / "x")]) == 2
    assert "unknown scenario 'tanker'" in capsys.readouterr().err
    assert main(["simulate", "--duration", "1000", "--out", str(tmp_path / "y")]) == 2
    assert "duration must be within" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["simulate", "--camera-size", "1920by1200", "--out", str(tmp_path / "z")])
    assert "'1920by1200' is not WIDTHxHEIGHT" in capsys.readouterr().err
    assert main(["simulate", "--camera-size", "10x10", "--out", str(tmp_path / "w")]) == 2
    assert "camera size 10x10 is outside" in capsys.readouterr().err


def test_info_on_the_bundled_recording(capsys) -> None:
    assert main(["info"]) == 0
    text = capsys.readouterr().out
    assert "small-boat" in text and "901 frames" in text and "9001 samples" in text
    assert main(["info", str(DEFAULT_RECORDING), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["duration_s"] == pytest.approx(90.0)
    assert info["reference"]["present"] is True


def test_info_names_a_broken_recording(tmp_path: Path, capsys) -> None:
    (tmp_path / "manifest.json").write_text("{not json")
    assert main(["info", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "manifest.json" in err
