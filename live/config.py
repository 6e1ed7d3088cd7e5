"""The live session's configuration: a TOML file naming the devices, the installation and the
outputs (``live/example.toml`` is the commented example; ``berthing-aid emulate
--write-config`` writes one).

``load_config(path)`` checks every field and raises :class:`ConfigError` naming the file and
the field; relative paths in the file are relative to the file's directory.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["ConfigError", "ImuInput", "CameraInput", "BridgeConfig", "LiveConfig",
           "load_config", "load_bridge_config", "config_text"]

SENTENCE_GROUPS = ("heading", "course", "position", "time")


class ConfigError(ValueError):
    """A live configuration that cannot be used (the message names the file and field)."""


@dataclass(frozen=True)
class ImuInput:
    kind: str  # "text" (the text protocol on url) or "esf" (UBX ESF-RAW in a receiver stream)
    url: str | None = None  # text: udp://:PORT, serial://..., tcp://...
    receiver: int = 1  # esf: the receiver (1..4) whose stream carries ESF-RAW
    offset_s: float = 0.0  # esf: sensor time offset (live.ubx_imu)


@dataclass(frozen=True)
class CameraInput:
    url: str
    latency_s: float = 0.0  # capture-to-reception delay, subtracted from the arrival time


@dataclass(frozen=True)
class BridgeConfig:
    udp: tuple[str, int] | None = None  # IEC 61162-450 datagrams to this group/address
    source_id: str = "II0001"
    tcp: tuple[str, int] | None = None  # plain sentences to every client of this port
    rates_hz: dict[str, float] = field(default_factory=dict)
    leap_seconds: int = 18


@dataclass(frozen=True)
class LiveConfig:
    path: Path  # the file itself
    name: str
    receivers: tuple[str, ...]  # receiver i = antenna i of the calibration
    imu: ImuInput
    camera: CameraInput
    calibration: Path
    hull: Path
    origin_llh_deg: tuple[float, float, float]
    record_dir: Path | None  # a new recording per session under it; None: not recorded
    nav_seed: Path | None = None
    stall_timeout_s: float = 3.0  # a device silent this long is declared stopped
    max_lag_s: float = 0.5  # the longest a message waits for a lagging stream
    bridge: BridgeConfig = field(default_factory=BridgeConfig)


def _address(text: Any, where: str) -> tuple[str, int]:
    if not isinstance(text, str) or ":" not in text:
        raise ValueError(f"{where} must be \"HOST:PORT\", got {text!r}")
    host, _, port = text.rpartition(":")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{where}: port {port!r} is not 1..65535")
    return host.strip("[]") or "127.0.0.1", int(port)


class _Table:
    """A TOML table read field by field, errors naming the field's full path."""

    def __init__(self, data: Any, where: str):
        if not isinstance(data, dict):
            raise ValueError(f"[{where}] must be a table")
        self.data, self.where, self.used = data, where, set()

    def get(self, key: str, kind: type | tuple[type, ...], default: Any = ...) -> Any:
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                raise ValueError(f"{self.where}.{key} is missing")
            return default
        value = self.data[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            raise ValueError(f"{self.where}.{key} = {value!r} is not a {_kind_name(kind)}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{self.where}.{key} = {value!r} is not finite")
        return value

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:  # a misspelt key would otherwise be silently ignored
            raise ValueError(f"[{self.where}] has unknown key(s) {unknown}")


def _kind_name(kind: type | tuple[type, ...]) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join({str: "string", float: "number", int: "integer", list: "list",
                        dict: "table", bool: "boolean"}.get(k, k.__name__) for k in kinds)


def load_config(path: str | Path) -> LiveConfig:
    """Read and check a live configuration file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    try:
        return _parse(path, data)
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _parse(path: Path, data: dict[str, Any]) -> LiveConfig:
    base = path.parent
    top = _Table(data, "config")

    def rel(value: str) -> Path:
        p = Path(value).expanduser()
        return p if p.is_absolute() else base / p

    session = _Table(top.get("session", dict), "session")
    name = session.get("name", str, "live")
    calibration = rel(session.get("calibration", str))
    hull = rel(session.get("hull", str))
    origin = session.get("origin_llh_deg", list)
    if len(origin) != 3 or not all(isinstance(v, int | float) and math.isfinite(v)
                                   for v in origin):
        raise ValueError(f"session.origin_llh_deg must be [lat, lon, height], got {origin!r}")
    if not (-90 <= origin[0] <= 90 and -180 <= origin[1] <= 360 and -1e4 < origin[2] < 1e5):
        raise ValueError(f"session.origin_llh_deg {origin!r} is not a place on Earth")
    record = session.get("record_dir", str, "")
    stall = session.get("stall_timeout_s", float, 3.0)
    lag = session.get("max_lag_s", float, 0.5)
    for key, value, lo, hi in (("stall_timeout_s", stall, 0.2, 60.0),
                               ("max_lag_s", lag, 0.05, 10.0)):
        if not lo <= value <= hi:
            raise ValueError(f"session.{key} = {value} is outside {lo}..{hi} s")
    session.done()
    for what, p in (("session.calibration", calibration), ("session.hull", hull)):
        if not p.is_file():
            raise ValueError(f"{what}: {p} does not exist")

    gnss = _Table(top.get("gnss", dict), "gnss")
    receivers = gnss.get("receivers", list)
    if len(receivers) != 4 or not all(isinstance(r, str) and r for r in receivers):
        raise ValueError(f"gnss.receivers must list the 4 receivers' stream URLs (antenna 1..4),"
                         f" got {receivers!r}")
    seed = gnss.get("nav_seed", str, "")
    gnss.done()
    if seed and not rel(seed).is_file():
        raise ValueError(f"gnss.nav_seed: {rel(seed)} does not exist")

    imu_t = _Table(top.get("imu", dict), "imu")
    kind = imu_t.get("kind", str)
    if kind == "text":
        imu = ImuInput("text", url=imu_t.get("url", str))
    elif kind == "esf":
        rx = imu_t.get("receiver", int, 1)
        if not 1 <= rx <= 4:
            raise ValueError(f"imu.receiver = {rx} is not 1..4")
        imu = ImuInput("esf", receiver=rx, offset_s=imu_t.get("offset_s", float, 0.0))
    else:
        raise ValueError(f"imu.kind = {kind!r} is neither \"text\" nor \"esf\"")
    imu_t.done()

    cam_t = _Table(top.get("camera", dict), "camera")
    camera = CameraInput(cam_t.get("url", str), cam_t.get("latency_s", float, 0.0))
    if not 0.0 <= camera.latency_s <= 5.0:
        raise ValueError(f"camera.latency_s = {camera.latency_s} is outside 0..5 s")
    cam_t.done()

    bridge = _bridge(top.get("bridge", dict)) if "bridge" in data else BridgeConfig()
    top.done()
    return LiveConfig(path=path, name=name, receivers=tuple(receivers), imu=imu, camera=camera,
                      calibration=calibration, hull=hull,
                      origin_llh_deg=(float(origin[0]), float(origin[1]), float(origin[2])),
                      record_dir=rel(record) if record else None,
                      nav_seed=rel(seed) if seed else None, stall_timeout_s=stall,
                      max_lag_s=lag, bridge=bridge)


def _bridge(table: dict[str, Any]) -> BridgeConfig:
    b = _Table(table, "bridge")
    udp = b.get("udp", str, "")
    tcp = b.get("tcp", str, "")
    rates = b.get("rates_hz", dict, {})
    unknown = set(rates) - set(SENTENCE_GROUPS)
    if unknown:
        raise ValueError(f"bridge.rates_hz: unknown group(s) {sorted(unknown)} (known: "
                         f"{', '.join(SENTENCE_GROUPS)})")
    for key, value in rates.items():
        if not isinstance(value, int | float) or not 0 <= value <= 50:
            raise ValueError(f"bridge.rates_hz.{key} = {value!r} is not 0..50")
    out = BridgeConfig(udp=_address(udp, "bridge.udp") if udp else None,
                       source_id=b.get("source_id", str, "II0001"),
                       tcp=_address(tcp, "bridge.tcp") if tcp else None,
                       rates_hz={k: float(v) for k, v in rates.items()},
                       leap_seconds=b.get("leap_seconds", int, 18))
    b.done()
    if out.udp is None and out.tcp is None:
        raise ValueError("[bridge] names no output: set udp and/or tcp")
    return out


def load_bridge_config(path: str | Path) -> BridgeConfig:
    """The ``[bridge]`` table of a TOML file (for ``serve --bridge`` on replays)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        if "bridge" not in data:
            raise ValueError("no [bridge] table")
        return _bridge(data["bridge"])
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _q(value: str | Path) -> str:
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def config_text(*, receivers: list[str], imu: ImuInput, camera: CameraInput,
                calibration: Path, hull: Path, origin_llh_deg: tuple[float, float, float],
                record_dir: Path | None, name: str = "live",
                bridge: BridgeConfig | None = None, comment: str = "") -> str:
    """A configuration file's text (what ``emulate --write-config`` writes)."""
    lines = [f"# {line}" for line in comment.splitlines()] + [
        "[session]",
        f"name = {_q(name)}",
        f"calibration = {_q(calibration)}",
        f"hull = {_q(hull)}",
        "origin_llh_deg = [{:.9f}, {:.9f}, {:.3f}]".format(*origin_llh_deg),
        f"record_dir = {_q(record_dir or '')}",
        "",
        "[gnss]",
        "receivers = [" + ", ".join(_q(r) for r in receivers) + "]",
        "",
        "[imu]",
        f"kind = {_q(imu.kind)}",
    ]
    if imu.kind == "text":
        lines.append(f"url = {_q(imu.url or '')}")
    else:
        lines += [f"receiver = {imu.receiver}", f"offset_s = {imu.offset_s}"]
    lines += ["", "[camera]", f"url = {_q(camera.url)}", f"latency_s = {camera.latency_s}"]
    if bridge is not None:
        lines += ["", "[bridge]"]
        if bridge.udp:
            lines.append(f"udp = {_q(f'{bridge.udp[0]}:{bridge.udp[1]}')}")
        lines.append(f"source_id = {_q(bridge.source_id)}")
        if bridge.tcp:
            lines.append(f"tcp = {_q(f'{bridge.tcp[0]}:{bridge.tcp[1]}')}")
        if bridge.rates_hz:
            lines.append("rates_hz = { " + ", ".join(f"{k} = {v}" for k, v in
                                                      bridge.rates_hz.items()) + " }")
    return "\n".join(lines) + "\n"
