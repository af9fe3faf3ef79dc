"""Fuzzing what a u-blox receiver's serial line can deliver: the UBX/NMEA/RTCM3 framer, the epoch decoder
and the receiver set-up conversation. No byte sequence may raise, hang, grow memory without bound, or cost
so much time per byte that the reader falls behind the line."""

from __future__ import annotations

import functools
import itertools
import math
import os
import struct
import time
from typing import Any

import pytest
import serial
from extras import HealthCheck, given, settings, st
from pynmeagps.nmeahelpers import calc_checksum as nmea_checksum
from pyubx2.ubxhelpers import calc_checksum as ubx_checksum

from sensors.errors import SensorError
from sensors.ublox import GnssDecoder, GnssFix, GnssTime, TimePulse, UbxNmeaFramer
from sensors.ublox_config import configure_receiver
from sensors.ublox_frames import NMEA_MAX_LEN, UBX_HEADER_LEN, UBX_MAX_PAYLOAD, crc24q

# FUZZ_EXAMPLES=5000 (environment) searches deeper than the suite's default.
FUZZ = settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", "300")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
MAX_PENDING = UBX_HEADER_LEN + UBX_MAX_PAYLOAD + 2  # the longest frame the framer may wait for

# Every message the decoder and the set-up read, and a few it ignores (class, id).
UBX_IDS = [(0x01, 0x07), (0x01, 0x17), (0x01, 0x06), (0x01, 0x02), (0x01, 0x14), (0x01, 0x12), (0x01, 0x03),
           (0x01, 0x04), (0x01, 0x20), (0x01, 0x21), (0x01, 0x26), (0x01, 0x61), (0x0D, 0x01), (0x28, 0x00),
           (0x02, 0x15), (0x05, 0x01), (0x05, 0x00), (0x0A, 0x04), (0x06, 0x00), (0x06, 0x8A), (0x01, 0x35),
           (0x27, 0x03), (0xFF, 0xFF)]
NMEA_KINDS = ["GGA", "RMC", "GSA", "VTG", "ZDA", "GST", "GLL", "GNS", "GSV", "GBS", "TXT"]


def ubx_frame(cls: int, mid: int, payload: bytes) -> bytes:
    body = bytes([cls, mid]) + struct.pack("<H", len(payload)) + payload
    return b"\xb5\x62" + body + ubx_checksum(body)


def nmea_sentence(talker: str, kind: str, fields: list[str]) -> bytes:
    body = f"{talker}{kind}," + ",".join(fields)
    return f"${body}*{nmea_checksum(body)}\r\n".encode()


def rtcm_frame(payload: bytes) -> bytes:
    head = bytes([0xD3, (len(payload) >> 8) & 0x03, len(payload) & 0xFF]) + payload
    return head + crc24q(head).to_bytes(3, "big")


ubx_frames = st.builds(ubx_frame, st.sampled_from(UBX_IDS).map(lambda x: x[0]),
                       st.sampled_from(UBX_IDS).map(lambda x: x[1]), st.binary(max_size=140))
ubx_known = st.sampled_from(UBX_IDS).flatmap(
    lambda ids: st.binary(max_size=140).map(functools.partial(lambda i, p: ubx_frame(i[0], i[1], p), ids)))
nmea_field = st.one_of(st.just(""), st.from_regex(r"[0-9]{1,9}(\.[0-9]{1,6})?", fullmatch=True),
                       st.sampled_from(["A", "V", "N", "S", "E", "W", "M", "K", "T", "1", "2", "3", "AAN"]),
                       st.text(alphabet="0123456789.-ABCDEFNSEWMKT", max_size=10))
nmea_sentences = st.builds(nmea_sentence, st.sampled_from(["GP", "GN", "GL", "GA", "BD"]), st.sampled_from(NMEA_KINDS),
                           st.lists(nmea_field, max_size=20))
valid_pieces = st.one_of(ubx_known, ubx_frames, nmea_sentences, st.builds(rtcm_frame, st.binary(max_size=60)))
pieces = st.one_of(valid_pieces.map(lambda b: (True, b)), st.binary(max_size=64).map(lambda b: (False, b)))


def decode_in_pieces(data: bytes, cuts: list[int]) -> tuple[UbxNmeaFramer, list[bytes], list[Any]]:
    framer, decoder = UbxNmeaFramer(), GnssDecoder()
    raws: list[bytes] = []
    items: list[Any] = []
    bounds = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    for a, b in itertools.pairwise(bounds):
        frames = framer.feed(data[a:b])
        assert framer.pending <= MAX_PENDING
        raws += [f.raw for f in frames]
        items += decoder.push_all(frames)
    frames = framer.finish()
    raws += [f.raw for f in frames]
    items += decoder.push_all(frames) + decoder.flush()
    return framer, raws, items


def check_items(items: list[Any]) -> None:
    for item in items:
        assert isinstance(item, GnssFix | TimePulse | GnssTime)
        if isinstance(item, GnssFix):
            assert item.fix_mode in (0, 1, 2, 3)
            for v in (item.lat_deg, item.lon_deg):
                assert v is None or math.isfinite(v)
            assert item.time_utc_ns is None or isinstance(item.time_utc_ns, int)


@FUZZ
@given(st.binary(max_size=4000), st.lists(st.integers(0, 4000), max_size=20))
def test_random_bytes_in_random_pieces(data: bytes, cuts: list[int]) -> None:
    framer, raws, items = decode_in_pieces(data, cuts)
    check_items(items)
    # However the port cut the stream, the same frames come out of it.
    whole = UbxNmeaFramer()
    same = [f.raw for f in whole.feed(data)] + [f.raw for f in whole.finish()]
    assert raws == same
    assert whole.garbage_bytes == framer.garbage_bytes


@FUZZ
@given(st.lists(pieces, max_size=30), st.lists(st.integers(0, 6000), max_size=20))
def test_checksum_valid_frames_with_nonsense_content(parts: list[tuple[bool, bytes]], cuts: list[int]) -> None:
    data = b"".join(b for _, b in parts)
    _, raws, items = decode_in_pieces(data, cuts)
    check_items(items)
    # Garbage in front of a good frame costs only the garbage: every good frame is found (a sentence longer
    # than NMEA allows is refused on purpose), unless garbage and frame happen to form a longer good frame.
    for valid, piece in parts:
        if valid and not (piece.startswith(b"$") and len(piece) > NMEA_MAX_LEN):
            assert any(piece in raw for raw in raws), piece


@FUZZ
@given(st.lists(st.sampled_from(UBX_IDS), min_size=1, max_size=40), st.randoms(use_true_random=False))
def test_full_length_messages_with_random_fields(ids: list[tuple[int, int]], rnd: Any) -> None:
    """Messages of their real lengths, every field random: impossible dates, NaN-free but absurd values."""
    lengths = {(0x01, 0x07): 92, (0x01, 0x17): 116, (0x01, 0x06): 52, (0x01, 0x02): 28, (0x01, 0x14): 36,
               (0x01, 0x12): 36, (0x01, 0x03): 16, (0x01, 0x04): 18, (0x01, 0x20): 16, (0x01, 0x21): 20,
               (0x01, 0x26): 24, (0x01, 0x61): 4, (0x0D, 0x01): 16, (0x28, 0x00): 72, (0x02, 0x15): 16}
    decoder = GnssDecoder()
    items: list[Any] = []
    itow = rnd.randrange(2**32)
    for cls, mid in ids:
        payload = bytearray(rnd.randbytes(lengths.get((cls, mid), 20)))
        if cls == 0x01 and rnd.random() < 0.7:
            payload[0:4] = struct.pack("<I", itow)  # the same epoch, mostly
        framer = UbxNmeaFramer()
        items += decoder.push_all(framer.feed(ubx_frame(cls, mid, bytes(payload))))
        if rnd.random() < 0.2:
            itow = (itow + 1000) % 2**32
    check_items(items + decoder.flush())


# ---- time per byte: a reader that cannot keep up with its line is as good as hung ------------------------------
#
# Measured against a yardstick taken in the same process on the same bytes, not against the clock: one pass of
# Python over every byte (a table look-up and a shift, a CRC step's work). The framer is Python that looks at each
# byte a few times and checks each candidate header's checksum: a UBX Fletcher in numpy, an RTCM3 CRC in Python
# paid from a budget of RTCM3_CHECK_PER_BYTE (32) CRC bytes per byte, so 20-45 passes per byte on x86 and under
# armhf emulation alike. The faults this guards against cost hundreds: a UBX checksum in a Python loop re-runs
# 8 kB for every 6-byte forged header (470-600 passes per byte), an RTCM3 CRC without the budget 1 kB for every
# 3 bytes (190-450). A machine ten times slower is ten times slower at both, so the ratio holds anywhere.

PASSES_PER_BYTE_MAX = 100
_TABLE = tuple((i * 0x9E3779B1) & 0xFFFFFF for i in range(256))


def _best_of(measure: Any, data: bytes, runs: int = 3) -> float:
    """The least time of a few runs: what the work costs, without what a busy host added to some of them."""
    return min(measure(data) for _ in range(runs))


def _python_pass(data: bytes) -> float:
    """Seconds for one Python pass over every byte of ``data``."""
    t0 = time.perf_counter()
    acc = 0
    for byte in data:
        acc = ((acc << 8) & 0xFFFFFF) ^ _TABLE[((acc >> 16) ^ byte) & 0xFF]
    return time.perf_counter() - t0


def _framing(data: bytes) -> float:
    """Seconds for the framer to take ``data`` in as a serial port hands it over."""
    framer = UbxNmeaFramer()
    t0 = time.perf_counter()
    for i in range(0, len(data), 1024):
        framer.feed(data[i : i + 1024])
    framer.finish()
    return time.perf_counter() - t0


@pytest.mark.parametrize("pattern", [
    b"\xb5\x62\x01\x07\x00\x20",  # UBX headers claiming the longest payload, none of them real
    b"\xd3\x03\xff",  # RTCM3 headers claiming 1023 bytes
    b"\xd3\x03\xff\x3e\x90",  # ... with a plausible message number (1001) after the header
])
def test_forged_headers_cost_little_per_byte(pattern: bytes) -> None:
    """Every candidate header is checked against its checksum; that check must cost a few Python passes over each
    byte at most, not a pass over the length each header claims, or 64 kB of forged headers (a minute of a
    9600-baud line) would keep the reader busy for hundreds of times as long as real traffic."""
    data = pattern * (65536 // len(pattern))
    passes = _best_of(_framing, data) / _best_of(_python_pass, data)
    print(f"{pattern.hex()}: {passes:.1f} Python passes per byte")
    assert passes < PASSES_PER_BYTE_MAX, passes


def test_ubx_checksum_matches_pyubx2_on_every_length() -> None:
    from sensors.ublox_frames import ubx_fletcher

    for n in (0, 1, 2, 255, 256, 257, 8191, 8192, 8200):
        body = bytes((i * 37 + 11) % 256 for i in range(n))
        assert ubx_fletcher(body) == ubx_checksum(body), n


def test_real_rtcm3_frames_are_never_refused_and_come_back_after_forged_ones() -> None:
    real = [rtcm_frame(bytes([0x3E, 0xD0]) + bytes([k]) * 1021) for k in range(100)]  # 1005, the longest size
    framer = UbxNmeaFramer()
    assert len(framer.feed(b"".join(real))) == 100 and framer.rtcm3_unchecked == 0
    # After 64 kB of forged headers the budget is spent; real frames that follow are found again, and
    # however the port cuts the stream, the same frames come out.
    stream = b"\xd3\x03\xff" * 40_000 + b"".join(real[:20])
    whole = UbxNmeaFramer()
    got = [f.raw for f in whole.feed(stream)]
    assert whole.rtcm3_unchecked > 0
    assert got[-18:] == real[2:20]  # at most the first two are lost while the budget refills
    cut = UbxNmeaFramer()
    pieces = [f.raw for i in range(0, len(stream), 777) for f in cut.feed(stream[i : i + 777])]
    assert pieces == got and cut.rtcm3_unchecked == whole.rtcm3_unchecked


def test_a_receiver_answering_with_runt_messages_is_refused_not_crashed() -> None:
    """Found by fuzzing: MON-VER and ACK-ACK with a good checksum and no payload made pyubx2 messages without
    their fields, and reading them raised AttributeError out of the set-up (which killed the GNSS thread)."""
    runt_ver, runt_ack = ubx_frame(0x0A, 0x04, b""), ubx_frame(0x05, 0x01, b"")
    port = ReplyingPort([runt_ver, runt_ack] * 10)
    with pytest.raises(SensorError, match="did not answer UBX-MON-VER"):
        configure_receiver(port, sleep=lambda s: None, reply_timeout_s=0.1, poll_s=0.02, tries=2)


# ---- the receiver set-up conversation ------------------------------------------------------------------------

class ReplyingPort(serial.SerialBase):
    """A pyserial port that is never opened: whatever is written, the next scripted reply becomes readable."""

    def __init__(self, replies: list[bytes]) -> None:
        super().__init__(baudrate=9600)
        self.port = "/dev/fuzz"
        self.replies = list(replies)
        self.rx = bytearray()
        self.writes = 0

    @property
    def in_waiting(self) -> int:
        return len(self.rx)

    def read(self, n: int = 1) -> bytes:
        out = bytes(self.rx[:n])
        del self.rx[:n]
        return out

    def write(self, data: bytes) -> int:
        self.writes += 1
        if self.replies:
            self.rx += self.replies.pop(0)
        return len(data)

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        self.rx.clear()


@FUZZ
@given(st.lists(st.lists(st.one_of(ubx_known, st.binary(max_size=40)), max_size=4).map(b"".join), max_size=40))
def test_setup_conversation_with_a_receiver_that_talks_nonsense(replies: list[bytes]) -> None:
    port = ReplyingPort(replies)
    try:
        configure_receiver(port, sleep=lambda s: None, reply_timeout_s=0.1, poll_s=0.02, tries=2)
    except SensorError:
        pass  # refused, silent or broken: each is a readable SensorError
    assert port.writes < 200  # bounded: retries are counted, not endless
