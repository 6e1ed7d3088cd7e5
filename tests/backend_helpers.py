"""What the server tests share: ``ReferenceEngine`` (a fast test double of the fusion engine),
the real server (uvicorn on a free loopback port, in a thread) and stream / status helpers."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
import uvicorn
import websockets

from backend.app import Settings, create_app
from estimator.frames import euler_to_dcm
from recordings.format import Recording

RECORDING = "small-boat-12s"  # the directory name of the conftest's sim_recording


# --------------------------------------------------------------------------- test double


@dataclass
class _Status:
    phase: str = "fused"
    compass_fixed: bool = True
    satellites: int = 17
    vo_status: str = "tracking"
    scale: float | None = 1.0
    scale_converged: bool = True
    message: str = "reference double"


@dataclass
class _Fused:
    time: float
    position_ned: np.ndarray
    llh_deg: np.ndarray
    velocity_ned: np.ndarray
    euler: np.ndarray
    C_body_to_level: np.ndarray
    rate_of_turn: float
    omega_body: np.ndarray
    position_cov: np.ndarray
    attitude_cov: np.ndarray
    status: _Status
    velocity_cov: np.ndarray = field(default_factory=lambda: np.eye(3) * 1e-6)
    position_drift_cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


class ReferenceEngine:
    """Test double, for the server mechanics only: the pose of each frame is the recording's
    reference, in the real engine's convention (world origin = body origin at the first
    frame); the structure is the reference scene points."""

    def __init__(self, rec: Recording) -> None:
        self.rec = rec
        self.origin: np.ndarray | None = None
        self._state: _Fused | None = None

    def process_imu(self, t, gyro, accel) -> None:
        pass

    def process_gnss(self, t, epochs) -> None:
        pass

    def process_frame(self, t, image) -> _Fused:
        ref = self.rec.reference
        p, v, e = ref.interpolate(t)
        if self.origin is None:
            self.origin = p.copy()
        i = int(np.searchsorted(ref.time, t))
        _, _, ahead = ref.interpolate(min(t + 0.05, ref.time[-1]))
        _, _, behind = ref.interpolate(max(t - 0.05, ref.time[0]))
        rate = float(np.angle(np.exp(1j * (ahead[2] - behind[2])))) / 0.1
        self._state = _Fused(float(t), p - self.origin, ref.llh_deg[min(i, len(ref) - 1)], v, e,
                             euler_to_dcm(*e), rate, np.zeros(3), np.eye(3) * 1e-4,
                             np.eye(3) * 1e-6, _Status())
        return self._state

    def state(self) -> _Fused | None:
        return self._state

    def structure(self):
        pts = self.rec.scene_points - (self.origin if self.origin is not None else 0.0)
        return pts, np.full(len(pts), 0.05), np.arange(len(pts))

    def solved_views(self) -> None:
        return None

    def timing(self) -> dict:
        return {}


# ------------------------------------------------------------------------------- servers


@dataclass
class Live:
    url: str
    ws: str
    app: Any
    rec: Recording


def serve(settings: Settings, rec: Recording) -> Iterator[Live]:
    app = create_app(settings)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))  # bound here: no race for a "free" port
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    end = time.monotonic() + 20
    while not server.started:
        assert time.monotonic() < end and thread.is_alive(), "server did not start"
        time.sleep(0.02)
    yield Live(f"http://127.0.0.1:{port}", f"ws://127.0.0.1:{port}", app, rec)
    server.should_exit = True
    thread.join(10)
    sock.close()


# ------------------------------------------------------------------------------- helpers


@dataclass
class Frame:
    header: dict[str, Any]
    jpeg: bytes
    received: float


async def collect(url: str, stop: Callable[[list[Frame], list[dict]], bool],
                   timeout: float = 60.0, delay: float = 0.0, ack: bool = True
                   ) -> tuple[list[Frame], list[dict]]:
    """Read a session stream until ``stop(frames, statuses)``; ``delay`` s of 'work' after
    each frame makes a slow client; each frame is acknowledged after that work."""
    frames: list[Frame] = []
    statuses: list[dict] = []
    async with websockets.connect(url + ("?ack=1" if ack else ""), max_size=None) as ws:
        async with asyncio.timeout(timeout):
            while not stop(frames, statuses):
                message = await ws.recv()
                assert isinstance(message, str), "a JPEG without its header"
                header = json.loads(message)
                if header["type"] == "frame":
                    jpeg = await ws.recv()
                    assert isinstance(jpeg, bytes) and len(jpeg) == header["jpeg_bytes"]
                    frames.append(Frame(header, jpeg, time.time()))
                    if delay:
                        await asyncio.sleep(delay)
                    if ack:  # the server may have closed meanwhile: its last words wait
                        with contextlib.suppress(websockets.ConnectionClosed):
                            await ws.send(json.dumps({"type": "ack", "seq": header["seq"]}))
                elif header["type"] == "status":
                    statuses.append(header["session"])
                else:
                    statuses.append(header)
                    break
    return frames, statuses


def ended(frames: list[Frame], statuses: list[dict]) -> bool:
    return bool(statuses) and statuses[-1].get("state") == "ended"


def wait_status(client: httpx.Client, sid: str, predicate: Callable[[dict], bool],
                 timeout: float = 60.0) -> dict:
    end = time.monotonic() + timeout
    while True:
        status = client.get(f"/api/sessions/{sid}").json()
        if predicate(status):
            return status
        assert time.monotonic() < end, f"timed out; last status {status}"
        time.sleep(0.05)
