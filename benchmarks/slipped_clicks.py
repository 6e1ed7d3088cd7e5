"""Clicks an officer might make anywhere, and clicks that slip off an edge, through the server:
is the distance read, with its σ, the distance of what the clicked pixel shows?

Starts ``berthing-aid serve`` on a simulated recording (real fusion engine, viewer off), pauses
a session at each of ``--times`` and designates (``POST .../targets``, the page's click):

- ``random``: ``--random`` pixels per time (seeded), rows 25–70 % of the image down;
- ``edge +1.5`` / ``edge +3``: every 75 px across the image, that many pixels below the first
  depth edge from above (the true depth map drops by half: a quay's top edge in front of
  the buildings, a boat's in front of the quay), on the nearer surface;
- ``edge -1.5``: as many pixels above it, on the farther surface.

The truth is the simulator's depth map at the frame (``evaluation.truth.scene_depth``, the
scene rebuilt from the seed), as a range along the pixel's ray. Printed per group: clicks,
refused (4xx: nothing to measure there), the share within 2σ and within 1 m, and the tight and
wrong ones (beyond 2σ with a σ under 20 % of the true range: a confident wrong answer), the
worst of them listed.

    .venv/bin/python benchmarks/slipped_clicks.py RECORDING [--times 40,60,75] [--random 150]
        [--seed 7] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
from serverproc import recording_path, serve

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from anywhere without installing

from evaluation.truth import rebuild_scene, scene_depth, true_cameras  # noqa: E402
from recordings.format import load  # noqa: E402

EDGE_RATIO = 2.0  # a depth edge: the surface below is at most half as far
EDGE_OFFSETS_PX = (1.5, 3.0, -1.5)
EDGE_COLUMN_STEP_PX = 75
ROWS = (0.25, 0.70)  # the band of rows the random clicks fall in (fractions of the height)


def true_ranges(rec, t_s: float) -> tuple[int, np.ndarray]:
    """(frame index, range map in m along each pixel's ray) of the frame nearest ``t_s``."""
    times = np.asarray(rec.frame_times, float)
    k = int(np.argmin(np.abs(times - rec.manifest.start_gpst - t_s)))
    scene = rebuild_scene(rec)
    if scene is None:
        raise SystemExit(f"{rec.manifest.name}: not a simulated recording whose scene can be "
                         "rebuilt (the truth is its depth map)")
    cam = rec.calibration.camera
    truth = true_cameras(rec, times[k:k + 1], None)
    depth = scene_depth(scene, truth, 0, float(times[k] - rec.manifest.start_gpst), cam)
    h, w = depth.shape
    uv = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)),
                  axis=-1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(uv, np.asarray(cam.K, float),
                             np.asarray(cam.distortion, float)).reshape(h, w, 2)
    return k, depth * np.sqrt(1.0 + np.sum(xy**2, axis=-1))


def clicks_at(ranges: np.ndarray, n_random: int, rng: np.random.Generator
              ) -> list[tuple[str, float, float]]:
    """(group, u, v) of the clicks on one frame (module docstring)."""
    h, w = ranges.shape
    out = [("random", float(rng.uniform(20, w - 20)), float(rng.uniform(*ROWS) * h))
           for _ in range(n_random)]
    for u in range(40, w - 20, EDGE_COLUMN_STEP_PX):
        col = ranges[:, u]
        for v in range(int(ROWS[0] * h), int(ROWS[1] * h)):
            if np.isfinite(col[v - 1]) and col[v] * EDGE_RATIO <= col[v - 1]:
                out += [(f"edge {off:+g}", float(u), v - 0.5 + off) for off in EDGE_OFFSETS_PX]
                break
    return out


def designate_all(http: httpx.Client, sid: str, t_s: float,
                  clicks: list[tuple[str, float, float]], ranges: np.ndarray) -> list[dict]:
    """Each click designated on the frame at ``t_s`` and removed again; its reading and truth."""
    http.post(f"/api/sessions/{sid}/control", json={"action": "seek", "time": t_s})
    end = time.monotonic() + 300
    while True:
        s = http.get(f"/api/sessions/{sid}").json()
        if s["state"] == "paused" and abs(s["time_s"] - t_s) <= 0.11:
            break
        if time.monotonic() > end:
            raise RuntimeError(f"the seek to {t_s:g} s did not end")
        time.sleep(0.1)
    out = []
    for group, u, v in clicks:
        true = float(ranges[int(round(v)), int(round(u))])
        if not np.isfinite(true):
            continue  # the sky
        r = http.post(f"/api/sessions/{sid}/targets", json={"u": u, "v": v, "frame_time": t_s})
        row = {"t_s": t_s, "group": group, "u": round(u, 1), "v": round(v, 1),
               "true_m": round(true, 3)}
        if r.status_code != 201:
            row["refused"] = f"{r.status_code}: {r.json().get('detail', '')[:120]}"
        else:
            tg = r.json()
            row.update(shown_m=tg["distance_m"], sigma_m=tg["distance_sigma_m"],
                       method=tg["method"], status=tg["status"])
            http.delete(f"/api/sessions/{sid}/targets/{tg['id']}")
        out.append(row)
    return out


def summary(rows: list[dict]) -> dict:
    shown = [r for r in rows if r.get("shown_m") is not None and r.get("sigma_m")]
    err = np.array([abs(r["shown_m"] - r["true_m"]) for r in shown])
    sig = np.array([r["sigma_m"] for r in shown])
    true = np.array([r["true_m"] for r in shown])
    wrong = (err > 2 * sig) & (sig < 0.2 * true) if len(shown) else np.zeros(0, bool)
    return {"clicks": len(rows), "refused": sum("refused" in r for r in rows),
            "within_2_sigma": float(np.mean(err <= 2 * sig)) if len(shown) else None,
            "within_1_m": float(np.mean(err <= 1.0)) if len(shown) else None,
            "tight_and_wrong": int(wrong.sum()),
            "worst": sorted(([r for r, bad in zip(shown, wrong, strict=True) if bad]),
                            key=lambda r: -abs(r["shown_m"] - r["true_m"]) / r["sigma_m"])[:8]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording")
    parser.add_argument("--times", default="40,60,75",
                        help="s after the start (default %(default)s)")
    parser.add_argument("--random", type=int, default=150, help="random clicks per time")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--json", type=Path, default=None, help="write every click here")
    args = parser.parse_args()
    recording = recording_path(args.recording)
    if recording is None:
        return 2
    rec = load(recording)
    rng = np.random.default_rng(args.seed)
    rows: list[dict] = []
    with serve(recording, viewer=False) as server, \
            httpx.Client(base_url=server.base, timeout=120) as http:
        name = http.get("/api/recordings").json()["default"]
        sid = http.post("/api/sessions", json={"recording": name, "speed": 1,
                                               "paused": True}).json()["id"]
        for t_s in (float(x) for x in args.times.split(",")):
            _k, ranges = true_ranges(rec, t_s)
            rows += designate_all(http, sid, t_s, clicks_at(ranges, args.random, rng), ranges)
            print(f"{t_s:g} s: {len(rows)} clicks so far", file=sys.stderr, flush=True)
        http.delete(f"/api/sessions/{sid}")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    groups = ["random", *(f"edge {o:+g}" for o in EDGE_OFFSETS_PX)]
    print(f"{recording.name}, clicks at {args.times} s (seed {args.seed})")
    print("group       clicks  refused  within 2σ  within 1 m  tight & wrong")
    for g in groups:
        s = summary([r for r in rows if r["group"] == g])
        if not s["clicks"]:
            continue
        w2 = "–" if s["within_2_sigma"] is None else f"{s['within_2_sigma']:.3f}"
        w1 = "–" if s["within_1_m"] is None else f"{s['within_1_m']:.3f}"
        print(f"{g:10s}  {s['clicks']:6d}  {s['refused']:7d}  {w2:>9s}  {w1:>10s}  "
              f"{s['tight_and_wrong']:13d}")
        for r in s["worst"]:
            print(f"    {r['t_s']:g} s ({r['u']:g}, {r['v']:g}): {r['shown_m']:.2f} ± "
                  f"{r['sigma_m']:.2f} m, true {r['true_m']:.2f} m ({r['method']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
