"""PNG plots of a replay report (``--plots DIR``): trajectories from above, horizontal and
heading error over time, the port structure from above, fig. 14."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)
import numpy as np  # noqa: E402

from .report import MAIN, Evaluated  # noqa: E402
from .scoring import quay_line  # noqa: E402
from .text import f  # noqa: E402

COLOURS = ("tab:orange", "tab:green", "tab:purple", "tab:blue", "tab:red", "tab:brown",
           "tab:pink", "tab:gray", "tab:olive", "tab:cyan")


def write_plots(out: Path, ev: Evaluated) -> list[str]:
    out.mkdir(parents=True, exist_ok=True)
    colours = {name: COLOURS[i % len(COLOURS)] for i, name in enumerate(ev.errors)}
    written = [_trajectories(out, ev, colours), _horizontal_error(out, ev, colours),
               _heading_error(out, ev, colours)]
    if ev.structure_plot is not None:
        written.append(_structure(out, ev))
    ss = ev.report.single_satellite_heading
    if ss is not None and ss.satellites:
        written.append(_single_satellite(out, ev))
    return written


def _origin(ev: Evaluated) -> np.ndarray:
    return ev.rs.rec.reference.interpolate(ev.runs[MAIN].origin_time)[0]  # type: ignore


def _save(fig: Any, path: Path) -> str:
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return str(path)


def _trajectories(out: Path, ev: Evaluated, colours: dict[str, str]) -> str:
    main, rec = ev.runs[MAIN], ev.rs.rec
    origin = _origin(ev)
    quay = quay_line(rec.scene_points, rec.scene_point_kinds, origin)
    t0 = ev.report.window_s[0]
    fig, ax = plt.subplots(figsize=(8, 8))
    ref_pos = rec.reference.interpolate(main.time)[0] - origin  # type: ignore[union-attr]
    ax.plot(ref_pos[:, 1], ref_pos[:, 0], "k-", lw=3, alpha=0.35, label="reference")
    for name, run in ev.runs.items():
        ax.plot(run.position[:, 1], run.position[:, 0], "-", color=colours.get(name), lw=1.2,
                label=name)
    if quay is not None:
        ax.plot(quay[:, 1], quay[:, 0], "-", color="saddlebrown", lw=2, label="quay (scene pts)")
    k0 = int(np.searchsorted(main.time - ev.rs.start, t0))
    if k0 < len(ref_pos):
        ax.plot(ref_pos[k0, 1], ref_pos[k0, 0], "ko", ms=6, label=f"window start (+{t0:g} s)")
    lim = ref_pos[np.isfinite(ref_pos).all(axis=1)]
    pad = 15.0
    ax.set_xlim(lim[:, 1].min() - pad, lim[:, 1].max() + pad)
    ax.set_ylim(lim[:, 0].min() - pad,
                max(lim[:, 0].max(), -np.inf if quay is None else quay[:, 0].max()) + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"{ev.report.recording}: trajectories (aligned at the fusion origin)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return _save(fig, out / "trajectories.png")


def _horizontal_error(out: Path, ev: Evaluated, colours: dict[str, str]) -> str:
    fig, ax = plt.subplots(figsize=(10, 5))
    for name, err in ev.errors.items():
        if err is None:
            continue
        h = np.hypot(err.position[:, 0], err.position[:, 1])
        ax.semilogy(err.time, np.maximum(h, 1e-4), label=name, color=colours[name], lw=1)
    ax.axvline(ev.report.window_s[0], color="k", ls="--", lw=0.8)
    ax.set_xlabel("time since the recording start (s)")
    ax.set_ylabel("horizontal error (m)")
    ax.set_title("horizontal error of the body origin (window after the dashed line)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, out / "horizontal_error.png")


def _heading_error(out: Path, ev: Evaluated, colours: dict[str, str]) -> str:
    fig, ax = plt.subplots(figsize=(10, 5))
    for name, err in ev.errors.items():
        if err is None or not np.isfinite(err.heading).any():
            continue
        ax.plot(err.time, np.degrees(err.heading), label=name, color=colours[name], lw=1)
    ax.axvline(ev.report.window_s[0], color="k", ls="--", lw=0.8)
    ax.set_xlabel("time since the recording start (s)")
    ax.set_ylabel("heading error (deg)")
    ax.set_ylim(-1.2, 1.2)
    ax.set_title("heading error (clipped to ±1.2°)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, out / "heading_error.png")


def _structure(out: Path, ev: Evaluated) -> str:
    sp = ev.structure_plot
    assert sp is not None
    rec, main = ev.rs.rec, ev.runs[MAIN]
    origin = _origin(ev)
    ref_pos = rec.reference.interpolate(main.time)[0] - origin  # type: ignore[union-attr]
    pts, cam = sp.points, sp.camera
    fig, axes = plt.subplots(1, 2, figsize=(15, 7))
    sc = None
    for ax, span in zip(axes, (None, 30.0), strict=True):
        if rec.scene_points is not None:
            tt = rec.scene_points - origin
            ax.scatter(tt[:, 1], tt[:, 0], s=6, c="red", marker="x", lw=0.6,
                       label="true scene points")
        if sp.quay is not None:
            ax.plot(sp.quay[:, 1], sp.quay[:, 0], "-", color="saddlebrown", lw=1.5, label="quay")
        sc = ax.scatter(pts[:, 1], pts[:, 0], s=4, c=np.minimum(sp.distance, 5.0),
                        cmap="viridis", label="fused structure (colour: m to nearest true, ≤5)")
        ax.plot(ref_pos[:, 1], ref_pos[:, 0], "k-", lw=1, label="reference track")
        ax.plot(cam[1], cam[0], "k^", ms=8, label="camera at the end")
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
        if span is None:
            c = np.median(pts, axis=0)
            r = max(np.percentile(np.abs(pts[:, :2] - c[:2]), 95) * 1.3, 40.0)
            ax.set_xlim(c[1] - r, c[1] + r)
            ax.set_ylim(c[0] - r, c[0] + r)
            ax.set_title("point cloud from above (95 % of the points)")
        else:
            ax.set_xlim(cam[1] - span, cam[1] + span)
            ax.set_ylim(cam[0] - span, cam[0] + span)
            ax.set_title(f"within {span:g} m of the camera at the end")
    fig.colorbar(sc, ax=axes, shrink=0.7, label="distance to the nearest true point (m)")
    axes[0].legend(fontsize=7, loc="lower left")
    return _save(fig, out / "structure.png")


def _single_satellite(out: Path, ev: Evaluated) -> str:
    ss = ev.report.single_satellite_heading
    assert ss is not None
    sats = ss.satellites
    names = list(sats[0].heading_std_deg)
    width = 0.8 / len(names)
    fig, axes = plt.subplots(2, 1, figsize=(10, 8), sharex=True)
    for ax, key, title in zip(axes, ("snapshot_std_deg", "heading_std_deg"), (
            "single-epoch heading from the single differences (no gyro)",
            "filtered with the gyro over the window"), strict=True):
        for k, name in enumerate(names):
            vals = [getattr(e, key).get(name) for e in sats]
            ax.bar(np.arange(len(vals)) + k * width, [np.nan if v is None else v for v in vals],
                   width, label=name if name == "all six" else f"baseline {name}")
        ax.set_yscale("log")
        ax.set_ylabel("heading σ (deg)")
        ax.set_title(f"one satellite, single baselines vs all six (fig. 14): {title}")
        ax.grid(alpha=0.3, axis="y", which="both")
    axes[1].set_xticks(np.arange(len(sats)) + 0.4 - width / 2)
    axes[1].set_xticklabels([f"{e.sat} ({f(e.elevation_deg, '.0f')}°)" for e in sats])
    axes[0].legend(fontsize=7, ncol=4)
    return _save(fig, out / "single_satellite_heading.png")
