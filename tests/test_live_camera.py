"""Camera input (live.camera) and the emulator's MJPEG camera (live.mjpeg).

The server runs in another process, as a network camera does (OpenCV holds the GIL while it
opens a stream, so an in-process server could not answer it). Frames are the bundled
recording's video.
"""

from __future__ import annotations

import itertools
import multiprocessing
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import recordings
from live.camera import CameraError, CameraSource, CameraStalled
from live.mjpeg import MjpegServer

RECORDING = Path(__file__).parents[1] / "recordings" / "default"
N_SERVED = 25  # 2.5 s of 10 fps video


def _serve(port_queue, stop_event) -> None:
    rec = recordings.load(RECORDING, load_gnss=False)
    rec.frame_times = rec.frame_times[:N_SERVED]  # the recording's first 2.5 s only
    server = MjpegServer.for_recording(rec).start()
    port_queue.put(server.url)
    stop_event.wait(30)
    server.stop()


@pytest.fixture(scope="module")
def originals() -> list[np.ndarray]:
    rec = recordings.load(RECORDING, load_gnss=False)
    return [img for _, _, img in itertools.islice(rec.frames(), N_SERVED)]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(float) - b.astype(float)) ** 2)
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def test_mjpeg_camera_frames_times_and_stall(originals):
    ctx = multiprocessing.get_context("spawn")
    urls, stop = ctx.Queue(), ctx.Event()
    proc = ctx.Process(target=_serve, args=(urls, stop), daemon=True)
    proc.start()
    try:
        url = urls.get(timeout=30)
        base = time.monotonic()
        clock = lambda: 1.4e9 + (time.monotonic() - base)  # a gpst clock for the test
        cam = CameraSource(url, latency_s=0.08, clock=clock, read_timeout_s=1.0)
        got, arrivals = [], []
        with pytest.raises(CameraStalled) as stalled:
            for frame in cam:
                arrivals.append(clock())
                got.append(frame)
                if len(got) == 12:
                    stop.set()  # the camera is switched off
                    stop_time = time.monotonic()
        waited = time.monotonic() - stop_time
    finally:
        stop.set()
        proc.join(10)
    assert "stalled" in str(stalled.value) and cam.status.startswith("stalled")
    assert waited < 1.0 + 2.5  # reported within the read timeout (+ slack), no hang
    assert len(got) >= 12
    # each frame is one of the recording's, in order, through JPEG (quality 90)
    matches = []
    for f in got[:12]:
        scores = [psnr(f.image, o) for o in originals]
        best = int(np.argmax(scores))
        assert scores[best] > 30.0
        matches.append(best)
    assert np.all(np.diff(matches) == 1)
    assert [f.index for f in got] == list(range(len(got)))
    # HTTP MJPEG has no timestamps: reception time minus the configured latency
    t = np.array([f.t for f in got[:12]])
    np.testing.assert_allclose(t, np.array(arrivals[:12]) - 0.08, atol=0.02)
    assert np.median(np.diff(t)) == pytest.approx(0.1, abs=0.02)


def test_video_file_uses_stream_timestamps():
    video = RECORDING / "video.mp4"
    cam = CameraSource(str(video), latency_s=0.05, clock=lambda: 1.4e9)
    frames = list(itertools.islice(cam, 15))
    t = np.array([f.t for f in frames])
    assert t[0] == pytest.approx(1.4e9 - 0.05)
    np.testing.assert_allclose(np.diff(t), 0.1, atol=1e-3)  # the file's 10 fps pts
    assert cam.timestamps == "stream" and cam.reanchors == 0
    assert frames[0].image.shape == (600, 960, 3)
    assert cv2.mean(frames[3].image)[0] > 0


def test_unreachable_camera_is_an_error_not_a_hang():
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    start = time.monotonic()
    with pytest.raises(CameraError, match="cannot open"):
        next(iter(CameraSource(f"http://127.0.0.1:{port}/stream.mjpg", open_timeout_s=2)))
    assert time.monotonic() - start < 5
    with pytest.raises(CameraError, match="no such file"):
        next(iter(CameraSource("/nonexistent/video.mp4")))
