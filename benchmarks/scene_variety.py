"""Contact sheets of the simulator's scene variety, and its rendering cost.

    .venv/bin/python benchmarks/scene_variety.py [--small 12] [--large 4] [--first-seed 1]
        [--times 30 60 85] [--out DIR] [--thumb 320]

Renders, for each of the first ``--small`` small-boat and ``--large`` large-ship seeds, the
frame the simulator would write at each of ``--times`` (s after the start, on the seed's own
path with its own camera), and writes one PNG per time into ``--out`` (a grid of thumbnails
labelled with the scenario, seed, light, water chop and camera height), then prints each seed's
draw (light, water, quay, buildings, boats, camera, speed) and the median rendering time per
frame (full size, the thumbnails excluded). Look at the sheets after changing the simulator.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from recordings.sim.motion import ShipMotion  # noqa: E402
from recordings.sim.scenarios import SCENARIOS  # noqa: E402
from recordings.sim.scene import PortScene, camera_calibration  # noqa: E402
from recordings.sim.variety import look, seeded  # noqa: E402


def frames(name: str, seed: int, times: list[float]) -> tuple[list[np.ndarray], list[float],
                                                               str]:
    """The seed's frames at ``times``, the render time of each and a one-line summary."""
    base = SCENARIOS[name]
    sc, lk = seeded(base, seed), look(base, seed)
    scene = PortScene.build(base, seed)
    motion = ShipMotion(sc, seed)
    cam = camera_calibration(sc)
    rng = np.random.default_rng(seed + 1000)
    out, cost = [], []
    for t in times:
        t = min(t, sc.duration_s)
        C_b_l = motion.state(t).C_body_to_level[0]
        p = motion.point_position_ned(t, cam.lever_arm_body)
        t0 = time.perf_counter()
        out.append(scene.render((C_b_l @ cam.C_camera_to_body).T, p, t, cam, rng))
        cost.append(time.perf_counter() - t0)
    speed = np.linalg.norm(motion.state(np.linspace(0, sc.duration_s, 200)).velocity_ned[:, :2],
                           axis=1)
    moving = sum(b.moves for b in lk.port.boats)
    height = -sc.reference_point_down_m - sc.camera_lever_arm[2]
    hull = " (own hull in view)" if scene.sees_own_hull(cam) else ""
    summary = (f"{name:10s} seed {seed:3d}: {lk.light.kind:8s} sun {lk.light.sun_az_deg:5.0f}/"
               f"{lk.light.sun_el_deg:4.0f} deg, chop {lk.water.chop:.2f}, quay "
               f"{lk.port.quay_material} {lk.port.quay_height_m:.1f} m, buildings "
               f"{min(lk.port.heights_m):.0f}-{max(lk.port.heights_m):.0f} m at "
               f"{lk.port.setback_m[0]:.0f}+ m, boats {len(lk.port.boats)} ({moving} moving), "
               f"cranes {lk.port.cranes}, camera {height:.1f} m tilt {sc.camera_tilt_deg:.1f} "
               f"pan {sc.camera_pan_deg:.0f} deg{hull}, "
               f"speed max {speed.max():.2f} m/s, AE {lk.light.auto_exposure:.1f}, "
               f"{len(lk.light.exposure_steps)} exposure steps")
    return out, cost, summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--small", type=int, default=12)
    ap.add_argument("--large", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--times", type=float, nargs="+", default=[30.0, 60.0, 85.0])
    ap.add_argument("--out", type=Path, default=Path("scene-variety"))
    ap.add_argument("--thumb", type=int, default=320, help="thumbnail width, px")
    args = ap.parse_args(argv)
    jobs = [("small-boat", args.first_seed + k) for k in range(args.small)] + \
        [("large-ship", args.first_seed + k) for k in range(args.large)]
    tiles: list[list[np.ndarray]] = [[] for _ in args.times]
    costs = []
    for name, seed in jobs:
        imgs, cost, summary = frames(name, seed, args.times)
        print(summary, flush=True)
        costs += cost
        for k, img in enumerate(imgs):
            th = cv2.resize(img, (args.thumb, args.thumb * img.shape[0] // img.shape[1]),
                            interpolation=cv2.INTER_AREA)
            lk = look(SCENARIOS[name], seed)
            label = f"{name} {seed} {lk.light.kind} chop {lk.water.chop:.1f}"
            cv2.rectangle(th, (0, 0), (8 + 7 * len(label), 18), (0, 0, 0), -1)
            cv2.putText(th, label, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                        cv2.LINE_AA)
            tiles[k].append(th)
    args.out.mkdir(parents=True, exist_ok=True)
    cols = int(np.ceil(np.sqrt(len(jobs))))
    for t, row in zip(args.times, tiles, strict=True):
        blank = np.zeros_like(row[0])
        row = row + [blank] * (-len(row) % cols)
        sheet = np.vstack([np.hstack(row[i:i + cols]) for i in range(0, len(row), cols)])
        path = args.out / f"sheet_{t:g}s.png"
        cv2.imwrite(str(path), sheet)
        print(f"wrote {path}")
    print(f"render time per frame (960x600 ideal + lens): median {1000 * np.median(costs):.0f} ms,"
          f" p90 {1000 * np.percentile(costs, 90):.0f} ms over {len(costs)} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
