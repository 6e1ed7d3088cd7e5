"""RINEX 2.10/2.11 observation files and compressed files (gzip, Hatanaka; others refused).

Real data: AJAC3550.21O / .21D (RINEX 2.11 and its Hatanaka form from the station network),
aopr0010.17o (RINEX 2.10), and the project's RINEX 3 excerpt run through hatanaka's own
compressor (tests/data/README.md).
"""

from __future__ import annotations

import bz2
import gzip
import math
import zipfile
from datetime import datetime
from pathlib import Path

import hatanaka
import numpy as np
import pytest

from estimator.frames import FREQ_L1, SPEED_OF_LIGHT, gpst_from_datetime
from recordings.rinex import RinexError, l1_epochs, read_nav, read_obs

DATA = Path(__file__).parent / "data"
AJAC = DATA / "AJAC3550.21O"
AJAC_CRX = DATA / "AJAC3550.21D"
AOPR = DATA / "aopr0010.17o"
STATIC = DATA / "static_base.obs"


def same_obs(a, b) -> None:
    """Two ObsFiles hold the same epochs and observations (NaN = NaN)."""
    assert a.header.obs_types == b.header.obs_types
    assert [e.time for e in a.epochs] == [e.time for e in b.epochs]
    for ea, eb in zip(a.epochs, b.epochs, strict=True):
        assert ea.flag == eb.flag and set(ea.observations) == set(eb.observations)
        for sat, va in ea.observations.items():
            vb = eb.observations[sat]
            assert set(va) == set(vb)
            for code, (x, lli, ssi) in va.items():
                y = vb[code]
                assert (x == y[0] or (math.isnan(x) and math.isnan(y[0]))) and (lli, ssi) == y[1:]


def test_rinex211_header_and_values():
    obs = read_obs(AJAC)
    hd = obs.header
    assert (hd.version, hd.marker_name, hd.receiver_type, hd.interval, hd.leap_seconds) == (
        2.11, "AJAC", "LEICA GR50", 30.0, 18)
    np.testing.assert_array_equal(hd.approx_position_ecef, [4696989.6880, 723994.1970,
                                                            4239678.3040])
    # RINEX 2 types under RINEX 3 codes: C/A on L1 (C1 declared), P(Y) as W
    assert hd.obs_types["G"][:10] == ["L1C", "L2W", "C1C", "C2X", "C1W", "C2W", "D1C", "D2W",
                                      "S1C", "S2W"]
    assert hd.obs_types["E"][:3] == ["L1X", "L2P", "C1X"]
    t0 = gpst_from_datetime(datetime(2021, 12, 21))
    assert [e.time for e in obs.epochs] == [t0, t0 + 30.0] and hd.time_first_obs == t0
    assert all(len(e.observations) == 26 for e in obs.epochs)  # 12 + 12 + 2 ids over 3 lines
    first = l1_epochs(obs)[0].satellites
    assert sorted(first)[:3] == ["E04", "E11", "E12"] and len(first) == 24  # SBAS left out
    # values as printed in the file (5 fields per line, 5 lines per satellite)
    g07 = first["G07"]
    assert (g07.carrier_phase, g07.pseudorange, g07.doppler, g07.snr, g07.lli) == (
        131857102.133, 25091572.3, -411.138, 37.35, 0)
    assert obs.epochs[0].observations["G07"]["L2W"] == (102745756.542, 4, 5)
    assert math.isnan(obs.epochs[0].observations["G07"]["C1W"][0])  # P1 blank
    e04 = first["E04"]
    assert (e04.carrier_phase, e04.pseudorange, e04.doppler) == (150111373.216, 28565244.28,
                                                                 2782.722)


def test_rinex211_phase_code_doppler_consistency():
    """30 s apart: λΔφ agrees with Δρ (decimetres) and with -λ·D̄·30 s (the trapezoid of the
    Doppler misses the range jerk: ~1 m); a sign or unit error would be kilometres."""
    a, b = l1_epochs(read_obs(AJAC), systems="GE")
    lam = SPEED_OF_LIGHT / FREQ_L1
    n = 0
    for sat, ob in b.satellites.items():
        oa = a.satellites[sat]
        dphi = (ob.carrier_phase - oa.carrier_phase) * lam
        assert abs(dphi - (ob.pseudorange - oa.pseudorange)) < 1.0
        assert abs(dphi + 0.5 * (oa.doppler + ob.doppler) * lam * 30.0) < 2.0
        assert abs(dphi) > 100.0  # the satellites do move: the checks are not empty
        n += 1
    assert n == 17


def test_rinex210_gps_only_with_blank_padded_ids():
    obs = read_obs(AOPR)
    assert obs.header.version == 2.10 and set(obs.header.obs_types) == {"G"}
    assert [len(e.observations) for e in obs.epochs] == [10, 9, 11]
    assert "G03" in obs.epochs[0].observations  # written "G 3"
    assert obs.epochs[0].time == gpst_from_datetime(datetime(2017, 1, 1))
    ep = l1_epochs(obs)[0]
    assert ep.satellites["G31"].pseudorange == 22513484.637  # C1 (LLI 4: A/S on)
    assert ep.satellites["G31"].carrier_phase == -14746974.730
    assert math.isnan(ep.satellites["G31"].doppler)  # no D1 in this file


def test_real_hatanaka_file_equals_its_plain_twin(tmp_path):
    same_obs(read_obs(AJAC_CRX), read_obs(AJAC))
    gz = tmp_path / "AJAC3550.21D.gz"
    gz.write_bytes(gzip.compress(AJAC_CRX.read_bytes()))
    same_obs(read_obs(gz), read_obs(AJAC))


def test_rinex3_through_hatanaka_and_gzip(tmp_path):
    plain = read_obs(STATIC)
    crx = tmp_path / "static_base.crx"
    crx.write_text(hatanaka.rnx2crx(STATIC.read_text()))
    assert crx.stat().st_size < STATIC.stat().st_size / 2
    same_obs(read_obs(crx), plain)
    crx_gz = tmp_path / "static_base.crx.gz"
    crx_gz.write_bytes(gzip.compress(crx.read_bytes()))
    same_obs(read_obs(crx_gz), plain)
    rnx_gz = tmp_path / "static_base.rnx.gz"
    rnx_gz.write_bytes(gzip.compress(STATIC.read_bytes()))
    same_obs(read_obs(rnx_gz), plain)
    nav_gz = tmp_path / "static.nav.gz"
    nav_gz.write_bytes(gzip.compress((DATA / "static.nav").read_bytes()))
    assert read_nav(nav_gz).ephemerides == read_nav(DATA / "static.nav").ephemerides


def test_other_compressions_are_refused_by_name(tmp_path):
    z = tmp_path / "ajac3550.21o.Z"
    z.write_bytes(b"\x1f\x9d\x90" + AJAC.read_bytes()[:100])
    with pytest.raises(RinexError, match=r"Unix-compressed \(\.Z\) file"):
        read_obs(z)
    zf = tmp_path / "ajac.zip"
    with zipfile.ZipFile(zf, "w") as arch:
        arch.write(AJAC, "AJAC3550.21O")
    with pytest.raises(RinexError, match="a zip archive"):
        read_obs(zf)
    bz = tmp_path / "ajac.21o.bz2"
    bz.write_bytes(bz2.compress(AJAC.read_bytes()))
    with pytest.raises(RinexError, match="bzip2-compressed"):
        read_obs(bz)


def test_corrupt_compressed_files_are_errors(tmp_path):
    crx = hatanaka.rnx2crx(STATIC.read_text())
    half = len(crx) // 2
    bad = tmp_path / "bad.crx"
    bad.write_text(crx[:half] + "garbage line\n" + crx[half:])
    with pytest.raises(RinexError, match=r"bad\.crx: corrupt Hatanaka"):
        read_obs(bad)
    gz = tmp_path / "cut.obs.gz"
    gz.write_bytes(gzip.compress(STATIC.read_bytes())[:5000])
    with pytest.raises(RinexError, match=r"cut\.obs\.gz: corrupt gzip data"):
        read_obs(gz)
