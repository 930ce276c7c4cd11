"""Inter-chip framing (devices/controlbus/frames.py): reference frames, splits, resync, properties."""

from __future__ import annotations

import itertools
from collections.abc import Iterable

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.frames import (
    BOARD_BUFFER,
    FLAG_LONG,
    FLAG_STANDARD,
    MAX_STANDARD_PAYLOAD,
    Dropped,
    Frame,
    FrameDecoder,
    checksum,
    encode_frame,
)

REQUEST_CODES = p.DEFAULT_PROFILE.request_codes
PROPS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
STREAM_PROPS = settings(PROPS, max_examples=80)


def frames_of(items: Iterable[Frame | Dropped]) -> list[Frame]:
    return [f for f in items if isinstance(f, Frame)]


def feed_all(dec: FrameDecoder, chunks: Iterable[bytes]) -> list[Frame]:
    out: list[Frame] = []
    for chunk in chunks:
        out += frames_of(dec.feed(chunk))
        assert dec.buffered <= BOARD_BUFFER
    return out


def flush(dec: FrameDecoder) -> list[Frame]:
    """End of stream: give up on whatever incomplete candidate is left (what a timeout does)."""
    out: list[Frame] = []
    while dec.buffered:
        dec.skip_candidate()
        out += frames_of(dec.frames_from_buffer())
    return out


# --------------------------------------------------------------------------------------------
# The reference's example frames, byte for byte
# --------------------------------------------------------------------------------------------

# (hex, frame, direction's valid codes)
EXAMPLES = [
    ("10 02 F8 30 DA", Frame(0xF8, b"\x30", False), REQUEST_CODES),  # GET_BASE_STATUS, standard
    ("50 02 00 F8 30 9A", Frame(0xF8, b"\x30", True), REQUEST_CODES),  # GET_BASE_STATUS, long
    ("10 03 F8 10 01 FA", Frame(0xF8, b"\x10\x01", False), REQUEST_CODES),  # CONNECT_BASE v1
    ("50 03 00 02 57 05 03", Frame(0x02, b"\x57\x05", True), p.REPLY_CODES),  # OK 87 %, charging on dock
    ("50 03 00 03 00 80 D0", Frame(0x03, b"\x00\x80", True), p.REPLY_CODES),  # ERROR 0x8000
]
EXAMPLE_IDS = ["status-std", "status-long", "connect", "ok-status", "error-8000"]


@pytest.mark.parametrize(("hexstr", "frame", "codes"), EXAMPLES, ids=EXAMPLE_IDS)
def test_example_encode(hexstr: str, frame: Frame, codes: frozenset[int]) -> None:
    wire = bytes.fromhex(hexstr)
    assert frame.encode() == wire
    assert encode_frame(frame.code, frame.payload, long=frame.long) == wire
    assert checksum(wire) == 0


@pytest.mark.parametrize(("hexstr", "frame", "codes"), EXAMPLES, ids=EXAMPLE_IDS)
@pytest.mark.parametrize("filtered", [True, False], ids=["codes", "nofilter"])
def test_example_decode_three_ways(hexstr: str, frame: Frame, codes: frozenset[int], filtered: bool) -> None:
    wire = bytes.fromhex(hexstr)
    valid = codes if filtered else None

    # Whole.
    dec = FrameDecoder(valid)
    assert dec.feed(wire) == [frame]
    assert dec.buffered == 0

    # One byte at a time: nothing until the last byte.
    dec = FrameDecoder(valid)
    for b in wire[:-1]:
        assert dec.feed(bytes((b,))) == []
    assert dec.feed(wire[-1:]) == [frame]
    assert dec.buffered == 0

    # With trailing bytes (the start of the next frame): they stay buffered, and the next frame
    # decodes once its remaining bytes arrive.
    nxt = bytes.fromhex(EXAMPLES[(EXAMPLES.index((hexstr, frame, codes)) + 1) % len(EXAMPLES)][0])
    nxt_frame = FrameDecoder().feed(nxt)
    for cut in range(1, len(nxt)):
        dec = FrameDecoder(None)
        assert dec.feed(wire + nxt[:cut]) == [frame]
        assert dec.buffered == cut
        assert dec.feed(nxt[cut:]) == nxt_frame
        assert dec.buffered == 0
        assert dec.stats.frames == 2
        assert dec.stats.dropped == 0 and dec.stats.garbage_bytes == 0


def test_example_typed_meaning() -> None:
    assert p.decode_request(Frame(0xF8, b"\x30")) == p.GetBaseStatus()
    assert p.decode_request(Frame(0xF8, b"\x30", True)) == p.GetBaseStatus()
    assert p.decode_request(Frame(0xF8, b"\x10\x01")) == p.ConnectBase(1)
    status = p.decode_reply(Frame(0x02, b"\x57\x05", True), p.BaseStatus)
    assert status == p.BaseStatus(87, 0x05)
    assert isinstance(status, p.BaseStatus)
    assert status.charging and status.on_dock and not status.external_power
    assert p.decode_reply(Frame(0x03, b"\x00\x80", True), None) == p.ErrorReply(0x8000)
    assert p.encode_request(p.GetBaseStatus()) == bytes.fromhex("10 02 F8 30 DA")
    assert p.encode_request(p.GetBaseStatus(), p.Profile(long_requests=True)) == bytes.fromhex("50 02 00 F8 30 9A")
    assert p.encode_request(p.ConnectBase(1)) == bytes.fromhex("10 03 F8 10 01 FA")
    assert p.encode_ok(p.BaseStatus(87, 0x05)) == bytes.fromhex("50 03 00 02 57 05 03")
    assert p.encode_error(p.ErrorCode.NOT_SUPPORTED) == bytes.fromhex("50 03 00 03 00 80 D0")


# --------------------------------------------------------------------------------------------
# Standard vs long
# --------------------------------------------------------------------------------------------


def test_standard_and_long_layout() -> None:
    assert encode_frame(0x02, b"") == bytes((FLAG_STANDARD, 1, 0x02, FLAG_STANDARD ^ 1 ^ 2))
    assert encode_frame(0x02, b"", long=True)[:4] == bytes((FLAG_LONG, 1, 0, 0x02))
    # 254 payload bytes still fit a standard frame (length byte 255) ...
    std = encode_frame(0x02, bytes(range(MAX_STANDARD_PAYLOAD)))
    assert std[:3] == bytes((FLAG_STANDARD, 0xFF, 0x02))
    assert len(std) == 2 + 1 + 254 + 1
    # ... 255 force a long one, length little-endian (0x0100).
    lng = encode_frame(0x02, bytes(255))
    assert lng[:4] == bytes((FLAG_LONG, 0x00, 0x01, 0x02))
    assert len(lng) == 3 + 1 + 255 + 1
    for wire in (std, lng):
        assert checksum(wire) == 0
    assert FrameDecoder().feed(std) == [Frame(0x02, bytes(range(254)), False)]
    assert FrameDecoder().feed(lng) == [Frame(0x02, bytes(255), True)]


def test_encode_rejects_non_byte_code() -> None:
    with pytest.raises(ValueError):
        encode_frame(0x100, b"")
    with pytest.raises(ValueError):
        encode_frame(-1, b"")


def test_largest_frame_fits_buffer_and_one_more_does_not() -> None:
    biggest = encode_frame(0x02, bytes(BOARD_BUFFER - 5), long=True)  # 3 head + code + payload + cs
    assert len(biggest) == BOARD_BUFFER
    assert FrameDecoder().feed(biggest) == [Frame(0x02, bytes(BOARD_BUFFER - 5), True)]
    too_big = encode_frame(0x02, bytes(BOARD_BUFFER - 4), long=True)
    dec = FrameDecoder(report_drops=True)
    out = dec.feed(too_big)
    assert out[0] == Dropped("too_long", 1)
    assert frames_of(out) == []
    assert dec.stats.bad_length == 1


# --------------------------------------------------------------------------------------------
# Resynchronisation
# --------------------------------------------------------------------------------------------

GOOD = bytes.fromhex("50 03 00 02 57 05 03")
GOOD_FRAME = Frame(0x02, b"\x57\x05", True)


@pytest.mark.parametrize("codes", [p.REPLY_CODES, None], ids=["codes", "nofilter"])
def test_garbage_before(codes: frozenset[int] | None) -> None:
    dec = FrameDecoder(codes, report_drops=True)
    out = dec.feed(b"\x00\xff\x42\x99" + GOOD)
    assert out == [Dropped("garbage", 4), GOOD_FRAME]
    assert dec.stats.garbage_bytes == 4 and dec.stats.frames == 1


@pytest.mark.parametrize("codes", [p.REPLY_CODES, None], ids=["codes", "nofilter"])
def test_bad_checksum_then_good(codes: frozenset[int] | None) -> None:
    bad = bytearray(GOOD)
    bad[-1] ^= 0x01
    dec = FrameDecoder(codes, report_drops=True)
    out = dec.feed(bytes(bad) + GOOD)
    assert frames_of(out) == [GOOD_FRAME]
    assert out[0] == Dropped("checksum", 1)
    assert dec.stats.bad_checksum == 1
    assert dec.buffered == 0


@pytest.mark.parametrize("codes", [p.REPLY_CODES, None], ids=["codes", "nofilter"])
def test_truncated_then_good(codes: frozenset[int] | None) -> None:
    dec = FrameDecoder(codes)
    assert frames_of(dec.feed(GOOD[:5] + GOOD)) == [GOOD_FRAME]
    assert dec.stats.bad_checksum == 1
    assert dec.buffered == 0


@pytest.mark.parametrize("cut", range(1, len(GOOD)))
def test_every_truncation_then_good(cut: int) -> None:
    # A truncated frame may claim bytes of the next one; it is then rejected on its checksum
    # (the good frame decodes at once) or, if it waits for more, a timeout's skip releases it.
    for codes in (p.REPLY_CODES, None):
        dec = FrameDecoder(codes)
        got = frames_of(dec.feed(GOOD[:cut] + GOOD)) + flush(dec)
        assert got == [GOOD_FRAME]


@pytest.mark.parametrize("codes", [p.REPLY_CODES, None], ids=["codes", "nofilter"])
def test_over_long_length_then_good(codes: frozenset[int] | None) -> None:
    # A long frame claiming 0xFFFF bytes (and one just over the buffer): refused at once, not awaited.
    for length in (0xFFFF, BOARD_BUFFER - 3):
        head = bytes((FLAG_LONG, length & 0xFF, length >> 8, 0x02))
        dec = FrameDecoder(codes, report_drops=True)
        out = dec.feed(head + GOOD)
        assert out[0] == Dropped("too_long", 1)
        assert frames_of(out) == [GOOD_FRAME]
        assert dec.stats.bad_length == 1
        assert dec.buffered == 0


def test_zero_length_is_dropped() -> None:
    dec = FrameDecoder(None, report_drops=True)
    out = dec.feed(b"\x10\x00\xaa" + GOOD)
    assert out[0] == Dropped("zero_length", 1)
    assert frames_of(out) == [GOOD_FRAME]


def test_bad_code_rejected_before_length_is_awaited() -> None:
    # 0x77 is no response code: the master's decoder drops the candidate without waiting for
    # the 0x1F0 bytes it claims; an unfiltered decoder has to wait.
    false_start = bytes((FLAG_LONG, 0xF0, 0x01, 0x77))
    dec = FrameDecoder(p.REPLY_CODES, report_drops=True)
    out = dec.feed(false_start + GOOD)
    assert out[0] == Dropped("bad_code", 1)
    assert frames_of(out) == [GOOD_FRAME]
    dec = FrameDecoder(None)
    assert dec.feed(false_start + GOOD) == []
    assert dec.buffered == len(false_start + GOOD)


def test_skip_candidate_releases_false_start_claiming_long_length() -> None:
    # 50 F0 01 02: a "long OK frame" of 0x1F0 bytes, plausible to the filtered decoder too.
    false_start = bytes((FLAG_LONG, 0xF0, 0x01, 0x02))
    dec = FrameDecoder(p.REPLY_CODES)
    assert dec.feed(false_start + GOOD) == []  # held back behind the false start
    assert dec.buffered == len(false_start) + len(GOOD)
    dec.skip_candidate()
    assert dec.stats.abandoned == 1
    assert frames_of(dec.frames_from_buffer()) == [GOOD_FRAME]
    assert dec.buffered == 0
    # Without the skip the frame is only delayed, not lost: enough bytes settle it.
    dec = FrameDecoder(p.REPLY_CODES)
    assert dec.feed(false_start + GOOD) == []
    filler = bytes(3 + 0x1F0 + 1 - len(false_start) - len(GOOD))  # completes the false candidate
    assert frames_of(dec.feed(filler)) == [GOOD_FRAME]  # 50^F0^01^02 != 0: its checksum fails
    assert dec.stats.bad_checksum == 1
    assert dec.buffered == 0


def test_skip_candidate_on_empty_buffer_is_harmless() -> None:
    dec = FrameDecoder()
    dec.skip_candidate()
    assert dec.stats.abandoned == 0
    assert dec.frames_from_buffer() == []


def test_buffer_never_exceeds_board_buffer_on_flag_floods() -> None:
    dec = FrameDecoder(None)
    # Every byte a flag claiming the largest length that still fits: the worst case for waiting.
    for chunk in (b"\x50\xfb\x01\x02" * 300, b"\x10\xff" * 700, bytes(range(256)) * 5):
        for i in range(0, len(chunk), 97):
            dec.feed(chunk[i : i + 97])
            assert dec.buffered < BOARD_BUFFER


def test_reset_clears_buffer() -> None:
    dec = FrameDecoder()
    dec.feed(GOOD[:4])
    assert dec.buffered == 4
    dec.reset()
    assert dec.buffered == 0
    assert dec.feed(GOOD) == [GOOD_FRAME]


# --------------------------------------------------------------------------------------------
# Properties
# --------------------------------------------------------------------------------------------

codes_st = st.integers(0, 255)
payloads_st = st.binary(max_size=BOARD_BUFFER - 5)  # the largest frame the decoder accepts


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points)]


@PROPS
@given(code=codes_st, payload=payloads_st, long=st.booleans(), cuts=st.lists(st.integers(0, 600), max_size=8))
def test_roundtrip(code: int, payload: bytes, long: bool, cuts: list[int]) -> None:
    wire = encode_frame(code, payload, long=long)
    forced_long = long or len(payload) > MAX_STANDARD_PAYLOAD
    assert wire[0] == (FLAG_LONG if forced_long else FLAG_STANDARD)
    assert len(wire) == (4 if forced_long else 3) + len(payload) + 1
    assert checksum(wire) == 0
    dec = FrameDecoder()
    assert feed_all(dec, chunked(wire, cuts)) == [Frame(code, payload, forced_long)]
    assert dec.buffered == 0


@PROPS
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 3000), max_size=20), filtered=st.booleans())
def test_any_bytes_never_raise(data: bytes, cuts: list[int], filtered: bool) -> None:
    dec = FrameDecoder(p.REPLY_CODES if filtered else None, report_drops=True)
    for chunk in chunked(data, cuts):
        for item in dec.feed(chunk):
            assert isinstance(item, (Frame, Dropped))
        assert dec.buffered < BOARD_BUFFER
    flush(dec)
    assert dec.buffered == 0


reply_frames_st = st.builds(
    Frame,
    st.sampled_from(sorted(p.REPLY_CODES)),
    st.binary(max_size=300),
    st.booleans(),
).map(lambda f: f._replace(long=f.long or len(f.payload) > MAX_STANDARD_PAYLOAD))

# Garbage rich in flag and response-code bytes, so false candidates are common.
FLAGGY_BYTES = st.lists(
    st.one_of(st.sampled_from([FLAG_STANDARD, FLAG_LONG, *sorted(p.REPLY_CODES)]), st.integers(0, 255)), max_size=40
).map(bytes)
NO_FLAG_BYTES = st.binary(max_size=40).map(lambda b: b.replace(b"\x10", b"\x11").replace(b"\x50", b"\x51"))


@STREAM_PROPS
@given(
    frames=st.lists(reply_frames_st, min_size=1, max_size=8),
    garbage=st.lists(NO_FLAG_BYTES, min_size=9, max_size=9),
    cuts=st.lists(st.integers(0, 5000), max_size=30),
)
def test_frames_in_flagless_garbage_all_recovered(frames: list[Frame], garbage: list[bytes], cuts: list[int]) -> None:
    """Garbage without flag bytes cannot start a false candidate: every frame comes out, in order.

    (Frames' own payloads may contain 0x10/0x50 bytes; the decoder never looks inside a frame it
    has accepted, so that does not matter.)
    """
    stream = b"".join(g + f.encode() for g, f in zip(garbage, frames, strict=False)) + garbage[-1]
    dec = FrameDecoder(p.REPLY_CODES)
    got = feed_all(dec, chunked(stream, cuts)) + flush(dec)
    assert got == frames
    assert dec.stats.bad_checksum + dec.stats.bad_length + dec.stats.bad_code == 0


@STREAM_PROPS
@given(
    frames=st.lists(reply_frames_st, min_size=1, max_size=8),
    garbage=st.lists(FLAGGY_BYTES, min_size=9, max_size=9),
    cuts=st.lists(st.integers(0, 5000), max_size=30),
)
def test_frames_in_random_garbage(frames: list[Frame], garbage: list[bytes], cuts: list[int]) -> None:
    """Arbitrary garbage may contain flag bytes that start false candidates.

    A false candidate that fails its length, code or checksum check costs one byte and the scan
    resumes right after its flag, so it can never skip the start of a real frame. The only way a
    real frame is lost is when a false candidate passes all checks (its XOR happens to be 0,
    about 1 in 256 of the false candidates that reach the checksum) and is *delivered*, jumping
    over the real frame's first byte. So the sound property is: the real frames are recovered
    in order, and if any is missing, a spurious frame was delivered (which, with the code filter
    and hypothesis-sized garbage, is rare).
    """
    stream = b"".join(g + f.encode() for g, f in zip(garbage, frames, strict=False)) + garbage[-1]
    dec = FrameDecoder(p.REPLY_CODES)
    got = feed_all(dec, chunked(stream, cuts)) + flush(dec)
    matched, spurious, i = 0, 0, 0
    for f in got:
        j = i
        while j < len(frames) and frames[j] != f:
            j += 1
        if j < len(frames):
            matched += 1
            i = j + 1
        else:
            spurious += 1
    assert matched == len(frames) or spurious > 0
    if spurious == 0:
        assert got == frames


def test_valid_codes_can_change_between_feeds() -> None:
    # The decoder caches a 256-entry table of valid codes; replacing valid_codes must take effect.
    odd = encode_frame(0x77, b"\x01")
    dec = FrameDecoder(None)
    assert dec.feed(odd) == [Frame(0x77, b"\x01")]
    dec.valid_codes = p.REPLY_CODES
    assert dec.feed(odd) == []
    assert dec.stats.bad_code == 1
    dec.valid_codes = frozenset({0x77})
    assert dec.feed(odd) == [Frame(0x77, b"\x01")]


def test_frames_built_by_the_decoder_are_frames() -> None:
    dec = FrameDecoder(p.REPLY_CODES, report_drops=True)
    out = dec.feed(b"\x99" + GOOD + GOOD[:-1] + b"\x00" + GOOD)  # garbage, frame, bad checksum, frame
    assert out == [Dropped("garbage", 1), GOOD_FRAME, Dropped("checksum", 1), Dropped("garbage", 6), GOOD_FRAME]
    assert [type(x) for x in out] == [Dropped, Frame, Dropped, Dropped, Frame]
    assert out[1] == GOOD_FRAME and out[1].code == 0x02 and out[1].payload == b"\x57\x05" and out[1].long
    assert out[1].encode() == GOOD
    assert dec.stats.frames == 2
