"""The RPLIDAR codec (devices.rplidar.protocol): encoders, the master's decoder, revolutions, requests.

Every stream is fed three ways (h11's habit): whole, one byte at a time, and with trailing bytes
that must stay buffered. Hypothesis checks the decoder never raises and resynchronises.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetlink.devices.rplidar import protocol as lp

# -- helpers ------------------------------------------------------------------------------------


def whole(dec: lp.LidarDecoder, data: bytes) -> list[lp.Event]:
    return dec.feed(data)


def bytewise(dec: lp.LidarDecoder, data: bytes) -> list[lp.Event]:
    out: list[lp.Event] = []
    for i in range(len(data)):
        out += dec.feed(data[i : i + 1])
    return out


def chunked(dec: lp.LidarDecoder, data: bytes) -> list[lp.Event]:
    out: list[lp.Event] = []
    for i in range(0, len(data), 7):
        out += dec.feed(data[i : i + 7])
    return out


FEEDERS: list[Callable[[lp.LidarDecoder, bytes], list[lp.Event]]] = [whole, bytewise, chunked]


def nodes_of(events: list[lp.Event]) -> list[lp.Node]:
    out: list[lp.Node] = []
    for ev in events:
        if isinstance(ev, lp.Node):
            out.append(ev)
        elif isinstance(ev, lp.NodeBatch):
            out += ev.nodes()
    return out


def realistic_turn(seed: int, n: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wire-order nodes of a plausible turn: increasing angles, room-like distances, some no-returns."""
    rng = np.random.default_rng(seed)
    ang = (np.arange(n) * 360.0 / n + rng.uniform(0, 360.0 / n)) % 360.0
    dist = np.round(rng.uniform(0.15, 8.0, n) * 4000) / 4000
    dist[rng.random(n) < 0.05] = 0.0
    q = np.where(dist > 0, rng.integers(10, 64, n), 0)
    return ang, dist, q


def expected_nodes(ang: np.ndarray, dist: np.ndarray, q: np.ndarray) -> list[tuple[bool, int, float, float]]:
    q6 = np.rint(ang * 64) % (360 * 64)
    return [(i == 0, int(q[i]), q6[i] / 64, dist[i]) for i in range(ang.size)]


def as_tuples(nodes: list[lp.Node]) -> list[tuple[bool, int, float, float]]:
    return [(n.start, n.quality, n.angle_deg, n.distance_m) for n in nodes]


# -- encoders -----------------------------------------------------------------------------------


def test_request_bytes() -> None:
    assert lp.encode_request(lp.Command.STOP) == bytes.fromhex("A525")
    assert lp.encode_request(lp.Command.RESET) == bytes.fromhex("A540")
    assert lp.encode_request(lp.Command.SCAN) == bytes.fromhex("A520")
    assert lp.encode_request(lp.Command.GET_INFO) == bytes.fromhex("A550")
    assert lp.encode_request(lp.Command.GET_HEALTH) == bytes.fromhex("A552")
    # SET_MOTOR_PWM 660: size 2, payload 94 02, checksum = XOR of A5 F0 02 94 02
    assert lp.encode_request(lp.Command.SET_MOTOR_PWM, (660).to_bytes(2, "little")) == bytes.fromhex("A5F0029402C1")
    assert lp.encode_request(0x82, bytes(5)) == bytes.fromhex("A582050000000000") + bytes((0xA5 ^ 0x82 ^ 0x05,))


def test_request_encoding_errors() -> None:
    with pytest.raises(ValueError):
        lp.encode_request(lp.Command.SCAN, b"\x01")  # no payload without bit 0x80
    with pytest.raises(ValueError):
        lp.encode_request(0x1FF)
    with pytest.raises(ValueError):
        lp.encode_request(0xF0, bytes(256))


def test_descriptor_bytes() -> None:
    assert lp.SCAN_DESCRIPTOR.encode() == bytes.fromhex("A55A0500004081")
    assert lp.encode_descriptor(20, 0, 0x04) == bytes.fromhex("A55A1400000004")
    assert lp.encode_descriptor(3, 0, 0x06) == bytes.fromhex("A55A0300000006")


def test_node_bytes() -> None:
    # start node, quality 15, 90.0 degrees, 1.5 m (the example in docs/protocols/rplidar.md)
    b = lp.encode_node(True, 15, 90.0, 1.5)
    assert b == bytes.fromhex("3D012D7017")
    assert b[0] == (15 << 2) | 0b01
    assert int.from_bytes(b[1:3], "little") == (90 * 64) << 1 | 1
    assert int.from_bytes(b[3:5], "little") == 6000
    b = lp.encode_node(False, 63, 359.99, 0.0)
    assert b[0] == (63 << 2) | 0b10
    assert int.from_bytes(b[1:3], "little") >> 1 == round(359.99 * 64)
    assert lp.encode_node(False, 0, 360.0, 0.0)[1:3] == bytes((1, 0))  # 360 wraps to 0


def test_angle_conventions_round_trip() -> None:
    rad = np.array([0.0, 0.1, math.pi / 2, math.pi, 6.0])
    deg = lp.rad_to_device_deg(rad)
    assert deg[2] == pytest.approx(270.0)  # 90 deg counter-clockwise is 270 clockwise
    np.testing.assert_allclose(lp.device_deg_to_rad(deg), rad, atol=1e-12)


# -- answers, three ways ------------------------------------------------------------------------


INFO = lp.DeviceInfo(0x18, (1, 29), 7, bytes(range(16)))
HEALTH = lp.DeviceHealth(lp.HEALTH_WARNING, 0x1234)
RATE = lp.SampleRate(125, 63)
ANSWERS = (
    lp.encode_descriptor(20, 0, lp.AnswerType.DEVICE_INFO)
    + lp.encode_device_info(INFO)
    + lp.encode_descriptor(3, 0, lp.AnswerType.DEVICE_HEALTH)
    + lp.encode_health(HEALTH)
    + lp.encode_descriptor(4, 0, lp.AnswerType.SAMPLE_RATE)
    + lp.encode_samplerate(RATE)
)


@pytest.mark.parametrize("feed", FEEDERS)
def test_single_answers(feed: Callable[[lp.LidarDecoder, bytes], list[lp.Event]]) -> None:
    dec = lp.LidarDecoder()
    events = feed(dec, ANSWERS)
    assert events == [
        lp.Descriptor(20, 0, 4),
        INFO,
        lp.Descriptor(3, 0, 6),
        HEALTH,
        lp.Descriptor(4, 0, 0x15),
        RATE,
    ]
    assert dec.buffered == 0 and dec.state == "idle"
    assert INFO.firmware_str == "1.29" and INFO.serial_hex.startswith("000102")
    assert not HEALTH.ok and HEALTH.status_name == "warning"


def test_single_answers_with_trailing_bytes() -> None:
    dec = lp.LidarDecoder()
    tail = lp.encode_descriptor(20, 0, 4) + lp.encode_device_info(INFO)[:11]
    events = dec.feed(ANSWERS + tail)
    assert len(events) == 7 and events[-1] == lp.Descriptor(20, 0, 4)
    assert dec.buffered == 11 and dec.state == "answer"
    assert dec.feed(lp.encode_device_info(INFO)[11:]) == [INFO]


def test_garbage_before_descriptor_and_wrong_size() -> None:
    dec = lp.LidarDecoder()
    data = b"\x00\xa5\x11junk" + lp.encode_descriptor(2, 0, lp.AnswerType.DEVICE_HEALTH) + b"\x01\x02"
    events = dec.feed(data)
    assert events == [lp.Descriptor(2, 0, 6), lp.Response(6, b"\x01\x02")]
    assert dec.stats.garbage_bytes == 7 and dec.stats.wrong_size == 1


def test_false_descriptor_is_skipped() -> None:
    dec = lp.LidarDecoder()
    bogus = bytes.fromhex("A55AFFFFFFFF81")  # size over MAX_ANSWER, reserved mode
    events = dec.feed(bogus + ANSWERS[:27])
    assert events == [lp.Descriptor(20, 0, 4), INFO]
    assert dec.stats.bad_descriptors == 1


def test_trailing_sync_byte_is_kept() -> None:
    dec = lp.LidarDecoder()
    assert dec.feed(b"xyz\xa5") == []
    assert dec.buffered == 1
    assert dec.feed(ANSWERS[1:27]) == [lp.Descriptor(20, 0, 4), INFO]


# -- nodes, three ways --------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [False, True])
@pytest.mark.parametrize("feed", FEEDERS)
def test_scan_stream(feed: Callable[[lp.LidarDecoder, bytes], list[lp.Event]], batch: bool) -> None:
    ang, dist, q = realistic_turn(1, 300)
    stream = lp.SCAN_DESCRIPTOR.encode() + lp.encode_nodes(ang, dist, q) + lp.encode_nodes(ang, dist, q)
    dec = lp.LidarDecoder(batch=batch)
    events = feed(dec, stream + b"\x3e\x01")  # a trailing partial node stays buffered
    assert events[0] == lp.SCAN_DESCRIPTOR
    nodes = nodes_of(events[1:])
    assert as_tuples(nodes) == expected_nodes(ang, dist, q) * 2
    assert dec.buffered == 2 and dec.state == "stream"
    assert dec.stats.resync_bytes == 0 and dec.stats.nodes == 600


def test_descriptor_after_stream_is_found() -> None:
    """STOP then GET_HEALTH without a decoder reset: the descriptor is picked out of the stream."""
    ang, dist, q = realistic_turn(2, 50)
    dec = lp.LidarDecoder()
    stream = lp.SCAN_DESCRIPTOR.encode() + lp.encode_nodes(ang, dist, q)
    stream += lp.encode_descriptor(3, 0, 6) + lp.encode_health(HEALTH)
    events = dec.feed(stream)
    assert events[-2:] == [lp.Descriptor(3, 0, 6), HEALTH]
    assert dec.state == "idle"


def test_assume_joins_a_running_stream() -> None:
    ang, dist, q = realistic_turn(3, 20)
    dec = lp.LidarDecoder()
    dec.assume(lp.SCAN_DESCRIPTOR)
    assert as_tuples(nodes_of(dec.feed(lp.encode_nodes(ang, dist, q)))) == expected_nodes(ang, dist, q)


def test_other_streams_are_cut_into_responses() -> None:
    # 0x84: ultra capsules (A2/A3 boost modes), which fleetlink does not interpret
    dec = lp.LidarDecoder()
    events = dec.feed(lp.encode_descriptor(132, 1, 0x84) + bytes(range(132)) * 2 + b"\x00")
    assert events[1:] == [lp.Response(0x84, bytes(range(132)))] * 2
    assert dec.buffered == 1


def test_out_of_step_nodes_are_skipped_bytewise() -> None:
    dec = lp.LidarDecoder()
    dec.assume(lp.SCAN_DESCRIPTOR)
    good = lp.encode_node(False, 20, 10.0, 1.0)
    bad_s = bytes((0b11,)) + good[1:]  # S and !S agree
    bad_check = good[:1] + bytes((good[1] & 0xFE,)) + good[2:]  # check bit 0
    # A byte-offset read between them may pass the check bits; the in-step run after it must
    # still come through whole (angle continuity lets a run of RESYNC_RUN nodes re-anchor).
    run = b"".join(lp.encode_node(False, 20, 10.0 + 0.5 * i, 1.0) for i in range(lp.RESYNC_RUN))
    nodes = nodes_of(dec.feed(bad_s + bad_check + run))
    want = [(False, 20, 10.0 + 0.5 * i, 1.0) for i in range(lp.RESYNC_RUN)]
    assert as_tuples(nodes)[-lp.RESYNC_RUN :] == want
    assert dec.stats.resync_bytes >= 2


# -- fuzz ---------------------------------------------------------------------------------------

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(st.binary(max_size=600), st.integers(1, 40), st.sampled_from(["idle", "stream", "answer"]), st.booleans())
def test_decoder_never_raises(data: bytes, chunk: int, start: str, batch: bool) -> None:
    dec = lp.LidarDecoder(batch=batch)
    if start == "stream":
        dec.assume(lp.SCAN_DESCRIPTOR)
    elif start == "answer":
        dec.assume(lp.Descriptor(20, 0, 4))
    for i in range(0, len(data), chunk):
        dec.feed(data[i : i + chunk])
        assert dec.buffered <= lp.MAX_ANSWER + lp.DESCRIPTOR_LEN
    asm = lp.RevolutionAssembler(max_nodes=64)
    dec2 = lp.LidarDecoder(batch=batch)
    dec2.assume(lp.SCAN_DESCRIPTOR)
    asm.push_all(dec2.feed(data))


@SETTINGS
@given(st.binary(max_size=200), st.integers(0, 10_000), st.booleans())
def test_nodes_after_garbage_are_recovered(garbage: bytes, seed: int, batch: bool) -> None:
    ang, dist, q = realistic_turn(seed, 200)
    dec = lp.LidarDecoder(batch=batch)
    dec.assume(lp.SCAN_DESCRIPTOR)
    nodes = nodes_of(dec.feed(garbage + lp.encode_nodes(ang, dist, q)))
    want = expected_nodes(ang, dist, q)
    # Garbage may leave the decoder out of step for a few nodes; it is back in step long before the end.
    assert as_tuples(nodes[-150:]) == want[-150:]


@SETTINGS
@given(st.integers(0, 10_000), st.integers(5, 1900))
def test_lost_byte_resynchronises_within_a_few_nodes(seed: int, cut: int) -> None:
    ang, dist, q = realistic_turn(seed, 400)
    stream = lp.encode_nodes(ang, dist, q)
    damaged = stream[:cut] + stream[cut + 1 :]
    dec = lp.LidarDecoder(batch=True)
    dec.assume(lp.SCAN_DESCRIPTOR)
    got = as_tuples(nodes_of(dec.feed(damaged)))
    want = expected_nodes(ang, dist, q)
    hit = cut // lp.NODE_LEN  # the node that lost a byte
    assert got[:hit] == want[:hit]
    # Back in step within a few nodes: the decoded tail equals the original tail.
    tail = len(want) - hit - 8
    if tail > 0:
        assert got[-tail:] == want[-tail:]
    assert len(got) >= len(want) - 9


# -- revolutions --------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [False, True])
def test_revolutions_are_assembled_between_start_flags(batch: bool) -> None:
    ang, dist, q = realistic_turn(5, 100)
    partial = lp.encode_nodes(ang[60:], dist[60:], q[60:], start_first=False)  # the tail of a turn
    turn = lp.encode_nodes(ang, dist, q)
    dec = lp.LidarDecoder(batch=batch)
    dec.assume(lp.SCAN_DESCRIPTOR)
    asm = lp.RevolutionAssembler()
    revs: list[lp.Revolution] = []
    stream = partial + turn * 3
    for i in range(0, len(stream), 33):
        revs += asm.push_all(dec.feed(stream[i : i + 33]))
    assert len(revs) == 2  # the third turn completes only when a fourth starts
    assert asm.stats.orphan_nodes == 40 and asm.partial == 100
    rev = revs[0]
    assert len(rev) == 100
    assert np.all(np.diff(rev.angles_rad) >= 0) and rev.angles_rad.min() >= 0 and rev.angles_rad.max() < 2 * math.pi
    q6 = np.rint(ang * 64) % (360 * 64)
    order = np.argsort(lp.device_deg_to_rad(q6 / 64), kind="stable")
    np.testing.assert_allclose(rev.distances_m, dist[order])
    np.testing.assert_array_equal(rev.qualities, q[order])
    assert rev.points().shape == (int(np.count_nonzero(dist)), 2)


def test_assembler_caps_a_turn_without_start_flags() -> None:
    asm = lp.RevolutionAssembler(max_nodes=10)
    asm.push(lp.Node(True, 10, 0.0, 1.0))
    for i in range(30):
        asm.push(lp.Node(False, 10, i * 12.0, 1.0))
    assert asm.partial == 10 and asm.stats.overflow_nodes == 21
    (rev,) = asm.push(lp.Node(True, 10, 0.0, 1.0))
    assert len(rev) == 10


@pytest.mark.parametrize("batch", [False, True])
def test_false_start_flags_do_not_split_a_turn(batch: bool) -> None:
    """A node decoded out of step may carry a start flag mid-turn; only a wrapping angle starts a turn."""
    ang, dist, q = realistic_turn(9, 100)
    turn = lp.encode_nodes(ang, dist, q)
    # A start flag mid-turn on a node whose angle does continue the turn (so angle continuity in
    # the decoder lets it through and only the assembler's wrap check can catch it).
    mid = lp.LidarDecoder()
    mid.assume(lp.SCAN_DESCRIPTOR)
    prev_deg = nodes_of(mid.feed(turn[245:250]))[0].angle_deg
    bogus = lp.encode_node(True, 5, prev_deg + 0.5, 1.0)
    stream = turn + turn[:250] + bogus + turn[250:] + turn
    results = {}
    for check in (True, False):
        dec = lp.LidarDecoder(batch=batch)
        dec.assume(lp.SCAN_DESCRIPTOR)
        asm = lp.RevolutionAssembler(check_wrap=check)
        results[check] = [len(r) for r in asm.push_all(dec.feed(stream))], asm.stats.false_starts
    assert results[True] == ([100, 101], 1)
    assert results[False] == ([100, 50, 51], 0)


# -- requests (the lidar's side) -----------------------------------------------------------------


def test_request_decoder() -> None:
    reqs = (
        lp.encode_request(lp.Command.STOP)
        + b"\x00\x13"
        + lp.encode_request(lp.Command.SET_MOTOR_PWM, b"\x94\x02")
        + bytes.fromhex("A5F0029402C2")  # bad checksum: dropped
        + lp.encode_request(lp.Command.SCAN)
    )
    for chunks in ([reqs], [reqs[i : i + 1] for i in range(len(reqs))]):
        dec = lp.RequestDecoder()
        got = [r for c in chunks for r in dec.feed(c)]
        assert got == [lp.Request(0x25), lp.Request(0xF0, b"\x94\x02"), lp.Request(0x20)]
        assert dec.stats.bad_checksum == 1 and dec.buffered == 0
    assert lp.split_requests([reqs[:3], reqs[3:]])[0] == lp.Request(0x25)


@SETTINGS
@given(st.binary(max_size=400))
def test_request_decoder_never_raises(data: bytes) -> None:
    dec = lp.RequestDecoder()
    dec.feed(data)
    assert dec.buffered <= 3 + 255 + 1


# -- GET_LIDAR_CONF ---------------------------------------------------------------------------------


def test_conf_request_bytes_and_parsing() -> None:
    # type 0x70 (count), no mode: A5 84 04 70 00 00 00 cs
    req = lp.encode_conf_request(lp.ConfType.SCAN_MODE_COUNT)
    assert req[:7] == bytes.fromhex("A58404700000 00".replace(" ", "")) and lp.checksum(req) == 0
    # the examples in docs/protocols/rplidar.md
    assert lp.encode_conf_request(lp.ConfType.SCAN_MODE_TYPICAL) == bytes.fromhex("A5 84 04 7C 00 00 00 59")
    assert lp.encode_conf_request(lp.ConfType.SCAN_MODE_NAME, 1) == bytes.fromhex("A5 84 06 7F 00 00 00 01 00 59")
    # per-mode entries carry the mode id as a u16 after the u32 type
    req = lp.encode_conf_request(lp.ConfType.SCAN_MODE_NAME, 1)
    assert req[2] == 6 and req[3:9] == bytes.fromhex("7F0000000100")
    assert lp.split_requests([req]) == [lp.Request(0x84, bytes.fromhex("7F0000000100"))]
    assert lp.parse_conf_request(bytes.fromhex("7F0000000100")) == (0x7F, 1)
    assert lp.parse_conf_request(bytes.fromhex("7C000000")) == (0x7C, None)
    assert lp.parse_conf_request(b"\x70\x00") is None


CONF_ANSWERS = (
    lp.encode_lidar_conf(lp.ConfType.SCAN_MODE_COUNT, (2).to_bytes(2, "little"))
    + lp.encode_lidar_conf(lp.ConfType.SCAN_MODE_US_PER_SAMPLE, (64000).to_bytes(4, "little"))
    + lp.encode_lidar_conf(lp.ConfType.SCAN_MODE_NAME, b"Express\x00")
)


@pytest.mark.parametrize("feed", FEEDERS)
def test_conf_answers(feed: Callable[[lp.LidarDecoder, bytes], list[lp.Event]]) -> None:
    dec = lp.LidarDecoder()
    events = [
        e for e in feed(dec, CONF_ANSWERS + lp.encode_descriptor(6, 0, 0x20) + b"\x70") if isinstance(e, lp.LidarConf)
    ]
    count, us, name = events
    assert count == lp.LidarConf(0x70, b"\x02\x00") and count.u16() == 2
    assert us.q8() == 250.0  # the protocol's own example: 64000 / 256 = 250 microseconds
    assert name.text() == "Express"
    assert dec.buffered == 1 and dec.state == "answer"  # a trailing partial answer waits
    with pytest.raises(ValueError, match="need 4"):
        count.u32()


def test_conf_answer_too_short_for_its_type() -> None:
    dec = lp.LidarDecoder()
    events = dec.feed(lp.encode_descriptor(2, 0, 0x20) + b"\x70\x00")
    assert events[1:] == [lp.Response(0x20, b"\x70\x00")] and dec.stats.wrong_size == 1


# -- express scan capsules --------------------------------------------------------------------------


def test_express_request_bytes() -> None:
    # the legacy express scan as SLAMTEC documents it: working mode 0, four reserved bytes
    assert lp.encode_express_request(0) == bytes.fromhex("A5820500000000 0022".replace(" ", ""))
    assert lp.encode_express_request(1)[3] == 1
    assert lp.EXPRESS_DESCRIPTOR.encode() == bytes.fromhex("A55A5400004082")


def capsule_stream(turns: int = 3, n: int = 800, chunk: int = 37) -> tuple[bytes, np.ndarray, np.ndarray]:
    """A device-side capsule stream of ``turns`` evenly sampled turns (wire q6 angles, distances)."""
    step = 360 * 64 / n
    enc = lp.CapsuleEncoder(step)
    q6 = np.rint(np.arange(n) * step).astype(np.int64) % (360 * 64)
    dist = np.round(1.0 + 0.5 * np.sin(np.arange(n) / 40.0), 3)
    dist[::97] = 0.0  # some no-returns
    out = b""
    for _ in range(turns):
        for i in range(0, n, chunk):
            j = min(n, i + chunk)
            out += enc.push(q6[i:j], dist[i:j], new_turn=i == 0, next_q6=int(q6[j]) if j < n else None)
    return out, q6, dist


def test_capsule_bytes() -> None:
    stream, _, dist = capsule_stream(1)
    cap = stream[:84]
    assert cap[0] >> 4 == 0xA and cap[1] >> 4 == 0x5
    assert lp.checksum(cap[2:]) == (cap[0] & 0xF) | ((cap[1] & 0xF) << 4)
    start = int.from_bytes(cap[2:4], "little")
    assert start & 0x8000  # the first capsule of a scan session
    assert int.from_bytes(stream[84 + 2 : 84 + 4], "little") & 0x8000 == 0
    # cabin 0: distance in whole mm above two offset bits
    assert int.from_bytes(cap[4:6], "little") >> 2 == round(dist[0] * 1000)
    assert len(stream) == 84 * (800 // 32)


def test_capsule_encoder_does_not_depend_on_chunking() -> None:
    assert capsule_stream(2, chunk=1)[0] == capsule_stream(2, chunk=37)[0] == capsule_stream(2, chunk=800)[0]


@pytest.mark.parametrize("feed", FEEDERS)
def test_capsule_stream_decodes_to_the_samples(feed: Callable[[lp.LidarDecoder, bytes], list[lp.Event]]) -> None:
    stream, q6, dist = capsule_stream(3)
    dec = lp.LidarDecoder(batch=True)
    events = feed(dec, lp.EXPRESS_DESCRIPTOR.encode() + stream + stream[:50])  # a partial capsule trails
    assert events[0] == lp.EXPRESS_DESCRIPTOR
    nodes = nodes_of(events[1:])
    # each capsule is decoded once the next one has come: all but the last full one
    assert len(nodes) == 3 * 800 - 32 and dec.stats.capsules == 75
    assert dec.buffered == 50 and dec.state == "stream"
    want_a = np.tile(q6 / 64, 3)[: len(nodes)]
    want_d = np.tile(dist, 3)[: len(nodes)]
    got_a = np.array([n.angle_deg for n in nodes])
    assert np.abs((got_a - want_a + 180) % 360 - 180).max() <= 2 / 64
    np.testing.assert_allclose([n.distance_m for n in nodes], want_d, atol=1e-9)
    assert all(n.quality == (47 if n.distance_m else 0) for n in nodes)
    assert [i for i, n in enumerate(nodes) if n.start] == [800, 1600]  # where the angle wraps
    revs = lp.RevolutionAssembler().push_all(events)
    assert [len(r) for r in revs] == [800]  # the turn between the two wraps


def test_bad_capsules_are_dropped_and_counted() -> None:
    stream, _, _ = capsule_stream(3)
    bad = bytearray(stream)
    bad[84 * 5 + 40] ^= 0x10  # a payload bit: the checksum fails
    bad[84 * 20] = 0x00  # a sync nibble
    bad[84 * 30 + 1] = 0xF5  # the other one
    dec = lp.LidarDecoder(batch=True)
    dec.assume(lp.EXPRESS_DESCRIPTOR)
    nodes = nodes_of(dec.feed(bytes(bad)))
    assert dec.stats.bad_capsules >= 1 and dec.stats.resync_bytes >= 84
    # the three damaged capsules and the three before them (no successor to interpolate to) are lost
    assert dec.stats.capsules == 75 - 3
    assert len(nodes) == 3 * 800 - 32 - 6 * 32
    ok = lp.LidarDecoder(batch=True)
    ok.assume(lp.EXPRESS_DESCRIPTOR)
    good = {(round(n.angle_deg * 64), n.distance_m) for n in nodes_of(ok.feed(stream))}
    assert {(round(n.angle_deg * 64), n.distance_m) for n in nodes} <= good  # nothing invented


def test_capsule_stream_lost_byte_and_descriptor_after_it() -> None:
    """A lost byte costs the capsules around it; a new scan's descriptor (STOP and EXPRESS_SCAN again
    without the decoder being told) is found once a capsule's worth of bytes has followed it."""
    stream, _, _ = capsule_stream(2)
    cut = stream[: 84 * 10 + 7] + stream[84 * 10 + 8 :]  # one byte lost in capsule 10
    dec = lp.LidarDecoder(batch=True)
    dec.assume(lp.EXPRESS_DESCRIPTOR)
    events = dec.feed(cut + lp.EXPRESS_DESCRIPTOR.encode() + stream[: 84 * 3])
    i = events.index(lp.EXPRESS_DESCRIPTOR)
    assert len(nodes_of(events[:i])) == 2 * 800 - 32 - 2 * 32
    assert len(nodes_of(events[i + 1 :])) == 2 * 32 and dec.stats.descriptors == 1


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=600), st.integers(1, 90))
def test_capsule_decoder_never_raises(data: bytes, chunk: int) -> None:
    stream, _, _ = capsule_stream(1)
    dec = lp.LidarDecoder(batch=True)
    dec.assume(lp.EXPRESS_DESCRIPTOR)
    mixed = stream[:300] + data + stream[300:]
    for i in range(0, len(mixed), chunk):
        dec.feed(mixed[i : i + chunk])
    assert dec.buffered <= lp.MAX_ANSWER


@settings(max_examples=100)
@given(st.integers(0, 23039), st.floats(1.0, 100.0), st.integers(0, 2**32 - 1), st.booleans())
def test_capsule_encoders_agree(start: int, step: float, seed: int, new_scan: bool) -> None:
    """The plain-Python encoder (a step's one or two capsules) and the NumPy one make the same bytes."""
    rng = np.random.default_rng(seed)
    t = [round(start - 100 + j * step + float(rng.uniform(-30, 30))) % 23040 for j in range(32)]
    nxt = round(start + 32 * step) % 23040
    d = rng.uniform(0, 20, 32).tolist()
    assert lp._encode_capsule(start, nxt, t, d, new_scan) == lp.encode_capsules([start], [nxt], t, d, new_scan)
