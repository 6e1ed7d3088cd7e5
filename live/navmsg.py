"""Broadcast navigation messages bit by bit: GPS/QZSS LNAV subframes and Galileo I/NAV words.

Decoding turns the words a receiver reports into :class:`estimator.records.KeplerEphemeris`
with exactly the fields and units of the RINEX navigation reader (angles in radians, times in
gpst); encoding is the inverse, for the emulator. One table per message lists every field as
(bit position, length) in the numbering of the interface documents, so that decoder and
encoder share one layout and the table reads against the documents:

- GPS LNAV: IS-GPS-200 20.3.2-20.3.3 (subframes 1-3, subframe 4 page 18), parity Table 20-XIV.
  Bits are numbered 1..300 within a subframe (word n holds bits 30(n-1)+1 .. 30n, of which
  the first 24 are data and the last 6 parity). QZSS L1C/A uses the same layout (IS-QZSS-PNT).
- Galileo I/NAV: OS SIS ICD 4.3.2 (nominal page: even part 120 bits, odd part 120 bits,
  CRC-24Q over 196 bits) and 4.3.5 / table 40 (word types 1-5, 128 bits numbered 1..128).

Words as u-blox reports them in UBX-RXM-SFRBX (what :mod:`live.ubx_gnss` feeds in):
- LNAV: ten 32-bit words per subframe; bits 29..0 are the word's 30 bits as transmitted and
  bits 31..30 the last two parity bits (D29*, D30*) of the previous word, which the parity
  check needs. Data bits are inverted on the air when D30* = 1 and restored here.
- I/NAV: eight 32-bit words per page pair: the even part in the first 120 of the first 128
  bits, the odd part in the first 120 of the last 128.

Any inconsistency raises :class:`NavMessageError` naming the check that failed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from pyrtcm.rtcmhelpers import calc_crc24q

from estimator.frames import SECONDS_PER_WEEK
from estimator.records import KeplerEphemeris

__all__ = [
    "NavMessageError",
    "LnavSubframe",
    "GalileoWord",
    "decode_lnav_subframe",
    "encode_lnav_subframe",
    "lnav_ephemeris",
    "lnav_subframes",
    "klobuchar_from_page18",
    "decode_inav_page",
    "encode_inav_page",
    "inav_ephemeris",
    "inav_words",
    "GALILEO_INAV_DATA_SOURCE",
]

SEMICIRCLE = math.pi  # radians per semicircle (the RINEX files hold radians)
LNAV_PREAMBLE = 0x8B
# RINEX 3.04 Galileo data sources: bit 0 = I/NAV E1-B, bit 9 = clock for E5b,E1
GALILEO_INAV_DATA_SOURCE = (1 << 0) | (1 << 9)


class NavMessageError(ValueError):
    """A navigation word/page that fails a check (parity, CRC, preamble, consistency)."""


# ------------------------------------------------------------------------------ fields


@dataclass(frozen=True)
class _Field:
    """One field: (first bit, length) segments MSB first, scale, two's complement or not."""

    segments: tuple[tuple[int, int], ...]
    scale: float = 1.0
    signed: bool = False

    @property
    def bits(self) -> int:
        return sum(n for _, n in self.segments)


def _f(*segments: tuple[int, int], scale: float = 1.0, signed: bool = False) -> _Field:
    return _Field(tuple(segments), scale, signed)


def _get(frame: int, total_bits: int, field: _Field) -> float:
    """Value of ``field`` in ``frame`` (an int of ``total_bits`` bits, bit 1 = MSB)."""
    raw = 0
    for start, n in field.segments:
        raw = (raw << n) | ((frame >> (total_bits - (start + n - 1))) & ((1 << n) - 1))
    if field.signed and raw >> (field.bits - 1):
        raw -= 1 << field.bits
    return raw * field.scale


def _put(frame: int, total_bits: int, field: _Field, value: float, name: str) -> int:
    """``frame`` with ``value`` quantised into ``field`` (ValueError when it does not fit)."""
    raw = round(value / field.scale)
    lo, hi = ((-(1 << (field.bits - 1)), (1 << (field.bits - 1)) - 1) if field.signed
              else (0, (1 << field.bits) - 1))
    if not lo <= raw <= hi:
        raise ValueError(f"{name} = {value!r} does not fit its {field.bits}-bit field")
    raw &= (1 << field.bits) - 1
    shift = field.bits
    for start, n in field.segments:
        shift -= n
        part = (raw >> shift) & ((1 << n) - 1)
        pos = total_bits - (start + n - 1)
        frame = (frame & ~(((1 << n) - 1) << pos)) | (part << pos)
    return frame


# ---------------------------------------------------------------------------- GPS LNAV

_SC = SEMICIRCLE
# IS-GPS-200 figure 20-1 (subframes 1-3) and 20-1 sheet 8 / table 20-IX (page 18)
_LNAV_COMMON = {
    "preamble": _f((1, 8)),
    "tow": _f((31, 17)),  # HOW: TOW count of the next subframe (units of 6 s)
    "subframe_id": _f((50, 3)),
}
_LNAV = {
    1: {
        "week": _f((61, 10)),
        "l2_codes": _f((71, 2)),
        "ura": _f((73, 4)),
        "health": _f((77, 6)),
        "iodc": _f((83, 2), (211, 8)),
        "l2p_flag": _f((91, 1)),
        "tgd": _f((197, 8), scale=2.0**-31, signed=True),
        "toc": _f((219, 16), scale=2.0**4),
        "af2": _f((241, 8), scale=2.0**-55, signed=True),
        "af1": _f((249, 16), scale=2.0**-43, signed=True),
        "af0": _f((271, 22), scale=2.0**-31, signed=True),
    },
    2: {
        "iode": _f((61, 8)),
        "crs": _f((69, 16), scale=2.0**-5, signed=True),
        "delta_n": _f((91, 16), scale=2.0**-43 * _SC, signed=True),
        "m0": _f((107, 8), (121, 24), scale=2.0**-31 * _SC, signed=True),
        "cuc": _f((151, 16), scale=2.0**-29, signed=True),
        "e": _f((167, 8), (181, 24), scale=2.0**-33),
        "cus": _f((211, 16), scale=2.0**-29, signed=True),
        "sqrt_a": _f((227, 8), (241, 24), scale=2.0**-19),
        "toe": _f((271, 16), scale=2.0**4),
        "fit_interval": _f((287, 1)),
        "aodo": _f((288, 5)),
    },
    3: {
        "cic": _f((61, 16), scale=2.0**-29, signed=True),
        "omega0": _f((77, 8), (91, 24), scale=2.0**-31 * _SC, signed=True),
        "cis": _f((121, 16), scale=2.0**-29, signed=True),
        "i0": _f((137, 8), (151, 24), scale=2.0**-31 * _SC, signed=True),
        "crc": _f((181, 16), scale=2.0**-5, signed=True),
        "omega": _f((197, 8), (211, 24), scale=2.0**-31 * _SC, signed=True),
        "omega_dot": _f((241, 24), scale=2.0**-43 * _SC, signed=True),
        "iode": _f((271, 8)),
        "idot": _f((279, 14), scale=2.0**-43 * _SC, signed=True),
    },
    4: {  # page 18 (SV ID 56): ionospheric and UTC parameters
        "data_id": _f((61, 2)),
        "page_sv_id": _f((63, 6)),
        "alpha0": _f((69, 8), scale=2.0**-30, signed=True),
        "alpha1": _f((77, 8), scale=2.0**-27, signed=True),
        "alpha2": _f((91, 8), scale=2.0**-24, signed=True),
        "alpha3": _f((99, 8), scale=2.0**-24, signed=True),
        "beta0": _f((107, 8), scale=2.0**11, signed=True),
        "beta1": _f((121, 8), scale=2.0**14, signed=True),
        "beta2": _f((129, 8), scale=2.0**16, signed=True),
        "beta3": _f((137, 8), scale=2.0**16, signed=True),
        "delta_t_ls": _f((241, 8), signed=True),
    },
}
PAGE18_SV_ID = 56
_LNAV_BITS = 300

# Table 20-XIV: for parity bits D25..D30, the previous word's bit (29 or 30) and the data bits
_PARITY = (
    (29, (1, 2, 3, 5, 6, 10, 11, 12, 13, 14, 17, 18, 20, 23)),
    (30, (2, 3, 4, 6, 7, 11, 12, 13, 14, 15, 18, 19, 21, 24)),
    (29, (1, 3, 4, 5, 7, 8, 12, 13, 14, 15, 16, 19, 20, 22)),
    (30, (2, 4, 5, 6, 8, 9, 13, 14, 15, 16, 17, 20, 21, 23)),
    (30, (1, 3, 5, 6, 7, 9, 10, 14, 15, 16, 17, 18, 21, 22, 24)),
    (29, (3, 5, 6, 8, 9, 10, 11, 13, 15, 19, 22, 23, 24)),
)
_PARITY_MASKS = tuple((star, sum(1 << (24 - i) for i in idx)) for star, idx in _PARITY)


def _parity(data24: int, d29: int, d30: int) -> int:
    """The six parity bits of a word's 24 source data bits (IS-GPS-200 Table 20-XIV)."""
    out = 0
    for star, mask in _PARITY_MASKS:
        bit = (d29 if star == 29 else d30) ^ (bin(data24 & mask).count("1") & 1)
        out = (out << 1) | bit
    return out


@dataclass(frozen=True)
class LnavSubframe:
    """A parity-checked LNAV subframe: its id, HOW time of week and decoded fields."""

    subframe_id: int
    tow: float  # s, time of week of the start of the NEXT subframe (HOW TOW count × 6)
    fields: dict[str, float]


def decode_lnav_subframe(words: Sequence[int]) -> LnavSubframe:
    """Check and decode ten u-blox LNAV words (see the module docstring for their layout).

    Raises NavMessageError for a wrong word count, a failed parity (naming the word), a wrong
    preamble or a subframe id outside 1-5. Subframe 4 is decoded only for page 18; other
    pages give an empty field set.
    """
    if len(words) != 10:
        raise NavMessageError(f"LNAV subframe needs 10 words, got {len(words)}")
    frame = 0
    for k, word in enumerate(words):
        d29, d30 = (word >> 31) & 1, (word >> 30) & 1
        transmitted = (word >> 6) & 0xFFFFFF
        data = transmitted ^ (0xFFFFFF if d30 else 0)  # D30* = 1 inverts the data on air
        if _parity(data, d29, d30) != word & 0x3F:
            raise NavMessageError(f"LNAV parity fails on word {k + 1}")
        frame = (frame << 30) | (data << 6) | (word & 0x3F)
    if int(_get(frame, _LNAV_BITS, _LNAV_COMMON["preamble"])) != LNAV_PREAMBLE:
        raise NavMessageError("LNAV preamble is not 10001011")
    sid = int(_get(frame, _LNAV_BITS, _LNAV_COMMON["subframe_id"]))
    if not 1 <= sid <= 5:
        raise NavMessageError(f"LNAV subframe id {sid} is not 1-5")
    tow = _get(frame, _LNAV_BITS, _LNAV_COMMON["tow"]) * 6.0
    layout = _LNAV.get(sid, {})
    if sid == 4 and int(_get(frame, _LNAV_BITS, _LNAV[4]["page_sv_id"])) != PAGE18_SV_ID:
        layout = {}
    return LnavSubframe(sid, tow, {name: _get(frame, _LNAV_BITS, f)
                                   for name, f in layout.items()})


def encode_lnav_subframe(subframe_id: int, tow: float, fields: Mapping[str, float]) -> list[int]:
    """Ten u-blox LNAV words of a subframe (fields of ``_LNAV[subframe_id]``; missing = 0).

    ``tow``: time of week (s, a multiple of 6) of the start of the next subframe, as the HOW
    carries it. Parity is computed as on air: the data of a word is inverted when the
    previous word's D30 is 1, and the two non-information bits of words 2 and 10 are chosen
    so that their D29 = D30 = 0 (IS-GPS-200 20.3.5.2).
    """
    if tow % 6.0 or not 0 <= tow < SECONDS_PER_WEEK + 6:
        raise ValueError(f"HOW time of week {tow} is not a multiple of 6 s within a week")
    frame = 0
    frame = _put(frame, _LNAV_BITS, _LNAV_COMMON["preamble"], LNAV_PREAMBLE, "preamble")
    frame = _put(frame, _LNAV_BITS, _LNAV_COMMON["tow"], (tow / 6.0) % 100800, "tow")
    frame = _put(frame, _LNAV_BITS, _LNAV_COMMON["subframe_id"], subframe_id, "subframe id")
    layout = _LNAV[subframe_id]
    unknown = set(fields) - set(layout)
    if unknown:
        raise ValueError(f"subframe {subframe_id} has no field(s) {sorted(unknown)}")
    for name, value in fields.items():
        frame = _put(frame, _LNAV_BITS, layout[name], value, name)
    words = []
    d29 = d30 = 0  # the previous subframe's word 10 ends with D29 = D30 = 0
    for k in range(10):
        data = (frame >> (30 * (9 - k) + 6)) & 0xFFFFFF
        if k in (1, 9):  # solve the two non-information bits (23, 24) for D29 = D30 = 0
            for t in range(4):
                trial = (data & ~0x3) | t
                if _parity(trial, d29, d30) & 0x3 == 0:
                    data = trial
                    break
        parity = _parity(data, d29, d30)
        transmitted = data ^ (0xFFFFFF if d30 else 0)
        words.append((d29 << 31) | (d30 << 30) | (transmitted << 6) | parity)
        d29, d30 = (parity >> 1) & 1, parity & 1
    return words


def _nearest_week(tow: float, ref: float) -> float:
    """The gpst with time of week ``tow`` nearest to ``ref``."""
    t = math.floor(ref / SECONDS_PER_WEEK) * SECONDS_PER_WEEK + tow
    return t - round((t - ref) / SECONDS_PER_WEEK) * SECONDS_PER_WEEK


def lnav_ephemeris(sat: str, sf1: LnavSubframe, sf2: LnavSubframe, sf3: LnavSubframe,
                   time_hint: float) -> KeplerEphemeris:
    """The ephemeris of subframes 1-3 of one issue (gpst toe/toc resolved near ``time_hint``).

    Raises NavMessageError when the three do not belong to one issue (IODC's 8 LSBs, IODE of
    subframes 2 and 3 differ), as during an upload.
    """
    a, b, c = sf1.fields, sf2.fields, sf3.fields
    iodc, iode2, iode3 = int(a["iodc"]), int(b["iode"]), int(c["iode"])
    if not iode2 == iode3 == iodc & 0xFF:
        raise NavMessageError(f"{sat}: subframes 1-3 of different issues "
                              f"(IODC {iodc}, IODE {iode2}/{iode3})")
    toe = _nearest_week(b["toe"], time_hint)
    toc = _nearest_week(a["toc"], toe)
    return KeplerEphemeris(
        sat=sat, toc=toc, af0=a["af0"], af1=a["af1"], af2=a["af2"], toe=toe,
        sqrt_a=b["sqrt_a"], e=b["e"], i0=c["i0"], omega0=c["omega0"], omega=c["omega"],
        m0=b["m0"], delta_n=b["delta_n"], idot=c["idot"], omega_dot=c["omega_dot"],
        cuc=b["cuc"], cus=b["cus"], crc=c["crc"], crs=b["crs"], cic=c["cic"], cis=c["cis"],
        iode=iode2, tgd=a["tgd"], health=int(a["health"]))


def lnav_subframes(eph: KeplerEphemeris, tow: float, *, iodc: int | None = None,
                   iono: tuple[Sequence[float], Sequence[float]] | None = None,
                   leap_seconds: int = 18) -> list[list[int]]:
    """u-blox words of subframes 1, 2, 3 (and 4 page 18 when ``iono`` = (alpha, beta)) of a
    GPS/QZSS ephemeris, the first transmitted at time of week ``tow`` (s, multiple of 6).

    ``iodc`` defaults to the IODE (its 8 LSBs must equal the IODE).
    """
    if eph.sat[0] not in "GJ":
        raise ValueError(f"{eph.sat}: LNAV is GPS/QZSS only")
    week = int(eph.toe // SECONDS_PER_WEEK)
    sf1 = {"week": week % 1024, "health": eph.health, "iodc": eph.iode if iodc is None else iodc,
           "tgd": eph.tgd, "toc": eph.toc % SECONDS_PER_WEEK, "af2": eph.af2, "af1": eph.af1,
           "af0": eph.af0}
    sf2 = {"iode": eph.iode, "crs": eph.crs, "delta_n": eph.delta_n, "m0": eph.m0,
           "cuc": eph.cuc, "e": eph.e, "cus": eph.cus, "sqrt_a": eph.sqrt_a,
           "toe": eph.toe % SECONDS_PER_WEEK}
    sf3 = {"cic": eph.cic, "omega0": eph.omega0, "cis": eph.cis, "i0": eph.i0, "crc": eph.crc,
           "omega": eph.omega, "omega_dot": eph.omega_dot, "iode": eph.iode, "idot": eph.idot}
    pages: list[tuple[int, Mapping[str, float]]] = [(1, sf1), (2, sf2), (3, sf3)]
    if iono is not None:
        alpha, beta = iono
        pages.append((4, {"data_id": 1, "page_sv_id": PAGE18_SV_ID, "delta_t_ls": leap_seconds,
                          **{f"alpha{i}": alpha[i] for i in range(4)},
                          **{f"beta{i}": beta[i] for i in range(4)}}))
    return [encode_lnav_subframe(sid, (tow + 6.0 * (k + 1)) % SECONDS_PER_WEEK, fields)
            for k, (sid, fields) in enumerate(pages)]


def klobuchar_from_page18(sf: LnavSubframe) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """(alpha, beta) of a subframe 4 page 18, None for any other subframe/page."""
    if sf.subframe_id != 4 or "alpha0" not in sf.fields:
        return None
    return (tuple(sf.fields[f"alpha{i}"] for i in range(4)),
            tuple(sf.fields[f"beta{i}"] for i in range(4)))


# ------------------------------------------------------------------------- Galileo I/NAV

# Galileo OS SIS ICD table 40 (word types 1-5), bits numbered 1..128 within the word
_INAV = {
    1: {
        "iodnav": _f((7, 10)),
        "toe": _f((17, 14), scale=60.0),
        "m0": _f((31, 32), scale=2.0**-31 * _SC, signed=True),
        "e": _f((63, 32), scale=2.0**-33),
        "sqrt_a": _f((95, 32), scale=2.0**-19),
    },
    2: {
        "iodnav": _f((7, 10)),
        "omega0": _f((17, 32), scale=2.0**-31 * _SC, signed=True),
        "i0": _f((49, 32), scale=2.0**-31 * _SC, signed=True),
        "omega": _f((81, 32), scale=2.0**-31 * _SC, signed=True),
        "idot": _f((113, 14), scale=2.0**-43 * _SC, signed=True),
    },
    3: {
        "iodnav": _f((7, 10)),
        "omega_dot": _f((17, 24), scale=2.0**-43 * _SC, signed=True),
        "delta_n": _f((41, 16), scale=2.0**-43 * _SC, signed=True),
        "cuc": _f((57, 16), scale=2.0**-29, signed=True),
        "cus": _f((73, 16), scale=2.0**-29, signed=True),
        "crc": _f((89, 16), scale=2.0**-5, signed=True),
        "crs": _f((105, 16), scale=2.0**-5, signed=True),
        "sisa": _f((121, 8)),
    },
    4: {
        "iodnav": _f((7, 10)),
        "svid": _f((17, 6)),
        "cic": _f((23, 16), scale=2.0**-29, signed=True),
        "cis": _f((39, 16), scale=2.0**-29, signed=True),
        "toc": _f((55, 14), scale=60.0),
        "af0": _f((69, 31), scale=2.0**-34, signed=True),
        "af1": _f((100, 21), scale=2.0**-46, signed=True),
        "af2": _f((121, 6), scale=2.0**-59, signed=True),
    },
    5: {
        "ai0": _f((7, 11), scale=2.0**-2),
        "ai1": _f((18, 11), scale=2.0**-8, signed=True),
        "ai2": _f((29, 14), scale=2.0**-15, signed=True),
        "bgd_e1e5a": _f((48, 10), scale=2.0**-32, signed=True),
        "bgd_e1e5b": _f((58, 10), scale=2.0**-32, signed=True),
        "e5b_hs": _f((68, 2)),
        "e1b_hs": _f((70, 2)),
        "e5b_dvs": _f((72, 1)),
        "e1b_dvs": _f((73, 1)),
        "wn": _f((74, 12)),
        "tow": _f((86, 20)),
    },
}
_WORD_TYPE = _f((1, 6))
_INAV_WORD_BITS = 128
# Page parts (OS SIS ICD figure 13): even = E/O, page type, data k (word bits 1-112), tail;
# odd = E/O, page type, data j (word bits 113-128), OSNMA, SAR, spare, CRC, reserved 2, tail.
_PART_BITS = 120
_CRC_FIELD = (82, 24)  # within the odd part, 0-based: after E/O, type, data j, OSNMA, SAR, spare


@dataclass(frozen=True)
class GalileoWord:
    """A CRC-checked I/NAV word: its type and decoded fields (types 1-5; others empty)."""

    word_type: int
    fields: dict[str, float]


def _inav_crc(even: int, odd: int) -> int:
    """CRC-24Q over the even part's first 114 bits and the odd part's first 82 bits."""
    bits = ((even >> (_PART_BITS - 114)) << 82) | (odd >> (_PART_BITS - 82))
    return calc_crc24q(bits.to_bytes(25, "big"))  # 196 bits, 4 leading zeros change nothing


def decode_inav_page(words: Sequence[int]) -> GalileoWord:
    """Check and decode the eight u-blox words of an I/NAV nominal page pair.

    Raises NavMessageError for a wrong word count, parts out of order, an alert page or a
    CRC mismatch.
    """
    if len(words) != 8:
        raise NavMessageError(f"I/NAV page needs 8 words, got {len(words)}")
    whole = 0
    for w in words:
        whole = (whole << 32) | (w & 0xFFFFFFFF)
    even = (whole >> (128 + 8)) & ((1 << _PART_BITS) - 1)
    odd = (whole >> 8) & ((1 << _PART_BITS) - 1)
    if even >> (_PART_BITS - 1) != 0 or odd >> (_PART_BITS - 1) != 1:
        raise NavMessageError("I/NAV page parts are not even then odd")
    if (even >> (_PART_BITS - 2)) & 1 or (odd >> (_PART_BITS - 2)) & 1:
        raise NavMessageError("I/NAV alert page (not a nominal page)")
    start, n = _CRC_FIELD
    crc = (odd >> (_PART_BITS - start - n)) & ((1 << n) - 1)
    if _inav_crc(even, odd) != crc:
        raise NavMessageError("I/NAV CRC-24Q mismatch")
    data_k = (even >> 6) & ((1 << 112) - 1)
    data_j = (odd >> (_PART_BITS - 18)) & 0xFFFF
    word = (data_k << 16) | data_j
    word_type = int(_get(word, _INAV_WORD_BITS, _WORD_TYPE))
    layout = _INAV.get(word_type, {})
    return GalileoWord(word_type, {name: _get(word, _INAV_WORD_BITS, f)
                                   for name, f in layout.items()})


def encode_inav_page(word_type: int, fields: Mapping[str, float]) -> list[int]:
    """The eight u-blox words of a nominal I/NAV page carrying one word (OSNMA/SAR zero)."""
    layout = _INAV[word_type]
    unknown = set(fields) - set(layout)
    if unknown:
        raise ValueError(f"word type {word_type} has no field(s) {sorted(unknown)}")
    word = _put(0, _INAV_WORD_BITS, _WORD_TYPE, word_type, "word type")
    for name, value in fields.items():
        word = _put(word, _INAV_WORD_BITS, layout[name], value, name)
    even = (word >> 16) << 6  # E/O = 0, page type = 0, data k, tail 0
    odd = ((1 << 119) | ((word & 0xFFFF) << (_PART_BITS - 18)))  # E/O = 1, data j
    start, n = _CRC_FIELD
    odd |= _inav_crc(even, odd) << (_PART_BITS - start - n)
    whole = (even << (128 + 8)) | (odd << 8)
    return [(whole >> (32 * (7 - k))) & 0xFFFFFFFF for k in range(8)]


def inav_ephemeris(sat: str, words: Mapping[int, GalileoWord], time_hint: float
                   ) -> KeplerEphemeris:
    """The ephemeris of I/NAV words 1-5 (one IODnav), toe/toc resolved near ``time_hint``.

    Health and group delay as the RINEX file holds them: health bits 0 E1-B DVS, 1-2 E1-B HS,
    6 E5b DVS, 7-8 E5b HS; ``tgd`` = BGD(E1,E5a); data source I/NAV E1-B with the E5b,E1
    clock (513).
    """
    w1, w2, w3, w4, w5 = (words[k].fields for k in range(1, 6))
    iods = {int(w["iodnav"]) for w in (w1, w2, w3, w4)}
    if len(iods) != 1:
        raise NavMessageError(f"{sat}: I/NAV words 1-4 of different issues (IODnav {sorted(iods)})")
    toe = _nearest_week(w1["toe"], time_hint)
    toc = _nearest_week(w4["toc"], toe)
    health = (int(w5["e1b_dvs"]) | int(w5["e1b_hs"]) << 1 | int(w5["e5b_dvs"]) << 6
              | int(w5["e5b_hs"]) << 7)
    return KeplerEphemeris(
        sat=sat, toc=toc, af0=w4["af0"], af1=w4["af1"], af2=w4["af2"], toe=toe,
        sqrt_a=w1["sqrt_a"], e=w1["e"], i0=w2["i0"], omega0=w2["omega0"], omega=w2["omega"],
        m0=w1["m0"], delta_n=w3["delta_n"], idot=w2["idot"], omega_dot=w3["omega_dot"],
        cuc=w3["cuc"], cus=w3["cus"], crc=w3["crc"], crs=w3["crs"], cic=w4["cic"],
        cis=w4["cis"], iode=iods.pop(), tgd=w5["bgd_e1e5a"], health=health,
        data_source=GALILEO_INAV_DATA_SOURCE)


def inav_words(eph: KeplerEphemeris, tow: float, *, bgd_e1e5b: float | None = None,
               sisa: int = 107) -> list[list[int]]:
    """u-blox words of the I/NAV pages of word types 1-5 carrying a Galileo ephemeris, the
    pages sent from time of week ``tow`` (s; word 5 carries it as GST time of week).

    The RINEX record keeps BGD(E1,E5a) in ``tgd``; BGD(E1,E5b) defaults to the same value.
    ``sisa`` is the SISA index (107: 3.12 m, the nominal accuracy).
    """
    if eph.sat[0] != "E":
        raise ValueError(f"{eph.sat}: I/NAV is Galileo only")
    week = int(eph.toe // SECONDS_PER_WEEK)
    common = {"iodnav": eph.iode}
    fields: dict[int, dict[str, float]] = {
        1: {**common, "toe": eph.toe % SECONDS_PER_WEEK, "m0": eph.m0, "e": eph.e,
            "sqrt_a": eph.sqrt_a},
        2: {**common, "omega0": eph.omega0, "i0": eph.i0, "omega": eph.omega, "idot": eph.idot},
        3: {**common, "omega_dot": eph.omega_dot, "delta_n": eph.delta_n, "cuc": eph.cuc,
            "cus": eph.cus, "crc": eph.crc, "crs": eph.crs, "sisa": sisa},
        4: {**common, "svid": int(eph.sat[1:]), "cic": eph.cic, "cis": eph.cis,
            "toc": eph.toc % SECONDS_PER_WEEK, "af0": eph.af0, "af1": eph.af1, "af2": eph.af2},
        5: {"bgd_e1e5a": eph.tgd, "bgd_e1e5b": eph.tgd if bgd_e1e5b is None else bgd_e1e5b,
            "e1b_dvs": eph.health & 1, "e1b_hs": (eph.health >> 1) & 3,
            "e5b_dvs": (eph.health >> 6) & 1, "e5b_hs": (eph.health >> 7) & 3,
            "wn": (week - 1024) % 4096, "tow": int(tow) % int(SECONDS_PER_WEEK)},
    }
    return [encode_inav_page(k, fields[k]) for k in range(1, 6)]
