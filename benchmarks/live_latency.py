"""Live latency: camera frame → browser, for a live session fed by the emulator at 10 fps.

Plays a recording through ``live.emulator.Emulator`` in this process (four UBX TCP receivers,
the text IMU over UDP, the camera as HTTP MJPEG at the recording's 10 fps), starts
``berthing-aid serve --live CONFIG`` in a subprocess (the live session records as it runs),
connects ``--clients`` WebSocket stream clients (acknowledgement flow control, as the page)
for ``--seconds`` and prints, over every frame every client received:

- **camera → browser**: client receive time minus the time the emulated camera published the
  frame (the frame is matched by its GNSS time to the camera's nearest frame), p50 / p95 / max;
- split into camera → engine done (MJPEG transport, time alignment, the fusion's queue and
  ``process_frame``) and engine done → browser (overlay + JPEG + WebSocket);
- frames received per client, frames the live session skipped because its engine was behind,
  server CPU (% of one core) and RSS (max).

Every clock is this machine's wall clock (emulator, server and clients share it).

    .venv/bin/python benchmarks/live_latency.py [RECORDING] [--clients 4] [--seconds 60]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
from serverproc import (
    DEFAULT_RECORDING,
    ROOT,
    recording_path,
    sample_server,
    serve,
    watch_frames,
)
from stream_latency import percentiles

sys.path.insert(0, str(ROOT))
from live.emulator import Emulator  # noqa: E402
from recordings.format import load  # noqa: E402


def published_at(published: list[tuple[float, float]], gpst: np.ndarray) -> np.ndarray:
    """The camera's publish time of the frame nearest to each ``gpst`` (NaN beyond 50 ms)."""
    t = np.array([p[0] for p in published])
    wall = np.array([p[1] for p in published])
    i = np.clip(np.searchsorted(t, gpst), 1, len(t) - 1)
    nearest = np.where(np.abs(t[i - 1] - gpst) <= np.abs(t[i] - gpst), i - 1, i)
    return np.where(np.abs(t[nearest] - gpst) <= 0.05, wall[nearest], np.nan)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", nargs="?", default=str(DEFAULT_RECORDING))
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=60.0,
                        help="measured span (after the session's first pose)")
    parser.add_argument("--json", action="store_true", help="the figures as JSON")
    args = parser.parse_args()
    recording = recording_path(args.recording)
    if recording is None:
        return 2
    rec = load(recording)
    emulator = Emulator(rec)
    with tempfile.TemporaryDirectory(prefix="live-latency-") as work:
        config = Path(work) / "live.toml"
        config.write_text(emulator.config_text(record_dir=Path(work) / "recorded"),
                          encoding="utf-8")
        emulator.start()
        try:
            with serve(recording, viewer=False, extra=("--live", str(config))) as server, \
                    httpx.Client(base_url=server.base, timeout=30) as http:
                result = measure(server, http, emulator, args)
        finally:
            emulator.stop()
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"recording {recording.name} emulated live at 10 fps; {args.clients} clients, "
          f"{result['seconds']:.1f} s measured")
    print(f"frames received per client: {result['frames_per_client']} "
          f"(camera published {result['camera_frames']}); the live session skipped "
          f"{result['skipped_frames']} (engine behind)")
    for key, label in (("camera_to_browser", "camera → browser:      "),
                       ("camera_to_engine_done", "camera → engine done:  "),
                       ("engine_done_to_browser", "engine done → browser: ")):
        print(label + result[key]["text"])
    print("engine ms per call: " + ", ".join(f"{k} {v}" for k, v in result["engine_ms"].items()))
    print(f"server CPU {result['cpu_percent']:.1f} % of one core, RSS max "
          f"{result['rss_max_mb']:.0f} MB")
    return 0


def measure(server, http: httpx.Client, emulator: Emulator, args: argparse.Namespace) -> dict:
    sessions = http.get("/api/sessions").json()["sessions"]
    sid = next(s["id"] for s in sessions if s["live"] is not None)
    deadline = time.monotonic() + 120
    while http.get(f"/api/sessions/{sid}").json()["frames_processed"] == 0:  # frames flow
        if time.monotonic() > deadline:
            raise RuntimeError("the live session processed no frame in 120 s")
        time.sleep(0.2)
    remaining = emulator.end_gpst - emulator.rec.manifest.start_gpst
    if emulator.clock.start is not None:
        remaining -= time.monotonic() - emulator.clock.start
    seconds = max(1.0, min(args.seconds, remaining - 1.0))
    url = f"{server.ws}/api/sessions/{sid}/stream"
    received: list[list[tuple[float, float, float]]] = [[] for _ in range(args.clients)]

    async def run() -> tuple[float, float, list[float]]:
        until = time.time() + seconds
        def keep(out: list) -> Callable[[dict, float], None]:
            def on_frame(header: dict, now: float) -> None:
                if header["pose"] is not None:  # (received, gpst, processed_at)
                    out.append((now, header["pose"]["gpst"], header["processed_at"]))
            return on_frame

        tasks = [asyncio.create_task(watch_frames(url, until, keep(out))) for out in received]
        return await sample_server(server.pid, until, tasks)

    cpu, wall, rss = asyncio.run(run())
    status = http.get(f"/api/sessions/{sid}").json()
    live = status["live"]
    rows = np.array([r for out in received for r in out])
    sent = published_at(list(emulator.camera.published), rows[:, 1])
    ok = np.isfinite(sent)

    def figure(values: np.ndarray) -> dict:
        return {"p50_ms": round(float(np.percentile(1e3 * values, 50)), 1),
                "p95_ms": round(float(np.percentile(1e3 * values, 95)), 1),
                "max_ms": round(float(1e3 * values.max()), 1),
                "text": percentiles(list(values))}

    return {
        "seconds": seconds, "frames_per_client": [len(out) for out in received],
        "camera_frames": len(emulator.camera.published), "matched": int(ok.sum()),
        "skipped_frames": live["skipped_frames"],
        "camera_to_browser": figure(rows[ok, 0] - sent[ok]),
        "camera_to_engine_done": figure(rows[ok, 2] - sent[ok]),
        "engine_done_to_browser": figure(rows[:, 0] - rows[:, 2]),
        "cpu_percent": 100 * cpu / wall, "rss_max_mb": max(rss),
        "engine_ms": {k: round(v, 1) for k, v in sorted(status["timing_ms"].items())},
    }


if __name__ == "__main__":
    sys.exit(main())
