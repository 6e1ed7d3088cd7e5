"""The ``baseline`` and ``compass`` reports: real static pair and a simulated small boat."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from evaluation.baseline import baseline_report, format_baseline_report
from evaluation.cli import add_baseline_parser, add_compass_parser
from evaluation.compass import compass_report, compass_report_for, format_compass_report
from evaluation.gnss_records import (
    ArrayVelocity,
    BaselineRestart,
    ReceiverVelocity,
    VelocityErrorStats,
)
from evaluation.records import to_json
from recordings.format import ReferenceTrajectory
from recordings.rinex import read_nav
from recordings.sim.gnss import simulate_gnss
from recordings.sim.imu import simulate_imu
from recordings.sim.motion import ShipMotion
from recordings.sim.scenarios import SMALL_BOAT
from recordings.sim.simulate import NAV_FILE

DATA = Path(__file__).parent / "data"
BUNDLED = Path(__file__).resolve().parent.parent / "recordings" / "default"


def test_baseline_report_on_the_real_static_pair():
    report = baseline_report(DATA / "static_base.obs", DATA / "static_rover.obs",
                             DATA / "static.nav", as_json=True)
    doc = json.loads(json.dumps(to_json(report), allow_nan=False))  # strict JSON
    assert doc["surveyed"]["wrong_fixes"] == 0 and len(doc["per_epoch"]) == doc["epochs"]
    s = report.surveyed  # found beside the files as <stem>_position.txt
    assert s is not None and s.length == pytest.approx(0.990, abs=0.001)
    assert abs(s.length_error_m) < 0.01 and abs(s.azimuth_error_deg) < 0.5
    assert s.wrong_fixes == 0
    t = report.time_to_fix
    assert t.restarts == 6 and t.fixed == 6 and t.max_s <= 30.0
    assert report.fixed_fraction > 0.95 and len(report.per_epoch) == report.epochs
    for v in report.velocity.values():
        assert v.horizontal_rms_mps < 0.01 and v.epochs >= 100
    text = format_baseline_report(report)
    assert "wrong fixes 0" in text and "TDCP velocity" in text
    # one receiver's file given twice is no baseline (it read "fixed 100 %, length 0 m")
    with pytest.raises(ValueError, match="the same, epoch for epoch"):
        baseline_report(DATA / "static_base.obs", DATA / "static_base.obs", DATA / "static.nav")


def test_json_of_the_gnss_records():
    """Figures that do not exist are absent keys, not nulls; the velocity configurations are
    keys of the velocity object itself (the JSON of the dict-based reports before)."""
    assert to_json(BaselineRestart(start_gpst=1.0, time_to_fix_s=None)) == {
        "start_gpst": 1.0, "time_to_fix_s": None}
    assert to_json(BaselineRestart(2.0, 1.0, length=0.99, azimuth_deg=193.0, error_m=0.01)) == {
        "start_gpst": 2.0, "time_to_fix_s": 1.0, "length": 0.99, "azimuth_deg": 193.0,
        "error_m": 0.01}
    assert to_json(ReceiverVelocity(epochs=0)) == {"epochs": 0}
    stats = VelocityErrorStats(solved_fraction=0.0, horizontal_rms_mps=None,
                               vertical_rms_mps=float("nan"))
    velocity = ArrayVelocity(reduced_after_s=10.0, kept_satellites={"2 satellites": None},
                             configurations={"all satellites": {"loose": stats}})
    assert to_json(velocity) == {
        "reduced_after_s": 10.0, "kept_satellites": {"2 satellites": None},
        "all satellites": {"loose": {"solved_fraction": 0.0, "horizontal_rms_mps": None,
                                     "vertical_rms_mps": None}}}


def small_boat_recording(duration: float = 30.0, seed: int = 1) -> SimpleNamespace:
    """What ``recordings.format.load`` gives, without the video: simulated GNSS, IMU and
    reference of the small-boat scenario."""
    nav = read_nav(NAV_FILE)
    motion = ShipMotion(SMALL_BOAT, seed)
    antennas = SMALL_BOAT.antennas_body()
    start = SMALL_BOAT.start_gpst
    gnss, _ = simulate_gnss(SMALL_BOAT, lambda t, i: motion.point_position_ned(t, antennas[i]),
                            nav, start, duration, seed)
    imu, _, _ = simulate_imu(motion, SMALL_BOAT, seed, start)
    sel = imu.time <= start + duration + 1e-9
    imu.time, imu.gyro, imu.accel = imu.time[sel], imu.gyro[sel], imu.accel[sel]
    state = motion.state(imu.time - start)
    lat, lon, h = SMALL_BOAT.origin_llh_deg
    origin = np.array([np.radians(lat), np.radians(lon), h])
    reference = ReferenceTrajectory.from_ned(imu.time, state.position_ned, state.velocity_ned,
                                             np.degrees(state.euler), origin)
    manifest = SimpleNamespace(name="small-boat-test", origin_llh=origin,
                               origin_llh_deg=SMALL_BOAT.origin_llh_deg)
    return SimpleNamespace(gnss=gnss, nav=nav, imu=imu, reference=reference, manifest=manifest,
                           calibration=SimpleNamespace(antennas_body=antennas))


def test_compass_report_on_a_simulated_small_boat():
    rec = small_boat_recording()
    report = compass_report_for(rec, trials=3, as_json=True, hold_window_s=5.0)
    doc = json.loads(json.dumps(to_json(report), allow_nan=False))  # strict JSON
    assert len(doc["methods"]["fast"]["per_trial"]) == 3
    assert doc["velocity_error"]["3 satellites"]["tight filter"]["solved_fraction"] == 1.0
    fast = report.methods["fast"]
    assert report.trials == 3 and fast.fixed_within_1s == 1.0
    assert fast.wrong_fixes == 0 and fast.attitude_error_deg.heading_rms < 1.5
    assert report.methods["conventional"].fixed_within_10s == 1.0
    assert report.velocity_error is not None
    v = report.velocity_error.configurations
    assert v["all satellites"]["loose"].horizontal_rms_mps < 0.01
    assert v["all satellites"]["tight"].horizontal_rms_mps < 0.01
    for config in ("3 satellites", "2 satellites", "4 satellites, one per receiver"):
        assert v[config]["loose"].solved_fraction == 0.0  # loosely coupled cannot
        assert v[config]["tight filter"].solved_fraction == 1.0
    assert v["4 satellites, one per receiver"]["tight"].solved_fraction == 1.0
    assert v["3 satellites"]["tight filter"].horizontal_rms_mps < 0.05
    assert "attitude fix" in format_compass_report(report)


@pytest.mark.skipif(not (BUNDLED / "manifest.json").is_file(), reason="no bundled recording")
def test_compass_report_on_the_bundled_recording():
    report = compass_report(BUNDLED, trials=2, velocity=False, hold_window_s=3.0)
    assert report.methods["fast"].fixed_within_10s == 1.0
    assert report.methods["fast"].wrong_fixes == 0
    assert report.velocity_error is None and report.methods["fast"].per_trial is None


def test_cli_parsers():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    add_baseline_parser(sub)
    add_compass_parser(sub)
    args = parser.parse_args(["baseline", "a.obs", "b.obs", "n.nav", "--json"])
    assert (args.base, args.rover, args.nav, args.json) == ("a.obs", "b.obs", "n.nav", True)
    args = parser.parse_args(["compass", "rec", "--trials", "5", "--gps-only", "--sky-mask", "180"])
    assert (args.recording, args.trials, args.gps_only, args.sky_mask) == ("rec", 5, True, 180.0)
    assert callable(args.func)
