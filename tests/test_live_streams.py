"""A receiver's UBX stream as the emulator sends it, read back over a real TCP connection.

The bundled recording's receiver 1 (RINEX observations, navigation file) and IMU go through
``receiver_messages`` → TCP loopback → ``UbxGnssSource`` with an ESF-RAW decoder: epochs,
ephemerides and IMU samples come back, and the stall of the stream is reported.
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import recordings
from engine.messages import ImuMessage
from estimator.frames import ecef_to_geodetic
from estimator.records import GnssEpoch
from estimator.spp import standalone_position
from live.streams import StreamStalled, open_stream
from live.ubx_encode import receiver_messages
from live.ubx_gnss import UbxGnssSource
from live.ubx_imu import EsfRawDecoder

RECORDING = Path(__file__).parents[1] / "recordings" / "default"
SECONDS = 40  # covers one 30 s SFRBX rebroadcast


@pytest.fixture(scope="module")
def rec():
    return recordings.load(RECORDING)


def serve_once(chunks: list[bytes], hold_s: float) -> tuple[str, threading.Thread]:
    """A TCP server sending ``chunks`` to its first client, then going silent until the
    client hangs up (at most ``hold_s``: a client slow to parse, on a busy machine, still
    finds the line open and silent rather than closed)."""
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def run():
        conn, _ = server.accept()
        for c in chunks:
            conn.sendall(c)
        conn.settimeout(hold_s)
        with contextlib.suppress(OSError):
            while conn.recv(4096):
                pass
        conn.close()
        server.close()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return f"tcp://127.0.0.1:{port}", th


def test_receiver_stream_over_tcp(rec):
    epochs = [e for e in rec.gnss[0] if e.time < rec.manifest.start_gpst + SECONDS]
    n_imu = int(np.searchsorted(rec.imu.time, epochs[-1].time, side="right"))
    imu = type(rec.imu)(rec.imu.time[:n_imu], rec.imu.gyro[:n_imu], rec.imu.accel[:n_imu])
    msgs = list(receiver_messages(epochs, rec.nav, imu=imu))
    assert [t for t, _ in msgs] == sorted(t for t, _ in msgs)
    url, th = serve_once([m for _, m in msgs], hold_s=30.0)
    decoder = EsfRawDecoder()
    stream = open_stream(url, stall_timeout_s=0.5)
    src = UbxGnssSource(stream, imu=decoder)
    got_epochs: list[GnssEpoch] = []
    got_imu: list[ImuMessage] = []
    last = time.monotonic()
    with pytest.raises(StreamStalled, match="no data for 0.5 s"):
        for item in src:
            (got_epochs if isinstance(item, GnssEpoch) else got_imu).append(item)
            last = time.monotonic()
    assert time.monotonic() - last < 3.0  # the silence declared, not waited out
    stream.close()
    th.join()
    assert src.bad_messages == 0 and not src.assembler.rejected
    # GNSS epochs back, to the fields' resolution
    assert [e.time for e in got_epochs] == [e.time for e in epochs]
    for a, b in zip(epochs, got_epochs, strict=True):
        assert set(b.satellites) == {s for s in a.satellites if s[0] in "GREJC"}
        for s, ob in b.satellites.items():
            oa = a.satellites[s]
            assert ob.pseudorange == oa.pseudorange and ob.carrier_phase == oa.carrier_phase
            assert ob.doppler == pytest.approx(oa.doppler, abs=5e-4)
    # IMU: the first epoch's sample (index 0) anchors the clock; later ones come back
    assert decoder.untimed_samples == 1 and decoder.anchor_jumps == 0
    assert len(got_imu) == n_imu - 1
    np.testing.assert_allclose([m.t for m in got_imu], imu.time[1:], atol=2e-6)
    np.testing.assert_allclose([m.gyro for m in got_imu], imu.gyro[1:],
                               atol=math.radians(2**-12))
    np.testing.assert_allclose([m.accel for m in got_imu], imu.accel[1:], atol=2**-10)
    # the ephemerides broadcast in the stream position the receiver where the recording is
    nav = src.assembler.nav
    assert {s[0] for s in nav.ephemerides} >= {"G", "E"}
    fix = standalone_position(got_epochs[-1], nav)
    assert fix is not None
    lat, lon, _ = ecef_to_geodetic(fix.position)
    origin = rec.manifest.origin_llh_deg
    assert math.degrees(lat) == pytest.approx(origin[0], abs=5e-4)
    assert math.degrees(lon) == pytest.approx(origin[1], abs=5e-4)


def test_unreachable_receiver_is_an_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConnectionError, match="cannot connect"):
        open_stream(f"tcp://127.0.0.1:{port}", stall_timeout_s=1.0)
    with pytest.raises(ValueError, match="unknown stream kind"):
        open_stream("ftp://x:1")


def test_the_emulators_receiver_port_takes_a_client_back():
    """A session that dropped a stalled receiver link connects again: the emulator's port
    serves the new client from then on, as a receiver would (it kept nothing for nobody),
    instead of having stopped at the first lost client."""
    from live.emulator import _Clock, _ReceiverServer

    msgs = [(100.0 + 0.1 * k, f"m{k:03d};".encode()) for k in range(30)]  # 3 s of them
    server = _ReceiverServer(msgs, "127.0.0.1")
    stop, clock = threading.Event(), _Clock(100.0, 1.0)
    first = socket.create_connection(server.address)
    assert server.accept(stop)
    clock.start = time.monotonic()
    player = threading.Thread(target=server.play, args=(clock, stop), daemon=True)
    player.start()
    try:
        first.settimeout(5)
        assert first.recv(64).startswith(b"m000;")
        first.close()  # the session gives up on it
        time.sleep(0.5)
        second = socket.create_connection(server.address)
        second.settimeout(5)
        data = b""
        while chunk := second.recv(4096):
            data += chunk
        second.close()
        assert data.endswith(b"m029;") and b"m000;" not in data, data
        player.join(5)
        assert not player.is_alive()
    finally:
        stop.set()
        server.close()
