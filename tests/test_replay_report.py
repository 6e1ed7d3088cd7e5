"""The ``replay --report`` experiments (evaluation/report.py) on the first 40 s of the
bundled small-boat recording, 20 s of initialisation: one report per module, checked against
tolerances a broken fusion fails; plus the bad inputs through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from backend.cli import main
from evaluation.records import ReplayReport, to_json
from evaluation.report import ReportOptions, replay_report
from evaluation.text import format_replay_report
from recordings.format import load

BUNDLED = Path(__file__).resolve().parent.parent / "recordings" / "default"


@pytest.fixture(scope="module")
def typed(tmp_path_factory: pytest.TempPathFactory) -> ReplayReport:
    plots = tmp_path_factory.mktemp("replay-plots")
    return replay_report(BUNDLED, ReportOptions(init_s=20.0, end_s=40.0, subset_sizes=(3, 0),
                                                single_satellites=2, without_cpp=False,
                                                plots_dir=plots))


@pytest.fixture(scope="module")
def report(typed: ReplayReport) -> dict:
    """The report as its JSON (what ``--json`` prints)."""
    return json.loads(json.dumps(to_json(typed), allow_nan=False))


def test_tracking_and_landmark_evaluations_are_part_of_the_report(report: dict,
                                                                 typed: ReplayReport) -> None:
    # Early in the berthing no quay point is 12-28 m away: the section says so, not a figure.
    assert isinstance(report["tracking"]["methods"], dict)
    assert report["tracking"]["methods"] or report["tracking"]["reason"]
    assert "error_vs_views" in report["landmarks"]
    assert "Designated-target tracking" in format_replay_report(typed)


def test_json_shape_is_stable_and_strict(report: dict) -> None:
    doc = report
    for key in ("recording", "methods", "satellite_subsets", "clock_drift",
                "single_satellite_heading", "structure", "realtime_factor", "timing_ms"):
        assert key in doc, key
    assert list(doc["methods"]) == ["INS", "VO", "INS+VO", "INS+VO+CPP"]
    for m in doc["methods"].values():
        assert {"horizontal_std_m", "horizontal_max_m"} <= set(m)
    for s in doc["satellite_subsets"]:
        assert {"n_satellites", "satellites", "loose", "tight"} <= set(s)
        assert len(s["satellites"]) == s["n_satellites"]
        for mode in ("loose", "tight"):
            assert {"velocity_std_mps", "horizontal_std_m", "heading_std_deg",
                    "misleading_epochs"} <= set(s[mode])
    assert {"common", "separate"} <= set(doc["clock_drift"])
    assert {"bands", "median_m", "p90_m"} <= set(doc["structure"])
    assert len(doc["structure"]["bands"]) == 4
    assert doc["realtime_factor"] > 0 and doc["timing_ms"]["vo"] > 0
    assert doc["window_s"] == pytest.approx([20.0, 40.0], abs=1.0)


def test_fusion_beats_its_parts(report: dict) -> None:
    m = report["methods"]
    full = m["INS+VO+CPP"]
    assert full["coverage"] > 0.95
    assert full["horizontal_std_m"] < 0.05 and full["horizontal_max_m"] < 0.2
    assert full["heading_std_deg"] < 0.3
    # Without carrier phase after the initialisation the INS drifts; the VO holds it better.
    assert m["INS"]["horizontal_max_m"] > 5 * full["horizontal_max_m"]
    assert m["INS"]["horizontal_std_m"] > 5 * full["horizontal_std_m"]
    assert m["VO"]["coverage"] > 0.8 and m["VO"]["horizontal_std_m"] is not None
    assert m["INS+VO"]["horizontal_max_m"] < m["INS"]["horizontal_max_m"]


def test_satellite_subsets_and_clock_drift(report: dict) -> None:
    by_n = {s["n_satellites"]: s for s in report["satellite_subsets"]}
    assert set(by_n) == {3, 0}
    three, none = by_n[3], by_n[0]
    assert len(set(three["satellites"])) == 3 and none["satellites"] == []
    # Three satellites: the η rows still give a velocity, the loose one cannot (< 4 per
    # receiver), so the tight trajectory is far better than dead reckoning.
    assert three["tight"]["horizontal_std_m"] < 0.5 * none["tight"]["horizontal_std_m"]
    assert three["tight"]["velocity_std_mps"] < three["loose"]["velocity_std_mps"]
    # ... and neither is ever confident and wrong (scored as the main run's integrity)
    assert three["tight"]["misleading_epochs"] == none["tight"]["misleading_epochs"] == 0
    cd = report["clock_drift"]
    assert len(set(cd["satellite_per_receiver"].values())) == 4
    assert cd["common"]["horizontal_std_m"] < 0.1
    assert cd["common"]["horizontal_std_m"] < 0.3 * cd["separate"]["horizontal_std_m"]


def test_single_satellite_heading(report: dict) -> None:
    ss = report["single_satellite_heading"]
    assert len(ss["satellites"]) == 2  # the first two of the best five
    for e in ss["satellites"]:
        assert set(e["heading_std_deg"]) == {"all six", "0-1", "0-2", "0-3", "1-2", "1-3", "2-3"}
        assert e["updates"]["all six"] > 10
        assert e["heading_std_deg"]["all six"] < 0.5
        assert e["pipeline_all_baselines_std_deg"] < 0.5
    # One epoch, one satellite: all six baselines beat the worst single one.
    assert ss["worst_all_six_snapshot_std_deg"] < ss["worst_single_baseline_snapshot_std_deg"]


def test_structure_and_plots(report: dict, typed: ReplayReport) -> None:
    st = report["structure"]
    assert st["points"] > 100 and st["matched"] > 20
    assert sum(b["points"] for b in st["bands"]) == st["points"]
    assert st["median_m"] < 2.0
    written = {Path(p).name for p in report["plots"]}
    for name in ("trajectories", "horizontal_error", "heading_error", "structure"):
        assert f"{name}.png" in written
        png = Path(report["plots"][0]).parent / f"{name}.png"
        assert png.is_file() and png.read_bytes()[:4] == b"\x89PNG"
    text = format_replay_report(typed)
    for needle in ("table 17", "tables 18-20", "table 21", "fig. 14", "structure",
                   "realtime factor"):
        assert needle in text


def test_recording_without_reference_is_an_error(tmp_path: Path, capsys) -> None:
    rec = tmp_path / "no-reference"
    rec.mkdir()
    for item in BUNDLED.iterdir():
        if item.name not in ("manifest.json", "reference"):
            (rec / item.name).symlink_to(item)
    manifest = json.loads((BUNDLED / "manifest.json").read_text())
    manifest["files"]["reference"] = manifest["files"]["scene_points"] = None
    (rec / "manifest.json").write_text(json.dumps(manifest))
    assert load(rec, load_gnss=False).reference is None
    assert main(["replay", str(rec), "--report", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no reference trajectory" in err
    # Without --report there is nothing to do: a clear error too.
    assert main(["replay", str(BUNDLED)]) == 2
    assert "--report" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "missing"), "--report", "--quiet"]) == 2


def test_window_beyond_the_recording_is_an_error() -> None:
    with pytest.raises(ValueError, match="no window"):
        replay_report(BUNDLED, ReportOptions(init_s=20.0, end_s=15.0))


def test_quay_foot_clicks_lie_on_the_true_quay_foot(sim_recording: Path) -> None:
    """The berth benchmark's and the page test's clicks (``evaluation.truth.quay_foot_clicks``):
    seen from the true camera, each click's ray meets the water on the recording's berth line,
    and the bow is nearer the line than the ship's centre on her approach."""
    import cv2
    import numpy as np

    from evaluation.truth import quay_foot_clicks, rebuild_scene, true_cameras

    rec = load(sim_recording)
    t = float(rec.manifest.start_gpst) + 10.0
    seen = quay_foot_clicks(rec, t)
    assert seen is not None
    clicks, bow = seen
    cam = rec.calibration.camera
    truth = true_cameras(rec, np.array([t]), None)
    line = np.asarray(rec.hull.berth_line_ned, float)
    d = (line[1] - line[0]) / np.linalg.norm(line[1] - line[0])

    def across(p: np.ndarray) -> float:
        return abs(d[0] * (p[1] - line[0, 1]) - d[1] * (p[0] - line[0, 0]))

    for u, v in clicks:
        xy = cv2.undistortPoints(np.array([[[u, v]]], float), np.asarray(cam.K, float),
                                 np.asarray(cam.distortion, float)).reshape(2)
        ray = truth.C_level_to_camera[0].T @ np.array([xy[0], xy[1], 1.0])
        c = truth.position[0]
        hit = c + (0.0 - c[2]) / ray[2] * ray  # the water: down 0 in the reference frame
        off = across(hit[:2])
        assert off < 0.05, (u, v, off)  # on the line (exact projections: no pixel rounding)
    pos = rec.reference.interpolate(t)[0]
    assert 0.0 < bow < across(pos[:2])
    assert rebuild_scene(rec) is not None  # the visibility check ran against the scene


def test_a_click_on_a_nearer_silhouette_has_no_far_truth() -> None:
    """``evaluation.truth.clickable``: a quay point is the truth of a click on it when it shows
    in the click's 3x3 pixels and nothing nearer does. The background beside a quay edge
    keeps it; a moored boat's corner before it does not (the click takes the boat, the
    nearest surface), nor does a point hidden altogether."""
    import numpy as np

    from evaluation.truth import clickable

    depth = np.full((9, 9), 200.0)  # far buildings
    depth[4:, :] = 20.0  # the quay face from row 4 down; its top edge at row 4
    uv = np.array([4.0, 4.0])
    assert clickable(depth, uv, 20.0)  # on the edge, the far background above: clickable
    boat = depth.copy()
    boat[4:, 5:] = 19.2  # a moored hull 0.8 m before the quay, its corner next to the click
    assert not clickable(boat, uv, 20.0)
    assert clickable(boat, np.array([2.0, 6.0]), 20.0)  # clear of the hull: clickable again
    assert not clickable(depth, uv, 25.0)  # hidden behind the quay face
    assert not clickable(depth, np.array([0.0, 4.0]), 20.0)  # at the image border


def test_sigma_cover_counts_a_point_between_two_surfaces_as_wrong() -> None:
    """``evaluation.landmarks._sigma_cover``: a structure point is covered when its depth is
    within 2σ of the rendered truth — on a depth edge, of either surface; a phantom between
    the quay's coping (10 m) and the building behind it (20 m) is wrong for both."""
    import numpy as np

    from evaluation.landmarks import _sigma_cover
    from evaluation.truth import Truth

    # One camera at the origin looking north (its z along north).
    C = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    truth = Truth(C[None], np.zeros((1, 3)), np.zeros(3))
    lt = {1: (0, 10.0, np.array([10.0, 0, 0])), 2: (0, 10.0, np.array([10.0, 0, 0])),
          3: (0, 40.0, np.array([40.0, 0, 0]))}
    edges = {4: (0, 10.0, 20.0), 5: (0, 10.0, 20.0)}
    X = np.array([[10.15, 0, 0], [10.5, 0, 0], [40.0, 0, 0], [15.0, 0, 0], [19.0, 0, 0]])
    sigma = np.array([0.1, 0.1, 0.1, 1.0, 1.0])
    cover = _sigma_cover(lt, edges, truth, np.arange(1, 6), X, sigma, np.zeros(3))
    # point 3 is beyond 30 m of the camera: left out
    assert (cover.points, cover.edge_points, cover.beyond_3sigma) == (4, 2, 2)
    assert cover.within_2sigma == 0.5 and cover.edge_within_2sigma == 0.5
    assert abs(cover.worst_ratio - 5.0) < 1e-9
