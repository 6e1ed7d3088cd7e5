"""The evaluation's subcommands of ``berthing-aid``: ``replay --report``, ``compass``,
``baseline``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from recordings import DEFAULT_RECORDING

from .baseline import baseline_report, format_baseline_report, read_position
from .campaign import (
    SAME_FIGURE_REL_TOL,
    format_summary,
    run_campaign,
    spec_from_args,
    summary_differences,
    write_plots,
)
from .compass import compass_report, format_compass_report
from .records import to_json
from .report import INIT_S, ReportOptions, replay_report
from .text import format_replay_report


def _progress(quiet: bool):  # noqa: ANN202 - a callable or a no-op
    """One line per stage on stderr (stdout carries the report)."""
    count = 0

    def show(text: str) -> None:
        nonlocal count
        count += 1
        print(f"replay [{count:2d}] {text}", file=sys.stderr, flush=True)

    return (lambda _text: None) if quiet else show


def _print(report: object, as_json: bool, as_text: Callable[[Any], str]) -> None:
    """A report on stdout: strict JSON (``--json``) or its text tables."""
    print(json.dumps(to_json(report), indent=2, allow_nan=False) if as_json else as_text(report))


def cmd_replay(args: argparse.Namespace) -> int:
    if not args.report:
        raise ValueError("replay: add --report to run the thesis' experiments (the interactive "
                         "replay is `berthing-aid serve`)")
    path = Path(args.recording) if args.recording else DEFAULT_RECORDING
    options = ReportOptions(init_s=args.init, end_s=args.end, plots_dir=args.plots,
                            tracking=not args.no_tracking)
    report = replay_report(path, options, _progress(args.quiet))
    _print(report, args.json, format_replay_report)
    return 0


def add_replay_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``berthing-aid replay RECORDING --report [--json] [--plots DIR]``."""
    p = sub.add_parser("replay", help="replay a recording through the fusion and reproduce the "
                                      "thesis' tables against its reference")
    p.add_argument("recording", nargs="?", help="recording directory (default: bundled)")
    p.add_argument("--report", action="store_true",
                   help="run the experiments (tables 17-21, fig. 14, structure, timing)")
    p.add_argument("--json", action="store_true", help="JSON instead of the tables")
    p.add_argument("--plots", metavar="DIR", default=None, help="write PNG plots into DIR")
    p.add_argument("--init", type=float, default=INIT_S, metavar="S",
                   help=f"initialisation before the window (default {INIT_S:g} s)")
    p.add_argument("--end", type=float, default=None, metavar="S",
                   help="replay only the first S seconds (default: all)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--no-tracking", action="store_true",
                   help="skip the designated-target and landmark evaluations")
    p.set_defaults(func=cmd_replay)
    return p


def cmd_compass(args: argparse.Namespace) -> int:
    path = Path(args.recording) if args.recording else DEFAULT_RECORDING
    report = compass_report(path, trials=args.trials, gps_only=args.gps_only,
                            sky_mask_deg=args.sky_mask, as_json=args.json)
    _print(report, args.json, format_compass_report)
    return 0


def add_compass_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``berthing-aid compass RECORDING [--json] [--trials N] [--gps-only]
    [--sky-mask DEG]``."""
    p = sub.add_parser("compass", help="GNSS compass time to fix / attitude error and "
                                       "carrier-phase velocity against the reference")
    p.add_argument("recording", nargs="?", help="recording directory (default: bundled)")
    p.add_argument("--json", action="store_true", help="JSON with the per-trial results")
    p.add_argument("--trials", type=int, default=20, help="cold starts (default 20)")
    p.add_argument("--gps-only", action="store_true", help="GPS satellites only")
    p.add_argument("--sky-mask", type=float, default=0.0, metavar="DEG",
                   help="block satellites within +-DEG/2 of north in azimuth (180 = half sky)")
    p.set_defaults(func=cmd_compass)
    return p


def cmd_baseline(args: argparse.Namespace) -> int:
    base_pos = rover_pos = None
    if args.surveyed:
        base_pos, rover_pos = (read_position(Path(p)) for p in args.surveyed)
    report = baseline_report(args.base, args.rover, args.nav, as_json=args.json,
                             restart_every_s=args.restart_every,
                             base_position_llh_deg=base_pos, rover_position_llh_deg=rover_pos)
    _print(report, args.json, format_baseline_report)
    return 0


def add_baseline_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``berthing-aid baseline BASE.obs ROVER.obs NAV [--json]``."""
    p = sub.add_parser("baseline", help="two-receiver carrier-phase baseline, time to fix, "
                                        "TDCP velocity (real RINEX files)")
    p.add_argument("base", help="RINEX observation file of the base receiver")
    p.add_argument("rover", help="RINEX observation file of the rover receiver")
    p.add_argument("nav", help="RINEX navigation file")
    p.add_argument("--json", action="store_true", help="JSON with the per-epoch baselines")
    p.add_argument("--restart-every", type=float, default=20.0, metavar="S",
                   help="cold-start restarts every S seconds (default 20)")
    p.add_argument("--surveyed", nargs=2, metavar=("BASE_POS", "ROVER_POS"),
                   help="files 'lat lon h' (deg, deg, m) of the surveyed antennas "
                        "(default: <obs stem>_position.txt beside each file, if present)")
    p.set_defaults(func=cmd_baseline)
    return p


def cmd_campaign(args: argparse.Namespace) -> int:
    spec = spec_from_args(args.scenario, args.seeds, args.duration, args.faults, args.options,
                          tracking=not args.no_tracking, quick=args.quick)
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers {args.workers}: must be at least 1")
    tic = time.monotonic()
    summary = run_campaign(spec, args.out, cache=args.cache, workers=args.workers,
                           scheduler=args.scheduler, show_progress=not args.quiet)
    if args.plots:
        write_plots(Path(args.out), spec.tasks())
    print(format_summary(summary))
    print(f"{summary['succeeded']} of {summary['tasks']} tasks in "
          f"{time.monotonic() - tic:.0f} s; {args.out}/summary.md", file=sys.stderr)
    return 0 if not summary["failed"] else 1


def add_campaign_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``berthing-aid campaign``."""
    p = sub.add_parser("campaign", help="the replay evaluation over many simulated berthings "
                                        "and injected faults, on a Dask cluster")
    p.add_argument("--scenario", default="small-boat", help="scenario name(s), comma-separated")
    p.add_argument("--seeds", default="1-3", help="seeds, e.g. 1-20 or 1,4,7-9")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="seconds per recording (default: the scenario's)")
    p.add_argument("--faults", default=None, metavar="LIST",
                   help="faults injected into each recording: all, or KIND[:a:b],... "
                        "(clean = none); default: none")
    p.add_argument("--options", default=None, metavar="JSON",
                   help="FusionOptions fields for every task (a parameter sweep)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None,
                       help="local cluster of N worker processes (default: one per core)")
    where.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                       help="a running Dask scheduler (workers: dask worker tcp://HOST:PORT)")
    p.add_argument("--out", required=True, help="output directory (resumable)")
    p.add_argument("--cache", default=None,
                   help="simulated recordings (default OUT/recordings; a path every worker "
                        "reaches when on a cluster)")
    p.add_argument("--plots", action="store_true", help="box plots and the Stanford scatter")
    p.add_argument("--no-tracking", action="store_true",
                   help="skip the designated-target and landmark evaluations")
    p.add_argument("--quick", action="store_true",
                   help="table 17 and the integrity only (no satellite subsets, fig. 14)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_campaign)
    return p


def cmd_campaign_compare(args: argparse.Namespace) -> int:
    a, b = (json.loads((Path(d) / "summary.json").read_text()) for d in (args.first, args.second))
    diffs = summary_differences(a, b)
    for line in diffs:
        print(line)
    print(f"{len(diffs)} difference(s) beyond {SAME_FIGURE_REL_TOL:g} relative between "
          f"{args.first} ({a['succeeded']} of {a['tasks']} tasks) and {args.second} "
          f"({b['succeeded']} of {b['tasks']} tasks)")
    return 0 if not diffs else 1


def add_campaign_compare_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``berthing-aid campaign-compare``."""
    p = sub.add_parser("campaign-compare", help="whether two campaigns' summaries agree (a "
                                                "local run and a cluster's, say)")
    p.add_argument("first", help="a campaign's --out directory")
    p.add_argument("second", help="another campaign's --out directory")
    p.set_defaults(func=cmd_campaign_compare)
    return p


def add_parsers(sub: argparse._SubParsersAction) -> None:
    add_campaign_compare_parser(sub)
    add_baseline_parser(sub)
    add_campaign_parser(sub)
    add_compass_parser(sub)
    add_replay_parser(sub)
