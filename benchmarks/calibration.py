"""Simulator calibration: one static receiver's TDCP velocity, real against simulated.

The same code runs on a real static pair of receivers (each receiver alone, its own clock) and
on simulated ``static`` recordings (each of the four receivers alone): ``cpp.receiver_velocities``
(the estimator's TDCP rows corrected with the fusion's atmosphere models, solved per receiver
with its clock drift). Since the antennas do not move, the velocity is its own error. Printed
per figure, real and simulated side by side with their ratio:

- the horizontal RMS of the 1 s TDCP velocity (and, for information, the vertical RMS);
- the horizontal drift of the integrated velocity over every 10, 30, 60 and 120 s window
  (median, p95, max), windows of all receivers pooled.

    .venv/bin/python benchmarks/calibration.py [--real DIR] [--seeds 1-5] [--keep DIR] [--json]

``--real`` is a directory with the two receivers' RINEX observations (``*base*.obs``,
``*rover*.obs``) and a navigation file (``*.nav``); default ``../shared/data/real-static-short-
baseline`` beside the repository (``tests/data`` holds a 2-minute excerpt). Each seed simulates
a full ``static`` recording (5 min, ~1 min of CPU), into ``--keep DIR`` when given (an existing
``DIR/static-seedN`` is reused).
"""

from __future__ import annotations

import os

# Before numpy is imported: small matrices lose more to BLAS threads than they gain.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from anywhere without installing

from estimator.cpp import receiver_velocities  # noqa: E402
from estimator.records import GnssEpoch, NavigationData  # noqa: E402

DEFAULT_REAL = ROOT.parent / "shared" / "data" / "real-static-short-baseline"
WINDOWS_S = (10, 30, 60, 120)
SYSTEMS = "GEJ"  # the simulator's constellations (GPS, Galileo, QZSS L1)
ELEVATION_MASK_DEG = 10.0  # the fusion's default sky mask


@dataclass
class StaticFigures:
    """TDCP velocity error figures of static receivers, each processed alone."""

    receivers: int
    epochs: int  # velocity epochs, all receivers
    horizontal_rms_mps: float
    vertical_rms_mps: float
    drift_m: dict[int, tuple[float, float, float]]  # window (s) → median, p95, max

    def rows(self) -> list[tuple[str, float]]:
        """(name, value in mm or mm/s) of every figure, in print order."""
        out = [("velocity RMS horizontal (mm/s)", 1e3 * self.horizontal_rms_mps)]
        for w, (med, p95, mx) in sorted(self.drift_m.items()):
            out += [(f"drift {w:>3d} s median (mm)", 1e3 * med),
                    (f"drift {w:>3d} s p95 (mm)", 1e3 * p95),
                    (f"drift {w:>3d} s max (mm)", 1e3 * mx)]
        return out


def receiver_velocity(epochs: Sequence[GnssEpoch], nav: NavigationData
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(times, NED velocities (N, 3)) of ONE receiver, as the fusion computes the TDCP
    velocity (``cpp.receiver_velocities`` with the atmosphere correction)."""
    v = receiver_velocities(epochs, nav, systems=SYSTEMS, elevation_mask_deg=ELEVATION_MASK_DEG)
    return (np.array([x.time for x in v]),
            np.array([x.velocity_ned for x in v]).reshape(-1, 3))


def horizontal_drift(times: np.ndarray, velocity_ned: np.ndarray, window_s: float,
                     interval_s: float = 1.0) -> np.ndarray:
    """Horizontal length (m) of the integrated velocity over every window of ``window_s``
    whose velocities are all present (consecutive ``interval_s`` steps)."""
    n_steps = int(round(window_s / interval_s))
    if len(times) < n_steps:
        return np.zeros(0)
    # Integrate each velocity over the interval ending at its time; windows must be gap-free.
    path = np.vstack([[0.0, 0.0], np.cumsum(velocity_ned[:, :2] * interval_s, axis=0)])
    gaps = np.concatenate([[0], np.cumsum(np.abs(np.diff(times) - interval_s) > 1e-3)])
    start = np.arange(len(times) - n_steps + 1)
    end = start + n_steps - 1
    whole = gaps[end] == gaps[start]
    return np.linalg.norm(path[end + 1] - path[start], axis=1)[whole]


Series = list[tuple[np.ndarray, np.ndarray]]  # (times, NED velocities) of each receiver


def velocity_series(receivers: Sequence[Sequence[GnssEpoch]], nav: NavigationData) -> Series:
    """The TDCP velocity of each receiver, alone."""
    return [receiver_velocity(epochs, nav) for epochs in receivers]


def figures(series: Series, windows_s: Sequence[int] = WINDOWS_S) -> StaticFigures:
    """Figures of static receivers' velocity series, epochs and windows of all pooled."""
    v = np.vstack([v for _, v in series])
    if len(v) == 0:
        raise ValueError("no TDCP velocity could be computed")
    drift = {}
    for w in windows_s:
        d = np.concatenate([horizontal_drift(t, vel, w) for t, vel in series])
        drift[w] = ((float(np.median(d)), float(np.percentile(d, 95)), float(d.max()))
                    if len(d) else (np.nan, np.nan, np.nan))
    return StaticFigures(
        receivers=len(series), epochs=len(v),
        horizontal_rms_mps=float(np.sqrt(np.mean(np.sum(v[:, :2] ** 2, axis=1)))),
        vertical_rms_mps=float(np.sqrt(np.mean(v[:, 2] ** 2))), drift_m=drift)


def static_figures(receivers: Sequence[Sequence[GnssEpoch]], nav: NavigationData,
                   windows_s: Sequence[int] = WINDOWS_S) -> StaticFigures:
    """Figures of static receivers, each alone, their epochs and windows pooled."""
    return figures(velocity_series(receivers, nav), windows_s)


def halves(series: Series) -> tuple[Series, Series]:
    """Each receiver's series cut in two at the middle of its time span."""
    first, second = [], []
    for t, v in series:
        early = t <= 0.5 * (t[0] + t[-1])
        first.append((t[early], v[early]))
        second.append((t[~early], v[~early]))
    return first, second


def load_real_pair(path: Path) -> tuple[list[list[GnssEpoch]], NavigationData]:
    """The two receivers' L1 epochs and the navigation data of a real static pair."""
    from recordings.rinex import l1_epochs, read_nav, read_obs

    path = Path(path)
    obs = [sorted(path.glob(f"*{name}*.obs")) for name in ("base", "rover")]
    navs = sorted(path.glob("*.nav"))
    if not all(len(o) == 1 for o in obs) or not navs:
        raise FileNotFoundError(f"{path}: expected one *base*.obs, one *rover*.obs and a *.nav")
    return [l1_epochs(read_obs(o[0]), systems=SYSTEMS) for o in obs], read_nav(navs[0])


def simulated_static(seed: int, out: Path, duration_s: float | None = None
                     ) -> tuple[list[list[GnssEpoch]], NavigationData]:
    """The four receivers' epochs and the navigation data of a simulated ``static`` recording
    (simulated into ``out`` unless it already holds one)."""
    from recordings import load
    from recordings.sim.simulate import simulate

    if not (out / "manifest.json").exists():
        simulate("static", seed, out, duration_s=duration_s, progress=False)
    rec = load(out)
    return rec.gnss, rec.nav


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def _ratio_summary(real: float, sims: Sequence[float]) -> tuple[float, float]:
    """(median ratio, worst ratio: the one farthest from 1 by factor) of sim / real."""
    ratios = np.array(sims) / real
    worst = ratios[np.argmax(np.abs(np.log(ratios)))]
    return float(np.median(ratios)), float(worst)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", type=Path, default=DEFAULT_REAL,
                        help="directory of the real static pair (default: %(default)s)")
    parser.add_argument("--seeds", default="1-5", help="simulated seeds, A-B (default 1-5)")
    parser.add_argument("--duration", type=float, default=None,
                        help="simulated seconds (default: the static scenario's 300 s)")
    parser.add_argument("--keep", type=Path, default=None,
                        help="keep (and reuse) the simulated recordings in this directory")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    if not args.real.is_dir():
        parser.error(f"--real {args.real}: no such directory (the repository's tests/data "
                     "holds a 2-minute excerpt of the pair)")

    receivers, nav = load_real_pair(args.real)
    real_series = velocity_series(receivers, nav)
    real = figures(real_series)
    sims: dict[int, StaticFigures] = {}
    pooled: Series = []
    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep or Path(tmp)
        for seed in _seeds(args.seeds):
            epochs, sim_nav = simulated_static(seed, base / f"static-seed{seed}", args.duration)
            series = velocity_series(epochs, sim_nav)
            sims[seed] = figures(series)
            pooled += series
            print(f"seed {seed} done", file=sys.stderr, flush=True)
    pooled_figures = figures(pooled)
    # The real data's own spread: its two halves (150 s each; no 120 s windows) side by side.
    real_halves = [figures(h, WINDOWS_S[:-1]) for h in halves(real_series)]

    if args.json:
        print(json.dumps({"real": asdict(real), "real_halves": [asdict(h) for h in real_halves],
                          "simulated": {s: asdict(f) for s, f in sims.items()},
                          "simulated_pooled": asdict(pooled_figures)}))
        return 0
    seeds = sorted(sims)
    print(f"real: {args.real} ({real.receivers} receivers alone, {real.epochs} velocities); "
          f"simulated: static seeds {seeds} ({sims[seeds[0]].receivers} receivers each)")
    print("ratio = simulated / real: the median and the worst (farthest from 1) over the seeds, "
          "and that of the seeds pooled (all their windows together)")
    head = f"{'figure':<32}{'real':>7}" + "".join(f"{'s' + str(s):>7}" for s in seeds)
    print(head + f"{'pooled':>8}{'ratio median':>14}{'worst':>7}{'pooled':>8}")
    sim_rows = {s: dict(sims[s].rows()) for s in seeds}
    pooled_rows = dict(pooled_figures.rows())
    all_ratios = []
    for name, value in real.rows():
        values = [sim_rows[s][name] for s in seeds]
        med, worst = _ratio_summary(value, values)
        all_ratios += [v / value for v in values]
        print(f"{name:<32}{value:>7.1f}" + "".join(f"{v:>7.1f}" for v in values)
              + f"{pooled_rows[name]:>8.1f}{med:>14.2f}{worst:>7.2f}"
              + f"{pooled_rows[name] / value:>8.2f}")
    vert = "".join(f"{1e3 * sims[s].vertical_rms_mps:>7.1f}" for s in seeds)
    print(f"{'(velocity RMS vertical, mm/s)':<32}{1e3 * real.vertical_rms_mps:>7.1f}{vert}"
          f"{1e3 * pooled_figures.vertical_rms_mps:>8.1f}")
    r = np.array(all_ratios)
    print(f"all figures and seeds: ratio {r.min():.2f} .. {r.max():.2f}, "
          f"{np.mean(np.abs(np.log(r)) <= np.log(1.5)):.0%} within a factor 1.5")
    first, second = (dict(h.rows()) for h in real_halves)
    spread = [max(first[n], second[n]) / min(first[n], second[n]) for n in first]
    print("the real pair's own spread: its first and second 150 s differ by a factor "
          f"{min(spread):.2f} .. {max(spread):.2f} on these figures (up to 60 s windows)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
