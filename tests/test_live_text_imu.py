"""The text IMU protocol (live.text_imu): lines over real UDP, and every kind of bad line."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from live.streams import StreamStalled, open_stream
from live.text_imu import TextImuParser, TextImuSource, format_line

T0 = 1403253000.0


def test_lines_over_udp_with_bad_lines_rejected_and_counted():
    rng = np.random.default_rng(2)
    gyro = rng.normal(0, 0.2, (50, 3))
    accel = rng.normal(0, 1.0, (50, 3)) + [0, 0, -9.81]
    lines = [format_line(T0 + 0.01 * k, gyro[k], accel[k]) for k in range(50)]
    bad = [
        b"$IMU,1403253000.255,0.1,0.1,0.1,0.1,0.1\r\n",  # 6 fields
        b"$IMU,1403253000.256,nan,0,0,0,0,-9.8\r\n",
        b"$IMU,1403253000.257,0,0,0,0,0,abc\r\n",
        b"$IMU,1403253000.258,50,0,0,0,0,-9.8\r\n",  # 50 rad/s
        b"$IMU,1403253000.259,0,0,0,0,0,-900\r\n",
        lines[10][:-4] + b"00\r\n",  # wrong checksum
        b"$GPGGA,junk\r\n",
        lines[3],  # time going back
        b"\xff\xfe\r\n",
    ]
    receiver = open_stream("udp://127.0.0.1:0", stall_timeout_s=0.5)
    address = receiver.local_address
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    datagrams = [b"".join(lines[:25]), b"# a comment\r\n\r\n", *bad, b"".join(lines[25:])]

    def send():
        for d in datagrams:
            sender.sendto(d, address)

    threading.Thread(target=send).start()
    src = TextImuSource(receiver)
    got = []
    with pytest.raises(StreamStalled):  # the sender stops: reported, no hang
        for sample in src:
            got.append(sample)
    receiver.close()
    sender.close()
    assert len(got) == 50
    np.testing.assert_allclose([s.t for s in got], T0 + 0.01 * np.arange(50), atol=1e-6)
    np.testing.assert_allclose([s.gyro for s in got], gyro, atol=1e-9)
    np.testing.assert_allclose([s.accel for s in got], accel, atol=1e-9)
    p = src.parser
    assert sum(p.rejected.values()) == len(bad) == src.rejected_total  # (the input's health)
    assert src.last_rejection == p.last_rejection and "not ASCII" in src.last_rejection
    reasons = set(p.rejected)
    assert "6 fields, expected 7" in reasons
    assert "gyro_x is nan" in reasons
    assert "accel_z is not a number: 'abc'" in reasons
    assert "rotation rate beyond ±35 rad/s" in reasons
    assert "specific force beyond ±160 m/s²" in reasons
    assert "checksum mismatch" in reasons
    assert "does not start with $IMU," in reasons
    assert "time not after the previous sample's" in reasons
    assert "not ASCII" in reasons


def test_parser_line_numbers_and_checksumless_lines():
    p = TextImuParser()
    assert p.parse_line("$IMU,1,0,0,0,0,0,-9.8") is not None  # no checksum: accepted
    assert p.parse_line("$IMU,2,0,0,0,0,0,inf") is None
    assert p.last_rejection == "line 2: accel_z is inf"


def test_one_line_far_ahead_does_not_reject_the_good_ones_after_it():
    """A line 2 s ahead (a corrupt time that still checks out) made every good line of the
    next 2 s "not after the previous sample's" (a user trial: 200 samples lost). It is passed
    on (the merge drops it against the receivers' clock), and the order stays the good
    lines' until one follows it; a real jump (a gap) is followed, and taken."""
    p = TextImuParser()
    lines = [format_line(T0 + 0.01 * k, np.zeros(3), np.array([0, 0, -9.8])) for k in range(300)]
    got = [p.parse_line(x) for x in lines[:100]]
    assert p.parse_line(format_line(T0 + 3.0, np.zeros(3), np.array([0, 0, -9.8]))) is not None
    got += [p.parse_line(x) for x in lines[100:]]
    assert all(g is not None for g in got) and not p.rejected
    # a gap: the stream goes on from the later time
    assert p.parse_line(format_line(T0 + 10.0, np.zeros(3), np.array([0, 0, -9.8])))
    assert p.parse_line(format_line(T0 + 10.01, np.zeros(3), np.array([0, 0, -9.8])))
    assert p.parse_line(lines[-1]) is None and "time not after" in p.last_rejection
