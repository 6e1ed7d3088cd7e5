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
                   progress=not args.quiet)
    print(f"wrote {out}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from recordings.format import format_summary, load, summary

    info = summary(load(_recording_arg(args.recording)))
    print(json.dumps(info, indent=2) if args.json else format_summary(info))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from backend.app import Settings, create_app

    recording = _recording_arg(args.recording).resolve()
    if not (recording / "manifest.json").is_file():
        hint = ("make one with: berthing-aid simulate --scenario small-boat --seed 1 --out DIR"
                if args.recording is None else "give a recording directory")
        raise ValueError(f"{recording}: no recording there (no manifest.json); {hint}")
    recordings_dir = Path(args.recordings_dir) if args.recordings_dir else None
    if recordings_dir is not None and not recordings_dir.is_dir():
        raise ValueError(f"--recordings-dir {recordings_dir}: not a directory")
    settings = Settings(recordings_dir=recordings_dir, default_recording=recording,
                        viser_host=args.host, viser_port=None if args.no_viewer
                        else args.viser_port, announce=True)
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: listening on {args.host}: anyone who reaches this machine can open "
              "and control sessions", file=sys.stderr)
    shown = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
    print(f"berthing aid: http://{shown}:{args.port}/  (API docs http://{shown}:{args.port}"
          f"/docs), recording {recording}", flush=True)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="warning")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="berthing-aid", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="synthesise a recorded berthing with a reference")
    p.add_argument("--scenario", default="small-boat", help="small-boat or large-ship")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", required=True, help="output directory (new or empty)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: scenario's)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("info", help="what a recording holds")
    p.add_argument("recording", nargs="?", help="recording directory (default: bundled)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("serve", help="web server: replay sessions, stream, API, 3-D viewer")
    p.add_argument("recording", nargs="?", help="default recording (default: bundled)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default: loopback)")
    p.add_argument("--port", type=int, default=8000, help="HTTP port (default 8000)")
    p.add_argument("--viser-port", type=int, default=8080,
                   help="3-D viewer port (default 8080; 0: any free port)")
    p.add_argument("--no-viewer", action="store_true", help="do not start the 3-D viewer")
    p.add_argument("--recordings-dir", default=None,
                   help="directory whose recordings (sub-directories) can be replayed too")
    p.set_defaults(func=cmd_serve)

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
