"""Soak: hours of looping replay watched by several clients, sessions coming and going.

Starts ``berthing-aid serve`` in a subprocess (real fusion engine, 3-D viewer on unless
``--no-viewer``) and for ``--minutes``:

- replays the recording at real-time pace in a loop (seek to 0 and play at each end),
  watched by ``--clients`` WebSocket clients with acknowledgement flow control;
- every ``--every`` seconds creates a second session (real time, unwatched), lets it run for
  half of that and deletes it — an officer opening and closing the page;
- every ``--report`` seconds prints a row: the server's RSS and threads (/proc), the frames
  the clients received in the window, the stream latency from the engine finishing a frame
  to a client receiving it (p50 / p95 / max over the window), how far the replay fell behind,
  the loops and churn sessions so far, and any errors (replay state error, reconnects, HTTP
  failures).

At the end: RSS and latency of the first and last windows. A server that leaks shows RSS or
threads creeping up row after row; one that slows down, latency creeping up.

    .venv/bin/python benchmarks/soak.py [RECORDING] [--minutes 120] [--clients 4]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from dataclasses import dataclass, field

import httpx
import numpy as np
import websockets
from serverproc import DEFAULT_RECORDING, proc_rss_mb, proc_threads, recording_path, serve


@dataclass
class Window:
    """What happened since the last report."""

    latency: list[float] = field(default_factory=list)  # s, engine done → client received
    frames: int = 0
    reconnects: int = 0
    errors: list[str] = field(default_factory=list)


@dataclass
class Totals:
    loops: int = 0
    created: int = 0
    deleted: int = 0
    rows: list[dict] = field(default_factory=list)


async def watch(url: str, window: list[Window], stop: asyncio.Event) -> None:
    """One client: receive and acknowledge frames until ``stop``; reconnect if dropped."""
    while not stop.is_set():
        try:
            async with websockets.connect(url + "?ack=1", max_size=None) as ws:
                while not stop.is_set():
                    try:
                        message = await asyncio.wait_for(ws.recv(), timeout=1.0)
                    except TimeoutError:
                        continue
                    if not isinstance(message, str):
                        continue
                    header = json.loads(message)
                    if header["type"] == "frame":
                        await ws.recv()  # its JPEG
                        window[0].latency.append(time.time() - header["processed_at"])
                        window[0].frames += 1
                        await ws.send(json.dumps({"type": "ack", "seq": header["seq"]}))
                    elif header["type"] == "status":
                        if header["session"]["state"] == "error":
                            window[0].errors.append(header["session"]["error"])
                    else:
                        window[0].errors.append(f"stream: {header}")
                        return
        except (OSError, websockets.ConnectionClosed) as exc:
            if stop.is_set():
                return
            window[0].reconnects += 1
            window[0].errors.append(f"stream dropped: {exc!r}")
            await asyncio.sleep(1.0)


async def keep_looping(http: httpx.AsyncClient, sid: str, totals: Totals, window: list[Window],
                       stop: asyncio.Event) -> float:
    """Seek to 0 and play whenever the replay ends; returns the last behind_s seen."""
    behind = 0.0
    while not stop.is_set():
        try:
            status = (await http.get(f"/api/sessions/{sid}")).json()
            behind = status["behind_s"]
            if status["state"] == "ended":
                await http.post(f"/api/sessions/{sid}/control", json={"action": "seek", "time": 0})
                await http.post(f"/api/sessions/{sid}/control", json={"action": "play"})
                totals.loops += 1
            elif status["state"] == "error":
                window[0].errors.append(f"replay: {status['error']}")
        except httpx.HTTPError as exc:
            window[0].errors.append(f"http: {exc!r}")
        await asyncio.sleep(1.0)
    return behind


async def churn(http: httpx.AsyncClient, name: str, every: float, totals: Totals,
                window: list[Window], stop: asyncio.Event) -> None:
    """Create a session every ``every`` s, delete it half-way to the next."""
    while not stop.is_set():
        started = time.monotonic()
        try:
            r = await http.post("/api/sessions", json={"recording": name, "speed": 1})
            r.raise_for_status()
            totals.created += 1
            await asyncio.sleep(every / 2)
            (await http.delete(f"/api/sessions/{r.json()['id']}")).raise_for_status()
            totals.deleted += 1
        except httpx.HTTPError as exc:
            window[0].errors.append(f"churn: {exc!r}")
        await asyncio.sleep(max(0.0, every - (time.monotonic() - started)))


def row(elapsed_s: float, pid: int, w: Window, totals: Totals, behind: float) -> dict:
    lat = 1e3 * np.asarray(w.latency) if w.latency else np.full(1, np.nan)
    return {"min": elapsed_s / 60.0, "rss_mb": proc_rss_mb(pid), "threads": proc_threads(pid),
            "frames": w.frames, "p50_ms": float(np.percentile(lat, 50)),
            "p95_ms": float(np.percentile(lat, 95)), "max_ms": float(lat.max()),
            "behind_s": behind, "loops": totals.loops, "churn": totals.created,
            "reconnects": w.reconnects, "errors": len(w.errors)}


HEADER = (f"{'min':>6} {'RSS MB':>7} {'thr':>4} {'frames':>7} {'p50 ms':>7} {'p95 ms':>7} "
          f"{'max ms':>7} {'behind':>7} {'loops':>5} {'churn':>5} {'recon':>5} {'errors':>6}")


def show(r: dict) -> str:
    return (f"{r['min']:6.1f} {r['rss_mb']:7.1f} {r['threads']:4d} {r['frames']:7d} "
            f"{r['p50_ms']:7.1f} {r['p95_ms']:7.1f} {r['max_ms']:7.1f} {r['behind_s']:7.1f} "
            f"{r['loops']:5d} {r['churn']:5d} {r['reconnects']:5d} {r['errors']:6d}")


async def soak(server, minutes: float, clients: int, every: float, report: float) -> Totals:
    totals = Totals()
    window = [Window()]  # replaced at each report; the tasks append to window[0]
    stop = asyncio.Event()
    async with httpx.AsyncClient(base_url=server.base, timeout=60) as http:
        name = (await http.get("/api/recordings")).json()["default"]
        r = await http.post("/api/sessions", json={"recording": name, "speed": 1})
        r.raise_for_status()
        sid = r.json()["id"]
        url = f"{server.ws}/api/sessions/{sid}/stream"
        watchers = [asyncio.create_task(watch(url, window, stop)) for _ in range(clients)]
        looper = asyncio.create_task(keep_looping(http, sid, totals, window, stop))
        churner = asyncio.create_task(churn(http, name, every, totals, window, stop))
        start = time.monotonic()
        print(HEADER, flush=True)
        behind = 0.0
        while (elapsed := time.monotonic() - start) < 60.0 * minutes:
            await asyncio.sleep(min(report, 60.0 * minutes - elapsed))
            status = (await http.get(f"/api/sessions/{sid}")).json()
            behind = status["behind_s"]
            done, window[0] = window[0], Window()
            totals.rows.append(row(time.monotonic() - start, server.pid, done, totals, behind))
            print(show(totals.rows[-1]), flush=True)
            for message in dict.fromkeys(done.errors):
                print(f"       ! {message}", flush=True)
        stop.set()
        await asyncio.gather(*watchers, looper, churner, return_exceptions=True)
        await http.delete(f"/api/sessions/{sid}")
    return totals


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", nargs="?", default=str(DEFAULT_RECORDING))
    parser.add_argument("--minutes", type=float, default=120.0)
    parser.add_argument("--clients", type=int, default=4)
    parser.add_argument("--every", type=float, default=60.0,
                        help="seconds between churn sessions (each runs half of it)")
    parser.add_argument("--report", type=float, default=60.0, help="seconds per printed row")
    parser.add_argument("--no-viewer", action="store_true", help="without the 3-D viewer")
    args = parser.parse_args()
    recording = recording_path(args.recording)
    if recording is None:
        return 2
    print(f"soak: {recording.name}, {args.minutes:g} min, {args.clients} clients, a session "
          f"created every {args.every:g} s, viewer {'off' if args.no_viewer else 'on'}")
    with serve(recording, viewer=not args.no_viewer) as server:
        print(f"server RSS at start {proc_rss_mb(server.pid):.0f} MB, "
              f"{proc_threads(server.pid)} threads", flush=True)
        totals = asyncio.run(soak(server, args.minutes, args.clients, args.every, args.report))
    rows = totals.rows
    if len(rows) >= 2:
        first, last = rows[0], rows[-1]
        rss = [r["rss_mb"] for r in rows]
        later = rows[1:]  # the first window includes the start-up
        print(f"RSS: first window {first['rss_mb']:.0f} MB, last {last['rss_mb']:.0f} MB "
              f"({100 * (last['rss_mb'] / first['rss_mb'] - 1):+.1f} %), range "
              f"{min(rss):.0f}–{max(rss):.0f} MB; threads {min(r['threads'] for r in rows)}–"
              f"{max(r['threads'] for r in rows)}")
        print(f"latency p95: second window {later[0]['p95_ms']:.0f} ms, last "
              f"{last['p95_ms']:.0f} ms, worst window {max(r['p95_ms'] for r in later):.0f} ms; "
              f"p50 median over windows {np.median([r['p50_ms'] for r in later]):.0f} ms")
        print(f"{totals.loops} loops of the recording, {totals.created} sessions created and "
              f"{totals.deleted} deleted, {sum(r['reconnects'] for r in rows)} reconnects, "
              f"{sum(r['errors'] for r in rows)} errors")
    return 0


if __name__ == "__main__":
    sys.exit(main())
