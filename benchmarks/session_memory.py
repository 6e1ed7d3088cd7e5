"""Memory returned after sessions: RSS of the server after each create / run / delete cycle.

Starts ``berthing-aid serve`` in a subprocess (real fusion engine), then ``--cycles`` times:
creates a session at max speed, watches its stream with one client for ``--run`` seconds,
deletes it, waits ``--settle`` s and reads the server's RSS and thread count from /proc. Once
without and once with the 3-D viewer (``--viewer both``, the default). A server that releases
what a session held stays within a few per cent of its RSS after the first cycle.

    .venv/bin/python benchmarks/session_memory.py [RECORDING] [--cycles 20] [--run 5]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from pathlib import Path

import httpx
import websockets
from serverproc import DEFAULT_RECORDING, proc_rss_mb, proc_threads, serve


async def watch(url: str, seconds: float) -> int:
    """Frames received by one acknowledging client in ``seconds``."""
    frames = 0
    until = time.monotonic() + seconds
    async with websockets.connect(url + "?ack=1", max_size=None) as ws:
        while (left := until - time.monotonic()) > 0:
            try:
                message = await asyncio.wait_for(ws.recv(), timeout=left)
            except TimeoutError:
                break
            if isinstance(message, str):
                header = json.loads(message)
                if header["type"] == "frame":
                    frames += 1
                    await ws.send(json.dumps({"type": "ack", "seq": header["seq"]}))
    return frames


def cycles(recording: Path, viewer: bool, n: int, run_s: float, settle_s: float
           ) -> list[tuple[float, int, int]]:
    """(RSS MB, threads, frames processed) after each cycle."""
    out = []
    with serve(recording, viewer=viewer) as server, \
            httpx.Client(base_url=server.base, timeout=60) as http:
        name = http.get("/api/recordings").json()["default"]
        print(f"viewer {'on' if viewer else 'off'}: RSS at start {proc_rss_mb(server.pid):.0f} "
              f"MB, {proc_threads(server.pid)} threads")
        for k in range(1, n + 1):
            r = http.post("/api/sessions", json={"recording": name, "speed": "max"})
            r.raise_for_status()
            sid = r.json()["id"]
            asyncio.run(watch(f"{server.ws}/api/sessions/{sid}/stream", run_s))
            frames = http.get(f"/api/sessions/{sid}").json()["frames_processed"]
            http.delete(f"/api/sessions/{sid}").raise_for_status()
            time.sleep(settle_s)
            out.append((proc_rss_mb(server.pid), proc_threads(server.pid), frames))
            rss, threads, _ = out[-1]
            print(f"  cycle {k:3d}: RSS {rss:7.1f} MB  threads {threads:3d}  "
                  f"frames replayed {frames}", flush=True)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", nargs="?", default=str(DEFAULT_RECORDING))
    parser.add_argument("--cycles", type=int, default=20)
    parser.add_argument("--run", type=float, default=5.0, help="seconds each session runs")
    parser.add_argument("--settle", type=float, default=1.0, help="seconds after each delete")
    parser.add_argument("--viewer", choices=("on", "off", "both"), default="both")
    args = parser.parse_args()
    recording = Path(args.recording).resolve()
    if not (recording / "manifest.json").is_file():
        print(f"no recording at {recording}", file=sys.stderr)
        return 2
    summary = []
    for viewer in {"on": [True], "off": [False], "both": [False, True]}[args.viewer]:
        result = cycles(recording, viewer, args.cycles, args.run, args.settle)
        first, last = result[0][0], result[-1][0]
        summary.append(f"viewer {'on ' if viewer else 'off'}: RSS after cycle 1 {first:.0f} MB,"
                       f" after cycle {len(result)} {last:.0f} MB ({100 * (last / first - 1):+.1f}"
                       f" %), max {max(r[0] for r in result):.0f} MB; threads "
                       f"{result[0][1]} → {result[-1][1]}")
    print("\n".join(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
