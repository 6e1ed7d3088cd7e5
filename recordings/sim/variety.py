"""What each seed of a scenario looks like: its port, light, water, camera and manoeuvre.

A real berthing aid meets ports it was not tuned on, so every simulated recording draws, from
(scenario, seed) alone, what real harbours differ in:

- the port (``Port``): quay height and wall material, a pontoon, moored boats (some surging on
  their lines, some passing slowly), building heights, spacing and setback, facades (windows,
  repetitive curtain walls, blank low-texture walls, sheds), trees, cranes, container stacks;
- the light (``Light``): clear sky, low sun (long cast shadows, glare when the camera looks into
  it), overcast, dusk; exposure steps and auto-exposure that reacts to the picture;
- the water (``Water``): from a calm mirror (sharp reflections of the quay and the buildings)
  to choppy, and the ship's wave motion with it;
- the camera's height, tilt, pan and place on the ship (on some small-boat seeds the bow is in
  view), and the manoeuvre (speed, S-turns, where and how the ship stops at the quay).

``look(scenario, seed)`` gives the first three; ``seeded(scenario, seed)`` gives the scenario of
that seed (path keyframes, camera mounting, wave motion, quay height replaced). Both depend only
on the scenario's name, kind and fixed geometry and on the seed, never on the fields ``seeded``
replaces, so ``seeded(seeded(s, k), k) == seeded(s, k)`` and ``PortScene.build`` rebuilds the
same port from a recording's manifest (base scenario + seed) as the simulator rendered.

Scenarios without an entry in ``_MANOEUVRES`` (e.g. a ship lying still) keep their path and
camera; their port, light and water still vary.

The estimator never sees any of this: it reads the recording (calibration.json holds the drawn
camera mounting, as a real installation's calibration would).
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass

import numpy as np

from .motion import ShipMotion
from .scenarios import SCENARIOS, Scenario

# The quay must be seen 6-28 m from the camera over this span of every small-boat recording:
# the tracking evaluation clicks quay points 5-30 m away at 45..78 s (backend.reports.tracking
# DEFAULT_CLICK_TIMES_S, CLICK_RANGE_M; a test keeps the two in step).
QUAY_IN_VIEW_S = (45.0, 78.0)
QUAY_IN_VIEW_RANGE_M = (6.0, 28.0)
KEYFRAME_SPACING_S = 5.0  # the motion model's speed knots are 5 s apart: no closer
MAX_SWAY_MS = 0.12
MAX_YAW_RATE = np.radians(12.0)
PASSING_CLEAR_M = 8.0  # a passing boat keeps this far (plus half lengths) from the ship

LIGHT_KINDS = ("clear", "low-sun", "overcast", "dusk")
QUAY_MATERIALS = ("blocks", "panels", "sheet-pile", "stone")
FACADE_STYLES = ("flats", "office", "curtain", "blank", "brick")


@dataclass(frozen=True)
class Light:
    """Sun, sky and camera exposure. Colours are BGR (0-255), factors multiply albedo."""

    kind: str  # one of LIGHT_KINDS
    sun_az_deg: float  # azimuth from north, clockwise
    sun_el_deg: float  # elevation above the horizon (negative: set)
    direct: float  # sunlight on a surface facing the sun (0: overcast)
    ambient: float  # skylight on every surface
    sun_colour: tuple[float, float, float]  # BGR factors of the sunlight
    ambient_colour: tuple[float, float, float]  # BGR factors of the skylight
    sky_zenith: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    sky_glow: tuple[float, float, float]  # added near the sun (dusk afterglow, low-sun haze)
    haze: tuple[float, float, float]  # aerial perspective colour
    haze_m: float  # distance at which 63 % of a surface's light is replaced by haze
    cloud_cover: float  # 0 clear sky .. 1 overcast
    cloud_colour: tuple[float, float, float]
    exposure: float  # mean gain of the camera
    exposure_steps: tuple[tuple[float, float, float], ...]  # (time s, gain factor, ramp s)
    auto_exposure: float  # 0: fixed gain .. 0.6: the gain follows the picture's brightness
    noise_sigma: float  # sensor noise, grey levels
    glare: float  # veiling glare and bloom when the sun is in or near the picture

    @property
    def sun_dir(self) -> np.ndarray:
        """Unit vector towards the sun, NED."""
        az, el = np.radians(self.sun_az_deg), np.radians(self.sun_el_deg)
        return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])


@dataclass(frozen=True)
class Water:
    chop: float  # 0 mirror-calm .. 1 choppy
    layers: tuple[tuple[float, float, float], ...]  # (wavelength m, heading deg, amplitude)
    deep: tuple[float, float, float]  # BGR of the water body seen straight down
    wobble_px: float  # how far the waves displace a reflection, ideal-image pixels


@dataclass(frozen=True)
class Boat:
    """A boat in the port: moored (still or surging on its lines) or passing slowly."""

    north: float  # position at t = 0 of its centre, m
    east: float
    yaw_deg: float
    length: float
    beam: float
    freeboard: float
    sail: bool
    speed: float = 0.0  # m/s along its heading (a passing boat)
    surge_m: float = 0.0  # amplitude of a moored boat's surge on its lines
    surge_period_s: float = 30.0
    surge_phase: float = 0.0
    kind: str = "yacht"  # "yacht", "feeder" (container feeder ship), "tug"

    @property
    def moves(self) -> bool:
        return self.speed != 0.0 or self.surge_m != 0.0

    def position(self, t: np.ndarray | float) -> np.ndarray:
        """(N, 2) or (2,) north, east of the centre at time t (s since the start)."""
        t = np.asarray(t, float)
        s = self.speed * t + self.surge_m * np.sin(
            2 * np.pi * t / self.surge_period_s + self.surge_phase)
        yaw = np.radians(self.yaw_deg)
        return np.stack([self.north + s * np.cos(yaw), self.east + s * np.sin(yaw)], axis=-1)


@dataclass(frozen=True)
class Port:
    quay_height_m: float
    quay_material: str  # one of QUAY_MATERIALS
    concrete: tuple[float, float, float]  # BGR of the quay wall's concrete/stone/steel
    pontoon: tuple[float, float, float] | None  # (east of its west side, length, width), m
    boats: tuple[Boat, ...]
    setback_m: tuple[float, float]  # buildings' distance behind the quay face
    heights_m: tuple[float, ...]  # building heights to choose from
    gap_m: tuple[float, float]  # spacing between buildings
    facade_weights: tuple[float, ...]  # probabilities of FACADE_STYLES
    repetitive: float  # probability that a facade is an exact repetition of one window bay
    trees: float  # 0..1 density of trees along the promenade
    cranes: int  # gantry cranes (terminal) or tower cranes (marina)
    crane_colours: tuple[tuple[float, float, float], tuple[float, float, float]]
    stack_tiers: int  # highest container stack (terminal)
    stack_fill: float  # share of the yard's bays holding a stack (terminal)
    hills_m: float  # height of the hills behind the town (0: none)
    town: bool  # the far town silhouette


@dataclass(frozen=True)
class Look:
    light: Light
    water: Water
    port: Port


# ------------------------------------------------------------------------------- helpers


def _rng(scenario: Scenario, seed: int, stream: str) -> np.random.Generator:
    """Independent generator for (scenario name, seed, what is drawn)."""
    key = zlib.crc32(f"{scenario.name}/{stream}".encode())
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, key])


def _pick(rng: np.random.Generator, options, p=None):
    return options[int(rng.choice(len(options), p=p))]


def _mix(a, b, f: float) -> tuple[float, float, float]:
    return tuple(float(x + (y - x) * f) for x, y in zip(a, b, strict=True))


def _base(scenario: Scenario) -> Scenario:
    """The registered scenario (scenarios.SCENARIOS) that ``scenario`` is, up to the fields a
    seed draws; ``scenario`` itself when it is not one (a variant made by a caller)."""
    base = SCENARIOS.get(scenario.name)
    if base is None or base is scenario:
        return scenario
    same = all(getattr(base, f.name) == getattr(scenario, f.name)
               for f in dataclasses.fields(base) if f.name not in _SEEDED_FIELDS)
    return base if same else scenario


_SEEDED_FIELDS = frozenset({"quay_height_m", "camera_lever_arm", "camera_tilt_deg",
                            "camera_pan_deg", "path_keyframes", "wave_roll_deg",
                            "wave_pitch_deg", "wave_heave_m", "wave_period_s"})
_CACHE: dict[tuple[str, str, int], object] = {}


def _cached(what: str, scenario: Scenario, seed: int, make):
    """Memoise draws of registered scenarios (variants are drawn afresh)."""
    if SCENARIOS.get(scenario.name) is not scenario:
        return make()
    key = (what, scenario.name, seed)
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


# --------------------------------------------------------------------------------- light


def _draw_light(rng: np.random.Generator, duration_s: float) -> Light:
    kind = _pick(rng, LIGHT_KINDS, p=[0.35, 0.25, 0.25, 0.15])
    az = float(rng.uniform(0.0, 360.0))
    clear_zen, clear_hor = (196.0, 140.0, 88.0), (226.0, 214.0, 200.0)
    haze_clear = (205.0, 198.0, 188.0)
    if kind == "clear":
        el = rng.uniform(28.0, 62.0)
        t = rng.uniform(-1.0, 1.0)  # deeper or paler blue
        light = dict(direct=rng.uniform(0.38, 0.5), ambient=rng.uniform(0.52, 0.62),
                     sun_colour=(0.97, 1.0, 1.02), ambient_colour=(1.04, 1.0, 0.96),
                     sky_zenith=_mix(clear_zen, (215.0, 165.0, 120.0), 0.5 + 0.5 * t),
                     sky_horizon=clear_hor, sky_glow=(30.0, 35.0, 40.0), haze=haze_clear,
                     haze_m=rng.uniform(3000.0, 7000.0), cloud_cover=rng.uniform(0.0, 0.45),
                     cloud_colour=(242.0, 242.0, 242.0), exposure=rng.uniform(0.95, 1.05),
                     noise_sigma=2.2, glare=0.6)
    elif kind == "low-sun":
        el = rng.uniform(4.0, 14.0)
        warm = rng.uniform(0.4, 1.0)
        light = dict(direct=rng.uniform(0.55, 0.75), ambient=rng.uniform(0.36, 0.46),
                     sun_colour=_mix((0.95, 1.0, 1.03), (0.72, 0.9, 1.12), warm),
                     ambient_colour=(1.08, 1.0, 0.94),
                     sky_zenith=(190.0, 135.0, 90.0),
                     sky_horizon=_mix(clear_hor, (190.0, 205.0, 225.0), warm),
                     sky_glow=_mix((60.0, 70.0, 80.0), (40.0, 90.0, 140.0), warm),
                     haze=_mix(haze_clear, (170.0, 190.0, 215.0), warm),
                     haze_m=rng.uniform(2000.0, 5000.0), cloud_cover=rng.uniform(0.0, 0.35),
                     cloud_colour=_mix((235.0, 238.0, 240.0), (190.0, 215.0, 245.0), warm),
                     exposure=rng.uniform(0.9, 1.0), noise_sigma=2.4, glare=1.0)
    elif kind == "overcast":
        el = rng.uniform(20.0, 50.0)
        grey = rng.uniform(175.0, 215.0)
        light = dict(direct=rng.uniform(0.0, 0.08), ambient=rng.uniform(0.82, 0.95),
                     sun_colour=(1.0, 1.0, 1.0), ambient_colour=(1.0, 1.0, 1.0),
                     sky_zenith=(grey - 20.0, grey - 22.0, grey - 26.0),
                     sky_horizon=(grey + 12.0, grey + 12.0, grey + 10.0),
                     sky_glow=(8.0, 8.0, 8.0), haze=(grey, grey, grey - 4.0),
                     haze_m=rng.uniform(1200.0, 3500.0), cloud_cover=rng.uniform(0.85, 1.0),
                     cloud_colour=(grey + 8.0, grey + 8.0, grey + 8.0),
                     exposure=rng.uniform(0.95, 1.1), noise_sigma=2.6, glare=0.0)
    else:  # dusk: the sun has just set, an afterglow over the horizon
        el = rng.uniform(-4.0, 1.0)
        light = dict(direct=0.0, ambient=rng.uniform(0.42, 0.55),
                     sun_colour=(0.7, 0.85, 1.1), ambient_colour=(1.15, 0.95, 0.85),
                     sky_zenith=(120.0, 80.0, 55.0), sky_horizon=(150.0, 150.0, 170.0),
                     sky_glow=(20.0, 90.0, 160.0), haze=(130.0, 125.0, 135.0),
                     haze_m=rng.uniform(1500.0, 4000.0), cloud_cover=rng.uniform(0.1, 0.6),
                     cloud_colour=(120.0, 140.0, 190.0), exposure=rng.uniform(0.55, 0.75),
                     noise_sigma=rng.uniform(3.5, 5.0), glare=0.3)
    # Exposure: a few steps (the camera's auto-exposure hunting, a cloud over the sun) and,
    # on some seeds, a gain that follows the picture's brightness (looking into a bright sky
    # darkens the port).
    n_steps = int(rng.choice(4, p=[0.35, 0.3, 0.2, 0.15]))
    steps = tuple(sorted(
        (float(rng.uniform(5.0, duration_s - 5.0)),
         float(np.exp(rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 0.32))),
         float(rng.uniform(0.3, 2.0))) for _ in range(n_steps)))
    ae = float(rng.choice([0.0, rng.uniform(0.2, 0.6)], p=[0.4, 0.6]))
    return Light(kind=kind, sun_az_deg=az, sun_el_deg=float(el), exposure_steps=steps,
                 auto_exposure=ae, **{k: (tuple(float(x) for x in v) if isinstance(v, tuple)
                                          else float(v)) for k, v in light.items()})


# --------------------------------------------------------------------------------- water


def _draw_water(rng: np.random.Generator) -> Water:
    chop = float(_pick(rng, [rng.uniform(0.0, 0.2), rng.uniform(0.2, 0.6),
                             rng.uniform(0.6, 1.0)], p=[0.35, 0.4, 0.25]))
    wind = rng.uniform(0.0, 360.0)
    # long swell from far away, wind waves and ripples; calm water keeps only faint ripples
    amp = 0.12 + 1.1 * chop
    layers = ((float(7.0 * rng.uniform(0.8, 1.3)), float(rng.uniform(0, 360)),
               float(amp * rng.uniform(0.6, 1.0))),
              (float(1.6 * rng.uniform(0.8, 1.2)), float(wind + rng.uniform(-25, 25)),
               float(amp * 0.75)),
              (float(0.4 * rng.uniform(0.8, 1.2)), float(wind + rng.uniform(-40, 40)),
               float(0.6 * (0.3 + 0.9 * chop))))
    deep = _pick(rng, [(70.0, 68.0, 38.0), (78.0, 62.0, 34.0), (56.0, 70.0, 52.0),
                       (50.0, 62.0, 66.0), (62.0, 58.0, 40.0)])
    return Water(chop=chop, layers=layers, deep=deep, wobble_px=0.4 + 7.0 * chop)


# ---------------------------------------------------------------------------------- port


def _path_points(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """Times and positions (centre of motion) of a scenario's path, densely (piecewise
    linear between keyframes is enough to keep obstacles away)."""
    kf = np.asarray(scenario.path_keyframes, float)
    t = np.linspace(kf[0, 0], kf[-1, 0], int((kf[-1, 0] - kf[0, 0]) / 0.5) + 1)
    return t, np.column_stack([np.interp(t, kf[:, 0], kf[:, 1]),
                               np.interp(t, kf[:, 0], kf[:, 2])])


def _rect_distance(p: np.ndarray, n0: float, n1: float, e0: float, e1: float) -> np.ndarray:
    """Distance from points (N, 2) to the axis-aligned rectangle [n0, n1] x [e0, e1]."""
    dn = np.maximum(np.maximum(n0 - p[:, 0], p[:, 0] - n1), 0.0)
    de = np.maximum(np.maximum(e0 - p[:, 1], p[:, 1] - e1), 0.0)
    return np.hypot(dn, de)


def _draw_marina(rng: np.random.Generator, sc: Scenario) -> Port:
    e0, e1 = sc.quay_east_range
    _t, base_path = _path_points(sc)
    clear = 0.5 * sc.hull_length_m + 4.0  # the own ship's path keeps this far from obstacles
    pontoon = None
    if rng.random() < 0.7:
        for _ in range(20):
            length, width = rng.uniform(14.0, 30.0), rng.uniform(2.0, 3.2)
            pe = rng.uniform(e0 + 15.0, e1 - 20.0)
            if _rect_distance(base_path, -length - 3.0, 0.0, pe - 3.0, pe + width + 3.0).min() \
                    > clear:
                pontoon = (float(pe), float(length), float(width))
                break
    boats: list[Boat] = []

    def free(n: float, e: float, length: float, beam: float, yaw: float) -> bool:
        half = 0.5 * max(length, beam) + 1.0
        for b in boats:
            if np.hypot(b.north - n, b.east - e) < half + 0.5 * b.length + 1.0:
                return False
        if pontoon is not None:
            pe, pl, pw = pontoon
            if _rect_distance(np.array([[n, e]]), -pl, 0.0, pe, pe + pw)[0] < half - 0.3:
                return False
        return _rect_distance(base_path, n - half, n + half, e - half, e + half).min() > clear

    def yacht(n: float, e: float, yaw: float, moored: bool = True) -> Boat | None:
        length = float(rng.uniform(6.0, 12.0))
        beam = float(length * rng.uniform(0.3, 0.36))
        if not free(n, e, length, beam, yaw):
            return None
        surge = rng.random() < 0.3 and moored
        return Boat(north=float(n), east=float(e), yaw_deg=float(yaw), length=length, beam=beam,
                    freeboard=float(rng.uniform(0.7, 1.2)), sail=bool(rng.random() < 0.55),
                    surge_m=float(rng.uniform(0.3, 1.0)) if surge else 0.0,
                    surge_period_s=float(rng.uniform(15.0, 40.0)),
                    surge_phase=float(rng.uniform(0, 2 * np.pi)))

    # alongside the quay, bow east or west
    for _ in range(int(rng.integers(0, 9))):
        e = rng.uniform(e0 + 6.0, e1 - 6.0)
        b = yacht(0.0, e, 90.0 + 180.0 * (rng.random() < 0.5))
        if b is not None:
            boats.append(dataclasses.replace(b, north=-0.5 * b.beam - 0.4))
    # along the pontoon, both sides
    if pontoon is not None:
        pe, pl, pw = pontoon
        for _ in range(int(rng.integers(0, 5))):
            side = rng.choice([-1.0, 1.0])
            n = -rng.uniform(4.0, pl - 3.0)
            b = yacht(n, 0.0, 180.0 + rng.uniform(-3.0, 3.0))
            if b is None:
                continue
            e = pe - 0.5 * b.beam - 0.5 if side < 0 else pe + pw + 0.5 * b.beam + 0.5
            if free(n, e, b.length, b.beam, b.yaw_deg):
                boats.append(dataclasses.replace(b, east=float(e)))
    # boats passing slowly across the basin (parallel to the quay), clear of the base path at
    # every time; the seed's own path is drawn afterwards around everything that is moored
    for _ in range(int(rng.choice(3, p=[0.5, 0.35, 0.15]))):
        heading = 90.0 if rng.random() < 0.5 else 270.0
        speed = float(rng.uniform(0.25, 0.7))
        n = float(rng.uniform(-60.0, -14.0))
        # in the picture around the middle of the recording: start so that it crosses e ~ 0
        e_start = float(rng.uniform(-70.0, 20.0)) * (1 if heading == 90.0 else -1)
        length = float(rng.uniform(6.0, 11.0))
        b = Boat(north=n, east=e_start, yaw_deg=heading, length=length,
                 beam=length * 0.33, freeboard=float(rng.uniform(0.7, 1.1)),
                 sail=bool(rng.random() < 0.4), speed=speed)
        if _passing_clear(b, sc, sc.duration_s):
            boats.append(b)
    skyline = _pick(rng, ["low", "mixed", "tall"], p=[0.3, 0.4, 0.3])
    heights = {"low": (6.0, 8.0, 10.0, 12.0), "mixed": (7.0, 10.0, 13.0, 16.0, 22.0),
               "tall": (13.0, 19.0, 28.0, 37.0, 46.0, 58.0)}[skyline]
    setback = float(rng.uniform(15.0, 45.0))
    gap_lo = float(rng.uniform(0.0, 5.0))
    weights = rng.dirichlet(np.ones(len(FACADE_STYLES)) * 0.8)
    return Port(
        quay_height_m=float(rng.uniform(1.0, 2.2)),
        quay_material=_pick(rng, QUAY_MATERIALS),
        concrete=_pick(rng, [(150.0, 156.0, 158.0), (128.0, 134.0, 138.0),
                             (170.0, 172.0, 168.0), (140.0, 150.0, 160.0)]),
        pontoon=pontoon, boats=tuple(boats),
        setback_m=(setback, setback + float(rng.uniform(5.0, 35.0))),
        heights_m=heights, gap_m=(gap_lo, gap_lo + float(rng.uniform(2.0, 15.0))),
        facade_weights=tuple(float(w) for w in weights),
        repetitive=float(rng.uniform(0.0, 0.8)), trees=float(rng.uniform(0.0, 1.0)),
        cranes=int(rng.random() < 0.35),
        crane_colours=_pick(rng, [((40.0, 190.0, 230.0), (40.0, 40.0, 40.0)),
                                  ((40.0, 45.0, 190.0), (232.0, 232.0, 230.0))]),
        stack_tiers=0, stack_fill=0.0,
        hills_m=float(rng.choice([0.0, rng.uniform(200.0, 700.0)], p=[0.3, 0.7])),
        town=bool(rng.random() < 0.8))


def _passing_clear(boat: Boat, scenario: Scenario, duration_s: float,
                   margin_m: float = PASSING_CLEAR_M) -> bool:
    """A passing boat stays ``margin_m`` + half lengths away from the ship's path, at every
    time (a boat can pass through where the ship was a minute before)."""
    t, path = _path_points(scenario)
    keep = t <= duration_s
    d = np.linalg.norm(boat.position(t[keep]) - path[keep], axis=1)
    return bool(d.min() > margin_m + 0.5 * (boat.length + scenario.hull_length_m))


def _draw_terminal(rng: np.random.Generator, sc: Scenario) -> Port:
    e0, e1 = sc.quay_east_range
    boats: list[Boat] = []
    for _ in range(int(rng.choice(3, p=[0.3, 0.5, 0.2]))):
        length = float(rng.uniform(90.0, 140.0))
        beam = float(rng.uniform(16.0, 24.0))
        e = float(rng.uniform(e0 + 0.5 * length, e1 - 0.5 * length))
        if any(abs(b.east - e) < 0.5 * (b.length + length) + 10.0 for b in boats):
            continue
        # keep the middle of the berth (where the ship comes alongside) free
        if abs(e) < 0.5 * length + 0.5 * sc.hull_length_m - 20.0:
            continue
        boats.append(Boat(north=-0.5 * beam - 0.8, east=e, yaw_deg=90.0 + 180.0 * (rng.random()
                          < 0.5), length=length, beam=beam, freeboard=float(rng.uniform(5.0,
                          9.0)), sail=False, kind="feeder",
                          surge_m=float(rng.uniform(0.2, 0.6)) if rng.random() < 0.3 else 0.0,
                          surge_period_s=float(rng.uniform(40.0, 90.0)),
                          surge_phase=float(rng.uniform(0, 2 * np.pi))))
    if rng.random() < 0.4:  # a tug crossing the basin behind or in front of the ship
        heading = 90.0 if rng.random() < 0.5 else 270.0
        tug = Boat(north=float(rng.uniform(-60.0, -35.0)),
                   east=float(rng.uniform(-200.0, 0.0)) * (1 if heading == 90.0 else -1),
                   yaw_deg=heading, length=28.0, beam=9.0, freeboard=3.0, sail=False,
                   speed=float(rng.uniform(0.8, 2.0)), kind="tug")
        boats.append(tug)
    return Port(
        quay_height_m=float(rng.uniform(2.5, 4.5)),
        quay_material=_pick(rng, ["panels", "sheet-pile", "blocks"]),
        concrete=_pick(rng, [(150.0, 156.0, 158.0), (128.0, 134.0, 138.0),
                             (170.0, 172.0, 168.0)]),
        pontoon=None, boats=tuple(boats), setback_m=(225.0, 260.0),
        heights_m=(10.0, 13.0, 16.0, 22.0, 28.0, 40.0), gap_m=(5.0, 40.0),
        facade_weights=(0.0, 0.35, 0.25, 0.4, 0.0), repetitive=float(rng.uniform(0.2, 0.9)),
        trees=0.0, cranes=int(rng.integers(2, 7)),
        crane_colours=_pick(rng, [((40.0, 45.0, 190.0), (232.0, 232.0, 230.0)),
                                  ((150.0, 90.0, 30.0), (232.0, 232.0, 230.0)),
                                  ((40.0, 190.0, 230.0), (70.0, 70.0, 70.0)),
                                  ((60.0, 130.0, 60.0), (225.0, 225.0, 220.0))]),
        stack_tiers=int(rng.integers(2, 7)), stack_fill=float(rng.uniform(0.5, 0.95)),
        hills_m=float(rng.choice([0.0, rng.uniform(300.0, 900.0)], p=[0.3, 0.7])),
        town=bool(rng.random() < 0.8))


def _draw_look(scenario: Scenario, seed: int) -> Look:
    light = _draw_light(_rng(scenario, seed, "light"), scenario.duration_s)
    water = _draw_water(_rng(scenario, seed, "water"))
    rng = _rng(scenario, seed, "port")
    if scenario.scene_kind == "marina":
        port = _draw_marina(rng, scenario)
    elif scenario.scene_kind == "container-terminal":
        port = _draw_terminal(rng, scenario)
    else:
        raise ValueError(f"unknown scene kind {scenario.scene_kind!r}")
    return Look(light=light, water=water, port=port)


def look(scenario: Scenario, seed: int) -> Look:
    """The port, light and water of ``scenario``'s recording ``seed``."""
    base = _base(scenario)
    return _cached("look", base, int(seed), lambda: _draw_look(base, int(seed)))


def reference_look(scenario: Scenario) -> Look:
    """The one look every seed had before the port varied: a clear day with the sun
    south-south-west 40 deg up, moderately rippled water, a block quay, mid-rise buildings,
    boats where the path does not go. For tests of the camera pipeline's mechanics (tracking a
    point, the VO's geometry) that are not about a hard port; the seeds are for robustness."""
    light = Light(kind="clear", sun_az_deg=215.0, sun_el_deg=40.0, direct=0.42, ambient=0.58,
                  sun_colour=(1.0, 1.0, 1.0), ambient_colour=(1.0, 1.0, 1.0),
                  sky_zenith=(196.0, 140.0, 88.0), sky_horizon=(226.0, 214.0, 200.0),
                  sky_glow=(25.0, 30.0, 35.0), haze=(205.0, 198.0, 188.0), haze_m=4500.0,
                  cloud_cover=0.27, cloud_colour=(242.0, 242.0, 242.0), exposure=1.0,
                  exposure_steps=(), auto_exposure=0.0, noise_sigma=2.2, glare=0.6)
    water = Water(chop=0.5, layers=((7.0, 200.0, 1.0), (1.6, 115.0, 0.75), (0.4, 330.0, 0.6)),
                  deep=(70.0, 68.0, 38.0), wobble_px=3.9)
    if scenario.scene_kind == "marina":
        yachts = [Boat(north=-1.8, east=e, yaw_deg=yaw, length=8.5, beam=2.6, freeboard=0.9,
                       sail=sail) for e, yaw, sail in ((-52.0, 90.0, True), (-43.0, 270.0, False),
                                                       (38.0, 90.0, True), (48.0, 270.0, True))]
        yachts += [Boat(north=n, east=24.4, yaw_deg=180.0, length=8.0, beam=2.6, freeboard=0.9,
                        sail=True) for n in (-6.0, -15.0)]
        port = Port(quay_height_m=1.5, quay_material="blocks", concrete=(150.0, 156.0, 158.0),
                    pontoon=(20.0, 24.0, 2.5), boats=tuple(yachts), setback_m=(30.0, 55.0),
                    heights_m=(7.0, 10.0, 13.0, 16.0, 22.0), gap_m=(3.0, 12.0),
                    facade_weights=(0.65, 0.35, 0.0, 0.0, 0.0), repetitive=0.0, trees=0.8,
                    cranes=0, crane_colours=((40.0, 45.0, 190.0), (232.0, 232.0, 230.0)),
                    stack_tiers=0, stack_fill=0.0, hills_m=480.0, town=True)
    else:
        feeder = Boat(north=-10.8, east=-160.0, yaw_deg=90.0, length=110.0, beam=20.0,
                      freeboard=7.0, sail=False, kind="feeder")
        port = Port(quay_height_m=3.0, quay_material="panels", concrete=(150.0, 156.0, 158.0),
                    pontoon=None, boats=(feeder,), setback_m=(225.0, 260.0),
                    heights_m=(16.0, 22.0, 28.0), gap_m=(10.0, 40.0),
                    facade_weights=(0.0, 1.0, 0.0, 0.0, 0.0), repetitive=0.0, trees=0.0,
                    cranes=4, crane_colours=((40.0, 45.0, 190.0), (232.0, 232.0, 230.0)),
                    stack_tiers=5, stack_fill=0.85, hills_m=800.0, town=True)
    return Look(light=light, water=water, port=port)


# ------------------------------------------------------------------------- the manoeuvre


def _bump(t: np.ndarray, start: float, duration: float) -> np.ndarray:
    """Raised-cosine pulse of unit height over [start, start + duration]."""
    x = np.clip((t - start) / duration, 0.0, 1.0)
    return 0.5 * (1.0 - np.cos(2 * np.pi * x))


def _ramp(t: np.ndarray, start: float, duration: float) -> np.ndarray:
    """Smooth step from 0 to 1 over [start, start + duration]."""
    x = np.clip((t - start) / duration, 0.0, 1.0)
    return 0.5 * (1.0 - np.cos(np.pi * x))


def _quay_in_view(centre: np.ndarray, psi: np.ndarray, cam_fwd: float, pan: float,
                  sc: Scenario, height: float, pontoon) -> np.ndarray:
    """Metres of quay wall seen at QUAY_IN_VIEW_RANGE_M within the picture, per sample."""
    cam = centre + cam_fwd * np.column_stack([np.cos(psi), np.sin(psi)])
    e = np.arange(sc.quay_east_range[0] + 1.0, sc.quay_east_range[1] - 1.0, 0.5)
    if pontoon is not None:  # the pontoon and its boats hide the wall behind them
        pe, _pl, pw = pontoon
        e = e[(e < pe - 6.0) | (e > pe + pw + 6.0)]
    d = np.stack([-cam[:, 0:1] + 0 * e, e[None, :] - cam[:, 1:2]], axis=-1)
    rng_m = np.hypot(np.linalg.norm(d, axis=-1), height)
    off = np.angle(np.exp(1j * (np.arctan2(d[..., 1], d[..., 0]) - (psi + pan)[:, None])))
    ok = (rng_m > QUAY_IN_VIEW_RANGE_M[0]) & (rng_m < QUAY_IN_VIEW_RANGE_M[1]) & \
        (np.abs(off) < np.radians(0.5 * sc.camera_hfov_deg - 6.0))
    return 0.5 * ok.sum(axis=1)


def _small_boat_path(rng: np.random.Generator, sc: Scenario, port: Port, cam_fwd: float,
                     pan: float, cam_height: float) -> tuple[tuple[float, ...], ...]:
    """Approach, an S-turn, slow down, a last swing and stop with the quay 7-15 m ahead."""
    T, dt = sc.duration_s, 0.1
    t = np.arange(0.0, T + 0.5 * dt, dt)
    r_hull = 0.5 * sc.hull_length_m + 0.3
    obstacles = [(-port.pontoon[1] - 1.0, 0.0, port.pontoon[0], port.pontoon[0]
                  + port.pontoon[2])] if port.pontoon else []
    passing = [b for b in port.boats if b.speed != 0.0]
    for b in port.boats:
        if b.speed == 0.0:
            h = 0.5 * b.length + b.surge_m + 1.0
            obstacles.append((b.north - h, b.north + h, b.east - h, b.east + h))
    check_t = (t >= QUAY_IN_VIEW_S[0]) & (t <= QUAY_IN_VIEW_S[1]) & \
        (np.abs(t / 1.5 - np.round(t / 1.5)) < 1e-6)
    for _ in range(2000):
        u0, u_end = rng.uniform(0.8, 1.4), rng.uniform(0.04, 0.18)
        t_slow = rng.uniform(35.0, 55.0)
        t_stop = rng.uniform(max(t_slow + 15.0, 70.0), 86.0)
        u = u0 + (u_end - u0) * _ramp(t, t_slow, t_stop - t_slow)
        r = np.zeros_like(t)
        ts, sign = rng.uniform(5.0, 16.0), rng.choice([-1.0, 1.0])
        for _k in range(int(rng.integers(2, 4))):
            dur = rng.uniform(7.0, 13.0)
            r += sign * np.radians(rng.uniform(5.0, 11.0)) * _bump(t, ts, dur)
            ts += dur + rng.uniform(2.0, 10.0)
            sign = -sign
        if ts > 68.0:
            continue
        t_last = rng.uniform(max(ts, 52.0), 74.0)
        r += rng.choice([-1.0, 1.0]) * np.radians(rng.uniform(2.0, 7.0)) * \
            _bump(t, t_last, rng.uniform(5.0, 10.0))
        psi = np.cumsum(r) * dt
        xy = np.cumsum(u[:, None] * np.column_stack([np.cos(psi), np.sin(psi)]), axis=0) * dt
        # place the end: heading and stop point drawn, the quay d_end ahead of the camera
        psi_end = np.radians(rng.uniform(-35.0, 40.0))
        d_end = rng.uniform(7.0, 15.0)
        rot = psi_end - psi[-1]
        c, s = np.cos(rot), np.sin(rot)
        xy = (xy - xy[-1]) @ np.array([[c, s], [-s, c]])
        psi = psi + rot
        cam_end = np.array([-d_end, rng.uniform(-35.0, 35.0)])
        centre = xy + cam_end - cam_fwd * np.array([np.cos(psi_end), np.sin(psi_end)])
        # plausible: starts well out, never near the quay or a moored boat, quay in view
        if not -140.0 < centre[0, 0] < -45.0 or np.abs(centre[:, 1]).max() > 130.0:
            continue
        if centre[:, 0].max() > -r_hull - 2.0:
            continue
        if any(_rect_distance(centre, *ob).min() < r_hull + 1.5 for ob in obstacles):
            continue
        if any(np.linalg.norm(b.position(t) - centre, axis=1).min() < PASSING_CLEAR_M + 0.5 * (
                b.length + sc.hull_length_m) for b in passing):
            continue
        seen = _quay_in_view(centre[check_t], psi[check_t], cam_fwd, pan, sc, cam_height,
                             port.pontoon)
        if seen.min() < 6.0:
            continue
        keys = np.arange(0.0, T + 1e-9, KEYFRAME_SPACING_S)
        idx = np.rint(keys / dt).astype(int)
        keys = tuple((float(tk), float(centre[i, 0]), float(centre[i, 1]),
                      float(np.degrees(psi[i]))) for tk, i in zip(keys, idx, strict=True))
        # the motion model turns through the keyframe headings its own (smooth) way: keep
        # the designs it follows with little sideways speed (a weak current's worth)
        # and turns no faster than the thesis' boat (~10 deg/s)
        motion = ShipMotion(dataclasses.replace(sc, path_keyframes=keys, wave_roll_deg=0.0,
                                                wave_pitch_deg=0.0, wave_heave_m=0.0), 0)
        _surge, sway = motion.surge_sway(t[::5])
        yaw_rate = motion.state(t[::5]).omega_body[:, 2]
        if np.abs(sway).max() > MAX_SWAY_MS or np.abs(yaw_rate).max() > MAX_YAW_RATE:
            continue
        return keys
    raise RuntimeError(f"no plausible berthing path for {sc.name}")  # pragma: no cover


def _large_ship_path(rng: np.random.Generator, sc: Scenario, side: float
                     ) -> tuple[tuple[float, ...], ...]:
    """Creeping along the quay (quay on the ``side``: -1 port, +1 starboard) while tugs push
    her sideways towards it and turn her a few degrees."""
    T = sc.duration_s
    t = np.linspace(0.0, T, int(T / 30.0) + 1)
    psi0 = (90.0 if side < 0 else 270.0) + rng.uniform(-6.0, 6.0)
    dpsi = rng.uniform(-8.0, 8.0)
    u0 = rng.uniform(0.06, 0.16)
    u_end = u0 * rng.uniform(0.0, 0.6)
    # along-track distance of a speed falling from u0 to u_end by a cosine ramp
    tt = np.linspace(0.0, T, 1201)
    u = u0 + (u_end - u0) * _ramp(tt, 0.0, T)
    s = np.interp(t, tt, np.concatenate([[0.0], np.cumsum(0.5 * (u[1:] + u[:-1]) * np.diff(tt))]))
    lateral = rng.uniform(3.0, 10.0) * _ramp(t, 0.0, T)
    psi = psi0 + dpsi * _ramp(t, 0.0, T)
    along = np.array([0.0, 1.0 if side < 0 else -1.0])
    n0 = rng.uniform(-135.0, -105.0)
    e0 = rng.uniform(-60.0, 60.0)
    pos = np.array([n0, e0]) + s[:, None] * along + lateral[:, None] * np.array([1.0, 0.0])
    return tuple((float(a), float(p[0]), float(p[1]), float(y))
                 for a, p, y in zip(t, pos, psi, strict=True))


def _small_boat(sc: Scenario, seed: int, lk: Look) -> dict:
    rng = _rng(sc, seed, "ship")
    # on a third of the boats the camera sits on the cabin top, looking over the foredeck (the
    # bow in the lower part of the picture); else on the stem, nothing of the boat in view
    bow_view = rng.random() < 0.35
    fwd = rng.uniform(0.4, 1.4) if bow_view else rng.uniform(2.7, 3.3)
    height = rng.uniform(1.8, 2.3) if bow_view else rng.uniform(0.8, 1.8)
    tilt, pan = rng.uniform(0.0, 8.0), rng.uniform(-4.0, 4.0)
    body_height = -sc.reference_point_down_m
    chop = lk.water.chop
    period = sc.wave_period_s * rng.uniform(0.8, 1.2)
    keys = _small_boat_path(rng, sc, lk.port, fwd, np.radians(pan), height)
    return dict(camera_lever_arm=(float(fwd), float(rng.uniform(-0.3, 0.3)),
                                  float(body_height - height)),
                camera_tilt_deg=float(tilt), camera_pan_deg=float(pan), path_keyframes=keys,
                wave_roll_deg=float(0.7 + 2.6 * chop), wave_pitch_deg=float(0.4 + 1.3 * chop),
                wave_heave_m=float(0.02 + 0.09 * chop), wave_period_s=float(period))


def _large_ship(sc: Scenario, seed: int, lk: Look) -> dict:
    rng = _rng(sc, seed, "ship")
    side = -1.0 if rng.random() < 0.5 else 1.0  # quay to port or to starboard
    height = rng.uniform(16.0, 28.0)
    body_height = -sc.reference_point_down_m
    pan = side * rng.uniform(62.0, 88.0)
    chop = lk.water.chop
    keys = _large_ship_path(rng, sc, side)
    return dict(camera_lever_arm=(float(rng.uniform(-4.0, 4.0)),
                                  float(side * rng.uniform(8.0, 14.0)),
                                  float(body_height - height)),
                camera_tilt_deg=float(rng.uniform(6.0, 16.0)), camera_pan_deg=float(pan),
                path_keyframes=keys, wave_roll_deg=float(0.1 + 0.4 * chop),
                wave_pitch_deg=float(0.05 + 0.12 * chop), wave_heave_m=float(0.03 + 0.06 * chop),
                wave_period_s=float(sc.wave_period_s * rng.uniform(0.85, 1.2)))


_MANOEUVRES = {"small-boat": _small_boat, "large-ship": _large_ship}


def _draw_seeded(base: Scenario, seed: int) -> Scenario:
    lk = look(base, seed)
    fields: dict = {"quay_height_m": lk.port.quay_height_m}
    # only the registered scenarios' manoeuvres are drawn (a caller's variant keeps its own)
    draw = _MANOEUVRES.get(base.name) if SCENARIOS.get(base.name) is base else None
    if draw is not None:
        fields.update(draw(base, seed, lk))
    return dataclasses.replace(base, **fields)


def seeded(scenario: Scenario, seed: int) -> Scenario:
    """``scenario`` as recording ``seed`` has it: path, camera mounting, wave motion and quay
    height drawn for the seed (see the module docstring)."""
    base = _base(scenario)
    return _cached("scenario", base, int(seed), lambda: _draw_seeded(base, int(seed)))
