"""The ``berthing-aid`` command: one subcommand per thing a user does.

Subcommands import their modules lazily so that ``berthing-aid info`` does not pay for the web
stack and a missing optional piece only affects its own subcommand.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

DEFAULT_RECORDING = Path(__file__).resolve().parent.parent / "recordings" / "default"


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
