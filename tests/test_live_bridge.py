"""Bridge outputs (live.nmea, live.bridge) read back from real loopback sockets.

Sentences are parsed by pynmeagps' NMEAReader (it checks each sentence's checksum); the
IEC 61162-450 framing (header, tag blocks, their checksums) is checked here by hand against
the standard's format, independently of the sender's code.
"""

from __future__ import annotations

import math
import re
import socket
import time
from datetime import datetime

import pytest
from pynmeagps import NMEAReader

from estimator.frames import gpst_from_datetime
from live.bridge import IEC450_HEADER, Iec450Sender, NmeaOutput, NmeaTcpServer
from live.nmea import Alert, BridgeState, SentenceMaker

T = gpst_from_datetime(datetime(2026, 3, 4, 5, 6, 25, 250000))  # 05:06:07.25 UTC (18 s)
STATE = BridgeState(time=T, llh_deg=(34.720512, 135.333123, 41.25),
                    velocity_ned=(1.0, -1.0, 0.0),
                    euler=(0.01, -0.02, math.radians(301.237)),
                    rate_of_turn=math.radians(-0.5), mode="rtk-fixed", satellites=14,
                    hdop=0.8)
TAG_RE = re.compile(rb"\\(s:([A-Z]{2}\d{4}),n:(\d{1,3}))\*([0-9A-F]{2})\\")


def parse_datagram(data: bytes) -> list[tuple[str, int, object]]:
    """(source id, line count, parsed sentence) of an IEC 61162-450 sentence datagram."""
    assert data[:6] == b"UdPbC\x00"
    out = []
    rest = data[6:]
    while rest:
        m = TAG_RE.match(rest)
        assert m, rest[:40]
        body, cks = m.group(1), m.group(4)
        x = 0
        for b in body:
            x ^= b
        assert f"{x:02X}".encode() == cks
        rest = rest[m.end():]
        end = rest.index(b"\r\n") + 2
        out.append((m.group(2).decode(), int(m.group(3)), NMEAReader.parse(rest[:end])))
        rest = rest[end:]
    return out


@pytest.fixture
def udp_receiver():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def test_sentences_over_iec450_udp(udp_receiver):
    sender = Iec450Sender(udp_receiver.getsockname(), source_id="HE0007")
    out = NmeaOutput([sender], SentenceMaker(leap_seconds=18))
    sent = out.update(STATE)
    assert len(sent) == 6
    data, _ = udp_receiver.recvfrom(2000)
    items = parse_datagram(data)
    assert [i[0] for i in items] == ["HE0007"] * 6
    assert [i[1] for i in items] == [1, 2, 3, 4, 5, 6]
    msgs = {m.msgID: m for _, _, m in items}
    assert msgs["HDT"].talker == "HE" and msgs["HDT"].headingT == pytest.approx(301.24)
    assert msgs["THS"].headt == pytest.approx(301.24) and msgs["THS"].mi == "A"
    assert msgs["ROT"].rot == pytest.approx(-30.0) and msgs["ROT"].valid == "A"  # deg/min
    vtg = msgs["VTG"]
    assert vtg.cogt == pytest.approx(315.0) and vtg.posMode == "A"
    assert vtg.sogn == pytest.approx(math.sqrt(2) * 3600 / 1852, abs=0.01)
    assert vtg.sogk == pytest.approx(math.sqrt(2) * 3.6, abs=0.01)
    gga = msgs["GGA"]
    assert gga.lat == pytest.approx(34.720512, abs=1e-7)
    assert gga.lon == pytest.approx(135.333123, abs=1e-7)
    assert gga.quality == 4 and gga.numSV == 14 and gga.alt + gga.sep == pytest.approx(41.25)
    assert gga.time.isoformat() == "05:06:07.250000"
    zda = msgs["ZDA"]
    assert (zda.year, zda.month, zda.day) == (2026, 3, 4)
    assert zda.time.isoformat() == "05:06:07.250000"

    # the 10 Hz group is next due at the .30 s slot, the 1 Hz ones at 06:08; line counts go on
    sent = out.update(BridgeState(**{**STATE.__dict__, "time": T + 0.03}))
    assert sent == []
    sent = out.update(BridgeState(**{**STATE.__dict__, "time": T + 0.05, "mode": "invalid"}))
    assert [NMEAReader.parse(s).msgID for s in sent] == ["HDT", "THS", "ROT"]
    items = parse_datagram(udp_receiver.recvfrom(2000)[0])
    assert [i[1] for i in items] == [7, 8, 9]
    hdt, ths, rot = (m for _, _, m in items)
    assert hdt.headingT == "" and ths.mi == "V" and rot.valid == "V"
    sender.close()


def test_alerts_over_udp_and_tcp(udp_receiver):
    server = NmeaTcpServer("127.0.0.1", 0)
    client = socket.create_connection(server.address, timeout=2.0)
    deadline = time.monotonic() + 2
    while server.client_count < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    sender = Iec450Sender(udp_receiver.getsockname())
    out = NmeaOutput([sender, server])
    alert = Alert(alert_id=12, text="Close to berth: 2.1 m", priority="warning",
                  changed=T)
    assert len(out.alerts([alert])) == 2
    assert out.alerts([alert]) == []  # unchanged: not repeated
    out.alerts([Alert(**{**alert.__dict__, "acknowledged": True})])
    items = parse_datagram(udp_receiver.recvfrom(2000)[0])
    alr, alf = (m for _, _, m in items)
    assert alr.alarmnum == "012" and alr.alarmcond == "A" and alr.alarmstate == "V"
    assert alr.alarmtext == "CLOSE TO BERTH: 2.1 M"
    assert alf.alertpriority == "W" and alf.alertstate == "V" and alf.alertid == "012"
    assert len(alf.alerttxt) <= 16
    # the TCP client gets the same sentences, plain
    buf = b""
    while buf.count(b"\r\n") < 4:
        buf += client.recv(4096)
    lines = [NMEAReader.parse(line + b"\r\n") for line in buf.split(b"\r\n") if line]
    assert [m.msgID for m in lines] == ["ALR", "ALF", "ALR", "ALF"]
    assert lines[2].alarmstate == "A" and lines[3].alertstate == "A"
    client.close()
    server.close()
    sender.close()


def test_datagrams_split_at_1472_bytes(udp_receiver):
    sender = Iec450Sender(udp_receiver.getsockname())
    maker = SentenceMaker()
    sentences = [maker.position(STATE)] * 40
    sender.send(sentences)
    got = []
    while len(got) < 40:
        data = udp_receiver.recvfrom(4000)[0]
        assert len(data) <= 1472
        got += parse_datagram(data)
    assert [n for _, n, _ in got] == list(range(1, 41))
    assert IEC450_HEADER == b"UdPbC\x00"
    sender.close()


def test_multicast_on_loopback():
    group, port = "239.192.0.4", 0
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    rx.bind(("", port))
    port = rx.getsockname()[1]
    try:
        rx.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                      socket.inet_aton(group) + socket.inet_aton("127.0.0.1"))
    except OSError as exc:
        rx.close()
        pytest.skip(f"no multicast on loopback here: {exc}")
    rx.settimeout(2.0)
    sender = Iec450Sender((group, port), interface="127.0.0.1")
    sender.send([SentenceMaker().time(T)])
    try:
        data = rx.recvfrom(2000)[0]
    except TimeoutError:
        pytest.skip("multicast loopback not delivered in this environment")
    finally:
        rx.close()
        sender.close()
    (_, n, zda), = parse_datagram(data)
    assert n == 1 and zda.msgID == "ZDA"


def test_a_state_is_sent_as_of_now():
    """A live state is 0.4 s old when sent (the frame's capture, transport, processing): the
    bridge gets it carried forward on its rate of turn and velocity, as an HDT of now (a
    user trial: 1.6° behind in a 4°/s turn); at most 1 s, and a replay's as it is."""
    from types import SimpleNamespace

    from live.bridge import bridge_state

    state = SimpleNamespace(
        time=1000.0, llh_deg=(34.669, 135.215, 40.0), velocity_ned=(2.0, 1.0, 0.0),
        euler=(0.0, 0.0, math.radians(90.0)), rate_of_turn=math.radians(4.0),
        status=SimpleNamespace(integrity=SimpleNamespace(trusted=True, mode="fused"),
                               satellites=12))
    now = bridge_state(state, ahead_s=0.4)
    assert now.time == pytest.approx(1000.4)
    assert math.degrees(now.euler[2]) == pytest.approx(91.6)
    # 0.8 m north, 0.4 m east
    assert (now.llh_deg[0] - 34.669) * 111_320 == pytest.approx(0.8, rel=0.01)
    assert (now.llh_deg[1] - 135.215) * 111_320 * math.cos(math.radians(34.669)) == \
        pytest.approx(0.4, rel=0.01)
    assert bridge_state(state, ahead_s=30.0).time == pytest.approx(1001.0)  # old news
    assert bridge_state(state).euler[2] == pytest.approx(math.radians(90.0))
    hdt = NMEAReader.parse(SentenceMaker().heading(now)[0].decode().strip())
    assert float(hdt.headingT) == pytest.approx(91.6, abs=0.05)


@pytest.mark.parametrize("damage", [
    {"rate_of_turn": math.nan}, {"euler": (0.0, 0.0, math.inf)},
    {"llh_deg": (math.nan, 135.215, 40.0)}, {"velocity_ned": (math.nan, 1.0, 0.0)}])
def test_a_damaged_state_goes_out_invalid_with_empty_fields(udp_receiver, damage):
    """A fused state with one non-finite number, though its integrity says trusted (a NaN
    rate of turn went out as ``$HEHDT,nan,T``): every sentence is sent, flagged invalid with
    its numbers empty, none with the text "nan"; a state without a time sends nothing."""
    from types import SimpleNamespace

    from live.bridge import bridge_state

    fields = {"time": T, "llh_deg": (34.669, 135.215, 40.0), "velocity_ned": (2.0, 1.0, 0.0),
              "euler": (0.0, 0.0, math.radians(90.0)), "rate_of_turn": math.radians(4.0)}
    status = SimpleNamespace(integrity=SimpleNamespace(trusted=True, mode="fused"),
                             satellites=12)
    good = bridge_state(SimpleNamespace(**fields, status=status), ahead_s=0.4)
    assert good.mode == "gnss"
    state = bridge_state(SimpleNamespace(**{**fields, **damage}, status=status), ahead_s=0.4)
    assert state.mode == "invalid"
    sender = Iec450Sender(udp_receiver.getsockname())
    out = NmeaOutput([sender])
    sent = out.update(state)
    assert len(sent) == 6 and not any(b"nan" in s.lower() or b"inf" in s.lower() for s in sent)
    msgs = {m.msgID: m for _, _, m in parse_datagram(udp_receiver.recvfrom(2000)[0])}
    assert msgs["HDT"].headingT == "" and msgs["THS"].mi == "V"
    assert msgs["ROT"].rot == "" and msgs["ROT"].valid == "V"
    assert msgs["VTG"].sogn == "" and msgs["VTG"].cogt == "" and msgs["VTG"].posMode == "N"
    assert msgs["GGA"].quality == 0 and msgs["GGA"].lat == "" and msgs["GGA"].alt == ""
    assert out.update(BridgeState(**{**good.__dict__, "time": math.nan})) == []
    sender.close()


def test_a_late_state_is_carried_on_the_gyro_samples_already_received(sim_recording):
    """The engine 1 s behind the sensors as a turn starts (a CI run: the HDT 1.0° off,
    carried on the rate of turn of its frame): the heading sent is carried on the gyro
    samples received meanwhile (``LiveRunner.turned_after``), through the real estimator, and
    matches the recording's truth 1 s later within 0.3°."""
    import collections
    import threading
    from types import SimpleNamespace

    import numpy as np

    from backend.live_session import LiveRunner
    from engine.driver import dispatch
    from engine.messages import ImuMessage, sensor_messages
    from estimator.pipeline import Fusion, FusionOptions
    from live.bridge import bridge_state
    from recordings.format import load

    rec = load(sim_recording)
    engine = Fusion(rec.calibration, rec.nav, FusionOptions(use_vo=False))
    start, done = float(rec.frame_times[0]), -np.inf
    gyro_errors, rate_errors = [], []
    for after in (5.6, 6.0, 6.5):  # s into the recording: the boat starts to turn
        t0 = start + after
        for msg in sensor_messages(rec, after=done, until=t0, frames=False):
            dispatch(engine, msg)
        done = t0
        state = engine.state()
        assert state is not None and state.status.phase == "fused"
        # what the session's queue holds: the next second's IMU samples, not processed
        queued = [ImuMessage(float(t), rec.imu.gyro[i], rec.imu.accel[i])
                  for i, t in enumerate(rec.imu.time) if t0 < t <= t0 + 1.0]
        runner = SimpleNamespace(_arrived=threading.Condition(),
                                 _queue=collections.deque(queued))
        turned = LiveRunner.turned_after(runner, engine, state.time)
        assert turned is not None and turned[1] == pytest.approx(1.0, abs=0.02)
        truth = math.degrees(float(rec.reference.interpolate(
            np.array([state.time + 1.0]))[2][0, 2]))
        for errors, carried in ((gyro_errors, turned), (rate_errors, None)):
            yaw = math.degrees(bridge_state(state, ahead_s=1.0, turned=carried).euler[2])
            errors.append(abs((yaw - truth + 180) % 360 - 180))
    assert max(gyro_errors) < 0.3, gyro_errors
    # the rate of turn at the frame alone would have been off (the test can fail)
    assert max(rate_errors) > 0.6, rate_errors
