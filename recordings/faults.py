"""Fault injection: a damaged copy of a recording, made reproducibly, for the integrity tests
and the campaign evaluation (``berthing-aid inject``).

A fault is named ``KIND`` or ``KIND:a:b`` with its parameters in seconds after the recording
start (or as stated). The copy shares the untouched files with the original (symbolic links)
and rewrites only what the fault damages; the reference trajectory and scene points are kept
(the truth does not change when a sensor fails). GNSS files are rewritten as L1 RINEX 3
(``rinex.write_obs``), video as mp4v: a damaged copy of a real multi-signal file keeps only
what the estimator reads.

| fault | what | parameters (default) |
| --- | --- | --- |
| imu-gap | IMU samples missing | start, length (40, 5) |
| imu-end | the IMU file ends | at (45) |
| imu-frozen | the IMU repeats one sample | start, length (40, 5) |
| imu-spikes | one-sample spikes (gyro 20 rad/s, accel 100 m/s²) every 0.5 s | start, length |
| imu-saturated | gyro z and accel x stuck at a ±250 °/s, ±2 g range | start, length (40, 5) |
| imu-backwards | a block of IMU time tags 1 s in the past | start, length (40, 0.5) |
| imu-bias | accelerometer x biased from then on (MEMS unit after a shock) | start, m/s² (40, 0.3) |
| gyro-bias | gyro z (yaw rate) biased from then on | start, °/s (40, 1) |
| receiver-missing | the last receiver's file and antenna removed | – |
| receiver-silent | one receiver without epochs | receiver (1-based), start, length (4, 40, 10) |
| cycle-slips | every satellite of every receiver slips (1–30 cycles, unflagged) at once | at (40) |
| clock-jump | the common clock jumps (or one receiver's: 1-based, 0 all) | at, ms, rx (40, 1, 0) |
| spp-outlier | every pseudorange off by 1–5 km (a broken code loop) | start, length (40, 10) |
| iono-storm | an ionosphere stronger than broadcast: the fix metres off | extra × Klobuchar (1) |
| half-sky | satellites of the quay-side half of the sky (north) lost from the start | – |
| video-zeroed | bytes of the video file zeroed | offset MiB, length MiB (3, 1) |
| video-end | the video ends early (``frames.csv`` keeps its rows) | at (45) |
| video-frozen | one frame repeated | start, length (40, 5) |
| video-black | black frames | start, length (40, 3) |
| video-blinded | saturated (blinded) frames | start, length (40, 3) |
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from estimator.cpp import epoch_geometry
from estimator.ephemeris import carrier_wavelength, klobuchar_delay
from estimator.frames import SPEED_OF_LIGHT, WAVELENGTH_L1, ned_to_ecef
from estimator.records import GnssEpoch, NavigationData, SatObservation

from .format import (
    IMU_COLUMNS,
    Recording,
    VideoWriter,
    load,
    write_calibration,
)
from .rinex import l1_epochs, read_obs, write_obs

SLIP_SEED = 7  # the slips' sizes: the same damage every time


@dataclass(frozen=True)
class Fault:
    kind: str
    params: tuple[float, ...]

    @property
    def name(self) -> str:
        params = list(self.params)
        # a parameter added later is named only when it is not its default: the names (and
        # the campaign's tasks) of before stay what they were
        for _ in range(ADDED_LATER.get(self.kind, 0)):
            if params and params[-1] == DEFAULTS[self.kind][len(params) - 1]:
                params.pop()
        return ":".join([self.kind, *(f"{p:g}" for p in params)])


DEFAULTS: dict[str, tuple[float, ...]] = {
    "imu-gap": (40.0, 5.0), "imu-end": (45.0,), "imu-frozen": (40.0, 5.0),
    "imu-spikes": (40.0, 5.0), "imu-saturated": (40.0, 5.0), "imu-backwards": (40.0, 0.5),
    "imu-bias": (40.0, 0.3), "gyro-bias": (40.0, 1.0),
    "receiver-missing": (), "receiver-silent": (4.0, 40.0, 10.0), "cycle-slips": (40.0,),
    "clock-jump": (40.0, 1.0, 0.0), "spp-outlier": (40.0, 10.0), "iono-storm": (1.0,),
    "half-sky": (),
    "video-zeroed": (3.0, 1.0), "video-end": (45.0,), "video-frozen": (40.0, 5.0),
    "video-black": (40.0, 3.0), "video-blinded": (40.0, 3.0),
}
FAULTS = tuple(DEFAULTS)
ADDED_LATER = {"clock-jump": 1}  # trailing parameters a kind gained (``Fault.name``)
# The parameter that is a time after the recording start (where the damage begins), by kind
TIME_PARAM = {k: 0 for k in DEFAULTS if k not in ("receiver-missing", "iono-storm", "half-sky",
                                                  "video-zeroed")} | {"receiver-silent": 1}


def parse_fault(text: str) -> Fault:
    """``KIND`` or ``KIND:a:b`` → a Fault (defaults for the parameters not given)."""
    kind, *values = text.strip().split(":")
    if kind not in DEFAULTS:
        raise ValueError(f"unknown fault {kind!r}; one of {', '.join(FAULTS)}")
    default = DEFAULTS[kind]
    if len(values) > len(default):
        raise ValueError(f"fault {kind} takes at most {len(default)} parameters "
                         f"({', '.join(f'{d:g}' for d in default) or 'none'}), got {text!r}")
    try:
        given = tuple(float(v) for v in values)
    except ValueError:
        raise ValueError(f"fault {text!r}: parameters must be numbers") from None
    params = given + default[len(given):]
    if not all(math.isfinite(p) and p >= 0 for p in params):
        raise ValueError(f"fault {text!r}: parameters must be finite and not negative")
    return Fault(kind, params)


def inject(source: str | Path, fault: str | Fault, out: str | Path) -> Path:
    """A copy of the recording at ``source`` with ``fault`` injected, written to ``out`` (a new
    or empty directory). Returns ``out``."""
    f = parse_fault(fault) if isinstance(fault, str) else fault
    rec = load(source)
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise ValueError(f"output directory {out} exists and is not empty")
    if out.resolve().is_relative_to(rec.path.resolve()):
        raise ValueError(f"output directory {out} is inside the recording {rec.path}: the copy "
                         "would copy itself")
    duration = float(rec.manifest.duration_s)
    if f.kind in TIME_PARAM and f.params[TIME_PARAM[f.kind]] >= duration:
        raise ValueError(f"fault {f.name}: it starts at {f.params[TIME_PARAM[f.kind]]:g} s, "
                         f"not before the recording's end ({duration:g} s): nothing would be "
                         "damaged")
    _link_copy(rec.path, out)
    _INJECT[f.kind](rec, out, f.params)
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["name"] = f"{manifest['name']}+{f.name}"
    manifest.setdefault("faults", []).append(f.name)
    _replace(out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return out


def _link_copy(src: Path, out: Path) -> None:
    """The recording's files as symbolic links (a fault replaces the ones it damages)."""
    for item in src.rglob("*"):
        target = out / item.relative_to(src)
        if item.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(item.resolve())


def _replace(path: Path) -> Path:
    """``path`` made a real file of its own (never write through a link to the original)."""
    if path.is_symlink():
        path.unlink()
    return path


def _span(rec: Recording, t: np.ndarray, start: float, length: float) -> np.ndarray:
    t0 = float(rec.manifest.start_gpst)
    return (t >= t0 + start) & (t < t0 + start + length)


# ------------------------------------------------------------------------------- IMU


def _write_imu(out: Path, rec: Recording, time: np.ndarray, gyro: np.ndarray,
               accel: np.ndarray) -> None:
    """``imu.csv`` (the manifest's name) as the format writes it; time tags are written as
    given, even when they do not increase (a fault)."""
    data = np.column_stack([time, gyro, accel])
    np.savetxt(_replace(out / rec.manifest.files["imu"]), data, fmt=["%.6f"] + ["%.9f"] * 6,
               delimiter=",", header=",".join(IMU_COLUMNS), comments="")


def _imu_gap(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    keep = ~_span(rec, rec.imu.time, p[0], p[1])
    _write_imu(out, rec, rec.imu.time[keep], rec.imu.gyro[keep], rec.imu.accel[keep])


def _imu_end(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    keep = rec.imu.time < float(rec.manifest.start_gpst) + p[0]
    _write_imu(out, rec, rec.imu.time[keep], rec.imu.gyro[keep], rec.imu.accel[keep])


def _imu_frozen(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    sel = np.flatnonzero(_span(rec, rec.imu.time, p[0], p[1]))
    gyro, accel = rec.imu.gyro.copy(), rec.imu.accel.copy()
    if len(sel):
        gyro[sel], accel[sel] = gyro[sel[0]], accel[sel[0]]
    _write_imu(out, rec, rec.imu.time, gyro, accel)


def _imu_spikes(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    sel = np.flatnonzero(_span(rec, rec.imu.time, p[0], p[1]))
    every = max(1, int(round(0.5 / np.median(np.diff(rec.imu.time)))))
    gyro, accel = rec.imu.gyro.copy(), rec.imu.accel.copy()
    spikes = sel[::every]
    gyro[spikes] += [0.0, 0.0, 20.0]
    accel[spikes] += [100.0, 0.0, 0.0]
    _write_imu(out, rec, rec.imu.time, gyro, accel)


def _imu_saturated(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    sel = _span(rec, rec.imu.time, p[0], p[1])
    gyro, accel = rec.imu.gyro.copy(), rec.imu.accel.copy()
    gyro[sel, 2] = math.radians(250.0)
    accel[sel, 0] = 2.0 * 9.80665
    _write_imu(out, rec, rec.imu.time, gyro, accel)


def _imu_bias(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    accel = rec.imu.accel.copy()
    accel[rec.imu.time >= float(rec.manifest.start_gpst) + p[0], 0] += p[1]
    _write_imu(out, rec, rec.imu.time, rec.imu.gyro, accel)


def _gyro_bias(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    gyro = rec.imu.gyro.copy()
    gyro[rec.imu.time >= float(rec.manifest.start_gpst) + p[0], 2] += math.radians(p[1])
    _write_imu(out, rec, rec.imu.time, gyro, rec.imu.accel)


def _imu_backwards(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    time = rec.imu.time.copy()
    time[_span(rec, time, p[0], p[1])] -= 1.0
    _write_imu(out, rec, time, rec.imu.gyro, rec.imu.accel)


# ------------------------------------------------------------------------------ GNSS


def _receivers(rec: Recording) -> list[list[GnssEpoch]]:
    return [l1_epochs(read_obs(rec.path / name)) for name in rec.manifest.files["gnss_obs"]]


def _write_receivers(rec: Recording, out: Path, epochs: list[list[GnssEpoch]]) -> None:
    for name, eps in zip(rec.manifest.files["gnss_obs"], epochs, strict=True):
        header = read_obs(rec.path / name).header
        write_obs(_replace(out / name), eps, marker_name=header.marker_name or "FAULT",
                  receiver_type="BERTHING-AID FAULT INJECTION",
                  approx_position_ecef=np.zeros(3) if header.approx_position_ecef is None
                  else header.approx_position_ecef, interval=header.interval or 1.0,
                  comments=["fault injected"], glonass_slots=header.glonass_slots or None)


def _edit_epochs(rec: Recording, out: Path,
                 edit: Callable[[int, GnssEpoch], GnssEpoch | None]) -> None:
    """Every epoch of every receiver through ``edit(receiver, epoch)`` (None: dropped)."""
    epochs = [[e for ep in eps if (e := edit(i, ep)) is not None]
              for i, eps in enumerate(_receivers(rec))]
    _write_receivers(rec, out, epochs)


def _receiver_missing(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    files = rec.manifest.files["gnss_obs"]
    if len(files) < 2:
        raise ValueError("receiver-missing needs a recording with at least two receivers")
    (out / files[-1]).unlink()
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["files"]["gnss_obs"] = files[:-1]
    _replace(out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    cal = rec.calibration
    cal.antennas_body = np.asarray(cal.antennas_body)[:-1]
    _replace(out / rec.manifest.files["calibration"])
    write_calibration(out, cal)


def _receiver_silent(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    rx, start, length = int(p[0]) - 1, p[1], p[2]
    if not 0 <= rx < len(rec.gnss):
        raise ValueError(f"receiver-silent: receiver {rx + 1} is not one of 1..{len(rec.gnss)}")
    t0 = float(rec.manifest.start_gpst)
    _edit_epochs(rec, out, lambda i, ep: None if i == rx and t0 + start <= ep.time
                 < t0 + start + length else ep)


def _cycle_slips(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    rng = np.random.default_rng(SLIP_SEED)
    t_slip = float(rec.manifest.start_gpst) + p[0]
    jumps: dict[tuple[int, str], int] = {}

    def edit(i: int, ep: GnssEpoch) -> GnssEpoch:
        if ep.time < t_slip - 1e-6:
            return ep
        sats = {}
        for s, o in ep.satellites.items():
            n = jumps.setdefault((i, s), int(rng.choice([-1, 1]) * rng.integers(1, 31)))
            sats[s] = SatObservation(o.pseudorange, o.carrier_phase + n, o.doppler, o.snr, o.lli)
        return GnssEpoch(ep.time, sats, ep.flag)

    _edit_epochs(rec, out, edit)


def _clock_jump(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    t_jump = float(rec.manifest.start_gpst) + p[0]
    dm = SPEED_OF_LIGHT * p[1] * 1e-3  # m: the clock jumps by p[1] ms
    receivers = len(rec.manifest.files["gnss_obs"])
    only = int(p[2]) - 1  # -1: every receiver (the common clock)
    if p[2] != int(p[2]) or only >= receivers:
        raise ValueError(f"clock-jump: receiver {p[2]:g} is not one of 1…{receivers} (0: all)")

    def edit(i: int, ep: GnssEpoch) -> GnssEpoch:
        if ep.time < t_jump - 1e-6 or only not in (-1, i):
            return ep
        sats = {}
        for s, o in ep.satellites.items():
            lam = carrier_wavelength(s, rec.nav)
            sats[s] = SatObservation(o.pseudorange + dm, o.carrier_phase + dm / lam, o.doppler,
                                     o.snr, o.lli)
        return GnssEpoch(ep.time, sats, ep.flag)

    _edit_epochs(rec, out, edit)


def _spp_outlier(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    t0 = float(rec.manifest.start_gpst)
    rng = np.random.default_rng(SLIP_SEED)
    offsets: dict[str, float] = {}  # one per satellite, the same at every receiver

    def edit(_i: int, ep: GnssEpoch) -> GnssEpoch:
        if not t0 + p[0] <= ep.time < t0 + p[0] + p[1]:
            return ep
        sats = {}
        for s, o in ep.satellites.items():
            d = offsets.setdefault(s, float(rng.choice([-1, 1]) * rng.uniform(1000, 5000)))
            sats[s] = SatObservation(o.pseudorange + d, o.carrier_phase, o.doppler, o.snr, o.lli)
        return GnssEpoch(ep.time, sats, ep.flag)

    _edit_epochs(rec, out, edit)


def iono_storm(nav: NavigationData, llh: np.ndarray, extra: float
               ) -> Callable[[int, GnssEpoch], GnssEpoch]:
    """An epoch edit: the ionosphere stronger than the broadcast model by ``extra`` times its
    delay (code delayed, carrier advanced alike), seen from ``llh`` (rad, rad, m)."""
    if nav.iono_alpha is None or nav.iono_beta is None:
        raise ValueError("iono-storm needs Klobuchar parameters in the navigation file")
    alpha, beta = nav.iono_alpha, nav.iono_beta
    site = ned_to_ecef(np.zeros(3), llh)

    def edit(_i: int, ep: GnssEpoch) -> GnssEpoch:
        geo = epoch_geometry(nav, sorted(ep.satellites), ep.time, site, 0.0, 0.0)
        sats = {}
        for s, o in ep.satellites.items():
            g = geo.satellites.get(s)
            if g is None:
                sats[s] = o
                continue
            lam = carrier_wavelength(s, nav)
            delay = extra * (lam / WAVELENGTH_L1) ** 2 * klobuchar_delay(
                alpha, beta, ep.time, llh[0], llh[1], g.elevation, g.azimuth)
            sats[s] = SatObservation(o.pseudorange + delay, o.carrier_phase - delay / lam,
                                     o.doppler, o.snr, o.lli)
        return GnssEpoch(ep.time, sats, ep.flag)

    return edit


def _iono_storm(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    _edit_epochs(rec, out, iono_storm(rec.nav, rec.manifest.origin_llh, p[0]))


def _half_sky(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    site = ned_to_ecef(np.zeros(3), rec.manifest.origin_llh)

    def edit(_i: int, ep: GnssEpoch) -> GnssEpoch:
        geo = epoch_geometry(rec.nav, sorted(ep.satellites), ep.time, site, 0.0, 0.0)
        north = {s for s, g in geo.satellites.items()
                 if abs((math.degrees(g.azimuth) + 180.0) % 360.0 - 180.0) < 90.0}
        return GnssEpoch(ep.time, {s: o for s, o in ep.satellites.items() if s not in north},
                         ep.flag)

    _edit_epochs(rec, out, edit)


# ----------------------------------------------------------------------------- video


def _video_zeroed(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    name = rec.manifest.files["video"]
    data = bytearray((rec.path / name).read_bytes())
    a = int(p[0] * 2**20)
    b = min(len(data), a + int(p[1] * 2**20))
    if a >= len(data):
        raise ValueError(f"video-zeroed: offset {p[0]:g} MiB is beyond the video "
                         f"({len(data) / 2**20:.1f} MiB)")
    data[a:b] = bytes(b - a)
    _replace(out / name).write_bytes(bytes(data))


def _rewrite_video(rec: Recording, out: Path,
                   edit: Callable[[int, float, np.ndarray], np.ndarray | None]) -> None:
    """Re-encode the video frame by frame through ``edit`` (None: the video ends there)."""
    cam = rec.calibration.camera
    path = _replace(out / rec.manifest.files["video"])
    with VideoWriter(path, (cam.width, cam.height)) as video:
        for k, t, image in rec.frames():
            frame = edit(k, t, image)
            if frame is None:
                break
            video.write(frame)


def _video_end(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    t_end = float(rec.manifest.start_gpst) + p[0]
    _rewrite_video(rec, out, lambda _k, t, img: None if t >= t_end else img)


def _video_span_edit(rec: Recording, out: Path, p: tuple[float, ...],
                     frame: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
    t0 = float(rec.manifest.start_gpst)
    held: list[np.ndarray] = []

    def edit(_k: int, t: float, image: np.ndarray) -> np.ndarray:
        if not t0 + p[0] <= t < t0 + p[0] + p[1]:
            return image
        if not held:
            held.append(image)
        return frame(image, held[0])

    _rewrite_video(rec, out, edit)


def _video_frozen(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    _video_span_edit(rec, out, p, lambda _img, first: first)


def _video_black(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    _video_span_edit(rec, out, p, lambda img, _first: np.zeros_like(img))


def _video_blinded(rec: Recording, out: Path, p: tuple[float, ...]) -> None:
    _video_span_edit(rec, out, p, lambda img, _first: cv2.add(img, np.full_like(img, 230)))


_INJECT: dict[str, Callable[[Recording, Path, tuple[float, ...]], None]] = {
    "imu-gap": _imu_gap, "imu-end": _imu_end, "imu-frozen": _imu_frozen,
    "imu-spikes": _imu_spikes, "imu-saturated": _imu_saturated,
    "imu-bias": _imu_bias, "gyro-bias": _gyro_bias,
    "imu-backwards": _imu_backwards, "receiver-missing": _receiver_missing,
    "receiver-silent": _receiver_silent, "cycle-slips": _cycle_slips,
    "clock-jump": _clock_jump, "spp-outlier": _spp_outlier, "iono-storm": _iono_storm,
    "half-sky": _half_sky,
    "video-zeroed": _video_zeroed, "video-end": _video_end, "video-frozen": _video_frozen,
    "video-black": _video_black, "video-blinded": _video_blinded,
}
assert set(_INJECT) == set(DEFAULTS)
