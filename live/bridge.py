"""Bridge outputs: NMEA sentences over UDP with IEC 61162-450 framing and over TCP.

IEC 61162-450 ("light-weight Ethernet", the sentence datagram) as implemented here:

    datagram = b"UdPbC\\0" + one or more (tag block + sentence)
    tag block = "\\" + "s:" source id + "," + "n:" line count + "*" + checksum + "\\"
    sentence = "$TTSSS,...*hh\\r\\n"

- the 6-byte header "UdPbC" + NUL marks a datagram of sentences;
- ``s:`` is the sender's source identification, a talker id and four digits (e.g.
  ``II0001``); ``n:`` a line count 1..999 incremented with every sentence sent and wrapping;
- the tag block checksum is the XOR of the characters between the opening backslash and the
  ``*``, two upper-case hex digits, as for the sentences;
- a datagram stays within 1472 bytes (one Ethernet frame); more sentences go into more
  datagrams.

Transmission groups are IPv4 multicast 239.192.0.1-239.192.0.64 on ports 60001-60064, the
group chosen by the bridge network's plan; a unicast address works as well (tests use
loopback). The TCP server sends the same sentences plainly (no tag blocks) to every
connected client, for equipment without 61162-450.
"""

from __future__ import annotations

import ipaddress
import math
import socket
import threading
from collections.abc import Iterable, Sequence
from typing import Any, Protocol

from .nmea import Alert, BridgeState, SentenceMaker

__all__ = [
    "IEC450_HEADER",
    "tag_block",
    "iec450_datagrams",
    "Iec450Sender",
    "NmeaTcpServer",
    "NmeaOutput",
    "SentenceSink",
    "bridge_state",
    "bridge_alerts",
]

IEC450_HEADER = b"UdPbC\x00"
MAX_DATAGRAM = 1472


def _checksum(text: str) -> str:
    value = 0
    for ch in text.encode("ascii"):
        value ^= ch
    return f"{value:02X}"


def tag_block(source_id: str, line_count: int) -> bytes:
    """The tag block ``\\s:<source>,n:<count>*hh\\`` of one sentence."""
    if len(source_id) != 6 or not source_id[:2].isalpha() or not source_id[2:].isdigit():
        raise ValueError(f"source id {source_id!r} is not a talker id + 4 digits (e.g. II0001)")
    if not 1 <= line_count <= 999:
        raise ValueError(f"line count {line_count} is not 1..999")
    body = f"s:{source_id},n:{line_count}"
    return f"\\{body}*{_checksum(body)}\\".encode("ascii")


def iec450_datagrams(sentences: Sequence[bytes], source_id: str, first_line: int
                     ) -> tuple[list[bytes], int]:
    """Datagrams carrying ``sentences`` with line counts from ``first_line``; returns them
    and the next line count."""
    datagrams: list[bytes] = []
    current = bytearray(IEC450_HEADER)
    line = first_line
    for sentence in sentences:
        item = tag_block(source_id, line) + sentence
        if len(current) + len(item) > MAX_DATAGRAM and len(current) > len(IEC450_HEADER):
            datagrams.append(bytes(current))
            current = bytearray(IEC450_HEADER)
        current += item
        line = line % 999 + 1
    if len(current) > len(IEC450_HEADER):
        datagrams.append(bytes(current))
    return datagrams, line


class SentenceSink(Protocol):
    def send(self, sentences: Sequence[bytes]) -> None: ...


class Iec450Sender:
    """Sends sentences as IEC 61162-450 datagrams to a multicast group or a unicast address."""

    def __init__(self, address: tuple[str, int], source_id: str = "II0001", *,
                 ttl: int = 1, interface: str | None = None):
        tag_block(source_id, 1)  # validates the id
        self.address = address
        self.source_id = source_id
        self._line = 1
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            multicast = ipaddress.ip_address(address[0]).is_multicast
        except ValueError:  # a host name: unicast
            multicast = False
        if multicast:
            self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, ttl)
            if interface:
                self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF,
                                      socket.inet_aton(interface))
        self.datagrams_sent = 0

    def send(self, sentences: Sequence[bytes]) -> None:
        datagrams, self._line = iec450_datagrams(sentences, self.source_id, self._line)
        for d in datagrams:
            self._sock.sendto(d, self.address)
            self.datagrams_sent += 1

    def close(self) -> None:
        self._sock.close()


class NmeaTcpServer:
    """A TCP server sending plain sentences to every connected client.

    A client that does not keep up (its socket buffer full for ``send_timeout_s``) or went
    away is dropped; the others go on.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, send_timeout_s: float = 0.5):
        self._server = socket.create_server((host, port))
        self._server.settimeout(0.2)
        self.address = self._server.getsockname()[:2]
        self.send_timeout_s = send_timeout_s
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, name="nmea-tcp", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(self.send_timeout_s)
            with self._lock:
                self._clients.append(conn)

    @property
    def client_count(self) -> int:
        with self._lock:
            return len(self._clients)

    def send(self, sentences: Sequence[bytes]) -> None:
        data = b"".join(sentences)
        with self._lock:
            for conn in list(self._clients):
                try:
                    conn.sendall(data)
                except OSError:  # gone or stalled: drop it
                    self._clients.remove(conn)
                    conn.close()

    def close(self) -> None:
        self._stop.set()
        self._server.close()
        self._thread.join(timeout=2)
        with self._lock:
            for conn in self._clients:
                conn.close()
            self._clients.clear()


class NmeaOutput:
    """The bridge output of a session: sentences at their rates, alerts when they change.

    ``rates_hz`` per sentence group: "heading" (HDT, THS, ROT), "course" (VTG), "position"
    (GGA), "time" (ZDA); a group is sent when its period has elapsed in the states' gpst.
    Every sink has a ``send(list of sentences)`` (an :class:`Iec450Sender`, a
    :class:`NmeaTcpServer`).
    """

    DEFAULT_RATES = {"heading": 10.0, "course": 1.0, "position": 1.0, "time": 1.0}

    def __init__(self, sinks: Sequence[SentenceSink], maker: SentenceMaker | None = None,
                 rates_hz: dict[str, float] | None = None):
        self.sinks = list(sinks)
        self.maker = maker if maker is not None else SentenceMaker()
        self.rates_hz = {**self.DEFAULT_RATES, **(rates_hz or {})}
        unknown = set(self.rates_hz) - set(self.DEFAULT_RATES)
        if unknown:
            raise ValueError(f"unknown sentence group(s) {sorted(unknown)}")
        self._next: dict[str, float] = {}
        self._alerts: dict[int, Alert] = {}

    def _due(self, group: str, t: float) -> bool:
        rate = self.rates_hz[group]
        if rate <= 0:
            return False
        nxt = self._next.get(group)
        if nxt is not None and t < nxt - 1e-6:
            return False
        # next slot on the rate's grid (10 Hz at .0, .1 ...), never earlier than now
        period = 1.0 / rate
        self._next[group] = (int(t / period + 1e-6) + 1) * period
        return True

    def update(self, state: BridgeState) -> list[bytes]:
        """Send the sentences due at ``state.time``; returns them (none for a state without
        a finite time: nothing could say when it held)."""
        out: list[bytes] = []
        if not math.isfinite(state.time):
            return out
        if self._due("heading", state.time):
            out += self.maker.heading(state)
        if self._due("course", state.time):
            out.append(self.maker.course_speed(state))
        if self._due("position", state.time):
            out.append(self.maker.position(state))
        if self._due("time", state.time):
            out.append(self.maker.time(state.time))
        if out:
            self._send(out)
        return out

    def alerts(self, alerts: Iterable[Alert]) -> list[bytes]:
        """Send ALR/ALF for every alert that is new or changed since the last call."""
        out: list[bytes] = []
        for a in alerts:
            if self._alerts.get(a.alert_id) != a:
                self._alerts[a.alert_id] = a
                out += self.maker.alert(a)
        if out:
            self._send(out)
        return out

    def _send(self, sentences: list[bytes]) -> None:
        for sink in self.sinks:
            sink.send(sentences)


# How far ahead a state is carried to the time it is sent at most: beyond, it is old news
# (a live feed gone quiet), sent with its own time.
MAX_AHEAD_S = 1.0
EARTH_RADIUS_M = 6378137.0


def bridge_state(state: Any, *, simulated: bool = False, ahead_s: float = 0.0,
                 turned: tuple[float, float] | None = None) -> BridgeState:
    """What the bridge is told of a fused state (``estimator.options.FusedState``).

    ``ahead_s``: how long before the sending the state is (its frame's capture, transport and
    processing): its heading, position and time are carried forward on the rate of turn and
    the velocity, so that the bridge gets now's (a user trial: the HDT 0.4 s old, 1.6° behind
    in a 4°/s turn). Up to ``MAX_AHEAD_S``; 0 for a replay. ``turned``: (rad, s) the gyro
    measured over the first s of it (``LiveRunner.turned_after``), the rest on the rate of
    turn: a turn that starts or ends meanwhile is in the samples, not in the rate.

    Mode: not trusted by the integrity layer, or any number not finite → ``invalid`` (the
    sentences' fields empty, GGA quality 0); trusted while coasting on the INS →
    ``dead-reckoning``; trusted → ``gnss`` (the absolute position is standalone-GNSS
    anchored: quality 1, never claimed RTK), or ``simulated`` for a replayed recording."""
    integrity = getattr(state.status, "integrity", None)
    if integrity is None or not integrity.trusted:
        mode = "invalid"
    elif simulated:
        mode = "simulated"
    elif integrity.mode == "coasting":
        mode = "dead-reckoning"
    else:
        mode = "gnss"
    dt = min(max(float(ahead_s), 0.0), MAX_AHEAD_S) if math.isfinite(ahead_s) else 0.0
    lat, lon, h = (float(x) for x in state.llh_deg)
    vn, ve, vd = (float(x) for x in state.velocity_ned)
    roll, pitch, yaw = (float(x) for x in state.euler)
    rot = float(state.rate_of_turn)
    if not all(math.isfinite(x) for x in (lat, lon, h, vn, ve, vd, roll, pitch, yaw, rot)):
        mode = "invalid"  # a damaged state is never sent as trusted, whatever its flags
    yaw_ahead = rot * dt
    if turned is not None and dt > 0.0 and all(math.isfinite(x) for x in turned):
        covered = min(max(turned[1], 0.0), dt)
        yaw_ahead = turned[0] * covered / max(turned[1], 1e-9) + rot * (dt - covered)
    lat_ahead = lat + math.degrees(vn * dt / EARTH_RADIUS_M)
    lon_ahead = lon + math.degrees(ve * dt / (EARTH_RADIUS_M * max(math.cos(math.radians(lat)),
                                                                     1e-6)))
    return BridgeState(
        time=float(state.time) + dt,
        llh_deg=(lat_ahead, lon_ahead, h - vd * dt),
        velocity_ned=(vn, ve, vd),
        euler=(roll, pitch, yaw + yaw_ahead),
        rate_of_turn=rot, mode=mode,
        satellites=int(getattr(state.status, "satellites", 0) or 0))


_PRIORITIES = {"alarm": "alarm", "warning": "warning", "caution": "caution"}


def bridge_alerts(alarms: Iterable[dict[str, Any]], start_gpst: float) -> list[Alert]:
    """A session's alarms (``backend.alarms.AlarmEntry.as_dict``: id ``A<n>``, severity,
    message, since_s, active, acknowledged) as bridge alerts, alert id = n (1..999)."""
    out = []
    for a in alarms:
        n = int(str(a["id"]).lstrip("A") or 0)
        out.append(Alert(alert_id=(n - 1) % 999 + 1, text=str(a["message"]),
                         priority=_PRIORITIES.get(a["severity"], "warning"),
                         active=bool(a["active"]), acknowledged=bool(a["acknowledged"]),
                         changed=start_gpst + float(a["since_s"])))
    return out
