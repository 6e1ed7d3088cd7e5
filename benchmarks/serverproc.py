"""What the server benchmarks share: ``berthing-aid serve`` in a subprocess on a free loopback
port, its CPU, memory and threads read from /proc (Linux), the recording argument, and a
stream client that watches frames as the page does."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_RECORDING = ROOT / "recordings" / "default"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def proc_cpu_seconds(pid: int) -> float:
    """user + system CPU seconds of a process and its threads (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _status_field(pid: int, name: str) -> int | None:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(name + ":"):
            return int(line.split()[1])
    return None


def proc_rss_mb(pid: int) -> float:
    kb = _status_field(pid, "VmRSS")
    return float("nan") if kb is None else kb / 1024.0


def proc_threads(pid: int) -> int:
    return _status_field(pid, "Threads") or 0


@dataclass
class Server:
    process: subprocess.Popen
    base: str  # http://127.0.0.1:port
    ws: str  # ws://127.0.0.1:port

    @property
    def pid(self) -> int:
        return self.process.pid


@contextmanager
def serve(recording: Path, viewer: bool = True, extra: tuple[str, ...] = ()) -> Iterator[Server]:
    """``berthing-aid serve RECORDING`` on a free port until the block ends (the 3-D viewer on
    any free port, or off)."""
    port = free_port()
    command = [sys.executable, "-m", "backend.cli", "serve", str(recording), "--port", str(port),
               *(["--viser-port", "0"] if viewer else ["--no-viewer"]), *extra]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True, env=env)
    base = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=base, timeout=10) as http:
            for _ in range(600):
                try:
                    http.get("/api/recordings")
                    break
                except httpx.TransportError:
                    if process.poll() is not None:
                        raise RuntimeError(f"the server exited: {process.stderr.read()}") from None
                    time.sleep(0.1)
        yield Server(process, base, f"ws://127.0.0.1:{port}")
    finally:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)


def recording_path(arg: str) -> Path | None:
    """The recording a benchmark was given, or None (said on stderr) when there is none."""
    recording = Path(arg).resolve()
    if not (recording / "manifest.json").is_file():
        print(f"no recording at {recording}; make one with berthing-aid simulate",
              file=sys.stderr)
        return None
    return recording


async def watch_frames(url: str, until: float, on_frame: Callable[[dict, float], None]) -> None:
    """A stream client as the page is (acknowledged frames) until ``until`` (wall clock):
    ``on_frame(header, received_at)`` for each frame; ends early on an error or close."""
    import websockets

    async with websockets.connect(url + "?ack=1", max_size=None) as ws:
        while time.time() < until:
            try:
                message = await asyncio.wait_for(ws.recv(), timeout=max(0.1, until - time.time()))
            except TimeoutError:
                break
            if not isinstance(message, str):
                continue
            header = json.loads(message)
            if header["type"] == "frame":
                await ws.recv()  # the JPEG
                on_frame(header, time.time())
                await ws.send(json.dumps({"type": "ack", "seq": header["seq"]}))
            elif header["type"] != "status":
                break


async def sample_server(pid: int, until: float, clients: list[asyncio.Task]
                        ) -> tuple[float, float, list[float]]:
    """The server's CPU seconds and wall seconds until ``until`` (wall clock) and its RSS
    every 0.5 s meanwhile; then waits for the clients."""
    cpu0, wall0 = proc_cpu_seconds(pid), time.monotonic()
    rss: list[float] = []
    while time.time() < until:
        rss.append(proc_rss_mb(pid))
        await asyncio.sleep(0.5)
    await asyncio.gather(*clients)
    return proc_cpu_seconds(pid) - cpu0, time.monotonic() - wall0, rss
