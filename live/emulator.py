"""The emulator: a recording played out at real time on loopback as the live devices speak.

- four receivers, each a TCP server (``tcp://127.0.0.1:PORT``) sending its UBX stream
  (``live.ubx_encode.receiver_messages``: RXM-RAWX, RXM-SFRBX, and with ``imu="esf"``
  ESF-RAW in receiver 1's stream);
- the IMU as the text protocol (``live.text_imu``), one datagram per sample to a UDP port
  (``imu="text"``), or ESF-RAW as above;
- the camera as HTTP MJPEG (``live.mjpeg.MjpegServer``).

All streams share one clock: a message of recording time t is sent at
``start + (t − t_start) / speed``. The clock starts when the four receivers and the camera
have a client (the live session has connected; its UDP port is bound before that), so that
the session sees the recording from its first sample, as a replay does. ``config_text``
gives the live configuration pointing at it.
"""

from __future__ import annotations

import bisect
import socket
import threading
import time
from collections.abc import Iterable
from pathlib import Path

from recordings.format import Recording

from .config import BridgeConfig, CameraInput, ImuInput, config_text
from .mjpeg import MjpegServer
from .text_imu import format_line
from .ubx_encode import receiver_messages

__all__ = ["Emulator", "free_udp_port"]


def free_udp_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class _ReceiverServer:
    """One receiver's TCP port: waits for a client, then sends on the shared clock."""

    def __init__(self, messages: list[tuple[float, bytes]], host: str):
        self.messages = messages
        self._server = socket.create_server((host, 0))
        self._server.settimeout(0.2)
        self.address = self._server.getsockname()[:2]
        self.url = f"tcp://{self.address[0]}:{self.address[1]}"
        self.client: socket.socket | None = None
        self.sent = 0

    def accept(self, stop: threading.Event) -> bool:
        while not stop.is_set():
            try:
                self.client, _ = self._server.accept()
                self.client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                return True
            except TimeoutError:
                continue
        return False

    def play(self, clock: _Clock, stop: threading.Event) -> None:
        """Send each message at its time. A client that goes away (the session dropped a
        stalled link) may come back, as to a receiver: the next one gets the messages from
        then on (a receiver does not keep what it sent to nobody)."""
        times = [t for t, _data in self.messages]
        k = 0
        try:
            while self.client is not None:
                try:
                    while k < len(self.messages):
                        if not clock.wait_until(times[k], stop):
                            return
                        self.client.sendall(self.messages[k][1])
                        self.sent += 1
                        k += 1
                    return
                except OSError:  # the session went away: as a receiver unplugged
                    self.client.close()
                    self.client = None
                    if not self.accept(stop):
                        return
                    k = max(k, bisect.bisect_left(times, clock.now()))
        finally:
            if self.client is not None:
                self.client.close()

    def close(self) -> None:
        self._server.close()


class _Clock:
    def __init__(self, t0: float, speed: float):
        self.t0, self.speed = t0, speed
        self.start: float | None = None

    def now(self) -> float:
        """The recording's time the clock is at."""
        assert self.start is not None
        return self.t0 + (time.monotonic() - self.start) * self.speed

    def wait_until(self, t: float, stop: threading.Event) -> bool:
        assert self.start is not None
        delay = self.start + (t - self.t0) / self.speed - time.monotonic()
        return not (delay > 0 and stop.wait(delay))


class Emulator:
    """Plays ``rec`` on loopback (module docstring); ``start()``, then ``wait()`` or ``stop()``."""

    def __init__(self, rec: Recording, *, host: str = "127.0.0.1", imu: str = "text",
                 imu_port: int | None = None, speed: float = 1.0, jpeg_quality: int = 90):
        if imu not in ("text", "esf"):
            raise ValueError(f"imu {imu!r} is neither 'text' nor 'esf'")
        if len(rec.gnss) != 4:
            raise ValueError(f"{rec.path}: the emulator plays 4 receivers, the recording has "
                             f"{len(rec.gnss)}")
        self.rec = rec
        self.host = host
        self.imu_kind = imu
        self.imu_port = imu_port or free_udp_port(host)
        self.clock = _Clock(float(rec.manifest.start_gpst), speed)
        self._stop = threading.Event()
        self.receivers = [
            _ReceiverServer(list(receiver_messages(
                epochs, rec.nav, imu=rec.imu if imu == "esf" and i == 0 else None)), host)
            for i, epochs in enumerate(rec.gnss)]
        self.camera = MjpegServer.for_recording(rec, host=host, quality=jpeg_quality,
                                                speed=speed)
        self.camera.clock_t0 = self.clock.t0
        self._threads: list[threading.Thread] = []
        self.started = threading.Event()
        self.imu_sent = 0

    # ------------------------------------------------------------------ config

    def config_text(self, *, record_dir: Path | None, calibration: Path | None = None,
                    hull: Path | None = None, bridge: BridgeConfig | None = None,
                    latency_s: float = 0.0) -> str:
        """The live configuration of this emulator (paths absolute)."""
        imu = (ImuInput("text", url=f"udp://{self.host}:{self.imu_port}")
               if self.imu_kind == "text" else ImuInput("esf", receiver=1))
        files = self.rec.manifest.files
        return config_text(
            receivers=[r.url for r in self.receivers], imu=imu,
            camera=CameraInput(self.camera.url, latency_s),
            calibration=(calibration or self.rec.path / files["calibration"]).resolve(),
            hull=(hull or self.rec.path / files["hull"]).resolve(),
            origin_llh_deg=self.rec.manifest.origin_llh_deg,
            record_dir=record_dir.resolve() if record_dir else None,
            name=self.rec.manifest.name, bridge=bridge,
            comment=f"live configuration of the emulator playing {self.rec.path}\n"
                    "(written by berthing-aid emulate; see live/example.toml for every key)")

    # ------------------------------------------------------------------ playing

    def start(self) -> Emulator:
        th = threading.Thread(target=self._run, name="emulator", daemon=True)
        th.start()
        self._threads.append(th)
        return self

    def _run(self) -> None:
        threading.Thread(target=self.camera._httpd.serve_forever, name="mjpeg-http",
                         daemon=True).start()
        for r in self.receivers:
            if not r.accept(self._stop):
                return
        while not self._stop.is_set() and self.camera.clients == 0:
            time.sleep(0.01)
        if self._stop.is_set():
            return
        self.clock.start = time.monotonic() + 0.2  # every stream ready before the first send
        self.camera.clock_start = self.clock.start
        jobs = [threading.Thread(target=r.play, args=(self.clock, self._stop), daemon=True)
                for r in self.receivers]
        jobs.append(threading.Thread(target=self.camera._play, daemon=True))
        if self.imu_kind == "text":
            jobs.append(threading.Thread(target=self._play_imu, daemon=True))
        for j in jobs:
            j.start()
        self._threads += jobs
        self.started.set()

    def _play_imu(self) -> None:
        imu = self.rec.imu
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            for t, w, f in zip(imu.time, imu.gyro, imu.accel, strict=True):
                if not self.clock.wait_until(float(t), self._stop):
                    return
                sock.sendto(format_line(float(t), w, f), (self.host, self.imu_port))
                self.imu_sent += 1

    @property
    def end_gpst(self) -> float:
        rec = self.rec
        return float(max(rec.imu.time[-1], rec.frame_times[-1],
                         *(e[-1].time for e in rec.gnss if e)))

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the end of the recording (True) or the timeout / stop (False)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.started.wait(0.1):
            if self._stop.is_set() or (deadline is not None and time.monotonic() > deadline):
                return False
        for th in self._threads[1:]:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            th.join(remaining)
            if th.is_alive():
                return False
        return True

    def stop(self) -> None:
        self._stop.set()
        for r in self.receivers:
            r.close()
        self.camera.stop()

    def streams(self) -> Iterable[str]:
        return [r.url for r in self.receivers] + [self.camera.url]
