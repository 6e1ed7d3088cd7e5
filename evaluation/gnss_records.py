"""Typed results of the GNSS reports: ``berthing-aid compass`` (the GNSS compass and the
carrier-phase velocity against the reference, thesis fig. 13 and table 21) and ``berthing-aid
baseline`` (two real receivers). Their JSON is these records through ``records.to_json``: the
keys are the field names; a field marked ``omitted_if_none`` is a key only when it has a value."""

from __future__ import annotations

from dataclasses import dataclass, field

from .records import INLINE, omitted_if_none

# ---------------------------------------------------------------------------- compass


@dataclass(frozen=True)
class CompassTrial:
    """One cold start of a compass method; the last three only once it fixed."""

    start_gpst: float
    time_to_fix_s: float | None  # a fix with the first epoch counts as one interval
    window_s: float  # the longest the trial could wait for a fix
    satellites: int | None = omitted_if_none()
    heading_error_deg: float | None = omitted_if_none()
    wrong: bool | None = omitted_if_none()  # heading error beyond WRONG_FIX_DEG at the fix


@dataclass(frozen=True)
class AttitudeErrors:
    """Attitude errors (deg) of every fixed epoch of all trials."""

    epochs: int
    heading_rms: float | None
    pitch_rms: float | None
    roll_rms: float | None
    heading_max: float | None


@dataclass(frozen=True)
class CompassMethodScores:
    """One attitude method ("fast" or "conventional") over the cold starts (fig. 13)."""

    trials: int
    fixed_within_1s: float
    fixed_within_10s: float
    fixed_within_150s: float
    median_time_to_fix_s: float | None
    wrong_fixes: int
    wrong_fix_rate: float | None
    first_fix_heading_rms_deg: float | None
    attitude_error_deg: AttitudeErrors
    per_trial: list[CompassTrial] | None = omitted_if_none()  # only in the JSON


@dataclass(frozen=True)
class VelocityErrorStats:
    """One velocity estimator against the true centroid velocity."""

    solved_fraction: float  # of the scored epochs
    horizontal_rms_mps: float | None
    vertical_rms_mps: float | None


@dataclass(frozen=True)
class ArrayVelocity:
    """The array's velocity error per satellite configuration (thesis table 21)."""

    reduced_after_s: float
    kept_satellites: dict[str, list[str] | None]  # per reduced configuration
    # configuration ("all satellites", "3 satellites", …) → estimator ("loose", "tight",
    # "tight filter") → errors; the configurations are keys of the JSON object itself.
    configurations: dict[str, dict[str, VelocityErrorStats]] = field(metadata=INLINE)


@dataclass(frozen=True)
class CompassReport:
    """``berthing-aid compass``: both attitude methods and the velocity on one recording."""

    recording: str
    epochs: int
    interval_s: float
    systems: str
    sky_mask_deg: float
    sky_mask_centre_deg: float
    masked_satellites: list[str]
    trials: int
    methods: dict[str, CompassMethodScores]
    velocity_error: ArrayVelocity | None = omitted_if_none()


# --------------------------------------------------------------------------- baseline


@dataclass(frozen=True)
class ValueStats:
    mean: float | None
    std: float | None
    min: float | None
    max: float | None


@dataclass(frozen=True)
class FixedBaseline:
    """The fixed baselines of the continuous run (m, up positive; azimuth in deg)."""

    north: ValueStats
    east: ValueStats
    up: ValueStats
    length: ValueStats
    azimuth_deg: ValueStats


@dataclass(frozen=True)
class BaselineEpoch:
    """The continuous run's baseline at one epoch."""

    time_gpst: float
    fixed: bool
    north: float
    east: float
    up: float
    length: float
    azimuth_deg: float
    ratio: float | None  # None: not finite (a float vector that is exactly integer)
    satellites: int


@dataclass(frozen=True)
class BaselineRestart:
    """One cold start; the rest only once it fixed (``error_m`` with a surveyed baseline)."""

    start_gpst: float
    time_to_fix_s: float | None
    length: float | None = omitted_if_none()
    azimuth_deg: float | None = omitted_if_none()
    error_m: float | None = omitted_if_none()


@dataclass(frozen=True)
class TimeToFix:
    restarts: int
    fixed: int
    max_s: float | None
    median_s: float | None


@dataclass(frozen=True)
class ReceiverVelocity:
    """TDCP velocity of one receiver at rest; only ``epochs`` (0) without any solution."""

    epochs: int
    horizontal_rms_mps: float | None = omitted_if_none()
    vertical_rms_mps: float | None = omitted_if_none()
    max_horizontal_mps: float | None = omitted_if_none()
    mean_ned_mps: list[float] | None = omitted_if_none()
    excluded: dict[str, int] | None = omitted_if_none()  # satellite-epochs left out, by why


@dataclass(frozen=True)
class SurveyedScores:
    """The surveyed baseline and the fixed ones' errors against it."""

    north: float
    east: float
    up: float
    length: float
    azimuth_deg: float
    length_error_m: float | None
    azimuth_error_deg: float | None
    max_error_m: float | None
    wrong_fixes: int


@dataclass(frozen=True)
class BaselineReport:
    """``berthing-aid baseline``: baseline, time to fix and TDCP velocity of two receivers."""

    epochs: int
    interval_s: float
    fixed_fraction: float
    fixed: FixedBaseline
    restarts: list[BaselineRestart]
    time_to_fix: TimeToFix
    velocity: dict[str, ReceiverVelocity]  # "base", "rover"
    surveyed: SurveyedScores | None = omitted_if_none()
    per_epoch: list[BaselineEpoch] | None = omitted_if_none()  # only in the JSON
