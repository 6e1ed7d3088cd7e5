"""Stream latency: several WebSocket clients watching one session in real time.

Starts ``berthing-aid serve`` in a subprocess (real fusion engine, 3-D viewer on), opens one
session at real-time pace (10 fps video), connects ``--clients`` stream clients (with
acknowledgement flow control) for ``--seconds`` and prints:

- frame-to-client latency p50 / p95 / max: client receive time minus ``processed_at`` (the
  server's wall time when the engine returned the frame's state; overlay + JPEG + queueing +
  transport) and minus ``sent_at`` (transport only);
- frames received per client and the frame rate;
- the engine's own per-frame time (``timing`` of the session) and how far it lags the clock;
- server CPU (% of one core, user + system) and RSS (max), read from /proc.

    .venv/bin/python benchmarks/stream_latency.py [RECORDING] [--clients 4] [--seconds 20]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time

import httpx
import numpy as np
from serverproc import (
    DEFAULT_RECORDING,
    recording_path,
    sample_server,
    serve,
    watch_frames,
)


def percentiles(values: list[float]) -> str:
    if not values:
        return "no frames"
    a = 1e3 * np.asarray(values)
    return (f"p50 {np.percentile(a, 50):6.1f} ms   p95 {np.percentile(a, 95):6.1f} ms   "
            f"max {a.max():6.1f} ms")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", nargs="?", default=str(DEFAULT_RECORDING))
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--speed", type=float, default=1.0, help="replay speed (10 fps at 1)")
    parser.add_argument("--no-viewer", action="store_true", help="without the 3-D viewer")
    args = parser.parse_args()
    recording = recording_path(args.recording)
    if recording is None:
        return 2

    with serve(recording, viewer=not args.no_viewer) as server, \
            httpx.Client(base_url=server.base, timeout=60) as http:
        name = http.get("/api/recordings").json()["default"]
        session = http.post("/api/sessions", json={"recording": name, "speed": args.speed,
                                                   "paused": True}).json()
        sid = session["id"]
        duration = min(args.seconds, session["duration_s"] / args.speed)
        url = f"{server.ws}/api/sessions/{sid}/stream"
        received: list[list[tuple[float, float, float]]] = [[] for _ in range(args.clients)]

        async def run() -> tuple[float, float, list[float]]:
            until = time.time() + duration + 0.5
            tasks = [asyncio.create_task(watch_frames(
                url, until, lambda h, now, out=out: out.append(
                    (now, h["processed_at"], h["sent_at"])))) for out in received]
            await asyncio.sleep(0.5)  # all connected
            http.post(f"/api/sessions/{sid}/control", json={"action": "play"})
            return await sample_server(server.pid, until, tasks)

        cpu, wall, rss = asyncio.run(run())
        status = http.get(f"/api/sessions/{sid}").json()
        http.delete(f"/api/sessions/{sid}")

    everything = [r for out in received for r in out]
    print(f"recording {recording.name}: {args.clients} clients, {duration:.1f} s at speed "
          f"{args.speed:g} (10 fps video), viewer {'off' if args.no_viewer else 'on'}")
    print(f"frames received per client: {[len(out) for out in received]} "
          f"(~{10 * args.speed * duration:.0f} expected); replay position {status['time_s']:.1f}"
          f" s, fell behind real time by {status['behind_s']:.1f} s, fusion phase "
          f"{(status['fusion'] or {}).get('phase')}")
    timing = status["timing_ms"]
    print("engine ms per call: " + ", ".join(f"{k} {v:.1f}" for k, v in sorted(timing.items())))
    print(f"latency engine-done → client: {percentiles([r - p for r, p, _ in everything])}")
    print(f"latency send → client:        {percentiles([r - s for r, _, s in everything])}")
    print(f"server CPU {100 * cpu / wall:5.1f} % of one core (user+system, "
          f"{os.cpu_count()} cores), RSS max {max(rss):.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
