"""The ``berthing-aid`` command: one subcommand per thing a user does.

Subcommands import their modules lazily so that ``berthing-aid info`` does not pay for the web
stack and a missing optional piece only affects its own subcommand.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from recordings import DEFAULT_RECORDING

# The estimator's matrices are small (~40 states): a multi-threaded BLAS costs far more in
# thread hand-offs than it gains, and starves the VO on a 2-core machine. Set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")



def _recording_arg(value: str | None) -> Path:
    return Path(value) if value else DEFAULT_RECORDING


def cmd_simulate(args: argparse.Namespace) -> int:
    from recordings.sim.simulate import simulate

    out = simulate(args.scenario, args.seed, args.out, duration_s=args.duration,
                   progress=not args.quiet, camera_size=args.camera_size)
    print(f"wrote {out}")
    return 0


def cmd_inject(args: argparse.Namespace) -> int:
    from recordings.faults import inject

    out = inject(_recording_arg(args.recording), args.fault, args.out)
    print(f"wrote {out}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from recordings.format import format_summary, load, summary

    info = summary(load(_recording_arg(args.recording)))
    print(json.dumps(info, indent=2) if args.json else format_summary(info))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from backend.access import CONTROL_ENV, access_for, is_loopback
    from backend.app import Settings, create_app

    live_config = bridge = None
    if args.live:
        from live.config import load_config

        live_config = load_config(args.live)
        if args.recordings_dir is None and live_config.record_dir is not None:
            live_config.record_dir.mkdir(parents=True, exist_ok=True)
            args.recordings_dir = str(live_config.record_dir)  # its berthings replay here
    if args.bridge:
        from live.config import load_bridge_config

        bridge = load_bridge_config(args.bridge)
    recording = _recording_arg(args.recording).resolve()
    if not (recording / "manifest.json").is_file():
        hint = ("make one with: berthing-aid simulate --scenario small-boat --seed 1 --out DIR"
                if args.recording is None else "give a recording directory")
        raise ValueError(f"{recording}: no recording there (no manifest.json); {hint}")
    recordings_dir = Path(args.recordings_dir) if args.recordings_dir else None
    if recordings_dir is not None and not recordings_dir.is_dir():
        raise ValueError(f"--recordings-dir {recordings_dir}: not a directory")
    from estimator.integrity import IntegrityConfig

    for name, value in (("--alert-limit", args.alert_limit),
                        ("--heading-alert-limit", args.heading_alert_limit)):
        if not (value > 0 and value < 1e3):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    integrity = IntegrityConfig(alert_limit_m=args.alert_limit,
                                heading_alert_limit_deg=args.heading_alert_limit)
    _port_free(args.host, args.port, "--port")
    if not args.no_viewer and args.viser_port:
        _port_free(args.viser_host or args.host, args.viser_port, "--viser-port")
    access, generated = access_for(args.host)
    # The 3-D viewer (viser) has no access control of its own: off loopback it listens on
    # loopback only unless asked.
    viser_host = args.viser_host or (args.host if is_loopback(args.host) else "127.0.0.1")
    settings = Settings(recordings_dir=recordings_dir, default_recording=recording,
                        viser_host=viser_host, viser_port=None if args.no_viewer
                        else args.viser_port, announce=True, access=access,
                        integrity=integrity, live_config=live_config, bridge=bridge,
                        warm_scout=True)
    shown = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
    if ":" in shown:
        shown = f"[{shown}]"
    url = f"http://{shown}:{args.port}/"
    print(f"berthing aid: {url}  (API docs {url}docs), recording {recording}", flush=True)
    if access.required:
        source = "generated for this run" if generated else f"from ${CONTROL_ENV}"
        print(f"access tokens ({source}); open the page with one:", flush=True)
        print(f"  control:   {url}#token={access.control}", flush=True)
        if access.view:
            print(f"  read-only: {url}#token={access.view}", flush=True)
    if not is_loopback(viser_host) and not args.no_viewer:
        print(f"warning: the 3-D viewer listens on {viser_host} without access control",
              file=sys.stderr)
    # no per-message deflate: the stream is mostly JPEG, which it cannot shrink (it cost ~10 %
    # of a core with four clients)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="warning",
                ws_per_message_deflate=False)
    return 0


def _port_free(host: str, port: int, option: str) -> None:
    """Refuse, before anything starts or is printed, a port another program listens on (a
    second server printed its address, then died in uvicorn's bind with a thread's FATAL)."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ValueError(f"{option} {port}: cannot listen on {host}:{port} ({exc.strerror}"
                             "; another berthing-aid serve?)") from None


def cmd_emulate(args: argparse.Namespace) -> int:
    from live.config import BridgeConfig, _address
    from live.emulator import Emulator
    from recordings.format import load

    if not 0.1 <= args.speed <= 10:
        raise ValueError(f"--speed {args.speed} is outside 0.1..10")
    bridge = None
    if args.bridge_udp or args.bridge_tcp:
        bridge = BridgeConfig(
            udp=_address(args.bridge_udp, "--bridge-udp") if args.bridge_udp else None,
            tcp=_address(args.bridge_tcp, "--bridge-tcp") if args.bridge_tcp else None)
    rec = load(_recording_arg(args.recording))
    emulator = Emulator(rec, imu=args.imu, speed=args.speed)
    config = Path(args.write_config)
    config.write_text(emulator.config_text(
        record_dir=Path(args.record_dir) if args.record_dir else None, bridge=bridge),
        encoding="utf-8")
    emulator.start()
    print(f"emulating {rec.path} ({rec.manifest.duration_s:g} s); config: {config}", flush=True)
    print("waiting for a live session (berthing-aid serve --live "
          f"{config}) to connect…", flush=True)
    try:
        while not emulator.started.wait(0.5):
            pass
        print("playing", flush=True)
        emulator.wait()
        print("end of the recording", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        emulator.stop()
    return 0


def _size(text: str) -> tuple[int, int]:
    """``WxH`` → (W, H)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT (e.g. 1920x1200)"
                                         ) from None
    return w, h


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="berthing-aid", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="synthesise a recorded berthing with a reference")
    p.add_argument("--scenario", default="small-boat", help="small-boat or large-ship")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", required=True, help="output directory (new or empty)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: scenario's)")
    p.add_argument("--camera-size", type=_size, default=None, metavar="WxH",
                   help="video size, same field of view (default: the scenario's 960x600; "
                        "the thesis camera: 1920x1200)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_simulate)

    from recordings.faults import FAULTS

    p = sub.add_parser("inject", help="a damaged copy of a recording (fault injection)")
    p.add_argument("recording", nargs="?", help="recording directory (default: bundled)")
    p.add_argument("--fault", required=True, metavar="KIND[:a:b]",
                   help=f"one of {', '.join(FAULTS)}; parameters in s after the start "
                        "(see recordings/faults.py)")
    p.add_argument("--out", required=True, help="output directory (new or empty)")
    p.set_defaults(func=cmd_inject)

    p = sub.add_parser("info", help="what a recording holds")
    p.add_argument("recording", nargs="?", help="recording directory (default: bundled)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("serve", help="web server: replay sessions, stream, API, 3-D viewer")
    p.add_argument("recording", nargs="?", help="default recording (default: bundled)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default: loopback). Anything else requires access "
                        "tokens: from $BERTHING_AID_TOKEN (control) and $BERTHING_AID_VIEW_TOKEN "
                        "(read-only), else generated and printed")
    p.add_argument("--port", type=int, default=8000, help="HTTP port (default 8000)")
    p.add_argument("--viser-port", type=int, default=8080,
                   help="3-D viewer port (default 8080; 0: any free port)")
    p.add_argument("--viser-host", default=None,
                   help="address of the 3-D viewer (default: --host on loopback, else "
                        "127.0.0.1: the viewer has no access control)")
    p.add_argument("--no-viewer", action="store_true", help="do not start the 3-D viewer")
    p.add_argument("--recordings-dir", default=None,
                   help="directory whose recordings (sub-directories) can be replayed too")
    p.add_argument("--alert-limit", type=float, default=0.5, metavar="M",
                   help="horizontal alert limit: a protection level beyond it is not trusted "
                        "(default 0.5 m)")
    p.add_argument("--heading-alert-limit", type=float, default=1.0, metavar="DEG",
                   help="heading alert limit (default 1 deg)")
    p.add_argument("--live", default=None, metavar="CONFIG.toml",
                   help="also run a live session on the devices of this config (see "
                        "live/example.toml); the page opens it")
    p.add_argument("--bridge", default=None, metavar="FILE.toml",
                   help="send NMEA of every replay session to the [bridge] outputs of this "
                        "file (mode 'simulated'); a live session uses its config's [bridge]")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("emulate", help="play a recording on loopback as the live devices "
                                       "(4 UBX TCP streams, the IMU, an HTTP MJPEG camera)")
    p.add_argument("recording", nargs="?", help="recording directory (default: bundled)")
    p.add_argument("--write-config", required=True, metavar="FILE",
                   help="write the live config pointing at the emulator here")
    p.add_argument("--record-dir", default=None,
                   help="record_dir of the written config (default: none, not recorded)")
    p.add_argument("--imu", choices=("text", "esf"), default="text",
                   help="IMU as the text protocol over UDP (default) or UBX ESF-RAW in "
                        "receiver 1's stream")
    p.add_argument("--bridge-udp", default=None, metavar="HOST:PORT",
                   help="[bridge] udp of the written config")
    p.add_argument("--bridge-tcp", default=None, metavar="HOST:PORT",
                   help="[bridge] tcp of the written config")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed (default 1)")
    p.set_defaults(func=cmd_emulate)

    from evaluation.cli import add_parsers

    add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:  # RecordingError/RinexError are ValueErrors
        print(f"berthing-aid {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
