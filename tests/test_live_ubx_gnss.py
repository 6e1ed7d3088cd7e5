"""UBX GNSS input (live.ubx_gnss, live.navmsg) on real receiver bytes.

Two real captures (tests/data/README.md): 14 RXM-RAWX epochs from pyubx2's test data, and a
cold start with RAWX + SFRBX whose RINEX conversion by RTKLIB's convbin (an independent
decoder of the same bytes) is stored beside it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pyubx2 import UBX_PROTOCOL, UBXReader

from estimator.ephemeris import carrier_frequency
from estimator.frames import (
    FREQ_GLONASS_L1_BASE,
    FREQ_GLONASS_L1_STEP,
    SPEED_OF_LIGHT,
    ecef_to_geodetic,
    gpst_from_week_tow,
)
from estimator.records import KeplerEphemeris
from estimator.spp import standalone_position
from live.navmsg import NavMessageError, decode_inav_page, decode_lnav_subframe
from live.streams import open_stream
from live.ubx_gnss import EphemerisAssembler, UbxGnssSource
from recordings.rinex import l1_epochs, read_nav, read_obs

DATA = Path(__file__).parent / "data"
RAWX = DATA / "ubx_rawx_pyubx2.ubx"
COLD = DATA / "ubx_coldstart.ubx"
COLD_OBS = DATA / "ubx_coldstart_convbin.obs"
COLD_NAV = DATA / "ubx_coldstart_convbin.nav"


def ubx_messages(path: Path, identity: str) -> list:
    with path.open("rb") as fh:
        return [m for _, m in UBXReader(fh, protfilter=UBX_PROTOCOL) if m.identity == identity]


@pytest.fixture(scope="module")
def rawx_source():
    src = UbxGnssSource(open_stream(str(RAWX)))
    return src, list(src)


@pytest.fixture(scope="module")
def cold_source():
    src = UbxGnssSource(open_stream(str(COLD)))
    return src, list(src)


# -------------------------------------------------------------- pyubx2's RAWX capture


def test_rawx_epochs_time_tags_and_counts(rawx_source):
    src, epochs = rawx_source
    assert [e.time for e in epochs] == [gpst_from_week_tow(2327, 223793.0 + k) for k in range(14)]
    assert src.bad_messages == 0
    # every measurement is a kept signal (GPS L1C/A, E1, B1I, L1OF) with a pseudorange
    counts = [m.numMeas for m in ubx_messages(RAWX, "RXM-RAWX")]
    assert counts == [23] * 9 + [22, 22, 22, 20, 21]
    assert [len(e.satellites) for e in epochs] == counts
    assert {s[0] for s in epochs[0].satellites} == {"G", "E", "C", "R"}
    first = epochs[0].satellites
    # values straight from the first message (pyubx2's own field parsing)
    assert first["G11"].pseudorange == pytest.approx(21431659.961167824, abs=1e-6)
    assert first["G11"].carrier_phase == pytest.approx(112624126.09217028, abs=1e-6)
    assert first["G11"].doppler == pytest.approx(366.0107421875)
    assert first["G11"].snr == 43.0
    # phase not valid (lock time 0): blank phase, pseudorange kept
    assert math.isnan(first["R17"].carrier_phase) and first["R17"].pseudorange > 2e7
    # GLONASS frequency numbers from freqId - 7
    assert src.rawx.glonass_slots["R03"] == 5 and src.rawx.glonass_slots["R18"] == -3
    assert src.rawx.leap_seconds == 18


def _wavelength(sat: str, slots: dict[str, int]) -> float:
    if sat[0] == "R":
        return SPEED_OF_LIGHT / (FREQ_GLONASS_L1_BASE + slots[sat] * FREQ_GLONASS_L1_STEP)
    return SPEED_OF_LIGHT / carrier_frequency(sat)


def test_rawx_phase_pseudorange_doppler_consistency(rawx_source):
    """Over 1 s, λ·Δφ must equal Δρ (code noise, metres) and -λ·D̄·Δt (Doppler, cm).

    Satellites move by 0-800 m/s along the line of sight: a sign error on phase or Doppler
    makes the difference twice that, a phase in metres instead of cycles or a wrong GLONASS
    wavelength shows as tens of centimetres to hundreds of metres. Tolerances: code noise of
    the weakest (28-30 dB-Hz) signals reaches a few metres, hence 5 m worst / 0.3 m median;
    Doppler noise and the unmodelled range acceleration stay below 0.25 m.
    """
    src, epochs = rawx_source
    vs_code, vs_doppler = [], []
    for a, b in zip(epochs, epochs[1:], strict=False):
        dt = b.time - a.time
        for sat, ob in b.satellites.items():
            oa = a.satellites.get(sat)
            if oa is None or ob.lli & 1 or math.isnan(ob.carrier_phase) \
                    or math.isnan(oa.carrier_phase):
                continue
            lam = _wavelength(sat, src.rawx.glonass_slots)
            dphi = (ob.carrier_phase - oa.carrier_phase) * lam
            vs_code.append(dphi - (ob.pseudorange - oa.pseudorange))
            vs_doppler.append(dphi + 0.5 * (ob.doppler + oa.doppler) * lam * dt)
    vs_code, vs_doppler = np.abs(vs_code), np.abs(vs_doppler)
    assert len(vs_code) > 180  # ~16 phase-tracked satellites over 13 intervals
    assert vs_code.max() < 5.0 and np.median(vs_code) < 0.3
    assert vs_doppler.max() < 0.25 and np.median(vs_doppler) < 0.05


def test_rawx_half_cycle_and_slip_flags(rawx_source):
    """R19: its phase appears newly locked without a resolved half cycle (LLI 1 | 2), then
    resolved with the half cycle subtracted (subHalfCyc toggles) → slip possible (LLI 1)."""
    _, epochs = rawx_source
    flags = [e.satellites["R19"].lli for e in epochs if not math.isnan(
        e.satellites["R19"].carrier_phase)]
    assert flags[:2] == [3, 1] and set(flags[2:]) == {0}
    raw = ubx_messages(RAWX, "RXM-RAWX")
    # every other phase: lock time kept growing, half cycle resolved → no flag
    n_flags = sum(1 for e in epochs for o in e.satellites.values() if o.lli)
    assert n_flags == 2
    assert len(raw) == 14


# ------------------------------------------------------- cold start vs RTKLIB convbin


def test_coldstart_epochs_match_convbin(cold_source):
    src, epochs = cold_source
    ref = {e.time: e for e in l1_epochs(read_obs(COLD_OBS))}
    assert src.rawx.skipped_no_time == 20  # before the receiver knew the week
    assert [e.time for e in epochs] == sorted(ref)
    cp_std = {}  # (time, sat) -> cpStdev index, straight from the bytes
    for m in ubx_messages(COLD, "RXM-RAWX"):
        for i in range(1, m.numMeas + 1):
            g = lambda n, i=i, m=m: getattr(m, f"{n}_{i:02d}")
            sat = {0: "G", 2: "E"}[g("gnssId")] + f"{g('svId'):02d}"
            cp_std[(gpst_from_week_tow(m.week, m.rcvTow), sat)] = g("cpStd")
    n_phase = n_blank = n_first = 0
    for e in epochs:
        r = ref[e.time]
        assert set(e.satellites) == set(r.satellites)
        for sat, o in e.satellites.items():
            q = r.satellites[sat]
            # RINEX holds 3 decimals: equal to its rounding
            assert o.pseudorange == pytest.approx(q.pseudorange, abs=6e-4)
            assert o.doppler == pytest.approx(q.doppler, abs=6e-4)
            assert o.snr == q.snr
            if math.isnan(q.carrier_phase):
                # convbin drops phases with cpStdev > 5 (0.02 cycles): ours keeps them
                assert cp_std[(e.time, sat)] > 5 and math.isfinite(o.carrier_phase)
                n_blank += 1
            else:
                assert o.carrier_phase == pytest.approx(q.carrier_phase, abs=6e-4)
                n_phase += 1
                k = epochs.index(e)
                if k and sat in epochs[k - 1].satellites:
                    assert o.lli == q.lli, (e.time, sat)
                else:
                    # convbin flags every satellite at its first epoch, we only those whose
                    # lock began after the previous epoch (a continuing lock is no slip)
                    assert q.lli == 1 and o.lli in (0, 1)
                    n_first += 1
    assert n_phase > 550 and n_blank < 30 and n_first < 25


def test_coldstart_ephemerides_match_convbin(cold_source):
    src, _ = cold_source
    nav = src.assembler.nav
    assert not src.assembler.rejected  # every subframe/page passed parity / CRC
    ref = read_nav(COLD_NAV)
    got = {(e.sat, e.toe): e for v in nav.ephemerides.values() for e in v}
    assert len(got) == 18 and {s[0] for s, _ in got} == {"G", "E"}
    for (sat, toe), eph in got.items():
        (r,) = [x for x in ref.ephemerides[sat] if x.toe == toe]
        assert isinstance(r, KeplerEphemeris)
        for name in KeplerEphemeris.__dataclass_fields__:
            a, b = getattr(eph, name), getattr(r, name)
            if isinstance(a, float):  # RINEX prints 12 significant digits
                assert a == pytest.approx(b, rel=1e-11, abs=1e-24), (sat, name)
            else:
                assert a == b, (sat, name)
    assert nav.leap_seconds == 18


def test_assembler_seeded_from_rinex_grows():
    seed = read_nav(DATA / "static.nav")
    n_seed = sum(len(v) for v in seed.ephemerides.values())
    asm = EphemerisAssembler(seed=seed)
    src = UbxGnssSource(open_stream(str(COLD)), assembler=asm)
    list(src)
    assert asm.nav is seed and "C01" in asm.nav.ephemerides  # the seed's BeiDou kept
    assert sum(len(v) for v in asm.nav.ephemerides.values()) == n_seed + 18
    assert asm.nav.iono_alpha == seed.iono_alpha  # no page 18 in the capture


def test_coldstart_standalone_position(cold_source):
    """Satellite positions from the decoded subframes fit the same capture's pseudoranges:
    a standalone fix near the receiver's own (NAV-POSECEF) with small residuals."""
    src, epochs = cold_source
    own = {m.iTOW: np.array([m.ecefX, m.ecefY, m.ecefZ]) / 100.0
           for m in ubx_messages(COLD, "NAV-POSECEF")}
    for e in epochs[-5:]:
        fix = standalone_position(e, src.assembler.nav)
        assert fix is not None and len(fix.satellites) >= 15
        itow = round(e.time % 604800 * 1000)
        ref = min(own.items(), key=lambda kv: abs(kv[0] - itow))[1]
        # the receiver's own cold-start fix is itself good to ~3-5 m (hAcc)
        assert np.linalg.norm(fix.position - ref) < 10.0
        lat, lon, h = ecef_to_geodetic(fix.position)
        assert math.degrees(lat) == pytest.approx(47.2513, abs=2e-4)
        assert math.degrees(lon) == pytest.approx(5.9934, abs=2e-4)
        # no ionosphere model in the excerpt (no page 18): residuals of metres, not km
        rms = math.sqrt(np.mean(np.square(list(fix.residuals_m.values()))))
        assert rms < 6.0


# --------------------------------------------------------------- parity and CRC checks


def test_lnav_parity_rejects_a_flipped_bit():
    msg = next(m for m in ubx_messages(COLD, "RXM-SFRBX") if m.gnssId == 0)
    words = [getattr(msg, f"dwrd_{i:02d}") for i in range(1, 11)]
    assert decode_lnav_subframe(words).subframe_id in (1, 2, 3, 4, 5)
    for k in range(10):
        for bit in (6, 20, 29):  # data bits of the word (parity bits are 0-5)
            bad = list(words)
            bad[k] ^= 1 << bit
            with pytest.raises(NavMessageError, match=f"parity fails on word {k + 1}$"):
                decode_lnav_subframe(bad)
    asm = EphemerisAssembler()
    bad = list(words)
    bad[4] ^= 1 << 10
    assert asm.add_lnav("G32", bad, 1.4e9) is None
    assert asm.rejected == {"LNAV parity fails on word 5": 1}


def test_inav_crc_rejects_a_flipped_bit():
    msg = next(m for m in ubx_messages(COLD, "RXM-SFRBX") if m.gnssId == 2)
    words = [getattr(msg, f"dwrd_{i:02d}") for i in range(1, 9)]
    decode_inav_page(words)
    bad = list(words)
    bad[2] ^= 1 << 7
    with pytest.raises(NavMessageError, match="CRC-24Q mismatch"):
        decode_inav_page(bad)


# ------------------------------------------- GPS subframes vs GPSD's decode of the same


def test_gps_subframes_match_gpsd_decode():
    """A NED-M8T's subframes of G03: every one passes parity, and the ephemeris and page 18
    equal GPSD's decode of the same bytes (raw integers from its regression output, scaled
    here by the IS-GPS-200 factors)."""
    path = DATA / "ubx_sfrbx_gpsd.log"
    asm = EphemerisAssembler()
    msgs = ubx_messages(path, "RXM-SFRBX")
    assert len(msgs) == 165
    hint = gpst_from_week_tow(2048 + 69, 442596.0)  # GPSD: WN 69 (10 bits), TOW 442596
    for m in msgs:
        asm.add_sfrbx(m, hint)
    assert not asm.rejected
    (eph,) = asm.nav.ephemerides["G03"]
    sc = math.pi
    gpsd = {  # EPHEM1/2/3 of ublox-ned-m8t-sbfrx3.log.chk (IODC/IODE 94)
        "af0": -564075 * 2.0**-31, "af1": -98 * 2.0**-43, "af2": 0.0, "tgd": 4 * 2.0**-31,
        "crs": -2629 * 2.0**-5, "delta_n": 12436 * 2.0**-43 * sc,
        "m0": 711953732 * 2.0**-31 * sc, "cuc": -2404 * 2.0**-29, "e": 26888654 * 2.0**-33,
        "cus": 3112 * 2.0**-29, "sqrt_a": 2702062248 * 2.0**-19,
        "idot": (4294966727 - 2**32) * 2.0**-43 * sc, "cic": (4294967291 - 2**32) * 2.0**-29,
        "omega0": 1955503549 * 2.0**-31 * sc, "cis": 0.0, "i0": 660807403 * 2.0**-31 * sc,
        "crc": 8635 * 2.0**-5, "omega": 559388649 * 2.0**-31 * sc,
        "omega_dot": -22915 * 2.0**-43 * sc,
    }
    for name, value in gpsd.items():
        assert getattr(eph, name) == pytest.approx(value, rel=1e-15, abs=1e-30), name
    assert (eph.iode, eph.health) == (94, 0)
    assert eph.toe % 604800 == 27900 * 16 and eph.toc == eph.toe
    # IONO of the page 18: a0..a3 = 5, 2, -1, -1; b0..b3 = 38, 3, -1, -5; leap seconds 18
    assert asm.nav.iono_alpha == (5 * 2.0**-30, 2 * 2.0**-27, -(2.0**-24), -(2.0**-24))
    assert asm.nav.iono_beta == (38 * 2.0**11, 3 * 2.0**14, -(2.0**16), -5 * 2.0**16)
    assert asm.nav.leap_seconds == 18


def test_line_noise_does_not_swallow_the_good_messages_after_it(tmp_path: Path):
    """Noise on the link: a fake UBX header claiming 16 KB, one with a length its message
    can have but a wrong checksum, and 3000 random bytes, each before good RAWX messages of
    pyubx2's capture. pyubx2's reader took the fake length and swallowed the messages after
    it (a user trial: a receiver cut off for 29 s to the rest of a run); the random bytes
    dropped the connection with a codec error. Every good epoch is read, the noise counted."""
    data = RAWX.read_bytes()
    frames = [data[k:] for k in range(len(data)) if data[k:k + 4] == b"\xb5\x62\x02\x15"]
    cuts = [len(data) - len(f) for f in frames]
    msgs = [data[a:b] for a, b in zip(cuts, [*cuts[1:], len(data)], strict=True)]
    rng = np.random.default_rng(3)
    noise = [b"\xb5\x62\x02\x15\x00\x40" + bytes(20),  # RAWX claiming 16 KB
             b"\xb5\x62\x02\x15\x30\x00" + bytes(rng.integers(0, 256, 60, dtype=np.uint8)),
             bytes(rng.integers(0, 256, 3000, dtype=np.uint8))]
    stream = b"".join(m + (noise[k % 3] if k % 4 == 1 else b"") for k, m in enumerate(msgs))
    path = tmp_path / "noisy.ubx"
    path.write_bytes(stream)
    src = UbxGnssSource(open_stream(str(path)))
    epochs = list(src)
    assert [e.time for e in epochs] == [gpst_from_week_tow(2327, 223793.0 + k) for k in range(14)]
    assert src.rejected_total >= 3 and "UBX" in (src.last_rejection or "")


def test_a_measurement_not_finite_is_left_out_and_counted(tmp_path: Path):
    """A RAWX whose checksum checks out but whose Doppler is infinite (a corrupt receiver):
    that measurement is left out and counted on the input, not handed on."""
    from live.ubx_encode import RawxEncoder

    epoch = next(iter(UbxGnssSource(open_stream(str(RAWX)))))
    sats = {s: o for s, o in epoch.satellites.items() if s[0] != "R"}  # (GLONASS slots aside)
    g11 = sats["G11"]
    sats["G11"] = type(g11)(g11.pseudorange, g11.carrier_phase, math.inf, g11.snr, g11.lli)
    path = tmp_path / "inf.ubx"
    path.write_bytes(RawxEncoder(leap_seconds=18).encode(type(epoch)(epoch.time, sats)))
    src = UbxGnssSource(open_stream(str(path)))
    (got,) = list(src)
    assert "G11" not in got.satellites and len(got.satellites) == len(sats) - 1
    assert src.rawx.not_finite == 1 and src.rejected_total == 1
