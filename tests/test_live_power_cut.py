"""A live recording cut by power loss loads up to the cut.

A subprocess writes the 12 s simulated recording through ``live.recorder.LiveRecorder`` at
twice real time, as a live session does, and is killed with SIGKILL part way (no ``close``,
no ``finally``). The directory must load and replay up to the cut. Then the last writes are
torn as a power cut can leave them (the page cache lost mid-record: a CSV line, an observation
epoch and a JPEG cut short) and it must still load, with what was torn noted.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

FEEDER = """
import sys, time
from engine.messages import sensor_messages
from live.recorder import LiveRecorder
from recordings.format import load

rec = load(sys.argv[1])
writer = LiveRecorder(sys.argv[2], name="cut", calibration=rec.calibration, hull=rec.hull,
                      origin_llh_deg=tuple(rec.manifest.origin_llh_deg))
start, t0 = time.monotonic(), rec.manifest.start_gpst
for msg in sensor_messages(rec):
    delay = start + (msg.t - t0) / 2 - time.monotonic()
    if delay > 0:
        time.sleep(delay)
    writer.write(msg, rec.nav)
    print(f"{msg.t - t0:.3f}", flush=True)
"""

CUT_AT_S = 8.0  # recording seconds written when the power goes


@pytest.fixture(scope="module")
def cut_recording(sim_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cut") / "recorded"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-c", FEEDER, str(sim_recording), str(out)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    deadline = time.monotonic() + 120
    assert proc.stdout is not None
    for line in proc.stdout:
        if float(line) >= CUT_AT_S:
            break
        assert time.monotonic() < deadline, "the writer is too slow"
    else:
        pytest.fail(f"the writer ended before the cut: {proc.stderr.read()}")
    proc.send_signal(signal.SIGKILL)  # power loss: no close, no finally, no atexit
    proc.wait(10)
    return out


def _replay_all(path: Path) -> tuple[object, int, int]:
    from engine.messages import FrameMessage, sensor_messages
    from recordings.format import load

    rec = load(path)
    frames = imu = 0
    for msg in sensor_messages(rec):
        if isinstance(msg, FrameMessage):
            assert msg.image is not None and msg.image.shape[:2] == (
                rec.calibration.camera.height, rec.calibration.camera.width)
            frames += 1
        else:
            imu += 1
    return rec, frames, imu


def test_killed_live_recording_loads_up_to_the_cut(cut_recording: Path):
    manifest = json.loads((cut_recording / "manifest.json").read_text())
    assert manifest["live"]["complete"] is False
    # the manifest was synced at least once a second of wall time (2 s of recording)
    assert CUT_AT_S - 2.5 <= manifest["duration_s"] <= CUT_AT_S + 0.5
    rec, frames, other = _replay_all(cut_recording)
    assert 10 * (CUT_AT_S - 0.5) <= frames <= 10 * (CUT_AT_S + 0.5)
    assert len(rec.frame_times) == frames
    assert len(rec.imu.time) >= 100 * (CUT_AT_S - 0.5)
    assert all(len(epochs) >= CUT_AT_S - 1 for epochs in rec.gnss)
    assert other >= len(rec.imu.time)


def test_torn_last_writes_load_with_a_note(cut_recording: Path, tmp_path: Path):
    from recordings.format import load

    torn = tmp_path / "torn"
    shutil.copytree(cut_recording, torn)
    whole = load(cut_recording)

    def chop(rel: str, nbytes: int) -> None:
        path = torn / rel
        data = path.read_bytes()
        path.write_bytes(data[:-nbytes])

    chop("imu.csv", 25)  # mid-line
    chop("frames.csv", 4)
    chop("video.mjpeg", 4000)  # mid-JPEG
    chop(whole.manifest.files["gnss_obs"][1], 150)  # mid-epoch
    rec, frames, _ = _replay_all(torn)
    assert len(rec.imu.time) == len(whole.imu.time) - 1
    assert frames >= len(whole.frame_times) - 2
    assert len(rec.gnss[1]) >= len(whole.gnss[1]) - 1
    assert len(rec.gnss[0]) == len(whole.gnss[0])
    cut = [w for w in rec.warnings if "cut short" in w]
    named = {"imu.csv", "frames.csv", "video.mjpeg", whole.manifest.files["gnss_obs"][1]}
    assert {n for n in named if any(w.startswith(n) for w in cut)} == named, rec.warnings


def test_a_truncated_file_of_a_finished_recording_is_still_an_error(cut_recording: Path,
                                                                    tmp_path: Path):
    """Only a live recording that did not end cleanly is read up to a torn end: in any other
    recording a file cut short is damage, and loading says so — and so does the listing's
    check, which reads no data (a user trial: a cut file listed fine, refused on open)."""
    from recordings.format import RecordingError, check_manifest, load

    done = tmp_path / "done"
    shutil.copytree(cut_recording, done)
    manifest = json.loads((done / "manifest.json").read_text())
    manifest["live"]["complete"] = True
    (done / "manifest.json").write_text(json.dumps(manifest))
    (done / "imu.csv").write_bytes((done / "imu.csv").read_bytes()[:-25])
    for check in (load, check_manifest):
        with pytest.raises(RecordingError, match=r"imu\.csv: ends inside a line, the file was "
                                                 r"cut short"):
            check(done)


def test_a_receiver_that_never_delivered_leaves_a_readable_recording(sim_recording: Path,
                                                                     tmp_path: Path):
    """Receiver 4 connected but silent from the start: its observation file is written with
    its header alone, so the recording loads (the other receivers' epochs all there) and says
    the receiver had none. Without it the manifest named a file that did not exist and the
    whole recording was refused (a second user trial)."""
    import dataclasses

    from engine.messages import GnssMessage, sensor_messages
    from live.recorder import LiveRecorder
    from recordings.format import load, summary

    rec = load(sim_recording)
    out = tmp_path / "recorded"
    writer = LiveRecorder(out, name="rx4-silent", calibration=rec.calibration, hull=rec.hull,
                          origin_llh_deg=tuple(rec.manifest.origin_llh_deg))
    for msg in sensor_messages(rec):
        if isinstance(msg, GnssMessage):
            msg = dataclasses.replace(msg, epochs=(*msg.epochs[:3], None))
        writer.write(msg, rec.nav)
    writer.close()
    got = load(out)
    assert [len(e) for e in got.gnss[:3]] == [len(e) for e in rec.gnss[:3]]
    assert len(got.gnss[3]) == 0
    assert summary(got)["gnss"]["receivers"][3]["epochs"] == 0
    assert any("rx4.obs: no epochs" in w for w in got.warnings)
    replayed = [m for m in sensor_messages(got, frames=False) if isinstance(m, GnssMessage)]
    assert len(replayed) == len(rec.gnss[0]) and all(m.epochs[3] is None for m in replayed)
