"""RINEX observation and navigation files (read both, write observations).

Reads real receiver output (RINEX 3.02-3.05 and 2.10-2.11 observation files, RINEX 3 mixed
navigation files, all constellations) and writes the L1 observations of the project as
RINEX 3.04. Files may be gzipped (``.gz``) and observation files Hatanaka-compressed
(``.crx``, ``.yyd``; decompressed with the ``hatanaka`` package); other compressions (``.Z``,
zip, bzip2, xz) are refused with a message naming them. RINEX 2 observation types are mapped
onto RINEX 3 codes (``_V2_ATTRIBUTES``) so that one reader of the L1 view serves both. Every
problem in an input file raises :class:`RinexError` naming the file, the line and what is
wrong.

Times are GPS seconds since the GPS epoch (``gpst``, see ``estimator.frames``): observation
epochs in another time scale (BDT, GLONASS UTC) and BeiDou / GLONASS ephemeris times are
converted on reading.
"""

from __future__ import annotations

import gzip
import math
import os
import warnings
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import hatanaka
import numpy as np

from estimator.frames import SECONDS_PER_WEEK, datetime_from_gpst, gpst_from_datetime
from estimator.records import (
    GlonassEphemeris,
    GnssEpoch,
    KeplerEphemeris,
    NavigationData,
    SatObservation,
)

__all__ = [
    "RinexError",
    "ObsHeader",
    "RawEpoch",
    "ObsEvent",
    "ObsFile",
    "read_obs",
    "l1_epochs",
    "write_obs",
    "read_nav",
    "ssi_from_snr",
]

SYSTEMS = "GRECJSI"  # GPS, GLONASS, Galileo, BeiDou, QZSS, SBAS, NavIC/IRNSS
BDT_MINUS_GPST = -14.0  # BDT = GPST - 14 s (BDT epoch 2006-01-01 00:00:00 UTC)
BDT_WEEK_OFFSET = 1356  # GPS week of the BDT epoch
_NAN = float("nan")
_BLANK = (_NAN, 0, 0)

# GPS - UTC (s) from these UTC dates on; used only when a file gives no LEAP SECONDS.
_LEAP_SECONDS = (
    (datetime(2017, 1, 1), 18),
    (datetime(2015, 7, 1), 17),
    (datetime(2012, 7, 1), 16),
    (datetime(2009, 1, 1), 15),
    (datetime(2006, 1, 1), 14),
    (datetime(1999, 1, 1), 13),
)

# Time system of the observation epochs when TIME OF FIRST OBS leaves it blank (by file type).
_DEFAULT_TIME_SYSTEM = {"G": "GPS", "R": "GLO", "E": "GAL", "C": "BDT", "J": "QZS", "I": "IRN",
                        "S": "GPS", "M": "GPS"}

# L1-band signal per system, by preference: band + attribute of the code / phase observations.
# GPS L1 C/A first, then the L1C and P(Y) tracking that some receivers report instead.
_L1_SIGNALS = {
    "G": ("1C", "1X", "1S", "1L", "1W", "1P", "1Y"),
    "J": ("1C", "1X", "1S", "1L"),
    "E": ("1C", "1X", "1B"),
    "R": ("1C", "1P"),  # L1OF, FDMA: carrier phase in cycles of the slot's own frequency
    "C": ("2I", "2X", "2Q"),  # B1I (RINEX >= 3.03 band 2)
    "S": ("1C",),
}
# RINEX 3.02 called BeiDou B1 band 1; from 3.03 on band 1 is B1C (a different signal).
_L1_SIGNALS_BDS_302 = ("1I", "1X", "1Q")
# What write_obs writes per system: the first choice above (C1C, or C2I for BeiDou B1I).
_WRITE_SIGNAL = {s: sig[0] for s, sig in _L1_SIGNALS.items()}


class RinexError(ValueError):
    """A RINEX file that cannot be read; the message names the file, the line and the fault."""

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None):
        super().__init__(message)
        self.path = path
        self.line = line


def _error(path: str, line: int | None, what: str) -> RinexError:
    where = f"{path}: line {line}: " if line is not None else f"{path}: "
    return RinexError(where + what, path=path, line=line)


# ----------------------------------------------------------------------------- records


@dataclass
class ObsHeader:
    version: float
    marker_name: str
    receiver_type: str
    approx_position_ecef: np.ndarray | None  # (3,) m
    obs_types: dict[str, list[str]]  # system letter -> observation codes
    interval: float | None
    time_first_obs: float | None  # gpst s
    glonass_slots: dict[str, int]  # "R01" -> frequency number
    leap_seconds: int | None = None
    comments: list[str] = field(default_factory=list)
    time_system: str = "GPS"  # time scale of the epochs in the file (converted to GPST on reading)


@dataclass
class RawEpoch:
    time: float  # gpst s (receiver time tag)
    flag: int  # 0 OK, 1 power failure before this epoch
    observations: dict[str, dict[str, tuple[float, int, int]]]  # sat -> code -> (value, LLI, SSI)


@dataclass
class ObsEvent:
    """An event record inside the data (epoch flags 2-6) with its special records as text."""

    time: float  # gpst s, NaN when the record leaves the time blank
    flag: int  # 2 moving antenna, 3 new site, 4 header info, 5 external event, 6 cycle slips
    line: int  # line number of the event record
    records: list[str] = field(default_factory=list)


@dataclass
class ObsFile:
    path: str
    header: ObsHeader
    epochs: list[RawEpoch]  # observation epochs (flags 0 and 1) in file order
    events: list[ObsEvent] = field(default_factory=list)
    cut_short: str | None = None  # read_obs(cut_ok=True): what was left out of a torn end


# ----------------------------------------------------------------------------- helpers


# leading bytes of compressed files that are not read (gzip and Hatanaka are)
_REFUSED_COMPRESSION = (
    (b"\x1f\x9d", "Unix-compressed (.Z)"),
    (b"PK\x03\x04", "a zip archive"),
    (b"BZh", "bzip2-compressed"),
    (b"\xfd7zXZ\x00", "xz-compressed"),
)


def _lines(path: Path) -> list[str]:
    """The file's lines, gunzipped and Hatanaka-decompressed when it is so compressed."""
    name = str(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise _error(name, None, f"cannot read: {exc.strerror or exc}") from exc
    for magic, what in _REFUSED_COMPRESSION:
        if data.startswith(magic):
            raise _error(name, None, f"{what} file: only gzip (.gz) and Hatanaka (.crx, .yyd) "
                                     "compression are read; decompress it first")
    if data.startswith(b"\x1f\x8b"):
        try:
            data = gzip.decompress(data)
        except (OSError, EOFError, zlib.error) as exc:
            raise _error(name, None, f"corrupt gzip data: {exc}") from None
    # latin-1 never fails: a stray byte in a comment must not make the file unreadable
    text = data.decode("latin-1")
    if _label(text[:text.find("\n") if "\n" in text else None]).startswith("CRINEX VERS"):
        # crx2rnx only warns about corrupt data (and drops epochs): that is an error here
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                text = hatanaka.crx2rnx(text)
            except hatanaka.HatanakaException as exc:
                raise _error(name, None, f"Hatanaka (Compact RINEX) decompression failed: "
                                         f"{str(exc).strip()}") from None
        if caught:
            raise _error(name, None, f"corrupt Hatanaka (Compact RINEX) data: "
                                     f"{str(caught[0].message).strip()}")
    return text.splitlines()


def _label(line: str) -> str:
    return line[60:80].strip()


def _leap_seconds_at(t: datetime) -> int:
    for start, leap in _LEAP_SECONDS:
        if t >= start:
            return leap
    return _LEAP_SECONDS[-1][1]


def _parse_leap_seconds(line: str) -> int:
    """LEAP SECONDS record as GPS - UTC; BeiDou-only files may give BDS - UTC instead."""
    leap = int(line[0:6])
    if line[24:27] == "BDS":
        leap -= int(BDT_MINUS_GPST)
    return leap


def _time_offset(system: str, leap_seconds: int | None, t: datetime) -> float:
    """Seconds to add to a time in ``system`` to get GPST."""
    if system in ("GPS", "GAL", "QZS", "IRN"):
        return 0.0  # aligned with GPST to the second; sub-µs offsets are below our needs
    if system == "BDT":
        return -BDT_MINUS_GPST
    if system in ("GLO", "UTC"):
        return float(leap_seconds if leap_seconds is not None else _leap_seconds_at(t))
    raise ValueError(f"unknown time system {system!r}")


def _fmt_time(t: float) -> str:
    return datetime_from_gpst(t).isoformat(sep=" ") if math.isfinite(t) else "blank"


def _check_first_line(path: str, lines: list[str], want_type: str, what: str,
                      versions: tuple[int, ...] = (3,)) -> float:
    if not lines:
        raise _error(path, None, f"empty file (not a RINEX {what} file)")
    first = lines[0]
    label = _label(first)
    if label != "RINEX VERSION / TYPE":
        raise _error(path, 1, f"not a RINEX {what} file (no 'RINEX VERSION / TYPE' record)")
    try:
        version = float(first[0:9])
    except ValueError:
        raise _error(path, 1, f"malformed RINEX version {first[0:9].strip()!r}") from None
    if int(version) not in versions:
        supported = " and ".join(f"{v}.xx" for v in versions)
        raise _error(path, 1, f"RINEX version {version:.2f} is not supported (only {supported})")
    if first[20:21] != want_type:
        raise _error(path, 1, f"not a RINEX {what} file (file type {first[20:21]!r}, "
                              f"expected {want_type!r})")
    return version


# ----------------------------------------------------------------- observation header


def _sat_id(raw: str) -> str:
    """'G05', also tolerating the blank-padded 'G 5' some writers produce."""
    return raw[0] + raw[1:3].replace(" ", "0")


@dataclass
class _HeaderCommon:
    """The observation-header records RINEX 2 and 3 share, read line by line."""

    marker: str = ""
    receiver: str = ""
    position: np.ndarray | None = None
    interval: float | None = None
    leap: int | None = None
    first_obs: tuple[datetime, float, str, int] | None = None  # (time, seconds, system, line)
    comments: list[str] = field(default_factory=list)

    def read(self, label: str, line: str, n: int) -> bool:
        """Take the record if it is one of the shared ones (True); ValueError if malformed."""
        if label == "COMMENT":
            self.comments.append(line[:60].rstrip())
        elif label == "MARKER NAME":
            self.marker = line[:60].strip()
        elif label == "REC # / TYPE / VERS":
            self.receiver = line[20:40].strip()
        elif label == "APPROX POSITION XYZ":
            self.position = np.array([float(line[k:k + 14]) for k in (0, 14, 28)])
        elif label == "INTERVAL":
            self.interval = float(line[0:10])
        elif label == "LEAP SECONDS":
            self.leap = _parse_leap_seconds(line)
        elif label == "TIME OF FIRST OBS":
            t = datetime(*(int(line[k:k + 6]) for k in range(0, 30, 6)))
            self.first_obs = (t, float(line[30:43]), line[48:51].strip(), n)
        else:
            return False
        return True

    def time_first(self, path: str, file_system: str) -> tuple[float | None, str]:
        """GPST of the first observation (None if not given) and the file's time system."""
        time_system = _DEFAULT_TIME_SYSTEM.get(file_system, "GPS")
        if self.first_obs is None:
            return None, time_system
        t, sec, system, n = self.first_obs
        time_system = system or time_system
        try:
            return gpst_from_datetime(t) + sec + _time_offset(time_system, self.leap, t), \
                time_system
        except ValueError as exc:
            raise _error(path, n, str(exc)) from None

    def header(self, version: float, obs_types: dict[str, list[str]],
               slots: dict[str, int], path: str, file_system: str) -> ObsHeader:
        time_first, time_system = self.time_first(path, file_system)
        return ObsHeader(version=version, marker_name=self.marker, receiver_type=self.receiver,
                         approx_position_ecef=self.position, obs_types=obs_types,
                         interval=self.interval, time_first_obs=time_first,
                         glonass_slots=slots, leap_seconds=self.leap, comments=self.comments,
                         time_system=time_system)


def _parse_obs_header(path: str, lines: list[str]) -> tuple[ObsHeader, int]:
    """Header fields and the index of the first data line."""
    version = _check_first_line(path, lines, "O", "observation")
    file_system = lines[0][40:41] or "M"
    common = _HeaderCommon()
    obs_types: dict[str, list[str]] = {}
    declared: dict[str, tuple[int, int]] = {}  # system -> (count, line number)
    slots: dict[str, int] = {}
    slot_count: tuple[int, int] | None = None  # (count, line number)
    current_sys: str | None = None

    for i in range(1, len(lines)):
        line = lines[i]
        n = i + 1
        label = _label(line)
        try:
            if label == "END OF HEADER":
                break
            if line.startswith(">"):
                raise _error(path, n, "missing END OF HEADER (data epoch found inside the header)")
            if common.read(label, line, n):
                continue
            if label == "SYS / # / OBS TYPES":
                if line[0] != " ":
                    current_sys = line[0]
                    if current_sys not in SYSTEMS:
                        raise _error(path, n, f"unknown satellite system {current_sys!r}")
                    if current_sys in obs_types:
                        raise _error(path, n, f"system {current_sys} declared twice")
                    declared[current_sys] = (int(line[3:6]), n)
                    obs_types[current_sys] = []
                elif current_sys is None:
                    raise _error(path, n, "SYS / # / OBS TYPES continuation without a system")
                for code in line[7:60].split():
                    if code[0] not in "CLDSX" or len(code) not in (2, 3):
                        raise _error(path, n, f"unknown observation type {code!r}")
                    obs_types[current_sys].append(code)
            elif label == "GLONASS SLOT / FRQ #":
                if line[0:3].strip():
                    slot_count = (int(line[0:3]), n)
                for k in range(4, 60, 7):
                    sat = line[k:k + 3]
                    if not sat.strip():
                        break
                    slots[_sat_id(sat)] = int(line[k + 4:k + 6])
        except ValueError as exc:
            if isinstance(exc, RinexError):
                raise
            raise _error(path, n, f"malformed {label or 'header'} record: {line.rstrip()!r}"
                         ) from None
    else:
        raise _error(path, len(lines), "missing END OF HEADER (file ends in the header)")

    for sys_, (count, n) in declared.items():
        if count != len(obs_types[sys_]):
            raise _error(path, n, f"SYS / # / OBS TYPES for {sys_} announces {count} types "
                                  f"but lists {len(obs_types[sys_])}")
    if not obs_types:
        raise _error(path, i + 1, "no SYS / # / OBS TYPES record in the header")
    if slot_count is not None and slot_count[0] != len(slots):
        raise _error(path, slot_count[1], f"GLONASS SLOT / FRQ # announces {slot_count[0]} "
                                          f"satellites but lists {len(slots)}")

    return common.header(version, obs_types, slots, path, file_system), i + 1


# ------------------------------------------------------------------- observation data

_INDICATOR = {" ": 0, "": 0, **{str(d): d for d in range(10)}}


def _parse_sat_line(path: str, n: int, line: str, layout: dict[str, tuple[str, ...]]
                    ) -> tuple[str, dict[str, tuple[float, int, int]]]:
    sys_ = line[0:1]
    codes = layout.get(sys_)
    if codes is None:
        if sys_ and sys_ in SYSTEMS:
            raise _error(path, n, f"satellite {line[0:3]!r} of system {sys_} which the header "
                                  "does not declare in SYS / # / OBS TYPES")
        raise _error(path, n, f"unknown satellite system in {line[0:3]!r}")
    if len(line) < 3 or not line[1:3].strip().isdigit():
        raise _error(path, n, f"malformed satellite id {line[0:3]!r}")
    sat = _sat_id(line)
    length = len(line)
    full = 3 + 16 * len(codes)
    if length > full and line[full:].strip():
        raise _error(path, n, f"{sat}: more than the {len(codes)} observations declared for "
                              f"system {sys_}")
    # F14.3 values end in a digit, so a line that lost its end stops inside a value field
    # (judged without trailing blanks: some writers pad lines)
    end = len(line.rstrip())
    if end < full and 0 < (end - 3) % 16 < 14:
        code = codes[(end - 3) // 16]
        raise _error(path, n, f"{sat}: line ends inside the {code} value (truncated line?)")
    values: dict[str, tuple[float, int, int]] = {}
    for k, code in enumerate(codes):
        a = 3 + 16 * k
        text = line[a:a + 14]
        if a >= length or text.isspace():
            values[code] = _BLANK
            continue
        try:
            value = float(text)
        except ValueError:
            raise _error(path, n, f"{sat}: malformed {code} value {text.strip()!r}") from None
        if not math.isfinite(value):
            raise _error(path, n, f"{sat}: malformed {code} value {text.strip()!r}")
        lli = _INDICATOR.get(line[a + 14:a + 15])
        ssi = _INDICATOR.get(line[a + 15:a + 16])
        if lli is None or ssi is None:
            raise _error(path, n, f"{sat}: malformed LLI/SSI {line[a + 14:a + 16]!r} after "
                                  f"{code}")
        values[code] = (value, lli, ssi)
    return sat, values


def _apply_event_records(path: str, header: ObsHeader, start: int, records: list[str]) -> None:
    """Header records inside the data (flags 3, 4): keep comments, refuse what we can't follow."""
    for k, rec in enumerate(records):
        label = _label(rec)
        if label == "COMMENT":
            header.comments.append(rec[:60].rstrip())
        elif label in ("SYS / # / OBS TYPES", "# / TYPES OF OBSERV"):
            raise _error(path, start + k, "observation types change inside the data "
                                          "(not supported)")


def read_obs(path: str | Path, cut_ok: bool = False) -> ObsFile:
    """Read a RINEX observation file (3.02-3.05 or 2.10-2.11, any constellations; gzipped
    and/or Hatanaka-compressed or not).

    Blank observations become (nan, 0, 0). Epochs with flag 0 or 1 become :class:`RawEpoch`;
    event records (flags 2-6) are kept in ``events`` with their special records, and comments
    among them are appended to the header's. Epoch times are converted to GPST from the
    header's time system. RINEX 2 observation types appear under their RINEX 3 codes.

    ``cut_ok``: the file may end torn (written live, then the power went): an unterminated
    last line and an epoch with fewer records than it announces are left out, and said in
    ``cut_short``, instead of being an error.
    """
    p = Path(path)
    name = str(p)
    lines = _lines(p)
    cut_short = None
    if cut_ok and lines and not ends_with_newline(p):
        cut_short = f"the last line ({len(lines)}) was cut short and is left out"
        lines = lines[:-1]
    if _check_first_line(name, lines, "O", "observation", versions=(2, 3)) < 3.0:
        return _read_obs_v2(name, lines)
    header, i = _parse_obs_header(name, lines)
    layout = {s: tuple(codes) for s, codes in header.obs_types.items()}
    epochs: list[RawEpoch] = []
    events: list[ObsEvent] = []
    minute_cache: dict[str, float] = {}  # "yyyy mm dd hh mm" -> gpst of that minute
    last_time, last_line = -math.inf, 0
    n_lines = len(lines)

    while i < n_lines:
        line = lines[i]
        n = i + 1
        if not line.strip():
            i += 1
            continue
        if line[0] != ">":
            raise _error(name, n, f"expected an epoch record starting with '>', found "
                                  f"{line[:40].rstrip()!r}")
        flag_text, count_text = line[31:32], line[32:35]
        if not flag_text.isdigit() or not count_text.strip().isdigit():
            raise _error(name, n, f"malformed epoch record {line.rstrip()!r}")
        flag, count = int(flag_text), int(count_text)
        if flag > 6:
            raise _error(name, n, f"invalid epoch flag {flag}")

        time = _NAN
        if line[2:29].strip() or flag in (0, 1, 6):
            key = line[2:18]
            try:
                base = minute_cache.get(key)
                if base is None:
                    t = datetime(int(line[2:6]), int(line[7:9]), int(line[10:12]),
                                 int(line[13:15]), int(line[16:18]))
                    base = gpst_from_datetime(t) + _time_offset(header.time_system,
                                                                header.leap_seconds, t)
                    minute_cache[key] = base
                sec = float(line[18:29])
                if not 0.0 <= sec < 61.0:
                    raise ValueError
            except ValueError:
                raise _error(name, n, f"malformed epoch time {line[2:29].strip()!r}") from None
            time = base + sec

        if n_lines - (i + 1) < count:
            if cut_ok:
                cut_short = (f"the epoch of line {n} was cut short ({n_lines - i - 1} of its "
                             f"{count} records) and is left out")
                break
            raise _error(name, n_lines, f"file ends inside the epoch of line {n}: it announces "
                                        f"{count} records, only {n_lines - i - 1} follow")
        block = lines[i + 1:i + 1 + count]
        if flag in (0, 1, 6):
            for k, rec in enumerate(block):
                if rec.startswith(">"):
                    raise _error(name, n + 1 + k, f"epoch of line {n} announces {count} "
                                                  f"satellites but only {k} lines follow")
        if flag in (0, 1):
            if time < last_time:
                raise _error(name, n, f"epoch {_fmt_time(time)} is earlier than the previous "
                                      f"one ({_fmt_time(last_time)}, line {last_line})")
            last_time, last_line = time, n
            observations: dict[str, dict[str, tuple[float, int, int]]] = {}
            for k, rec in enumerate(block):
                sat, values = _parse_sat_line(name, n + 1 + k, rec, layout)
                observations[sat] = values
            epochs.append(RawEpoch(time=time, flag=flag, observations=observations))
        else:
            if flag in (3, 4):
                _apply_event_records(name, header, n + 1, block)
            events.append(ObsEvent(time=time, flag=flag, line=n, records=list(block)))
        i += 1 + count

    return ObsFile(path=name, header=header, epochs=epochs, events=events, cut_short=cut_short)


def ends_with_newline(path: Path) -> bool:
    """Whether a file's last byte ends a line (a record written whole, not torn)."""
    with path.open("rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) in (b"\n", b"\r")


# ------------------------------------------------------------------ RINEX 2 observations

# RINEX 2 observation type (kind + band) -> RINEX 3 attribute, per system (C codes default
# to X, P codes to P). Band 1 phase, Doppler and SNR take the attribute of C1 when it is
# declared (C/A tracking), else of P1; on other bands P before C. BeiDou (RINEX 2.12 "C") B1
# is band 2.
_V2_ATTRIBUTES = {
    "G": {"C1": "C", "P1": "W", "C2": "X", "P2": "W", "C5": "X"},
    "R": {"C1": "C", "P1": "P", "C2": "C", "P2": "P"},
    "E": {},  # every Galileo signal: X (RINEX 2.11 does not tell the channel)
    "S": {"C1": "C", "C5": "X"},
    "J": {"C1": "C", "C2": "X", "C5": "X"},
    "C": {"C2": "I", "C7": "I", "C6": "I"},
}


def _v3_codes(system: str, v2_types: list[str]) -> tuple[str, ...]:
    attrs = _V2_ATTRIBUTES[system]
    declared = set(v2_types)
    out = []
    for t in v2_types:
        kind, band = t[0], t[1]
        if kind in "CP":
            code = "C" + band + attrs.get(t, "X" if kind == "C" else "P")
        else:  # L, D, S follow the band's code, C first on band 1, P first elsewhere
            order = ("C", "P") if band == "1" else ("P", "C")
            ref = next((k + band for k in order if k + band in declared), None)
            code = kind + band + (attrs.get(ref, "X" if ref[0] == "C" else "P") if ref
                                  else "X")
        out.append(code)
    if len(set(out)) != len(out):
        raise ValueError(f"RINEX 2 types {v2_types} map onto repeated RINEX 3 codes {out}")
    return tuple(out)


def _parse_obs_header_v2(path: str, lines: list[str]) -> tuple[ObsHeader, int, list[str]]:
    """Header of a RINEX 2 observation file, its first data line index and its types."""
    version = float(lines[0][0:9])
    file_system = (lines[0][40:41].strip() or "G")
    common = _HeaderCommon()
    types: list[str] = []
    declared: tuple[int, int] | None = None
    for i in range(1, len(lines)):
        line = lines[i]
        n = i + 1
        label = _label(line)
        try:
            if label == "END OF HEADER":
                break
            if common.read(label, line, n):
                continue
            if label == "WAVELENGTH FACT L1/2":
                if line[0:6].strip() == "2":
                    raise _error(path, n, "half-wavelength L1 phase (WAVELENGTH FACT 2) is "
                                          "not supported")
            elif label == "# / TYPES OF OBSERV":
                if line[0:6].strip():
                    if declared is not None:
                        raise _error(path, n, "# / TYPES OF OBSERV declared twice")
                    declared = (int(line[0:6]), n)
                elif declared is None:
                    raise _error(path, n, "# / TYPES OF OBSERV continuation without a count")
                for k in range(6, 60, 6):
                    code = line[k:k + 6].strip()
                    if not code:
                        continue
                    if len(code) != 2 or code[0] not in "CPLDS" or not code[1].isdigit():
                        raise _error(path, n, f"unknown observation type {code!r}")
                    types.append(code)
        except ValueError as exc:
            if isinstance(exc, RinexError):
                raise
            raise _error(path, n, f"malformed {label or 'header'} record: {line.rstrip()!r}"
                         ) from None
    else:
        raise _error(path, len(lines), "missing END OF HEADER (file ends in the header)")
    if declared is None:
        raise _error(path, i + 1, "no # / TYPES OF OBSERV record in the header")
    if declared[0] != len(types):
        raise _error(path, declared[1], f"# / TYPES OF OBSERV announces {declared[0]} types "
                                        f"but lists {len(types)}")
    systems = "GRESJC" if file_system == "M" else file_system
    if any(sys_ not in _V2_ATTRIBUTES for sys_ in systems):
        raise _error(path, 1, f"satellite system {file_system!r} is not supported")
    obs_types = {sys_: list(_v3_codes(sys_, types)) for sys_ in systems}
    return common.header(version, obs_types, {}, path, file_system), i + 1, types


def _v2_satellites(path: str, lines: list[str], i: int, count: int) -> tuple[list[str], int]:
    """Satellite ids of an epoch record (12 per line, continued) and the next line index."""
    sats: list[str] = []
    while len(sats) < count:
        if i >= len(lines):
            raise _error(path, len(lines), "file ends inside an epoch's satellite list")
        line = lines[i]
        for k in range(32, 68, 3):
            if len(sats) == count:
                break
            raw = line[k:k + 3]
            if not raw.strip():
                raise _error(path, i + 1, f"epoch announces {count} satellites but lists "
                                          f"{len(sats)}")
            system = raw[0] if raw[0] != " " else "G"  # blank system: GPS
            if not raw[1:3].strip().isdigit():
                raise _error(path, i + 1, f"malformed satellite id {raw!r}")
            sats.append(system + raw[1:3].replace(" ", "0"))
        i += 1
    return sats, i


def _read_obs_v2(path: str, lines: list[str]) -> ObsFile:
    header, i, types = _parse_obs_header_v2(path, lines)
    layout = {sys_: tuple(codes) for sys_, codes in header.obs_types.items()}
    per_sat = max(1, -(-len(types) // 5))  # lines of observations per satellite
    epochs: list[RawEpoch] = []
    events: list[ObsEvent] = []
    last_time, last_line = -math.inf, 0
    n_lines = len(lines)
    while i < n_lines:
        line = lines[i]
        n = i + 1
        if not line.strip():
            i += 1
            continue
        flag_text, count_text = line[28:29], line[29:32]
        if not flag_text.isdigit() or not count_text.strip().isdigit():
            raise _error(path, n, f"malformed epoch record {line.rstrip()!r}")
        flag, count = int(flag_text), int(count_text)
        if flag > 6:
            raise _error(path, n, f"invalid epoch flag {flag}")
        time = _NAN
        if line[0:26].strip() or flag in (0, 1, 6):
            try:
                yy = int(line[1:3])
                t = datetime(yy + (1900 if yy >= 80 else 2000), int(line[4:6]), int(line[7:9]),
                             int(line[10:12]), int(line[13:15]))
                sec = float(line[15:26])
                if not 0.0 <= sec < 61.0:
                    raise ValueError
            except ValueError:
                raise _error(path, n, f"malformed epoch time {line[0:26].strip()!r}") from None
            time = gpst_from_datetime(t) + sec + _time_offset(header.time_system,
                                                              header.leap_seconds, t)
        if flag not in (0, 1, 6):
            block = lines[i + 1:i + 1 + count]
            if len(block) < count:
                raise _error(path, n_lines, f"file ends inside the event of line {n}")
            if flag in (3, 4):
                _apply_event_records(path, header, n + 1, block)
            events.append(ObsEvent(time=time, flag=flag, line=n, records=list(block)))
            i += 1 + count
            continue
        sats, i = _v2_satellites(path, lines, i, count)
        observations: dict[str, dict[str, tuple[float, int, int]]] = {}
        for sat in sats:
            if i + per_sat > n_lines:
                raise _error(path, n_lines, f"file ends inside the epoch of line {n}")
            fields = ""
            for k in range(per_sat):
                obs_line = lines[i + k]
                end = len(obs_line.rstrip())
                if 0 < end % 16 < 14:
                    raise _error(path, i + k + 1, f"{sat}: line ends inside a value "
                                                  "(truncated line?)")
                fields += f"{obs_line:<80.80}"
            if sat[0] not in layout:
                raise _error(path, i + 1, f"satellite {sat} of a system the file does not "
                                          "declare")
            _, values = _parse_sat_line(path, i + 1, sat + fields[:16 * len(types)], layout)
            observations[sat] = values
            i += per_sat
        if flag in (0, 1):
            if time < last_time:
                raise _error(path, n, f"epoch {_fmt_time(time)} is earlier than the previous "
                                      f"one ({_fmt_time(last_time)}, line {last_line})")
            last_time, last_line = time, n
            epochs.append(RawEpoch(time=time, flag=flag, observations=observations))
        else:
            events.append(ObsEvent(time=time, flag=flag, line=n, records=[]))
    return ObsFile(path=path, header=header, epochs=epochs, events=events)


# ---------------------------------------------------------------------------- L1 view


def _l1_signal(header: ObsHeader, system: str) -> str | None:
    """Band + attribute of the L1-band signal used for a system (by the header's types)."""
    choices = _L1_SIGNALS.get(system, ())
    if system == "C" and header.version < 3.025:
        choices = choices + _L1_SIGNALS_BDS_302
    declared = set(header.obs_types.get(system, ()))
    for sig in choices:
        if "C" + sig in declared or "L" + sig in declared:
            return sig
    return None


def l1_epochs(obs: ObsFile, systems: str = "GREJC") -> list[GnssEpoch]:
    """L1 observations (GPS/QZSS L1 C/A, Galileo E1, GLONASS L1OF, BeiDou B1I, SBAS L1).

    The signal is chosen once per system from the declared types (so that carrier phase stays
    continuous), preferring C/A-type tracking. A satellite with neither pseudorange nor phase
    at an epoch is left out; systems without an L1 signal (or not in ``systems``) are skipped.
    The loss-of-lock indicator is that of the carrier phase.
    """
    signals: dict[str, tuple[str, str, str, str]] = {}
    for system in systems:
        sig = _l1_signal(obs.header, system)
        if sig is not None:
            signals[system] = ("C" + sig, "L" + sig, "D" + sig, "S" + sig)
    out: list[GnssEpoch] = []
    for epoch in obs.epochs:
        sats: dict[str, SatObservation] = {}
        for sat, values in epoch.observations.items():
            codes = signals.get(sat[0])
            if codes is None:
                continue
            pr = values.get(codes[0], _BLANK)[0]
            phase, lli, _ = values.get(codes[1], _BLANK)
            if math.isnan(pr) and math.isnan(phase):
                continue
            sats[sat] = SatObservation(pseudorange=pr, carrier_phase=phase,
                                       doppler=values.get(codes[2], _BLANK)[0],
                                       snr=values.get(codes[3], _BLANK)[0], lli=lli)
        out.append(GnssEpoch(time=epoch.time, satellites=sats, flag=epoch.flag))
    return out


# ----------------------------------------------------------------------------- writer


def ssi_from_snr(snr: float) -> int:
    """RINEX signal strength indicator for a C/N0 in dB-Hz (1: < 12, ..., 9: >= 54, 0: unknown)."""
    if not math.isfinite(snr) or snr <= 0.0:
        return 0
    return min(9, max(1, int(snr // 6.0)))


def _hline(content: str, label: str) -> str:
    if len(content) > 60:
        raise ValueError(f"header field too long for {label}: {content!r}")
    return f"{content:<60}{label:<20}"


def _f14(value: float, sat: str, what: str, t: float) -> str:
    text = f"{value:14.3f}"
    if len(text) > 14:
        raise ValueError(f"{sat} {what} {value} at {_fmt_time(t)} does not fit RINEX F14.3")
    return text


def _split_time(t: float) -> tuple[datetime, int]:
    """Whole-second datetime (GPS scale) and the fraction in 0.1 µs, the RINEX resolution."""
    whole = math.floor(t)
    ticks = round((t - whole) * 1e7)
    if ticks >= 10_000_000:
        whole, ticks = whole + 1, 0
    return datetime_from_gpst(whole), ticks


def _epoch_line(t: float, flag: int, nsat: int) -> str:
    d, ticks = _split_time(t)
    return (f"> {d.year:4d} {d.month:02d} {d.day:02d} {d.hour:02d} {d.minute:02d}"
            f"{d.second:3d}.{ticks:07d}  {flag:1d}{nsat:3d}")


def write_obs(path: str | Path, epochs: list[GnssEpoch], *, marker_name: str, receiver_type: str,
              approx_position_ecef: np.ndarray, interval: float, comments: Sequence[str] = (),
              glonass_slots: dict[str, int] | None = None,
              run_date: datetime | None = None) -> None:
    """Write L1 observations as a RINEX 3.04 mixed observation file (GPS time).

    Each system present gets C1C L1C D1C S1C (BeiDou: C2I L2I D2I S2I, B1I, which is what
    ``l1_epochs`` reads for it); values are F14.3 with the LLI of the phase and an SSI derived
    from the SNR on the code, phase and Doppler; NaN is a blank field.
    ``glonass_slots`` ("R01" -> frequency number) is required when GLONASS is present.
    """
    if not epochs:
        raise ValueError("write_obs needs at least one epoch")
    present: set[str] = set()
    for k, ep in enumerate(epochs):
        if k and ep.time < epochs[k - 1].time:
            raise ValueError(f"epoch {k} ({_fmt_time(ep.time)}) is earlier than the previous one")
        _check_epoch(ep, f"epoch {k}")
        present.update(ep.satellites)
    systems = [s for s in SYSTEMS if any(sat[0] == s for sat in present)]
    glonass = sorted(sat for sat in present if sat[0] == "R")
    slots = dict(glonass_slots or {})
    missing = [s for s in glonass if s not in slots]
    if missing:
        raise ValueError(f"glonass_slots must give the frequency number of {missing}")
    out = obs_header(systems, epochs[0].time, marker_name=marker_name,
                     receiver_type=receiver_type, approx_position_ecef=approx_position_ecef,
                     interval=interval, comments=comments,
                     glonass_slots=slots if glonass else None, run_date=run_date)
    for ep in epochs:
        out += obs_epoch_lines(ep)
    Path(path).write_text("\n".join(out) + "\n", encoding="ascii", errors="replace")


def _check_epoch(ep: GnssEpoch, where: str) -> None:
    if ep.flag not in (0, 1):
        raise ValueError(f"{where}: flag {ep.flag} is not an observation epoch (0 or 1)")
    for sat in ep.satellites:
        if len(sat) != 3 or sat[0] not in SYSTEMS or not sat[1:].isdigit():
            raise ValueError(f"not a RINEX satellite id: {sat!r}")
        if sat[0] not in _WRITE_SIGNAL:
            raise ValueError(f"{sat}: system {sat[0]} has no L1-band signal to write")


def obs_header(systems: Sequence[str], first_time: float, *, marker_name: str,
               receiver_type: str, approx_position_ecef: np.ndarray, interval: float,
               comments: Sequence[str] = (), glonass_slots: dict[str, int] | None = None,
               run_date: datetime | None = None) -> list[str]:
    """The header lines of an observation file holding ``systems`` (see ``write_obs``)."""
    slots = dict(glonass_slots or {})
    bad = [s for s, k in slots.items() if len(s) != 3 or s[0] != "R" or not s[1:].isdigit()
           or not -99 < k < 100]
    if bad:
        raise ValueError(f"glonass_slots entries that RINEX cannot hold: {bad}")
    unknown = [s for s in systems if s not in _WRITE_SIGNAL]
    if unknown:
        raise ValueError(f"system(s) {unknown} have no L1-band signal to write")
    pos = np.asarray(approx_position_ecef, dtype=float)
    t0, ticks0 = _split_time(first_time)
    # A fixed run_date makes the output byte-identical run to run (deterministic simulator).
    now = (run_date or datetime.now(UTC)).strftime("%Y%m%d %H%M%S UTC")
    h = [
        _hline(f"{3.04:9.2f}{'':11s}{'OBSERVATION DATA':20s}{'M (MIXED)':20s}",
               "RINEX VERSION / TYPE"),
        _hline(f"{'berthing-aid':20s}{'':20s}{now:20s}", "PGM / RUN BY / DATE"),
    ]
    for c in comments:
        for k in range(0, max(len(c), 1), 60):
            h.append(_hline(c[k:k + 60], "COMMENT"))
    h += [
        _hline(marker_name[:60], "MARKER NAME"),
        _hline("", "OBSERVER / AGENCY"),
        _hline(f"{'':20s}{receiver_type[:20]:20s}", "REC # / TYPE / VERS"),
        _hline("", "ANT # / TYPE"),
        _hline("".join(f"{v:14.4f}" for v in pos), "APPROX POSITION XYZ"),
        _hline("".join(f"{0.0:14.4f}" for _ in range(3)), "ANTENNA: DELTA H/E/N"),
    ]
    h += [_hline(f"{s}  {4:3d} " + " ".join(t + _WRITE_SIGNAL[s] for t in "CLDS"),
                 "SYS / # / OBS TYPES") for s in systems]
    h += [
        _hline("DBHZ", "SIGNAL STRENGTH UNIT"),
        _hline(f"{interval:10.3f}", "INTERVAL"),
        _hline(f"{t0.year:6d}{t0.month:6d}{t0.day:6d}{t0.hour:6d}{t0.minute:6d}"
               f"{t0.second:5d}.{ticks0:07d}"
               f"{'':5s}GPS", "TIME OF FIRST OBS"),
    ]
    # no phase shifts are applied to what we write: blank correction field
    h += [_hline(f"{s} L{_WRITE_SIGNAL[s]}", "SYS / PHASE SHIFT") for s in systems]
    if "R" in systems and slots:
        h.append(_hline(" C1C    0.000", "GLONASS COD/PHS/BIS"))
        entries = [f"{s} {slots[s]:2d}" for s in sorted(slots)]
        for k in range(0, len(entries), 8):
            lead = f"{len(entries):3d} " if k == 0 else "    "
            h.append(_hline(lead + " ".join(entries[k:k + 8]), "GLONASS SLOT / FRQ #"))
    h.append(_hline("", "END OF HEADER"))
    return h


def obs_epoch_lines(ep: GnssEpoch) -> list[str]:
    """The lines of one observation epoch (epoch line, one line per satellite)."""
    out = [_epoch_line(ep.time, ep.flag, len(ep.satellites))]
    blank = " " * 16
    for sat in sorted(ep.satellites):
        o = ep.satellites[sat]
        if not 0 <= o.lli <= 7:
            raise ValueError(f"{sat} LLI {o.lli} at {_fmt_time(ep.time)} is not in 0..7")
        ssi = ssi_from_snr(o.snr)
        ssi_c = str(ssi) if ssi else " "
        fields = []
        # LLI belongs to the phase (written as a digit, as receivers do); SSI to all three
        for value, what, lli_c in ((o.pseudorange, "pseudorange", " "),
                                   (o.carrier_phase, "carrier phase", str(o.lli)),
                                   (o.doppler, "Doppler", " ")):
            if math.isfinite(value):
                fields.append(_f14(value, sat, what, ep.time) + lli_c + ssi_c)
            else:
                fields.append(blank)
        # the SNR observation itself carries no indicators
        fields.append(_f14(o.snr, sat, "SNR", ep.time) if math.isfinite(o.snr) else blank)
        out.append((sat + "".join(fields)).rstrip())
    return out


# ------------------------------------------------------------------------- navigation

# minimum continuation lines after the first line of a record (RINEX 3.05 GLONASS adds a 4th)
_NAV_LINES = {"G": 7, "E": 7, "C": 7, "J": 7, "I": 7, "R": 3, "S": 3}


def _nav_float(path: str, n: int, text: str) -> float:
    s = text.strip()
    if not s:
        return _NAN
    try:
        value = float(s.replace("D", "E").replace("d", "e"))
    except ValueError:
        raise _error(path, n, f"malformed number {s!r}") from None
    if not math.isfinite(value):
        raise _error(path, n, f"malformed number {s!r}")
    return value


def _nav_record_values(path: str, first: int, rec: list[str]) -> list[float]:
    values = [_nav_float(path, first + 1, rec[0][k:k + 19]) for k in (23, 42, 61)]
    for j, line in enumerate(rec[1:], start=1):
        values += [_nav_float(path, first + 1 + j, line[k:k + 19]) for k in (4, 23, 42, 61)]
    return values


def _required(path: str, first: int, sat: str, values: list[float], idx: Sequence[int]) -> None:
    """Raise for a blank value the computation needs (``first``: index of the record line)."""
    for k in idx:
        if k >= len(values) or math.isnan(values[k]):
            # values 0-2 follow the epoch on the record's first line, then 4 per line
            j, pos = (0, k + 1) if k < 3 else ((k - 3) // 4 + 1, (k - 3) % 4 + 1)
            raise _error(path, first + 1 + j, f"{sat}: ephemeris value {pos} of this line is "
                                              "blank")


def _nearest_week(t: float, ref: float) -> float:
    """Shift t by whole weeks to lie within half a week of ref (week rollovers, 10-bit weeks)."""
    return t - round((t - ref) / SECONDS_PER_WEEK) * SECONDS_PER_WEEK


_KEPLER_REQUIRED = tuple(range(0, 20)) + (21, 24, 25)


def _kepler(path: str, first: int, sat: str, toc: float, v: list[float]) -> KeplerEphemeris:
    _required(path, first, sat, v, _KEPLER_REQUIRED)
    week = int(v[21])
    if sat[0] == "C":
        toe = (week + BDT_WEEK_OFFSET) * SECONDS_PER_WEEK + v[11] - BDT_MINUS_GPST
    else:  # GPS and QZSS weeks, and Galileo weeks as RINEX 3 writes them, count from the GPS epoch
        toe = week * SECONDS_PER_WEEK + v[11]
    toe = _nearest_week(toe, toc)
    data_source = int(v[20]) if sat[0] == "E" and not math.isnan(v[20]) else 0
    return KeplerEphemeris(
        sat=sat, toc=toc, af0=v[0], af1=v[1], af2=v[2], toe=toe, sqrt_a=v[10], e=v[8], i0=v[15],
        omega0=v[13], omega=v[17], m0=v[6], delta_n=v[5], idot=v[19], omega_dot=v[18],
        cuc=v[7], cus=v[9], crc=v[16], crs=v[4], cic=v[12], cis=v[14], iode=int(v[3]),
        tgd=v[25], health=int(v[24]), data_source=data_source)


def _glonass(path: str, first: int, sat: str, toe: float, v: list[float]) -> GlonassEphemeris:
    _required(path, first, sat, v, range(0, 14))
    km = 1000.0
    return GlonassEphemeris(
        sat=sat, toe=toe, tau_n=v[0], gamma_n=v[1],
        position=(v[3] * km, v[7] * km, v[11] * km),
        velocity=(v[4] * km, v[8] * km, v[12] * km),
        acceleration=(v[5] * km, v[9] * km, v[13] * km),
        frequency_number=int(v[10]), health=int(v[6]))


def read_nav(path: str | Path) -> NavigationData:
    """Read a RINEX 3 (mixed) navigation file: GPS, QZSS, Galileo, BeiDou and GLONASS records.

    Times become GPST (BeiDou +14 s and BDT weeks; GLONASS UTC + leap seconds), GLONASS
    positions metres. SBAS and NavIC records are skipped. Ephemerides per satellite are sorted
    by toe with exact duplicates removed.
    """
    p = Path(path)
    name = str(p)
    lines = _lines(p)
    _check_first_line(name, lines, "N", "navigation")
    nav = NavigationData()
    i = 1
    while True:
        if i >= len(lines):
            raise _error(name, len(lines), "missing END OF HEADER (file ends in the header)")
        line = lines[i]
        label = _label(line)
        try:
            if label == "END OF HEADER":
                break
            if label == "IONOSPHERIC CORR" and line[0:4] in ("GPSA", "GPSB"):
                coeffs = tuple(_nav_float(name, i + 1, line[k:k + 12]) for k in (5, 17, 29, 41))
                if line[0:4] == "GPSA":
                    nav.iono_alpha = coeffs  # type: ignore[assignment]
                else:
                    nav.iono_beta = coeffs  # type: ignore[assignment]
            elif label == "LEAP SECONDS":
                nav.leap_seconds = _parse_leap_seconds(line)
        except ValueError as exc:
            if isinstance(exc, RinexError):
                raise
            raise _error(name, i + 1, f"malformed {label} record: {line.rstrip()!r}") from None
        i += 1
    i += 1

    eph: dict[str, list[KeplerEphemeris | GlonassEphemeris]] = {}
    n_lines = len(lines)
    while i < n_lines:
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        sys_ = line[0]
        if sys_ not in _NAV_LINES:
            raise _error(name, i + 1, f"expected an ephemeris record starting with a satellite "
                                      f"id, found {line[:40].rstrip()!r}")
        j = i + 1
        while j < n_lines and lines[j].startswith("    ") and lines[j].strip():
            j += 1
        rec = lines[i:j]
        need = _NAV_LINES[sys_]
        if len(rec) - 1 < need:
            raise _error(name, j if j > i + 1 else i + 1,
                         f"{line[:3]}: ephemeris record of line {i + 1} has {len(rec) - 1} "
                         f"continuation lines, expected {need} (truncated?)")
        if sys_ in "SI":  # SBAS and NavIC are not used by the project
            i = j
            continue
        sat = _sat_id(line[0:3])
        if not sat[1:].isdigit():
            raise _error(name, i + 1, f"malformed satellite id {line[0:3]!r}")
        try:
            t = datetime(int(line[4:8]), int(line[9:11]), int(line[12:14]), int(line[15:17]),
                         int(line[18:20]), int(line[21:23]))
        except ValueError:
            raise _error(name, i + 1, f"{sat}: malformed epoch {line[4:23]!r}") from None
        values = _nav_record_values(name, i, rec)
        epoch = gpst_from_datetime(t)
        if sys_ == "R":
            leap = nav.leap_seconds if nav.leap_seconds is not None else _leap_seconds_at(t)
            e: KeplerEphemeris | GlonassEphemeris = _glonass(name, i, sat, epoch + leap, values)
        else:
            toc = epoch - BDT_MINUS_GPST if sys_ == "C" else epoch
            e = _kepler(name, i, sat, toc, values)
        eph.setdefault(sat, []).append(e)
        i = j

    for sat in sorted(eph):
        unique = list(dict.fromkeys(eph[sat]))  # the same broadcast may be logged repeatedly
        nav.ephemerides[sat] = sorted(unique, key=lambda x: x.toe)
    return nav


def _nav_number(x: float) -> str:
    return f"{x: .12E}" if math.isfinite(x) else " " * 19


def _nav_epoch(t_label: float) -> str:
    d = datetime_from_gpst(round(t_label))
    return f"{d.year:4d} {d.month:02d} {d.day:02d} {d.hour:02d} {d.minute:02d} {d.second:02d}"


def _nav_lines(sat: str, epoch: str, values: Sequence[float]) -> list[str]:
    first = f"{sat} {epoch}" + "".join(_nav_number(v) for v in values[:3])
    rest = values[3:]
    return [first] + ["    " + "".join(_nav_number(v) for v in rest[k:k + 4])
                      for k in range(0, len(rest), 4)]


def write_nav(path: str | Path, nav: NavigationData, *, run_date: datetime | None = None) -> None:
    """Write ``nav`` as a RINEX 3.04 mixed navigation file (what ``read_nav`` reads back:
    Kepler records of GPS, QZSS, Galileo and BeiDou, GLONASS records, the Klobuchar
    coefficients and the leap seconds)."""
    now = (run_date or datetime.now(UTC)).strftime("%Y%m%d %H%M%S UTC")
    out = [_hline(f"{3.04:9.2f}{'':11s}{'N: GNSS NAV DATA':20s}{'M: MIXED':20s}",
                  "RINEX VERSION / TYPE"),
           _hline(f"{'berthing-aid':20s}{'':20s}{now:20s}", "PGM / RUN BY / DATE")]
    for name, coeffs in (("GPSA", nav.iono_alpha), ("GPSB", nav.iono_beta)):
        if coeffs is not None:
            out.append(_hline(f"{name} " + "".join(f"{c:12.4E}" for c in coeffs),
                              "IONOSPHERIC CORR"))
    if nav.leap_seconds is not None:
        out.append(_hline(f"{nav.leap_seconds:6d}", "LEAP SECONDS"))
    out.append(_hline("", "END OF HEADER"))
    nan = math.nan
    for sat in sorted(nav.ephemerides):
        for e in nav.ephemerides[sat]:
            if isinstance(e, GlonassEphemeris):
                leap = nav.leap_seconds if nav.leap_seconds is not None else 18
                km = 1000.0
                p, v, a = e.position, e.velocity, e.acceleration
                values = [e.tau_n, e.gamma_n, 0.0,
                          p[0] / km, v[0] / km, a[0] / km, float(e.health),
                          p[1] / km, v[1] / km, a[1] / km, float(e.frequency_number),
                          p[2] / km, v[2] / km, a[2] / km, 0.0]
                out += _nav_lines(sat, _nav_epoch(e.toe - leap), values)
                continue
            if sat[0] == "C":
                toe_sys = e.toe + BDT_MINUS_GPST
                week = math.floor(toe_sys / SECONDS_PER_WEEK)
                sow = toe_sys - week * SECONDS_PER_WEEK
                week -= BDT_WEEK_OFFSET
                label = e.toc + BDT_MINUS_GPST
            else:
                week = math.floor(e.toe / SECONDS_PER_WEEK)
                sow = e.toe - week * SECONDS_PER_WEEK
                label = e.toc
            sources = float(e.data_source) if sat[0] == "E" else 0.0
            values = [e.af0, e.af1, e.af2,
                      float(e.iode), e.crs, e.delta_n, e.m0,
                      e.cuc, e.e, e.cus, e.sqrt_a,
                      sow, e.cic, e.omega0, e.cis,
                      e.i0, e.crc, e.omega, e.omega_dot,
                      e.idot, sources, float(week), 0.0,
                      2.0, float(e.health), e.tgd, float(e.iode) if sat[0] in "GJ" else nan,
                      sow, nan]
            out += _nav_lines(sat, _nav_epoch(label), values)
    Path(path).write_text("\n".join(out) + "\n", encoding="ascii")
