"""RINEX 3 reading and writing (recordings.rinex) on a real receiver excerpt and small files."""

from __future__ import annotations

import math
from collections import Counter
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from estimator.frames import (
    FREQ_GLONASS_L1_BASE,
    FREQ_GLONASS_L1_STEP,
    SPEED_OF_LIGHT,
    WAVELENGTH_L1,
    gpst_from_datetime,
)
from estimator.records import GlonassEphemeris, GnssEpoch, KeplerEphemeris, SatObservation
from recordings.rinex import (
    RinexError,
    l1_epochs,
    read_nav,
    read_obs,
    ssi_from_snr,
    write_obs,
)

DATA = Path(__file__).parent / "data"
BASE = DATA / "static_base.obs"
ROVER = DATA / "static_rover.obs"
NAV = DATA / "static.nav"
FULL = Path("/work/shared/data/real-static-short-baseline/base.obs")  # optional, not in the repo

T0 = gpst_from_datetime(datetime(2024, 6, 24, 8, 20))


def gpst(*args: int) -> float:
    return gpst_from_datetime(datetime(*args))


def h(content: str, label: str) -> str:
    """A header line: content padded to 60 columns, label in 61-80."""
    return f"{content:<60}{label:<20}"


@pytest.fixture(scope="module")
def base():
    return read_obs(BASE)


@pytest.fixture(scope="module")
def nav():
    return read_nav(NAV)


def raw_epoch_lines(path: Path, k: int) -> list[str]:
    """The satellite lines of the k-th epoch, straight from the file text."""
    lines = path.read_text().splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith(">")]
    return lines[starts[k] + 1:starts[k + 1]]


# ------------------------------------------------------------------- real excerpt: obs


def test_header_fields(base):
    hd = base.header
    assert hd.version == 3.04
    assert hd.marker_name == "SEPT"
    assert hd.receiver_type == "SEPT MOSAIC-X5"
    np.testing.assert_array_equal(hd.approx_position_ecef,
                                  [-3817680.7270, 3562839.5216, 3650159.2407])
    assert hd.obs_types == {s: ["C1C", "L1C", "D1C", "S1C"] for s in "GERJ"}
    assert hd.interval == 1.0
    assert hd.time_first_obs == T0
    assert hd.time_system == "GPS"
    assert hd.leap_seconds == 18
    # GLONASS SLOT / FRQ # spans a continuation line (R24 is on the second)
    assert hd.glonass_slots == {"R01": 1, "R02": -4, "R03": 5, "R11": 0, "R12": -1, "R13": -2,
                                "R17": 4, "R18": -3, "R24": 2}
    assert "SEPTENTRIO RECEIVERS OUTPUT ALIGNED CARRIER PHASES." in hd.comments


def test_epochs(base):
    assert len(base.epochs) == 120
    times = np.array([e.time for e in base.epochs])
    np.testing.assert_array_equal(times, T0 + np.arange(120.0))
    assert all(e.flag == 0 for e in base.epochs)
    assert len(base.epochs[0].observations) == 32
    assert base.events == []
    assert len(read_obs(ROVER).epochs) == 120


def test_observation_matches_file_text(base):
    line = "G05  20437584.735 7 107400233.90107        39.609 7        47.031"
    assert line in raw_epoch_lines(BASE, 0)
    g05 = base.epochs[0].observations["G05"]
    assert g05["C1C"] == (20437584.735, 0, 7)
    assert g05["L1C"] == (107400233.901, 0, 7)
    assert g05["D1C"] == (39.609, 0, 7)
    assert g05["S1C"] == (47.031, 0, 0)
    # every value of the first epoch equals the F14.3 field of its column in the text
    for raw in raw_epoch_lines(BASE, 0):
        obs = base.epochs[0].observations[raw[:3]]
        for k, code in enumerate(["C1C", "L1C", "D1C", "S1C"]):
            field = raw[3 + 16 * k:17 + 16 * k]
            expected = float(field) if field.strip() else math.nan
            np.testing.assert_equal(obs[code][0], expected)


def test_blank_phase_and_loss_of_lock(base):
    # G07 loses the phase from 08:20:19 to 08:20:24; it comes back with LLI 1
    assert raw_epoch_lines(BASE, 19)[10] == (
        "G07  25983888.089 4                     -2665.106 4        25.250")
    g07 = base.epochs[19].observations["G07"]
    assert math.isnan(g07["L1C"][0]) and g07["L1C"][1:] == (0, 0)
    assert g07["C1C"] == (25983888.089, 0, 4)
    assert base.epochs[25].observations["G07"]["L1C"] == (136562173.658, 1, 6)
    assert math.isnan(base.epochs[24].observations["G07"]["L1C"][0])
    l1 = l1_epochs(base)
    assert math.isnan(l1[19].satellites["G07"].carrier_phase)
    assert l1[19].satellites["G07"].pseudorange == 25983888.089  # kept: it has a pseudorange
    assert l1[25].satellites["G07"].lli == 1
    assert l1[26].satellites["G07"].lli == 0


def test_l1_epochs_every_system(base):
    l1 = l1_epochs(base)
    assert len(l1) == 120 and l1[0].time == T0
    raw = raw_epoch_lines(BASE, 0)
    assert Counter(s[0] for s in l1[0].satellites) == Counter(line[0] for line in raw)
    assert set(s[0] for s in l1[0].satellites) == set("GERJ")
    assert l1[0].satellites["E04"] == SatObservation(24494249.114, 128718180.960, 1490.131,
                                                     44.625, 0)
    assert l1[0].satellites["J03"].pseudorange == 37053986.361
    assert l1[0].satellites["R02"].carrier_phase == 107729136.354
    for s, o in l1[0].satellites.items():
        if s[0] in "GEJ":  # the receiver starts the phase near the pseudorange: same band
            assert abs(o.carrier_phase * WAVELENGTH_L1 - o.pseudorange) < 50.0, s
    only_gps = l1_epochs(base, "G")
    assert set(s[0] for s in only_gps[0].satellites) == {"G"}
    assert only_gps[0].satellites["G05"] == l1[0].satellites["G05"]


def test_doppler_sign_and_glonass_frequencies(base):
    l1 = l1_epochs(base)
    slots = base.header.glonass_slots
    first, later = l1[0].satellites, l1[10].satellites

    def wavelength(k: int) -> float:
        return SPEED_OF_LIGHT / (FREQ_GLONASS_L1_BASE + k * FREQ_GLONASS_L1_STEP)

    glonass = [s for s in first if s[0] == "R"]
    assert len(glonass) == 9
    for s in glonass:
        o = first[s]
        # phase in cycles of the slot's own frequency: right k within metres, k+1 off by km
        assert abs(o.carrier_phase * wavelength(slots[s]) - o.pseudorange) < 100.0
        assert abs(o.carrier_phase * wavelength(slots[s] + 1) - o.pseudorange) > 5000.0
        # RINEX Doppler is minus the range rate in cycles
        range_rate = (later[s].pseudorange - o.pseudorange) / 10.0
        assert abs(-o.doppler * wavelength(slots[s]) - range_rate) < 2.0


def test_l1_signal_choice_and_omissions(tmp_path):
    lines = [
        h("     3.02           OBSERVATION DATA    M", "RINEX VERSION / TYPE"),
        h("G    4 C1W L1W D1W S1W", "SYS / # / OBS TYPES"),
        h("E    4 C1X L1X D1X S1X", "SYS / # / OBS TYPES"),
        h("C    4 C1I L1I D1I S1I", "SYS / # / OBS TYPES"),  # 3.02: band 1 is B1
        h("I    2 C5A L5A", "SYS / # / OBS TYPES"),
        h("R    4 C1P L1P C1C L1C", "SYS / # / OBS TYPES"),  # C/A preferred over P
        h("  2024     6    24     8    20    0.0000000     GPS", "TIME OF FIRST OBS"),
        h("", "END OF HEADER"),
        "> 2024 06 24 08 20  0.0000000  0  6",
        "G01  20000000.000   105000000.00016      1000.000          40.000",
        "E02  21000000.000 7",
        "C03  37000000.000 7 192000000.000 7      -100.000 7        41.000",
        "G04                                      1000.000 7        40.000",
        "I05  30000000.000 7 157000000.000 7",
        "R07  20000001.000 7 107000001.000 7  20000002.000 7 107000002.000 7",
    ]
    path = tmp_path / "mix.obs"
    path.write_text("\n".join(lines) + "\n")
    (ep,) = l1_epochs(read_obs(path))
    # G04: no code, no phase; I: no L1 signal
    assert sorted(ep.satellites) == ["C03", "E02", "G01", "R07"]
    r07 = ep.satellites["R07"]
    assert (r07.pseudorange, r07.carrier_phase) == (20000002.0, 107000002.0)
    assert math.isnan(r07.doppler) and math.isnan(r07.snr)
    assert ep.satellites["G01"] == SatObservation(20000000.0, 105000000.0, 1000.0, 40.0, 1)
    e02 = ep.satellites["E02"]
    assert e02.pseudorange == 21000000.0 and math.isnan(e02.carrier_phase)
    assert math.isnan(e02.snr)
    assert ep.satellites["C03"].doppler == -100.0
    # from RINEX 3.03 on band 1 of BeiDou is B1C, not B1I: no longer picked
    path.write_text("\n".join(lines).replace("     3.02", "     3.04", 1) + "\n")
    (ep,) = l1_epochs(read_obs(path))
    assert "C03" not in ep.satellites and "G01" in ep.satellites


# ------------------------------------------------------- real receiver formatting quirks

G_TYPES = [
    h("G   17 X1  C1C L1C D1C S1C C2W L2W D2W S2W C2L L2L D2L S2L", "SYS / # / OBS TYPES"),
    h("       C5Q L5Q D5Q S5Q", "SYS / # / OBS TYPES"),
    h("C   13 X1  C2I L2I D2I S2I C7I L7I D7I S7I C6I L6I D6I S6I", "SYS / # / OBS TYPES"),
]
G05_LINE = ("G05         5.000    20437584.735 7 107400233.90107        39.609 7        47.031"
            "    20437579.112 8  83688469.71508        30.865 8        49.156    20437579.223 7"
            "  83688458.72507        30.918 7        46.844")
C23_LINE = ("C23        47.000    24503597.381 7 127596785.10007      3049.365 7        44.250"
            "                                                                    24503588.693 7"
            " 103682856.80707      2477.878 7        46.063")


def obs_text(body: list[str], *, version: str = "3.04", time_system: str = "GPS",
             types: list[str] | None = None, extra: list[str] = (), end: bool = True) -> str:
    head = [h(f"{version:>9s}           OBSERVATION DATA    M", "RINEX VERSION / TYPE"),
            *(types if types is not None else G_TYPES), *extra,
            h(f"  2024     6    24     8    20    0.0000000     {time_system}",
              "TIME OF FIRST OBS")]
    if end:
        head.append(h("", "END OF HEADER"))
    return "\n".join(head + body) + "\n"


def test_continuation_lines_short_lines_and_interior_blanks(tmp_path):
    path = tmp_path / "sept.obs"
    g13 = ("G13        13.000    19949559.087 7 104835649.64007      -649.778 7        46.875"
           "    19949552.526 6  81690093.17806      -506.319 6        39.094")
    padded = g13.ljust(200)  # blank padding (some writers) is not a truncated value
    path.write_text(obs_text(["> 2024 06 24 08 20  0.0000000  0  3", G05_LINE, C23_LINE,
                              padded]))
    obs = read_obs(path)
    assert obs.epochs[0].observations["G13"]["S2W"] == (39.094, 0, 0)
    assert math.isnan(obs.epochs[0].observations["G13"]["C2L"][0])
    assert len(obs.header.obs_types["G"]) == 17 and obs.header.obs_types["G"][-1] == "S5Q"
    g05 = obs.epochs[0].observations["G05"]
    assert g05["X1"] == (5.0, 0, 0)
    assert g05["L2W"] == (83688469.715, 0, 8)
    assert g05["S2L"] == (46.844, 0, 0)
    assert math.isnan(g05["C5Q"][0]) and g05["S5Q"][1:] == (0, 0)  # omitted trailing fields
    c23 = obs.epochs[0].observations["C23"]
    assert math.isnan(c23["L7I"][0]) and c23["C6I"] == (24503588.693, 0, 7)
    (ep,) = l1_epochs(obs)
    assert ep.satellites["C23"] == SatObservation(24503597.381, 127596785.100, 3049.365,
                                                  44.25, 0)  # B1I from band 2 (RINEX 3.04)
    assert ep.satellites["G05"].carrier_phase == 107400233.901


@pytest.mark.parametrize("system, offset", [("GPS", 0.0), ("GAL", 0.0), ("QZS", 0.0),
                                            ("BDT", 14.0), ("GLO", 18.0)])
def test_time_system_of_the_header(tmp_path, system, offset):
    path = tmp_path / "t.obs"
    path.write_text(obs_text(["> 2024 06 24 08 20 30.5000000  0  1", G05_LINE],
                             time_system=system, extra=[h("    18", "LEAP SECONDS")]))
    obs = read_obs(path)
    assert obs.header.time_first_obs == T0 + offset
    assert obs.epochs[0].time == T0 + 30.5 + offset


def test_event_flags_inside_the_data(tmp_path):
    body = [
        "> 2024 06 24 08 20  0.0000000  0  1", G05_LINE,
        "> 2024 06 24 08 20  0.5000000  5  0",  # external event, no records
        ">                              4  2",  # header information, time blank
        h("RECEIVER RESTARTED", "COMMENT"),
        h("   ANOTHER NOTE", "COMMENT"),
        "> 2024 06 24 08 20  2.0000000  1  1", G05_LINE,  # power failure before: kept
        "> 2024 06 24 08 20  2.0000000  6  1", G05_LINE,  # cycle slip records: skipped
        ">                              2  1", h("MOVING", "COMMENT"),
        "> 2024 06 24 08 20  3.0000000  0  1", C23_LINE,
    ]
    path = tmp_path / "events.obs"
    path.write_text(obs_text(body))
    obs = read_obs(path)
    assert [(e.time - T0, e.flag) for e in obs.epochs] == [(0.0, 0), (2.0, 1), (3.0, 0)]
    assert [(e.flag, e.line, len(e.records)) for e in obs.events] == [
        (5, 9, 0), (4, 10, 2), (6, 15, 1), (2, 17, 1)]
    assert obs.events[0].time == T0 + 0.5 and math.isnan(obs.events[1].time)
    assert obs.header.comments[-2:] == ["RECEIVER RESTARTED", "   ANOTHER NOTE"]
    assert [e.flag for e in l1_epochs(obs)] == [0, 1, 0]


# ------------------------------------------------------------------------ bad input


def expect_error(path: Path, line: int | None, *fragments: str) -> RinexError:
    with pytest.raises(RinexError) as info:
        read_obs(path) if path.suffix == ".obs" else read_nav(path)
    msg = str(info.value)
    assert str(path) in msg
    if line is not None:
        assert f"line {line}:" in msg and info.value.line == line
    for f in fragments:
        assert f in msg, msg
    return info.value


GOOD_BODY = ["> 2024 06 24 08 20  0.0000000  0  2", G05_LINE, C23_LINE,
             "> 2024 06 24 08 20  1.0000000  0  1", G05_LINE]  # lines 7-11


def test_error_truncated_epoch(tmp_path):
    path = tmp_path / "trunc.obs"
    path.write_text(obs_text(GOOD_BODY[:-1]))  # the second epoch announces 1, none follows
    expect_error(path, 10, "epoch of line 10", "announces 1")
    body = GOOD_BODY[:1] + GOOD_BODY[2:]  # first epoch: 2 announced, 1 line, then an epoch
    path.write_text(obs_text(body))
    expect_error(path, 9, "announces 2 satellites but only 1")


def test_error_truncated_final_line(tmp_path):
    path = tmp_path / "cut.obs"
    path.write_text(obs_text(GOOD_BODY[:-1] + [G05_LINE[:40]]))
    expect_error(path, 11, "G05", "inside the L1C value")


def test_error_malformed_number(tmp_path):
    path = tmp_path / "num.obs"
    bad = C23_LINE.replace("24503597.381", "2450359?.381")
    path.write_text(obs_text(GOOD_BODY[:2] + [bad] + GOOD_BODY[3:]))
    expect_error(path, 9, "C23", "C2I", "2450359?.381")
    path.write_text(obs_text(GOOD_BODY[:3] + ["> 2024 06 24 08 2x  1.0000000  0  1", G05_LINE]))
    expect_error(path, 10, "malformed epoch time")


def test_error_rinex4_and_not_rinex(tmp_path):
    path = tmp_path / "new.obs"
    path.write_text(h("     4.00           OBSERVATION DATA    M (MIXED)",
                      "RINEX VERSION / TYPE") + "\n")
    expect_error(path, 1, "version 4.00 is not supported (only 2.xx and 3.xx)")
    path.write_text("time,x,y\n1,2,3\n")
    expect_error(path, 1, "not a RINEX observation file")
    path.write_text(NAV.read_text())
    expect_error(path, 1, "not a RINEX observation file", "'N'")
    path.write_text("")
    expect_error(path, None, "empty file")


def test_error_missing_end_of_header(tmp_path):
    path = tmp_path / "noend.obs"
    path.write_text(obs_text(GOOD_BODY, end=False))
    expect_error(path, 6, "missing END OF HEADER")
    path.write_text(obs_text([], end=False))
    expect_error(path, 5, "missing END OF HEADER")


def test_error_decreasing_time(tmp_path):
    path = tmp_path / "back.obs"
    body = GOOD_BODY + ["> 2024 06 24 08 19 59.0000000  0  1", G05_LINE]
    path.write_text(obs_text(body))
    expect_error(path, 12, "earlier than the previous", "line 10")
    path.write_text(obs_text(GOOD_BODY + ["> 2024 06 24 08 20  1.0000000  0  1", G05_LINE]))
    assert len(read_obs(path).epochs) == 3  # a repeated time tag is not decreasing


def test_error_undeclared_or_unknown_system(tmp_path):
    path = tmp_path / "sys.obs"
    path.write_text(obs_text(GOOD_BODY[:2] + [C23_LINE.replace("C23", "E23")] + GOOD_BODY[3:]))
    expect_error(path, 9, "E23", "does not declare")
    path.write_text(obs_text(GOOD_BODY[:2] + [C23_LINE.replace("C23", "X23")] + GOOD_BODY[3:]))
    expect_error(path, 9, "unknown satellite system")


def test_error_header_records(tmp_path):
    path = tmp_path / "hdr.obs"
    types = [G_TYPES[0], G_TYPES[2]]  # G announces 17 types, the continuation is missing
    path.write_text(obs_text(GOOD_BODY, types=types))
    expect_error(path, 2, "announces 17 types but lists 13")
    path.write_text(obs_text(GOOD_BODY, extra=[h(" -3817680.7270  35628X9.5216  3650159.2407",
                                                 "APPROX POSITION XYZ")]))
    expect_error(path, 5, "malformed APPROX POSITION XYZ")


# --------------------------------------------------------------------------- writer


def synthetic_epochs() -> list[GnssEpoch]:
    nan = math.nan
    t = gpst(2024, 6, 24, 23, 59, 58) + 0.25
    e1 = GnssEpoch(t, {
        "G05": SatObservation(20437584.7354, 107400233.9012, -3255.149, 47.0, 0),
        "R02": SatObservation(20188391.642, 107729136.354, 418.104, 51.406, 1),
        "E11": SatObservation(24501075.099, 9_999_999_999.999, 2304.336, 11.9, 2),
        "J03": SatObservation(37053986.361, nan, 546.622, 54.0, 0),
        "C14": SatObservation(38928403.800, 202710447.704, nan, nan, 5),
        "S37": SatObservation(nan, 201234567.125, 0.0, 30.0, 3),
    })
    e2 = GnssEpoch(t + 2.0, {  # crosses midnight into the next day
        "G05": SatObservation(20437000.0, 107397000.0, -3254.0, 46.5, 1),
        "R02": SatObservation(nan, nan, 418.0, 50.0, 0),  # written, omitted on reading
    }, flag=1)
    return [e1, e2]


def test_write_read_round_trip_synthetic(tmp_path):
    path = tmp_path / "syn.obs"
    epochs = synthetic_epochs()
    write_obs(path, epochs, marker_name="SHIP-ANT1", receiver_type="SIM RX",
              approx_position_ecef=np.array([-3817680.7270, 3562839.5216, 3650159.2407]),
              interval=2.0, comments=["simulated", "x" * 70], glonass_slots={"R02": -4, "R01": 1})
    obs = read_obs(path)
    hd = obs.header
    assert (hd.version, hd.marker_name, hd.receiver_type, hd.interval) == (
        3.04, "SHIP-ANT1", "SIM RX", 2.0)
    assert hd.obs_types == {"G": ["C1C", "L1C", "D1C", "S1C"], "R": ["C1C", "L1C", "D1C", "S1C"],
                            "E": ["C1C", "L1C", "D1C", "S1C"], "C": ["C2I", "L2I", "D2I", "S2I"],
                            "J": ["C1C", "L1C", "D1C", "S1C"], "S": ["C1C", "L1C", "D1C", "S1C"]}
    assert hd.glonass_slots == {"R01": 1, "R02": -4}
    assert hd.comments == ["simulated", "x" * 60, "x" * 10]
    assert hd.time_first_obs == pytest.approx(epochs[0].time, abs=1e-6)
    np.testing.assert_allclose(hd.approx_position_ecef, [-3817680.727, 3562839.5216,
                                                         3650159.2407], atol=1e-4)

    back = l1_epochs(obs, "GREJCS")
    assert [e.flag for e in back] == [0, 1]
    for mine, theirs in zip(epochs, back, strict=True):
        assert theirs.time == pytest.approx(mine.time, abs=1e-6)
        kept = {s: o for s, o in mine.satellites.items()
                if not (math.isnan(o.pseudorange) and math.isnan(o.carrier_phase))}
        assert sorted(theirs.satellites) == sorted(kept)
        for s, o in kept.items():
            r = theirs.satellites[s]
            for name in ("pseudorange", "carrier_phase", "doppler", "snr"):
                a, b = getattr(o, name), getattr(r, name)
                assert (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 0.0005 + 1e-9, (s, name)
            expected_lli = o.lli if not math.isnan(o.carrier_phase) else 0
            assert r.lli == expected_lli, s

    raw = obs.epochs[0].observations
    assert raw["G05"]["C1C"] == (20437584.735, 0, 7)  # SSI from 47.0 dB-Hz
    assert raw["E11"]["L1C"] == (9_999_999_999.999, 2, 1)  # F14.3 holds 1e10 - 0.001; 11.9 -> 1
    assert raw["J03"]["D1C"][2] == 9  # 54 dB-Hz
    assert raw["C14"]["C2I"][2] == 0 and raw["C14"]["L2I"][1] == 5  # SNR unknown
    assert raw["S37"]["S1C"] == (30.0, 0, 0)  # the SNR itself carries no indicator


def test_written_header_layout(tmp_path):
    path = tmp_path / "layout.obs"
    write_obs(path, synthetic_epochs(), marker_name="M", receiver_type="R",
              approx_position_ecef=np.zeros(3), interval=1.0, glonass_slots={"R02": -4})
    lines = path.read_text().splitlines()
    end = lines.index(h("", "END OF HEADER"))
    header = lines[:end + 1]
    assert all(len(line) == 80 for line in header)
    labels = [line[60:].rstrip() for line in header]
    for label in ["RINEX VERSION / TYPE", "PGM / RUN BY / DATE", "MARKER NAME",
                  "REC # / TYPE / VERS", "ANT # / TYPE", "APPROX POSITION XYZ",
                  "ANTENNA: DELTA H/E/N", "SYS / # / OBS TYPES", "SIGNAL STRENGTH UNIT",
                  "INTERVAL", "TIME OF FIRST OBS", "SYS / PHASE SHIFT", "GLONASS COD/PHS/BIS",
                  "GLONASS SLOT / FRQ #", "END OF HEADER"]:
        assert label in labels, label
    assert labels[0] == "RINEX VERSION / TYPE" and header[0].startswith("     3.04")
    assert header[0][20] == "O" and header[0][40] == "M"
    assert h("  2024     6    24    23    59   58.2500000     GPS", "TIME OF FIRST OBS") in header
    assert lines[end + 1] == "> 2024 06 24 23 59 58.2500000  0  6"
    assert lines[end + 8] == "> 2024 06 25 00 00  0.2500000  1  2"
    assert lines[end + 2] == "C14  38928403.800   202710447.7045"  # LLI 5, no SSI, rest blank
    assert all(len(line) <= 3 + 16 * 4 for line in lines[end + 1:])


def test_writer_refuses_what_it_cannot_write(tmp_path):
    epochs = synthetic_epochs()
    kwargs = dict(marker_name="M", receiver_type="R", approx_position_ecef=np.zeros(3),
                  interval=1.0)
    with pytest.raises(ValueError, match="glonass_slots"):
        write_obs(tmp_path / "a.obs", epochs, **kwargs)
    too_big = [GnssEpoch(0.0, {"G01": SatObservation(1e10, 0.0, 0.0, 40.0)})]
    with pytest.raises(ValueError, match="F14.3"):
        write_obs(tmp_path / "b.obs", too_big, **kwargs)
    with pytest.raises(ValueError, match="flag 4"):
        write_obs(tmp_path / "d.obs", [GnssEpoch(0.0, {}, flag=4)], **kwargs)
    with pytest.raises(ValueError, match="earlier"):
        write_obs(tmp_path / "c.obs", epochs[::-1], glonass_slots={"R02": -4}, **kwargs)


def test_ssi_rule():
    assert [ssi_from_snr(x) for x in (math.nan, 0.0, 5.0, 12.0, 17.99, 18.0, 41.9, 42.0, 53.9,
                                      54.0, 70.0)] == [0, 0, 1, 2, 2, 3, 6, 7, 8, 9, 9]


def test_round_trip_real_excerpt_is_byte_identical(tmp_path, base):
    path = tmp_path / "again.obs"
    write_obs(path, l1_epochs(base), marker_name="SEPT", receiver_type="SEPT MOSAIC-X5",
              approx_position_ecef=base.header.approx_position_ecef, interval=1.0,
              glonass_slots=base.header.glonass_slots)

    def data(p: Path) -> list[str]:
        lines = p.read_text().splitlines()
        return lines[[line[60:].strip() for line in lines].index("END OF HEADER") + 1:]

    # the receiver's own values, LLI and SSI (its SSI follows the same RINEX rule) come back
    assert data(path) == data(BASE)
    again = read_obs(path)
    assert again.epochs == base.epochs


# ----------------------------------------------------------------------- navigation


def record_lines(sys_: str) -> int:
    return sum(1 for line in NAV.read_text().splitlines()[10:] if line[:1] == sys_)


def test_nav_counts_and_header(nav):
    counts = Counter(s[0] for s, ephs in nav.ephemerides.items() for _ in ephs)
    assert counts == {"G": 13, "E": 63, "C": 30, "J": 3, "R": 19}
    assert all(counts[s] == record_lines(s) for s in "GECJR")  # no record lost
    assert nav.iono_alpha == (1.8626e-08, 2.2352e-08, -1.1921e-07, -5.9605e-08)
    assert nav.iono_beta == (1.2902e05, 1.6384e05, -1.9661e05, -2.6214e05)
    assert nav.leap_seconds == 18
    for ephs in nav.ephemerides.values():
        toes = [e.toe for e in ephs]
        assert toes == sorted(toes)
        lo, hi = gpst(2024, 6, 24, 6), gpst(2024, 6, 24, 12)
        assert all(lo <= t <= hi for t in toes)


def test_gps_ephemeris_fields(nav):
    text = NAV.read_text()
    assert "G05 2024 06 24 10 00 00-1.774230040610E-04-1.364242052659E-12 0.000000000000E+00" \
        in text
    (g05,) = nav.ephemerides["G05"]
    assert isinstance(g05, KeplerEphemeris)
    t = gpst(2024, 6, 24, 10)
    assert g05.toc == t and g05.toe == 2320 * 604800 + 122400.0 == t
    assert (g05.af0, g05.af1, g05.af2) == (-1.774230040610e-04, -1.364242052659e-12, 0.0)
    assert (g05.iode, g05.crs, g05.delta_n, g05.m0) == (72, -98.21875, 4.293035965037e-09,
                                                        1.714815412488)
    assert (g05.cuc, g05.e, g05.cus, g05.sqrt_a) == (-5.291774868965e-06, 5.927642923780e-03,
                                                     1.830980181694e-06, 5.153635631561e03)
    assert (g05.cic, g05.omega0, g05.cis) == (3.352761268616e-08, 2.520897825810,
                                              -5.774199962616e-08)
    assert (g05.i0, g05.crc, g05.omega, g05.omega_dot) == (9.719266524177e-01, 353.625,
                                                           1.273307347665, -8.275344701323e-09)
    assert g05.idot == -2.610823036973e-10
    assert (g05.health, g05.tgd, g05.data_source) == (0, -1.071020960808e-08, 0)


def test_galileo_beidou_glonass_times(nav):
    e04 = nav.ephemerides["E04"][0]
    assert e04.toc == e04.toe == gpst(2024, 6, 24, 8)  # GAL week 2320 counts like GPS weeks
    assert e04.data_source == 517 and e04.iode == 65
    (c14,) = nav.ephemerides["C14"]
    # BDT 07:00:00 = GPST 07:00:14; toe 111600 s of BDT week 964 = GPS week 2320
    assert c14.toc == gpst(2024, 6, 24, 7, 0, 14)
    assert c14.toe == (964 + 1356) * 604800 + 111600 + 14 == c14.toc
    assert c14.tgd == 6.7e-09 and c14.iode == 2
    r01 = nav.ephemerides["R01"][0]
    assert isinstance(r01, GlonassEphemeris)
    assert r01.toe == gpst(2024, 6, 24, 8, 15, 18)  # UTC(SU) 08:15 + 18 leap seconds
    assert r01.tau_n == 8.934084326029e-05  # the RINEX field is -TauN, stored as is
    assert r01.gamma_n == 9.094947017729e-13
    np.testing.assert_allclose(r01.position, [-13736887.69531, -3309238.28125,
                                              21242412.59766], rtol=0, atol=1e-6)
    np.testing.assert_allclose(r01.velocity, [-1554.378509521, -2458.472251892,
                                              -1386.628150940], rtol=0, atol=1e-9)
    assert r01.frequency_number == 1 and r01.health == 0
    assert [e.toe for e in nav.ephemerides["R01"]] == [r01.toe, gpst(2024, 6, 24, 8, 45, 18)]
    assert nav.ephemerides["R02"][0].frequency_number == -4


def fmt19(values: list[float]) -> str:
    return "".join(f"{v:19.12E}".replace("E", "D") for v in values)


def kepler_record(sat: str, epoch: str, toe_sow: float, week: int) -> list[str]:
    v = [1e-4, 0.0, 0.0, 7.0, 10.0, 4e-9, 1.0, 1e-6, 0.01, 1e-6, 5153.6, toe_sow, 1e-8, 2.0,
         1e-8, 0.96, 200.0, 1.2, -8e-9, 1e-10, 1.0, float(week), 0.0, 2.0, 0.0, -1e-8, 7.0,
         toe_sow - 30.0, 4.0]
    return [f"{sat} {epoch}" + fmt19(v[:3])] + [
        "    " + fmt19(v[k:k + 4]) for k in range(3, len(v), 4)]


def nav_text(records: list[list[str]], version: str = "3.04") -> str:
    head = [h(f"{version:>9s}           N: GNSS NAV DATA    M: MIXED", "RINEX VERSION / TYPE"),
            h("    18", "LEAP SECONDS"), h("", "END OF HEADER")]
    return "\n".join(head + [line for rec in records for line in rec]) + "\n"


def test_nav_week_rollover_sorting_and_skipped_systems(tmp_path):
    toc = gpst(2024, 6, 29, 23, 59, 44)  # Saturday, end of GPS week 2320
    sbas = ["S24 2024 06 24 08 00 00" + fmt19([0.0, 0.0, 1.0])] + [
        "    " + fmt19([1.0, 0.0, 0.0, 0.0])] * 3
    glonass_305 = ["R05 2024 06 24 08 15 00" + fmt19([1e-5, 0.0, 1.0])] + [
        "    " + fmt19([1000.0, 1.0, 0.0, 0.0])] * 4  # 3.05: a fourth line of status flags
    records = [
        kepler_record("G07", "2024 06 29 23 59 44", 0.0, 2321),  # toe in the next week
        kepler_record("G07", "2024 06 24 10 00 00", 122400.0, 2320),
        sbas,
        kepler_record("G09", "2024 06 29 23 59 44", 0.0, 2320),  # week of toc, not of toe
        kepler_record("G09", "2024 06 29 23 59 44", 0.0, 2320),  # exact duplicate
        kepler_record("G07", "2024 06 29 23 59 44", 0.0, 2321),  # duplicate, not adjacent
        glonass_305,
        kepler_record("J02", "2024 06 29 23 59 44", 0.0, 2321 - 1024),  # 10-bit week number
        # BDT Saturday 23:59:50 is GPST Sunday 00:00:04 of the next GPS week
        kepler_record("C20", "2024 06 29 23 59 50", 604790.0, 964),
    ]
    path = tmp_path / "roll.nav"
    path.write_text(nav_text(records, "3.05"))
    nav = read_nav(path)
    assert sorted(nav.ephemerides) == ["C20", "G07", "G09", "J02", "R05"]
    week_2321 = 2321 * 604800.0
    assert [e.toe for e in nav.ephemerides["G07"]] == [gpst(2024, 6, 24, 10), week_2321]
    assert nav.ephemerides["G07"][1].toc == toc
    assert [e.toe for e in nav.ephemerides["G09"]] == [week_2321]
    assert nav.ephemerides["J02"][0].toe == week_2321
    (c20,) = nav.ephemerides["C20"]
    assert c20.toc == c20.toe == week_2321 + 4.0
    assert nav.ephemerides["R05"][0].position == (1e6, 1e6, 1e6)


def test_nav_errors(tmp_path):
    path = tmp_path / "bad.nav"
    rec = kepler_record("G07", "2024 06 24 10 00 00", 122400.0, 2320)
    path.write_text(nav_text([rec, rec[:5]]))  # second record cut after 4 of 7 lines
    expect_error(path, 16, "G07", "4 continuation lines, expected 7")
    broken = rec[:2] + [rec[2][:30] + "x" + rec[2][31:]] + rec[3:]
    path.write_text(nav_text([broken]))
    expect_error(path, 6, "malformed number")
    blank = rec[:4] + ["    " + " " * 19 + rec[4][23:]] + rec[5:]  # toe left blank
    path.write_text(nav_text([blank]))
    expect_error(path, 8, "G07", "blank")
    path.write_text(nav_text([rec]).replace("     3.04", "     2.10", 1))
    expect_error(path, 1, "version 2.10 is not supported")
    path.write_text(BASE.read_text())
    expect_error(path, 1, "not a RINEX navigation file")


# ------------------------------------------------------------- full file (optional)


@pytest.mark.skipif(not FULL.exists(), reason="shared full data set not available")
def test_full_receiver_file_with_beidou():
    obs = read_obs(FULL)
    assert len(obs.epochs) == 301 and obs.epochs[-1].time == T0 + 300.0
    l1 = l1_epochs(obs)
    c01 = l1[0].satellites["C01"]  # B1I (C2I), not the receiver channel X1 in front of it
    assert (c01.pseudorange, c01.carrier_phase, c01.doppler, c01.snr) == (
        36689218.704, 191050392.041, 305.142, 43.469)
    assert set(s[0] for s in l1[0].satellites) == set("GRECJ")
