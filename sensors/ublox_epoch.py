"""The UBX messages a receiver sends every epoch, decoded with one ``struct`` call each.

A u-blox receiver sends NAV-PVT, NAV-TIMEGPS and TIM-TP (and often NAV-DOP and NAV-EOE) every navigation epoch,
up to 25 times a second, for as long as the logger runs. pyubx2 builds each message field by field through its
generic definitions, about a third of the GNSS thread's CPU at 1 Hz (cProfile on the daemon, BENCHMARKS.md);
these few layouts are fixed by the u-blox interface descriptions, so they are unpacked here in one call, and
pyubx2 keeps every other message (set-up replies, RXM-RAWX, the messages of older receivers).

The result carries pyubx2's attribute names and values (scaled fields rounded to pyubx2's own SCALROUND, flags split
into their bits), so :class:`sensors.ublox_decode.GnssDecoder` reads either alike; ``tests/test_ublox_epoch.py``
holds them equal to pyubx2's on random payloads, of the layout's length and longer. A payload shorter than the
layout (an older protocol's 84-byte NAV-PVT) is left to pyubx2, as before, and the decoder's own minimum
lengths judge it; a longer one (a newer protocol version) is unpacked up to the layout's end, as pyubx2 reads it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

from pyubx2.ubxtypes_core import SCALROUND as SCALE_DIGITS  # the decimals pyubx2 rounds a scaled field to


class UbxEpochMessage:
    """One decoded message: ``identity`` ("NAV-PVT"), ``msg_cls`` and ``msg_id`` (one byte each), ``length``
    (of the payload) and the message's fields as attributes under pyubx2's names."""

    def __init__(self, identity: str, cls_id: bytes, length: int, fields: dict[str, Any]) -> None:
        self.identity = identity
        self.msg_cls = cls_id[:1]
        self.msg_id = cls_id[1:2]
        self.length = length
        self.__dict__.update(fields)

    def __repr__(self) -> str:
        fields = ", ".join(f"{k}={v}" for k, v in self.__dict__.items()
                           if k not in ("identity", "msg_cls", "msg_id", "length"))
        return f"<UBX({self.identity}, {fields})>"


def _bits(value: int, names: tuple[tuple[str, int], ...], out: dict[str, Any]) -> None:
    """Split a bitfield into named fields of the given widths, least significant first (reserved bits skipped, as
    pyubx2 skips them)."""
    for name, width in names:
        if not name.startswith("reserved"):
            out[name] = value & ((1 << width) - 1)
        value >>= width


_PVT = struct.Struct("<IHBBBBBBIiBBBBiiiiIIiiiiiIIHHIihH")
_PVT_VALID = (("validDate", 1), ("validTime", 1), ("fullyResolved", 1), ("validMag", 1))
_PVT_FLAGS = (("gnssFixOk", 1), ("diffSoln", 1), ("psmState", 3), ("headVehValid", 1), ("carrSoln", 2))
_PVT_FLAGS2 = (("reserved", 5), ("confirmedAvai", 1), ("confirmedDate", 1), ("confirmedTime", 1))
_PVT_FLAGS3 = (("invalidLlh", 1), ("lastCorrectionAge", 4), ("reserved1", 8), ("authTime", 1), ("nmaFixStatus", 1))


def _nav_pvt(payload: bytes) -> dict[str, Any]:
    (itow, year, month, day, hour, minute, second, valid, t_acc, nano, fix_type, flags, flags2, num_sv, lon, lat,
     height, h_msl, h_acc, v_acc, vel_n, vel_e, vel_d, g_speed, head_mot, s_acc, head_acc, p_dop, flags3, reserved0,
     head_veh, mag_dec, mag_acc) = _PVT.unpack_from(payload)
    out: dict[str, Any] = {"iTOW": itow, "year": year, "month": month, "day": day, "hour": hour, "min": minute,
                           "second": second}
    _bits(valid, _PVT_VALID, out)
    out.update(tAcc=t_acc, nano=nano, fixType=fix_type)
    _bits(flags, _PVT_FLAGS, out)
    _bits(flags2, _PVT_FLAGS2, out)
    out.update(numSV=num_sv, lon=round(lon * 1e-7, SCALE_DIGITS), lat=round(lat * 1e-7, SCALE_DIGITS),
               height=height, hMSL=h_msl, hAcc=h_acc, vAcc=v_acc, velN=vel_n, velE=vel_e, velD=vel_d,
               gSpeed=g_speed, headMot=round(head_mot * 1e-5, SCALE_DIGITS), sAcc=s_acc,
               headAcc=round(head_acc * 1e-5, SCALE_DIGITS), pDOP=round(p_dop * 0.01, SCALE_DIGITS))
    _bits(flags3, _PVT_FLAGS3, out)
    out.update(reserved0=reserved0, headVeh=round(head_veh * 1e-5, SCALE_DIGITS),
               magDec=round(mag_dec * 0.01, SCALE_DIGITS), magAcc=round(mag_acc * 0.01, SCALE_DIGITS))
    return out


_TIMEGPS = struct.Struct("<IihbBI")
_TIMEGPS_VALID = (("towValid", 1), ("weekValid", 1), ("leapSValid", 1))


def _nav_timegps(payload: bytes) -> dict[str, Any]:
    itow, ftow, week, leap_s, valid, t_acc = _TIMEGPS.unpack_from(payload)
    out: dict[str, Any] = {"iTOW": itow, "fTOW": ftow, "week": week, "leapS": leap_s}
    _bits(valid, _TIMEGPS_VALID, out)
    out["tAcc"] = t_acc
    return out


_TIMTP = struct.Struct("<IIiHBB")
_TIMTP_FLAGS = (("timeBase", 1), ("utc", 1), ("raim", 2), ("qErrInvalid", 1), ("TpNotLocked", 1))
_TIMTP_REFINFO = (("timeRefGnss", 4), ("utcStandard", 4))


def _tim_tp(payload: bytes) -> dict[str, Any]:
    tow_ms, tow_sub_ms, q_err, week, flags, refinfo = _TIMTP.unpack_from(payload)
    out: dict[str, Any] = {"towMS": tow_ms, "towSubMS": round(tow_sub_ms * 2.0**-32, SCALE_DIGITS), "qErr": q_err,
                           "week": week}
    _bits(flags, _TIMTP_FLAGS, out)
    _bits(refinfo, _TIMTP_REFINFO, out)
    return out


_DOP = struct.Struct("<IHHHHHHH")
_DOP_NAMES = ("gDOP", "pDOP", "tDOP", "vDOP", "hDOP", "nDOP", "eDOP")


def _nav_dop(payload: bytes) -> dict[str, Any]:
    itow, *dops = _DOP.unpack_from(payload)
    out: dict[str, Any] = {"iTOW": itow}
    for name, value in zip(_DOP_NAMES, dops, strict=True):
        out[name] = round(value * 0.01, SCALE_DIGITS)
    return out


def _nav_eoe(payload: bytes) -> dict[str, Any]:
    return {"iTOW": int.from_bytes(payload[:4], "little")}


# (class, id) -> (identity, payload length the layout needs, decoder)
_LAYOUTS: dict[bytes, tuple[str, int, Callable[[bytes], dict[str, Any]]]] = {
    b"\x01\x07": ("NAV-PVT", _PVT.size, _nav_pvt),
    b"\x01\x20": ("NAV-TIMEGPS", _TIMEGPS.size, _nav_timegps),
    b"\x0d\x01": ("TIM-TP", _TIMTP.size, _tim_tp),
    b"\x01\x04": ("NAV-DOP", _DOP.size, _nav_dop),
    b"\x01\x61": ("NAV-EOE", 4, _nav_eoe),
}


def decode_epoch_message(raw: bytes) -> UbxEpochMessage | None:
    """The message in the checksum-valid UBX frame ``raw`` if it is one of the epoch's (and long enough for its
    layout), else None: pyubx2's to decode."""
    cls_id = raw[2:4]
    layout = _LAYOUTS.get(cls_id)
    if layout is None:
        return None
    identity, need, decode = layout
    length = raw[4] | (raw[5] << 8)
    if length < need:
        return None
    return UbxEpochMessage(identity, cls_id, length, decode(raw[6 : 6 + length]))
