"""Recorded berthings: the recording format (``format``), RINEX (``rinex``), the simulator
(``sim``). ``recordings.load(path)`` is the usual entry point.

The format API is re-exported lazily (PEP 562) so that importing a sibling such as
``recordings.rinex`` or ``recordings.sim`` does not pull in OpenCV or create import cycles.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

# The bundled recording (small-boat, seed 1): what every command uses without a RECORDING.
DEFAULT_RECORDING = Path(__file__).resolve().parent / "default"

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Manifest",
    "Recording",
    "RecordingError",
    "RecordingWarning",
    "ReferenceTrajectory",
    "VideoInfo",
    "VideoWriter",
    "default_files",
    "format_summary",
    "gnss_obs_file",
    "time_gaps",
    "load",
    "summary",
    "write_calibration",
    "write_frame_times",
    "write_hull",
    "write_imu",
    "write_manifest",
    "write_reference",
    "write_scene_points",
]


def __getattr__(name: str) -> Any:
    if name in __all__:
        return getattr(importlib.import_module("recordings.format"), name)
    raise AttributeError(f"module 'recordings' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
