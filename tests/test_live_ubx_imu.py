"""UBX-ESF-RAW input (live.ubx_imu) on real bytes of a u-blox NEO-M8U lying still."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pyubx2 import UBX_PROTOCOL, UBXReader

from estimator.frames import gpst_from_week_tow
from live.streams import open_stream
from live.ubx_gnss import UbxGnssSource
from live.ubx_imu import EsfRawDecoder, SensorClock

LOG = Path(__file__).parent / "data" / "ubx_esfraw_gpsd.log"


@pytest.fixture(scope="module")
def decoded():
    imu = EsfRawDecoder()
    src = UbxGnssSource(open_stream(str(LOG)), imu=imu)
    return imu, list(src)


def test_esf_raw_samples_are_complete_and_dated(decoded):
    imu, samples = decoded
    with LOG.open("rb") as fh:
        msgs = [m for _, m in UBXReader(fh, protfilter=UBX_PROTOCOL)]
    n_raw = sum(m.identity == "ESF-RAW" for m in msgs)
    epochs = [gpst_from_week_tow(m.week, m.iTOW * 1e-3 + m.fTOW * 1e-9)
              for m in msgs if m.identity == "NAV-TIMEGPS"]
    assert n_raw == 29 and len(epochs) == 3
    # 10 samples per message; those before the first navigation epoch cannot be dated
    assert imu.incomplete_samples == 0
    assert imu.untimed_samples == 30
    assert len(samples) == 10 * n_raw - 30
    t = np.array([s.t for s in samples])
    dt = np.diff(t)
    assert (dt > 0).all()
    assert np.median(dt) == pytest.approx(0.010, abs=5e-5)  # 100 Hz
    assert dt.max() < 0.0115 and dt.min() > 0.0085
    # the sensor counter runs 1 s ± 1 ms between the 1 s epochs: the anchors barely move
    assert imu.anchor_jumps == 0
    # the sample closing each epoch's batch, dated before the anchor moved to it, falls on
    # that epoch within the counter's drift over 1 s
    for e in epochs[1:]:
        assert np.min(np.abs(t - e)) < 1e-3


def test_esf_raw_physical_values(decoded):
    """A module at rest: specific force of 1 g, rotation rates of a gyro bias only."""
    _, samples = decoded
    accel = np.array([s.accel for s in samples])
    gyro = np.array([s.gyro for s in samples])
    assert np.linalg.norm(accel.mean(axis=0)) == pytest.approx(9.81, abs=0.3)
    assert abs(accel.mean(axis=0)[2]) > 9.5  # gravity along the sensor's z axis
    assert np.abs(gyro.mean(axis=0)).max() < math.radians(1.0)
    assert gyro.std(axis=0).max() < math.radians(0.2)


def test_sensor_clock_wraps():
    clock = SensorClock()
    a = clock.unwrap(2**32 - 10)
    b = clock.unwrap(5)
    assert b - a == 15
    clock.anchor(a, 100.0)
    assert clock.to_gpst(b) == pytest.approx(100.0 + 15 / 25600.0)
