"""The campaign (evaluation/campaign.py): tasks on a local Dask cluster and on a two-worker
``dask scheduler`` / ``dask worker`` cluster on loopback give the same summary; a failing task
is recorded and the rest goes on; a second run with the same output skips what is done."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from evaluation.campaign import (
    CampaignSpec,
    Task,
    figure_value,
    parse_faults,
    parse_seeds,
    run_campaign,
    spec_from_args,
    summary_differences,
)

# One short recording (simulated once, shared through the cache), clean and damaged; one task
# whose fault cannot be injected (an offset beyond the video): its error is recorded.
SPEC = CampaignSpec(["small-boat"], [5], duration_s=12.0,
                    faults=[None, "imu-gap:6:1", "video-zeroed:999"], tracking=False,
                    quick=True)


def test_seeds_faults_and_options_are_checked() -> None:
    assert parse_seeds("1-3,7,9-10") == [1, 2, 3, 7, 9, 10]
    assert parse_faults("all")[0] is None and "imu-gap" in parse_faults("all")
    assert parse_faults("clean,clock-jump:5") == [None, "clock-jump:5"]
    for bad, msg in ((dict(seeds="3-1"), "backwards"), (dict(seeds="a"), "numbers"),
                     (dict(scenarios="tanker"), "unknown"), (dict(faults="imu-holes"),
                                                              "unknown fault"),
                     (dict(options="{"), "not JSON"), (dict(options='{"speed": 1}'),
                                                      "unknown FusionOptions")):
        args = dict(scenarios="small-boat", seeds="1", duration=None, faults=None, options=None,
                    tracking=False) | bad
        with pytest.raises(ValueError, match=msg):
            spec_from_args(**args)
    task = Task("small-boat", 3, 60.0, "imu-gap:40:5")
    assert task.key == "small-boat-seed3-60s-imu-gap_40_5"
    assert task.recording_key.startswith("small-boat-seed3-60s-sim")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def local(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    cache = tmp_path_factory.mktemp("cache")
    out = tmp_path_factory.mktemp("local")
    return cache, out, run_campaign(SPEC, out, cache=cache, workers=2, show_progress=False)


def test_local_campaign_records_results_and_errors(local: tuple[Path, Path, dict]) -> None:
    _cache, out, summary = local
    assert summary["tasks"] == 3 and summary["succeeded"] == 2
    (bad_key, error), = summary["failed"].items()
    assert bad_key.endswith("video-zeroed_999") and "beyond the video" in error
    clean = json.loads((out / "tasks" / "small-boat-seed5-12s-clean.json").read_text())
    gap = json.loads((out / "tasks" / "small-boat-seed5-12s-imu-gap_6_1.json").read_text())
    assert figure_value(clean["report"], "methods.INS+VO+CPP.horizontal_std_m") < 0.05
    assert "imu-gap" in {a["kind"] for a in gap["report"]["integrity"]["alerts"]}
    assert gap["report"]["integrity"]["misleading_epochs"] == 0
    fig = summary["figures"]["methods.INS+VO+CPP.horizontal_max_m"]
    assert fig["tasks"] == 2 and fig["worst"] >= fig["median"]
    assert fig["worst_task"] in ("small-boat-seed5-12s-clean", "small-boat-seed5-12s-imu-gap_6_1")
    assert "imu-gap" in summary["by_fault"]["imu-gap:6:1"]["alerts_raised"]
    md = (out / "summary.md").read_text()
    assert "| methods.INS+VO+CPP.horizontal_std_m |" in md and "## Failed tasks" in md


def test_a_second_run_skips_what_is_done(local: tuple[Path, Path, dict],
                                         tmp_path: Path) -> None:
    cache, first, summary = local
    # in a copy: the first output stays as it was for the cluster test's comparison
    out = shutil.copytree(first, tmp_path / "again")
    stamp = (out / "tasks" / "small-boat-seed5-12s-clean.json").stat().st_mtime
    tic = time.monotonic()
    again = run_campaign(CampaignSpec(**{**SPEC.__dict__, "faults": [None, "imu-gap:6:1"]}),
                         out, cache=cache, workers=1, show_progress=False)
    assert time.monotonic() - tic < 20  # nothing simulated or evaluated again
    assert (out / "tasks" / "small-boat-seed5-12s-clean.json").stat().st_mtime == stamp
    assert again["figures"] == {k: v for k, v in summary["figures"].items()}


def _wait_for_port(port: int, proc: subprocess.Popen, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        assert proc.poll() is None, "the dask scheduler exited"
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            assert time.monotonic() < deadline, f"no dask scheduler on port {port}"
            time.sleep(0.2)


def test_a_loopback_dask_cluster_gives_the_same_summary(local: tuple[Path, Path, dict],
                                                       tmp_path: Path) -> None:
    cache, local_out, summary = local
    port = _free_port()
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host",
                               "127.0.0.1", "--port", str(port), "--no-dashboard"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        _wait_for_port(port, procs[0])  # a loaded machine takes its time to import dask
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", f"tcp://127.0.0.1:{port}",
             "--nworkers", "2", "--nthreads", "1", "--no-dashboard", "--memory-limit", "3GiB"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        out = tmp_path / "cluster"
        remote = run_campaign(SPEC, out, cache=cache, scheduler=f"tcp://127.0.0.1:{port}",
                              show_progress=False)
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=30)
    assert remote["succeeded"] == summary["succeeded"] == 2
    assert summary_differences(remote, summary) == []
    # As a user checks it: the command compares the two output directories.
    done = subprocess.run([sys.executable, "-m", "backend.cli", "campaign-compare", str(out),
                           str(local_out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "0 difference(s)" in done.stdout


def test_summary_differences_tolerate_rounding_not_real_changes() -> None:
    fig = {"tasks": 2, "median": 0.1234, "p90": 0.2, "worst": 0.3, "worst_task": "b"}
    a = {"tasks": 2, "succeeded": 2, "failed": {}, "figures": {"x": fig}, "by_fault": {},
         "timing": {"realtime_factor": {"median": 3.0}}}
    close = {**a, "figures": {"x": {**fig, "median": 0.1234 * (1 + 3e-10)}},
             "timing": {"realtime_factor": {"median": 2.0}}}
    assert summary_differences(a, close) == []
    moved = {**a, "figures": {"x": {**fig, "median": 0.1235}}}
    other_worst = {**a, "figures": {"x": {**fig, "worst_task": "c"}}}
    failed = {**a, "failed": {"c": "boom"}}
    assert summary_differences(a, moved) == ["figures.x.median: 0.1234 != 0.1235"]
    assert summary_differences(a, other_worst) == ["figures.x.worst_task: 'b' != 'c'"]
    assert summary_differences(a, failed) == ["failed: [] != ['c']"]
