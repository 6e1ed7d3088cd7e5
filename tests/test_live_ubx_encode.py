"""UBX encoders (live.ubx_encode) → bytes → pyubx2 → decoders give the data back.

The data are real: RINEX observations of a Septentrio receiver and broadcast ephemerides of
real RINEX navigation files; the decoders themselves are anchored on real u-blox bytes in
test_live_ubx_gnss.py / test_live_ubx_imu.py.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from pyubx2 import UBX_PROTOCOL, UBXReader

from estimator.ephemeris import satellite_state
from estimator.records import KeplerEphemeris
from live.streams import ByteStream
from live.ubx_encode import RawxEncoder, esf_raw_message, sfrbx_messages
from live.ubx_gnss import EphemerisAssembler, UbxGnssSource
from live.ubx_imu import STTAG_TICK_S, EsfRawDecoder
from recordings.rinex import l1_epochs, read_nav, read_obs

DATA = Path(__file__).parent / "data"
NAVS = [DATA / "static.nav", Path(__file__).parents[1] / "recordings/data/nagoya_2024-06-24.nav"]


def stream_of(data: bytes) -> ByteStream:
    return ByteStream(io.BytesIO(data).read, "test bytes")


def test_rawx_round_trip_on_real_observations():
    obs = read_obs(DATA / "static_rover.obs")
    epochs = l1_epochs(obs)[:40]
    # a slip and an unresolved half cycle mid-stream, on top of the receiver's own flags
    sat = sorted(epochs[10].satellites)[0]
    o = epochs[10].satellites[sat]
    epochs[10].satellites[sat] = type(o)(o.pseudorange, o.carrier_phase, o.doppler, o.snr, 1)
    o = epochs[11].satellites[sat]
    epochs[11].satellites[sat] = type(o)(o.pseudorange, o.carrier_phase, o.doppler, o.snr, 2)
    enc = RawxEncoder(glonass_slots=obs.header.glonass_slots)
    data = b"".join(enc.encode(e) for e in epochs)
    src = UbxGnssSource(stream_of(data))
    back = list(src)
    assert src.bad_messages == 0
    assert [e.time for e in back] == [e.time for e in epochs]
    n = 0
    for a, b in zip(epochs, back, strict=True):
        assert set(a.satellites) == set(b.satellites)
        for s, oa in a.satellites.items():
            ob = b.satellites[s]
            assert ob.pseudorange == oa.pseudorange or (math.isnan(oa.pseudorange)
                                                         and math.isnan(ob.pseudorange))
            assert ob.carrier_phase == oa.carrier_phase or (math.isnan(oa.carrier_phase)
                                                             and math.isnan(ob.carrier_phase))
            assert ob.doppler == pytest.approx(oa.doppler, abs=5e-4)  # float32
            assert ob.snr == round(oa.snr)  # integer dB-Hz
            if math.isfinite(oa.carrier_phase):
                assert ob.lli == oa.lli, (a.time, s)
                n += 1
    assert n > 500
    assert src.rawx.glonass_slots == {s: k for s, k in obs.header.glonass_slots.items()
                                      if s in src.rawx.glonass_slots}


def _kepler_records(path: Path, systems: str) -> list[KeplerEphemeris]:
    nav = read_nav(path)
    return [e for v in nav.ephemerides.values() for e in v
            if isinstance(e, KeplerEphemeris) and e.sat[0] in systems]


@pytest.mark.parametrize("path", NAVS, ids=lambda p: p.name)
def test_sfrbx_round_trip_on_real_ephemerides(path):
    """Encoded then decoded broadcast ephemerides put the satellites where the RINEX
    records do: only the quantisation of the broadcast fields can differ."""
    nav = read_nav(path)
    records = _kepler_records(path, "GJE")
    galileo_inav = [e for e in records if e.sat[0] == "E" and e.data_source & 1]
    records = [e for e in records if e.sat[0] in "GJ"] + galileo_inav
    assert {e.sat[0] for e in records} >= {"G", "E"}
    worst_pos = worst_clock = 0.0
    for eph in records:
        data = b"".join(sfrbx_messages(eph, eph.toe - 3600.0,
                                       iono=(nav.iono_alpha, nav.iono_beta)))
        asm = EphemerisAssembler()
        for _, msg in UBXReader(io.BytesIO(data), protfilter=UBX_PROTOCOL):
            asm.add_sfrbx(msg, eph.toe - 3600.0)
        assert not asm.rejected
        (got,) = asm.nav.ephemerides[eph.sat]
        assert (got.toe, got.toc, got.iode, got.health) == (eph.toe, eph.toc, eph.iode,
                                                            eph.health)
        for dt in (-3600.0, 0.0, 3600.0):
            a = satellite_state(eph, eph.toe + dt)
            b = satellite_state(got, eph.toe + dt)
            worst_pos = max(worst_pos, float(np.linalg.norm(a.position - b.position)))
            worst_clock = max(worst_clock, abs(a.clock_bias - b.clock_bias) * 299792458.0)
        if eph.sat[0] == "G":
            assert asm.nav.iono_alpha == pytest.approx(nav.iono_alpha, rel=1e-3)
            assert asm.nav.iono_beta == pytest.approx(nav.iono_beta, rel=1e-3)
    # the RINEX values re-quantised: measured 26 µm / 0.15 µm at worst
    assert worst_pos < 1e-3  # metres
    assert worst_clock < 1e-3  # metres of clock


def test_esf_raw_round_trip():
    rng = np.random.default_rng(5)
    gyro = rng.normal(0, 0.3, (20, 3))
    accel = rng.normal(0, 2.0, (20, 3)) + [0, 0, -9.81]
    tag0 = 2**32 - 1000  # wraps inside the stream
    tags = [(tag0 + 256 * k) % 2**32 for k in range(20)]
    dec = EsfRawDecoder()
    # anchor: the first message's newest sample is at the epoch t0
    first = UBXReader.parse(esf_raw_message(tags[:10], gyro[:10], accel[:10]))
    assert dec.decode(first) == [] and dec.untimed_samples == 10
    t0 = 1.4e9
    dec.navigation_epoch(t0)
    out = dec.decode(UBXReader.parse(esf_raw_message(tags[10:], gyro[10:], accel[10:])))
    assert len(out) == 10
    np.testing.assert_allclose([m.t - t0 for m in out],
                               [256 * k * STTAG_TICK_S for k in range(1, 11)], atol=1e-6)
    np.testing.assert_allclose([m.gyro for m in out], gyro[10:], atol=math.radians(2**-12))
    np.testing.assert_allclose([m.accel for m in out], accel[10:], atol=2**-10)
