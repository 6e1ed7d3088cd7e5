"""Seek time: how long a seek takes through the server, anywhere in a recording.

Starts ``berthing-aid serve`` in a subprocess (real fusion engine, 3-D viewer off), creates a
session paused at the start and waits while the look-ahead engine (the scout) runs through the
recording (prints how long it took). Then seeks to a fixed list of targets spread over the
recording, forward and backward, first paused, then playing at real time, and prints for each
the wall time from the request until the session stands at the target (paused: state
``paused`` at or after it; playing: a frame at or after it shown), and the worst.

    .venv/bin/python benchmarks/seek_time.py [RECORDING] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import httpx
from serverproc import DEFAULT_RECORDING, recording_path, serve

# fractions of the recording, in this order: far forward, back, near, far back, ...
TARGETS = (0.95, 0.05, 0.5, 0.55, 0.2, 0.8, 0.33, 0.99, 0.01, 0.66)


def seek(http: httpx.Client, sid: str, t: float, playing: bool, timeout: float = 120.0
         ) -> float:
    """Seconds from the seek request until the session stands at ``t``."""
    start = time.monotonic()
    http.post(f"/api/sessions/{sid}/control", json={"action": "seek", "time": t})
    while time.monotonic() - start < timeout:
        s = http.get(f"/api/sessions/{sid}").json()
        if s["state"] == ("playing" if playing else "paused") and t - 0.11 <= s["time_s"]:
            if playing or s["time_s"] <= t + 0.2:
                return time.monotonic() - start
        time.sleep(0.02)
    raise RuntimeError(f"the seek to {t:.1f} s did not end in {timeout:.0f} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", nargs="?", default=str(DEFAULT_RECORDING))
    parser.add_argument("--json", action="store_true", help="the figures as JSON")
    args = parser.parse_args()
    recording = recording_path(args.recording)
    if recording is None:
        return 2
    result: dict = {"recording": recording.name}
    with serve(recording, viewer=False) as server, \
            httpx.Client(base_url=server.base, timeout=60) as http:
        name = http.get("/api/recordings").json()["default"]
        t0 = time.monotonic()
        session = http.post("/api/sessions", json={"recording": name, "speed": 1,
                                                   "paused": True}).json()
        sid, duration = session["id"], session["duration_s"]
        while True:
            s = http.get(f"/api/sessions/{sid}").json()
            if s["scouted_s"] is not None and s["scouted_s"] >= duration - 0.2:
                break
            if time.monotonic() - t0 > 600:
                raise RuntimeError(f"the scout got to {s['scouted_s']} s in 600 s")
            time.sleep(0.5)
        result["scout_s"] = round(time.monotonic() - t0, 1)
        result["duration_s"] = duration
        for playing in (False, True):
            if playing:
                http.post(f"/api/sessions/{sid}/control", json={"action": "play"})
            key = "playing" if playing else "paused"
            result[key] = [(round(f * duration, 1),
                            round(seek(http, sid, f * duration, playing), 2)) for f in TARGETS]
        http.delete(f"/api/sessions/{sid}")
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"recording {recording.name} ({result['duration_s']:.0f} s): the look-ahead engine "
          f"ran through it in {result['scout_s']:.0f} s (session paused)")
    for key in ("paused", "playing"):
        times = [s for _, s in result[key]]
        print(f"seeks while {key}: " + ", ".join(f"{t:.0f} s: {s:.2f}" for t, s in result[key]))
        print(f"    worst {max(times):.2f} s, median {sorted(times)[len(times) // 2]:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
