"""Replay speed: the whole fusion (VO inside ``Fusion.process_frame`` + INS + CPP + EKF) over a
recording as fast as possible, in one process, the way ``backend.replay`` feeds it.

Prints:
- the realtime factor (recording seconds per wall second), with and without video decoding;
- milliseconds per video frame for each stage: the caller's view (decode, ``process_imu`` for
  the ~10 IMU samples of a frame, ``process_gnss``, ``process_frame``) and the engine's own
  ``Fusion.timing()`` (ms per call: imu, gnss, frame, vo, vo_update, gnss_update, compass);
  the CPU each thread spent per frame (the main thread, the engine's workers: the VO's
  look-ahead front end, its backward LK and BA, the landmark window; Linux);
- the latency of ``process_frame`` (p50 / p95 / max): what a live 10 fps feed must fit in
  100 ms;
- the peak resident memory (``resource.getrusage`` maxrss).

    .venv/bin/python benchmarks/replay_speed.py [RECORDING] [--seconds S] [--json]

BLAS threads are pinned to one (``OPENBLAS_NUM_THREADS=1``, see ``estimator.pipeline``) unless
already set in the environment.
"""

from __future__ import annotations

import os

# Before numpy is imported: small matrices lose more to BLAS threads than they gain.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from anywhere without installing

DEFAULT_RECORDING = ROOT / "recordings" / "default"


def thread_cpu_s() -> dict[str, float]:
    """CPU seconds (user + system) of each live Python thread, by name, and of the whole
    process ("process"); Linux only (an empty dict elsewhere). What the process spent
    beyond the named threads went to OpenCV's own thread pool and to threads that have
    ended (the frame reader's)."""
    import threading

    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    out: dict[str, float] = {}
    for th in threading.enumerate():
        try:
            with open(f"/proc/self/task/{th.native_id}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        name = th.name.split("_")[0]  # a pool's threads as one
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    if out:
        out["process"] = time.process_time()
    return out


def replay_speed(path: Path, seconds: float | None = None) -> dict:
    from engine.driver import dispatch, frame_preparer
    from engine.messages import FrameMessage, GnssMessage, sensor_messages
    from estimator.pipeline import Fusion
    from recordings.format import load

    t_load = time.perf_counter()
    rec = load(path)
    load_s = time.perf_counter() - t_load
    end = rec.manifest.start_gpst + (rec.manifest.duration_s if seconds is None else seconds)
    fusion = Fusion(rec.calibration, rec.nav)
    spent = {"decode+merge": 0.0, "process_imu": 0.0, "process_gnss": 0.0, "process_frame": 0.0}
    frame_ms: list[float] = []
    counts = {"imu": 0, "gnss": 0, "frame": 0}
    first = last = None
    messages = sensor_messages(rec, until=end, prepare=frame_preparer(fusion))
    cpu0 = thread_cpu_s()
    wall0 = time.perf_counter()
    tic = wall0
    for msg in messages:
        got = time.perf_counter()
        spent["decode+merge"] += got - tic
        first = msg.t if first is None else first
        last = msg.t
        dispatch(fusion, msg)  # the server's own step
        kind = "frame" if isinstance(msg, FrameMessage) else \
            "gnss" if isinstance(msg, GnssMessage) else "imu"
        stage = f"process_{kind}"
        tic = time.perf_counter()
        spent[stage] += tic - got
        counts[kind] += 1
        if kind == "frame":
            frame_ms.append(1e3 * (tic - got))
    wall = time.perf_counter() - wall0
    cpu = {k: v - cpu0.get(k, 0.0) for k, v in thread_cpu_s().items()}
    span = (last - first) if first is not None and last is not None else 0.0
    n = max(counts["frame"], 1)
    state = fusion.state()
    compute = wall - spent["decode+merge"]
    return {
        "recording": rec.manifest.name,
        "replayed_s": span,
        "messages": counts,
        "load_s": load_s,
        "wall_s": wall,
        "realtime_factor": span / wall if wall > 0 else None,
        "realtime_factor_without_decoding": span / compute if compute > 0 else None,
        "ms_per_frame": {k: 1e3 * v / n for k, v in spent.items()},
        "engine_ms_per_call": fusion.timing(),
        # CPU ms per frame of each thread (the engine's workers beside the main thread)
        "thread_cpu_ms_per_frame": {k: 1e3 * v / n for k, v in cpu.items()},
        # the VO's own stages, ms per frame (ba_ms_per_call: one local bundle adjustment)
        "vo_stages": None if fusion.vo is None else fusion.vo.stats(),
        "vo_working_size": None if fusion.vo is None else
        "{}x{} (level {})".format(*fusion.vo.working_size, fusion.vo.level),
        "process_frame_ms": {"p50": float(np.percentile(frame_ms, 50)),
                             "p95": float(np.percentile(frame_ms, 95)),
                             "max": float(np.max(frame_ms))} if frame_ms else None,
        # Linux reports ru_maxrss in KiB.
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "final_phase": None if state is None else state.status.phase,
        "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }


def format_speed(r: dict) -> str:
    lines = [f"{r['recording']}: {r['replayed_s']:.1f} s replayed in {r['wall_s']:.1f} s "
             f"(load {r['load_s']:.1f} s) -> realtime factor {r['realtime_factor']:.2f} "
             f"({r['realtime_factor_without_decoding']:.2f} without decoding); "
             f"{r['messages']['frame']} frames, {r['messages']['imu']} IMU samples, "
             f"{r['messages']['gnss']} GNSS epochs; final phase {r['final_phase']}",
             "ms per video frame (caller's view):"]
    lines += [f"  {k:<14} {v:8.2f}" for k, v in r["ms_per_frame"].items()]
    lines.append(f"  {'total':<14} {sum(r['ms_per_frame'].values()):8.2f}   (10 fps live: 100)")
    lines.append("engine's Fusion.timing(), ms per call:")
    lines += [f"  {k:<14} {v:8.2f}" for k, v in r["engine_ms_per_call"].items()]
    if r.get("thread_cpu_ms_per_frame"):
        lines.append("CPU ms per video frame by thread (the rest of the process: OpenCV's pool,"
                     " the frame reader):")
        lines += [f"  {k:<26} {v:8.2f}" for k, v in r["thread_cpu_ms_per_frame"].items()]
    vo = r.get("vo_stages")
    if vo:
        lines.append(f"the VO's stages on its {r['vo_working_size']} working image, ms per frame "
                     f"({vo['keyframes']} keyframes, {vo['ba_calls']} local BAs of "
                     f"{vo['ba_ms_per_call']:.1f} ms):")
        lines += [f"  {k[:-3]:<14} {vo[k]:8.2f}" for k in vo if k.endswith("_ms")]
    p = r["process_frame_ms"]
    if p:
        lines.append(f"process_frame latency: p50 {p['p50']:.1f} ms, p95 {p['p95']:.1f} ms, "
                     f"max {p['max']:.1f} ms")
    lines.append(f"peak memory (maxrss): {r['peak_rss_mb']:.0f} MB; OPENBLAS_NUM_THREADS="
                 f"{r['blas_threads']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", nargs="?", default=str(DEFAULT_RECORDING))
    ap.add_argument("--seconds", type=float, default=None, help="replay only the first S s")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    result = replay_speed(Path(args.recording), args.seconds)
    print(json.dumps(result, indent=2) if args.json else format_speed(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
