"""Typed Control Bus messages (devices/controlbus/protocol.py) and the simulated board's answers."""

from __future__ import annotations

import math
import struct
import typing

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.frames import Frame, FrameDecoder, checksum, encode_frame
from fleetlink.field.board import BoardConfig, SimulatedBoard
from tests.test_board_link import COMMANDS

PROPS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

REPLY_TYPES: tuple[type, ...] = typing.get_args(p.Reply)

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFF_FFFF)
s32 = st.integers(-0x8000_0000, 0x7FFF_FFFF)
ascii_text = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=12)


def q16(n: int) -> float:
    return n / 65536.0  # exactly representable: the wire value survives the round trip


def mm(n: int) -> float:
    return n / 1000  # the decoder computes the same expression, so equality is exact


# One strategy per request class, with values that the wire carries exactly.
REQUEST_STRATEGIES: dict[type, st.SearchStrategy[typing.Any]] = {
    p.ConnectBase: st.builds(p.ConnectBase, u8),
    p.GetBaseConf: st.just(p.GetBaseConf()),
    p.GetBinaryConf: st.just(p.GetBinaryConf()),
    p.GetBaseStatus: st.just(p.GetBaseStatus()),
    p.GetMotorData: st.just(p.GetMotorData()),
    p.GetSensorData: st.just(p.GetSensorData()),
    p.GetBumperData: st.just(p.GetBumperData()),
    p.GetAutoHomeData: st.builds(p.GetAutoHomeData, u8),
    p.SetBaseMotor: st.tuples(s32, s32, s32, s32).map(lambda t: p.SetBaseMotor(tuple(mm(v) for v in t))),
    p.SetVelocity: st.builds(p.SetVelocity, s32.map(q16), s32.map(q16), s32.map(q16)),
    p.PollBaseCommand: st.just(p.PollBaseCommand()),
    p.AnswerBaseCommand: st.just(p.AnswerBaseCommand()),
    p.SendEvent: st.builds(p.SendEvent, u8),
    p.GetHealth: st.just(p.GetHealth()),
    p.GetHealthError: st.builds(p.GetHealthError, u8),
    p.ClearHealthError: st.builds(p.ClearHealthError, u32),
    p.SetUvLamp: st.builds(p.SetUvLamp, st.booleans()),
    p.SetAtomiser: st.builds(p.SetAtomiser, st.integers(0, 3)),
    p.SetFan: st.builds(p.SetFan, st.integers(0, 3)),
    p.GetPayloadStatus: st.just(p.GetPayloadStatus()),
    p.GetEnvData: st.just(p.GetEnvData()),
    p.GetPowerData: st.just(p.GetPowerData()),
    p.GetButtons: st.just(p.GetButtons()),
    p.GetImuData: st.just(p.GetImuData()),
    p.GetTelemetry: st.just(p.GetTelemetry()),
    p.SetLeds: st.builds(p.SetLeds, st.integers(0, 3), u8, u8, u8),
    p.Beep: st.builds(p.Beep, u16, u16.map(mm)),
}


def test_every_request_type_has_a_strategy() -> None:
    assert set(REQUEST_STRATEGIES) == set(p.REQUEST_TYPES)
    assert len(p.REQUEST_TYPES) == len(set(p.REQUEST_TYPES))


# --------------------------------------------------------------------------------------------
# The command table
# --------------------------------------------------------------------------------------------


def test_command_table_is_complete_and_consistent() -> None:
    rows = p.COMMANDS
    # Every Control Bus code has a row; a code shared by several requests tells them apart by a
    # sub-command byte, so (code, sub) is unique.
    assert {c.code for c in rows} == set(p.CtrlBus)
    keys = [(c.code, c.args.sub) for c in rows]
    assert len(set(keys)) == len(keys)
    assert all(c.args.sub is not None for c in rows if [r.code for r in rows].count(c.code) > 1)
    # The static unions (for the type checker) hold exactly the table's types.
    assert len(set(p.REQUEST_TYPES)) == len(rows)
    assert set(typing.get_args(p.Request)) == set(p.REQUEST_TYPES)
    assert set(REPLY_TYPES) == set(p.REPLY_TYPES) == {c.reply for c in rows}
    assert len(p.REPLIES) == len(set(p.REPLY_TYPES))
    for c in rows:
        cls = c.request
        assert (c.code, c.reply, c) == (cls.CODE, cls.REPLY, cls.COMMAND)
        # A valid request of each kind encodes with its code (and sub-command) and decodes back.
        req = COMMANDS[cls][0]
        frame = _via_wire(p.encode_request(req), p.DEFAULT_PROFILE)
        assert frame.payload[0] == c.code
        assert len(frame.payload) == 1 + c.args.size
        if c.args.sub is not None:
            assert frame.payload[1] == c.args.sub
        got = p.decode_request(frame)
        assert got == req and type(got) is cls
    # Every fixed-size reply decodes a payload of its size (zeros) and encodes it back.
    for layout in p.REPLIES:
        if layout.size is not None:
            reply = p.decode_reply(Frame(p.RESP_OK, bytes(layout.size), True), layout.type)
            assert type(reply) is layout.type, reply
            assert reply.encode() == bytes(layout.size)


def test_a_layout_that_does_not_fit_its_request_is_refused() -> None:
    with pytest.raises(TypeError, match="Beep"):
        p.Command(p.CtrlBus.BEEP, p.Beep, p.Args(p.U16), p.Empty)
    with pytest.raises(TypeError, match="GetBaseStatus"):
        p.Command(p.CtrlBus.GET_BASE_STATUS, p.GetBaseStatus, p.Args(p.U8), p.BaseStatus)


def test_requests_without_arguments_are_distinct_values() -> None:
    assert p.GetBaseStatus() == p.GetBaseStatus() and hash(p.GetBaseStatus()) == hash(p.GetBaseStatus())
    assert p.GetBaseStatus() != p.GetMotorData()  # declared once, yet each its own type
    assert repr(p.GetTelemetry()) == "GetTelemetry()"
    assert p.decode_request(Frame(p.DEFAULT_CTRL_BUS, b"\xab")) == p.GetTelemetry()


def test_error_codes_classify_once() -> None:
    """Below 0x8000 the exchange broke; from 0x8000 the board refused (known codes or not)."""
    for code in p.ErrorCode:
        assert p.ErrorReply(code).is_protocol_error == code.is_protocol_error == (code < 0x8000)
    assert p.ErrorReply(0x0001).is_protocol_error and not p.ErrorReply(0x9000).is_protocol_error


def _via_wire(data: bytes, profile: p.Profile) -> Frame:
    frames = FrameDecoder(valid_codes=profile.request_codes).feed(data)
    assert len(frames) == 1 and isinstance(frames[0], Frame)
    return frames[0]


@pytest.mark.parametrize("cls", p.REQUEST_TYPES, ids=lambda c: c.__name__)
@pytest.mark.parametrize(
    "profile",
    [p.DEFAULT_PROFILE, p.Profile(long_requests=True), p.Profile(ctrl_bus_cmd=0xA8)],
    ids=["std", "long", "A8"],
)
@settings(PROPS, max_examples=12)
@given(data=st.data())
def test_request_roundtrip(cls: typing.Any, profile: p.Profile, data: st.DataObject) -> None:
    req = data.draw(REQUEST_STRATEGIES[cls])
    wire = p.encode_request(req, profile)
    assert checksum(wire) == 0
    frame = _via_wire(wire, profile)
    assert frame.code == profile.ctrl_bus_cmd
    assert frame.payload[0] == cls.CODE
    assert frame.long == profile.long_requests
    got = p.decode_request(frame, profile)
    assert got == req
    assert type(got) is cls


@PROPS
@given(vx=st.floats(-30000, 30000), vy=st.floats(-30000, 30000), w=st.floats(-30000, 30000))
def test_velocity_quantisation(vx: float, vy: float, w: float) -> None:
    """Any float is carried to within half a Q16 step, and a decoded value re-encodes exactly."""
    req = p.SetVelocity(vx, vy, w)
    back = p.decode_request(_via_wire(p.encode_request(req), p.DEFAULT_PROFILE))
    assert isinstance(back, p.SetVelocity)
    for a, b in ((vx, back.vx), (vy, back.vy), (w, back.omega)):
        assert abs(a - b) <= 0.5 / 65536 + 1e-9
    assert p.encode_request(back) == p.encode_request(req)


# --------------------------------------------------------------------------------------------
# Byte layouts by hand
# --------------------------------------------------------------------------------------------


def test_set_velocity_layout() -> None:
    # vx = 1.0 m/s -> Q16 0x00010000 little-endian; vy = omega = 0.
    assert p.encode_request(p.SetVelocity(1.0)) == bytes.fromhex("10 0E F8 41 00000100 00000000 00000000 A6")
    # -0.5 m/s -> 0xFFFF8000; 0.25 rad/s -> 0x00004000.
    assert p.SetVelocity(-0.5, 0.0, 0.25).encode_args() == bytes.fromhex("0080FFFF 00000000 00400000")


def test_set_base_motor_layout() -> None:
    # 0.25 m/s -> 250 mm/s = 0xFA; -0.1 m/s -> -100 mm/s = 0xFFFFFF9C.
    args = p.SetBaseMotor.wheels(0.25, -0.1).encode_args()
    assert args == bytes.fromhex("FA000000 9CFFFFFF 00000000 00000000")
    assert p.decode_request(Frame(0xF8, b"\x40" + args)) == p.SetBaseMotor((0.25, -0.1, 0.0, 0.0))


def test_health_mgmt_layouts() -> None:
    assert p.encode_request(p.GetHealth()) == bytes.fromhex("10 03 F8 90 01") + bytes((0x10 ^ 3 ^ 0xF8 ^ 0x90 ^ 1,))
    assert p.GetHealthError(3).encode_args() == bytes.fromhex("02 03")
    assert p.ClearHealthError(0x0000_0003).encode_args() == bytes.fromhex("03 03000000")
    assert p.ClearHealthError(0x1234_5678).encode_args() == bytes.fromhex("03 78563412")
    assert p.decode_request(Frame(0xF8, bytes.fromhex("90 01"))) == p.GetHealth()
    assert p.decode_request(Frame(0xF8, bytes.fromhex("90 02 07"))) == p.GetHealthError(7)
    assert p.decode_request(Frame(0xF8, bytes.fromhex("90 03 78563412"))) == p.ClearHealthError(0x12345678)
    for bad in ("90", "90 00", "90 01 00", "90 02", "90 02 01 02", "90 03 010203", "90 03 0102030405", "90 04"):
        got = p.decode_request(Frame(0xF8, bytes.fromhex(bad)))
        assert isinstance(got, p.Rejected) and got.error == p.ErrorCode.BAD_ARGUMENTS, bad


def test_other_request_layouts() -> None:
    assert p.Beep(2000, 0.25).encode_args() == bytes.fromhex("D007 FA00")
    assert p.SetLeds(2, 255, 16, 0).encode_args() == bytes.fromhex("02 FF 10 00")
    assert p.ConnectBase().encode_args() == b"\x01"
    assert p.SetAtomiser(3).encode_args() == b"\x03"
    with pytest.raises(ValueError):
        p.SetAtomiser(4).encode_args()
    with pytest.raises(ValueError):
        p.SetVelocity(math.nan).encode_args()
    with pytest.raises(ValueError):
        p.SetVelocity(40000.0).encode_args()  # beyond s32 Q16


def test_reply_layouts() -> None:
    # SensorData: 16 x u32 Q16 mm; 1.5 m = 1500 mm = 0x05DC0000.
    s = p.SensorData.decode(bytes.fromhex("0000DC05") + bytes(60))
    assert s.distances[0] == 1.5 and s.distances[1:] == (0.0,) * 15
    assert p.SensorData((1.5,)).encode() == bytes.fromhex("0000DC05") + bytes(60)
    # Readings beyond the u32 Q16 mm range clamp to the largest value instead of failing.
    assert p.SensorData((100.0, math.inf)).encode()[:8] == b"\xff" * 8
    # DeadReckon: dx, dy mm Q16, dtheta deg Q16 -> rad. 90 deg = 90 * 65536.
    dr = p.DeadReckon.decode(struct.pack("<iiiB", 10 * 65536, -5 * 65536, 90 * 65536, 2))
    assert dr.dx == 0.010 and dr.dy == -0.005 and math.isclose(dr.dtheta, math.pi / 2) and dr.status == 2
    assert dr.encode() == struct.pack("<iiiB", 10 * 65536, -5 * 65536, 90 * 65536, 2)
    # MotorData: s32 mm -> m.
    assert p.MotorData.decode(struct.pack("<iiB", 1234, -50, 2)) == p.MotorData(1.234, -0.05, 2)
    # BaseConf: 264 bytes, so its OK frame must be long (length 265 = 0x0109).
    conf = p.BaseConf(0, 0.17, 0, (p.MountPose(0.17, 0.0, 0.05, 0.0),), ())
    assert len(conf.encode()) == 264
    assert p.encode_ok(conf)[:4] == bytes.fromhex("50 09 01 02")
    # BumperData: u8 or u32.
    assert p.BumperData.decode(b"\xfe") == p.BumperData(0xFE, 1)
    assert p.BumperData.decode(b"\xfe\xff\xff\xff").triggered(0)
    # triggered_bits: the triggered sensors as set bits, within the received width only.
    assert p.BumperData(0xFE, 1).triggered_bits == 0x01
    assert p.BumperData(0xFFFFFFF5, 4).triggered_bits == 0x0A
    for bitmap, width in ((0x00, 1), (0x5A, 1), (0xFFFF_FFFF, 4), (0x1234_5678, 4)):
        b = p.BumperData(bitmap, width)
        assert b.triggered_bits == sum(1 << i for i in range(8 * width) if b.triggered(i))
    # PendingBaseCommand: empty or one byte.
    assert p.PendingBaseCommand.decode(b"") == p.PendingBaseCommand(None)
    assert p.PendingBaseCommand.decode(b"\x01") == p.PendingBaseCommand(p.PendingCommandCode.GO_HOME)


# --------------------------------------------------------------------------------------------
# Replies: every class round-trips, from the wire and through an OK frame
# --------------------------------------------------------------------------------------------

pose_wire = st.tuples(s32, s32, s32, st.integers(0, 360 * 256 - 1))


def _conf_wire(t: tuple[int, int, int, list[tuple[int, int, int, int]], list[tuple[int, int, int, int]]]) -> bytes:
    base_type, radius, motor, sensors, bumpers = t
    out = struct.pack("<BIBB", base_type, radius, motor, len(sensors))
    for pose in [*sensors, *[(0, 0, 0, 0)] * (8 - len(sensors))]:
        out += struct.pack("<iiiI", *pose)
    out += bytes((len(bumpers),))
    for pose in [*bumpers, *[(0, 0, 0, 0)] * (8 - len(bumpers))]:
        out += struct.pack("<iiiI", *pose)
    return out


def _telemetry_wire(
    left: int, right: int, status: int, imu: tuple[int, int, int] | None, bumpers: int, sensors: list[int]
) -> bytes:
    """A GET_TELEMETRY payload; a board without a gyro sends zeros in its place (flags bit 0 clear)."""
    gyro = (1, *imu) if imu is not None else (0, 0, 0, 0)
    head = struct.pack("<BiiBiiIIB", gyro[0], left, right, status, *gyro[1:], bumpers, len(sensors))
    return head + struct.pack(f"<{len(sensors)}I", *sensors)


def _asciiz(n: int) -> st.SearchStrategy[bytes]:
    return st.binary(max_size=n).map(lambda b: bytes(c for c in b if 0 < c < 0x80)).map(lambda b: b.ljust(n, b"\0"))


# Wire payloads that each reply class must carry unchanged (decode, then encode gives the same bytes).
REPLY_WIRE: dict[type, st.SearchStrategy[bytes]] = {
    p.Empty: st.just(b""),
    p.BaseInfo: st.tuples(_asciiz(12), u16, u16, u32, u32, u32).map(lambda t: struct.pack("<12sHH3I", *t)),
    p.BaseConf: st.tuples(
        st.integers(0, 1), u32, u8, st.lists(pose_wire, max_size=8), st.lists(pose_wire, max_size=8)
    ).map(_conf_wire),
    p.BinaryConf: st.binary(max_size=400),
    p.BaseStatus: st.tuples(st.integers(0, 100), u8).map(bytes),
    p.MotorData: st.tuples(s32, s32, u8).map(lambda t: struct.pack("<iiB", *t)),
    p.SensorData: st.lists(u32, min_size=16, max_size=16).map(lambda v: struct.pack("<16I", *v)),
    p.BumperData: st.one_of(st.binary(min_size=1, max_size=1), st.binary(min_size=4, max_size=4)),
    p.AutoHomeData: st.tuples(u8, st.binary(max_size=255)).map(lambda t: bytes((t[0], len(t[1]))) + t[1]),
    p.DeadReckon: st.tuples(s32, s32, s32, u8).map(lambda t: struct.pack("<iiiB", *t)),
    p.PendingBaseCommand: st.binary(max_size=1),
    p.Health: st.binary(min_size=2, max_size=2),
    p.HealthError: st.tuples(u32, _asciiz(32)).map(lambda t: struct.pack("<I32s", *t)),
    p.PayloadStatus: st.tuples(st.integers(0, 1), st.integers(0, 3), st.integers(0, 1), st.integers(0, 100)).map(bytes),
    p.EnvData: st.tuples(st.integers(0, 100), st.integers(-0x8000, 0x7FFF), st.integers(0, 10000), u16, u16).map(
        lambda t: struct.pack("<BhHHH", *t)
    ),
    p.PowerData: st.tuples(u16, st.integers(-0x8000, 0x7FFF), u8, u8).map(lambda t: struct.pack("<HhBB", *t)),
    p.Buttons: st.binary(min_size=1, max_size=1),
    p.ImuData: st.tuples(s32, s32, u32).map(lambda t: struct.pack("<iiI", *t)),
    p.Telemetry: st.tuples(
        s32, s32, u8, st.one_of(st.just(None), st.tuples(s32, s32, u32)), u32, st.lists(u32, max_size=16)
    ).map(lambda t: _telemetry_wire(*t)),
}


def test_every_reply_type_has_a_strategy() -> None:
    assert set(REPLY_WIRE) == set(REPLY_TYPES)
    assert {c.REPLY for c in p.REQUEST_TYPES} <= set(REPLY_TYPES)


@pytest.mark.parametrize("cls", REPLY_TYPES, ids=lambda c: c.__name__)
@settings(PROPS, max_examples=25)
@given(data=st.data())
def test_reply_roundtrip(cls: typing.Any, data: st.DataObject) -> None:
    wire = data.draw(REPLY_WIRE[cls])
    obj = cls.decode(wire)
    assert type(obj) is cls
    assert obj.encode() == wire
    assert cls.decode(obj.encode()) == obj
    # Through a whole OK frame (always long), as the master sees it.
    frame_bytes = p.encode_ok(obj)
    assert frame_bytes[0] == 0x50
    frames = FrameDecoder(valid_codes=p.REPLY_CODES).feed(frame_bytes)
    assert frames == [Frame(p.RESP_OK, wire, True)]
    assert p.decode_reply(frames[0], cls) == obj


def test_reply_units() -> None:
    conf = p.BaseConf.decode(_conf_wire((0, 170 * 256, 0, [(170 * 256, 0, 50 * 256, 90 * 256)], [])))
    assert conf.radius == 0.17 and conf.sensors[0].x == 0.17 and conf.sensors[0].z == 0.05
    assert math.isclose(conf.sensors[0].angle, math.pi / 2) and conf.bumpers == ()
    assert p.EnvData.decode(struct.pack("<BhHHH", 80, -525, 4550, 123, 300)) == p.EnvData(80, -5.25, 45.5, 12.3, 300)
    assert p.PowerData.decode(struct.pack("<HhBB", 16800, -350, 100, 0)) == p.PowerData(16.8, -0.35, 100, 0)
    info = p.BaseInfo("FLK-UVC-01", 0x0102, 1, (1, 2, 3))
    assert p.BaseInfo.decode(info.encode()) == info
    assert info.firmware_text == "1.2" and info.serial_text == "000000010000000200000003"
    assert p.HealthError.decode(p.HealthError(3, "tank empty").encode()) == p.HealthError(3, "tank empty")


# --------------------------------------------------------------------------------------------
# Refusals and malformed replies
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("payload_hex", "reason_part"),
    [
        ("", "without a command byte"),
        ("30 00", "GET_BASE_STATUS"),  # argument to an argument-less command
        ("10", "CONNECT_BASE"),  # protocol version missing
        ("10 01 01", "CONNECT_BASE"),
        ("41 00000100 00000000", "SET_V_AND_GET_DEADRECKON"),  # 8 of 12 bytes
        ("40 00", "SET_BASE_MOTOR"),
        ("A0 02", "SET_UV_LAMP"),  # flag must be 0 or 1
        ("A1 04", "SET_ATOMISER"),  # level 0-3
        ("A7 04 00 00 00", "SET_LEDS"),  # mode 0-3
        ("34", "GET_AUTO_HOME_DATA"),
        ("60", "SEND_EVENT"),
        ("A9 D007", "BEEP"),
    ],
)
def test_bad_arguments_rejected(payload_hex: str, reason_part: str) -> None:
    got = p.decode_request(Frame(p.DEFAULT_CTRL_BUS, bytes.fromhex(payload_hex)))
    assert isinstance(got, p.Rejected)
    assert got.error == p.ErrorCode.BAD_ARGUMENTS
    assert reason_part in got.reason


def test_unknown_commands_not_supported() -> None:
    got = p.decode_request(Frame(p.DEFAULT_CTRL_BUS, b"\x77"))
    assert isinstance(got, p.Rejected) and got.error == p.ErrorCode.NOT_SUPPORTED and "0x77" in got.reason
    got = p.decode_request(Frame(0x42, b"\x30"))
    assert isinstance(got, p.Rejected) and got.error == p.ErrorCode.NOT_SUPPORTED and "0x42" in got.reason
    # 0xF9 base command: one byte.
    assert p.decode_request(Frame(p.CMD_BASE, b"\x02")) == p.BaseCommand(2)
    got = p.decode_request(Frame(p.CMD_BASE, b""))
    assert isinstance(got, p.Rejected) and got.error == p.ErrorCode.BAD_ARGUMENTS
    assert p.decode_request(Frame(p.CMD_SYNC, b"abc")) == p.Sync(b"abc")
    assert p.decode_request(Frame(p.CMD_ECHO, b"abc")) == p.Echo(b"abc")


def test_a8_profile() -> None:
    a8 = p.Profile(ctrl_bus_cmd=0xA8)
    wire = p.encode_request(p.GetBaseStatus(), a8)
    assert wire == bytes((0x10, 0x02, 0xA8, 0x30, 0x10 ^ 0x02 ^ 0xA8 ^ 0x30))
    assert 0xA8 in a8.request_codes and 0xF8 not in a8.request_codes
    assert p.decode_request(_via_wire(wire, a8), a8) == p.GetBaseStatus()
    # The same bytes mean nothing to a board on the default profile, and vice versa.
    got = p.decode_request(Frame(0xA8, b"\x30"))
    assert isinstance(got, p.Rejected) and got.error == p.ErrorCode.NOT_SUPPORTED
    got = p.decode_request(Frame(0xF8, b"\x30"), a8)
    assert isinstance(got, p.Rejected) and got.error == p.ErrorCode.NOT_SUPPORTED
    # A board on the 0xA8 profile answers it.
    board = SimulatedBoard(profile=a8)
    reply = FrameDecoder(p.REPLY_CODES).feed(board.receive(wire, 0.0))
    assert len(reply) == 1 and isinstance(p.decode_reply(reply[0], p.BaseStatus), p.BaseStatus)


def test_wrong_length_ok_payload_is_malformed() -> None:
    for cls in REPLY_TYPES:
        if cls is p.BinaryConf:
            continue  # opaque: any length is valid
        for size in (3, 7, 100, 265):
            if cls is p.PendingBaseCommand and size <= 1:
                continue
            got = p.decode_reply(Frame(p.RESP_OK, bytes(size), True), cls)
            assert isinstance(got, p.Malformed), (cls, size)
            assert cls.__name__ in got.reason
    got = p.decode_reply(Frame(p.RESP_OK, b"\x65\x00", True), p.BaseStatus)  # 101 %
    assert isinstance(got, p.Malformed)
    assert isinstance(p.decode_reply(Frame(p.RESP_OK, b""), None), p.Malformed)
    assert isinstance(p.decode_reply(Frame(0x42, b""), p.Empty), p.Malformed)


def test_telemetry_example_and_its_checks() -> None:
    # docs/protocols/control-bus.md's example, byte for byte: 1.5 m / 1.6 m on the wheels, the
    # gyro at 90 degrees after 1000 samples, no bumper or cliff triggered, one sensor at 0.5 m.
    assert p.encode_request(p.GetTelemetry()) == bytes.fromhex("10 02 F8 AB 41")
    example = bytes.fromhex(
        "50 20 00 02 01 DC 05 00 00 40 06 00 00 00 00 00 00 00 00 00 5A 00 E8 03 00 00 FF FF FF FF 01 00 00 F4 01 A9"
    )
    reply = p.Telemetry(
        p.MotorData(1.5, 1.6, 0), p.ImuData(0.0, math.pi / 2, 1000), p.SensorData((0.5,)), p.BumperData(0xFFFF_FFFF)
    )
    assert p.encode_ok(reply) == example
    frames = FrameDecoder(p.REPLY_CODES).feed(example)
    assert p.decode_reply(frames[0], p.Telemetry) == reply
    # Without a gyro the IMU fields are zero on the wire and None once decoded.
    no_gyro = reply._replace(imu=None)
    assert p.Telemetry.decode(no_gyro.encode()) == no_gyro
    # Each field keeps its own reply type, so the snapshot stores them as the separate polls would.
    assert type(reply.motor) is p.MotorData and type(reply.bumpers) is p.BumperData
    # A count that does not match the length, or more than 16 sensors, is malformed.
    payload = example[4:-1]
    for bad in (payload[:-1], payload + bytes(4), payload[:-5] + b"\x11" + bytes(4 * 17)):
        got = p.decode_reply(Frame(p.RESP_OK, bad, True), p.Telemetry)
        assert isinstance(got, p.Malformed) and "Telemetry" in got.reason and "sensors" in got.reason
    with pytest.raises(ValueError, match="at most 16"):
        p.Telemetry(reply.motor, None, p.SensorData((1.0,) * 17), reply.bumpers).encode()


def test_error_reply_decode() -> None:
    for code in p.ErrorCode:
        got = p.decode_reply(FrameDecoder(p.REPLY_CODES).feed(p.encode_error(code))[0], p.BaseStatus)
        assert got == p.ErrorReply(code)
        assert str(got).startswith(f"0x{code:04X} ")
    assert p.ErrorCode.CHECKSUM_MISMATCH.is_protocol_error and not p.ErrorCode.BAD_ARGUMENTS.is_protocol_error
    assert str(p.ErrorReply(0x1234)) == "0x1234 unknown error"
    assert isinstance(p.decode_reply(Frame(p.RESP_ERROR, b"\x00"), None), p.Malformed)
    assert isinstance(p.decode_reply(Frame(p.RESP_ERROR, b"\x00\x80\x00"), None), p.Malformed)
    assert p.decode_reply(Frame(p.RESP_INVALID, b"x"), None) == p.InvalidReply(b"x")
    assert p.decode_reply(Frame(p.RESP_SYNC, b"n"), None) == p.Sync(b"n")
    assert p.decode_reply(Frame(p.RESP_ECHO, b"n"), None) == p.Echo(b"n")


@settings(PROPS, max_examples=200)
@given(
    code=st.one_of(st.sampled_from([0x00, 0x01, 0x02, 0x03, 0xF8, 0xF9, 0xA8, 0xFF]), u8),
    payload=st.one_of(
        st.binary(max_size=300),
        st.tuples(st.sampled_from([int(c) for c in p.CtrlBus]), st.binary(max_size=40)).map(
            lambda t: bytes((t[0],)) + t[1]
        ),
    ),
    expected=st.sampled_from([None, *REPLY_TYPES]),
    profile=st.sampled_from([p.DEFAULT_PROFILE, p.Profile(ctrl_bus_cmd=0xA8)]),
)
def test_decoding_never_raises(code: int, payload: bytes, expected: type | None, profile: p.Profile) -> None:
    frame = Frame(code, payload)
    req = p.decode_request(frame, profile)
    assert isinstance(req, (*p.REQUEST_TYPES, p.Sync, p.Echo, p.BaseCommand, p.Rejected))
    if isinstance(req, p.Rejected):
        assert req.reason and req.error in (p.ErrorCode.BAD_ARGUMENTS, p.ErrorCode.NOT_SUPPORTED)
    elif isinstance(req, p.REQUEST_TYPES):
        # What was accepted re-encodes to the same bytes.
        assert p.encode_request(req, profile) == encode_frame(profile.ctrl_bus_cmd, payload)
    reply = p.decode_reply(frame, expected)
    assert isinstance(reply, (*REPLY_TYPES, p.Sync, p.Echo, p.ErrorReply, p.InvalidReply, p.Malformed))


# --------------------------------------------------------------------------------------------
# The simulated board, in-process
# --------------------------------------------------------------------------------------------


def _error_of(reply: bytes) -> int:
    frames = FrameDecoder(p.REPLY_CODES).feed(reply)
    assert len(frames) == 1, reply.hex(" ")
    got = p.decode_reply(frames[0], None)
    assert isinstance(got, p.ErrorReply), got
    return got.code


@pytest.mark.parametrize("long", [False, True])
@pytest.mark.parametrize("code", [p.CMD_SYNC, p.CMD_ECHO])
def test_board_sync_echo_returns_request_unchanged(code: int, long: bool) -> None:
    board = SimulatedBoard()
    for payload in (b"", b"\x01\x02\x03\x04", bytes(range(256))):
        req = encode_frame(code, payload, long=long)
        assert board.receive(req, 0.0) == req
    # In any split.
    req = encode_frame(code, b"nonce", long=long)
    got = b"".join(board.receive(req[i : i + 1], 0.0) for i in range(len(req)))
    assert got == req


def test_board_answers_a_request() -> None:
    board = SimulatedBoard()
    reply = board.receive(p.encode_request(p.ConnectBase(1)), 0.0)
    frames = FrameDecoder(p.REPLY_CODES).feed(reply)
    info = p.decode_reply(frames[0], p.BaseInfo)
    assert isinstance(info, p.BaseInfo) and info.model == board.config.model
    assert board.state.connected


def test_a_board_without_the_extension_refuses_every_extension_command() -> None:
    board = SimulatedBoard(BoardConfig(extensions=False))
    extension = [c for c in p.REQUEST_TYPES if c.CODE >= p.CtrlBus.SET_UV_LAMP]
    assert p.GetTelemetry in extension and p.GetImuData in extension and p.SetUvLamp in extension
    for cls in extension:
        req = COMMANDS[cls][0]  # a valid request of each kind
        assert _error_of(board.receive(p.encode_request(req), 0.0)) == p.ErrorCode.NOT_SUPPORTED, cls.__name__
    # The SLAMTEC commands are served as before.
    frames = FrameDecoder(p.REPLY_CODES).feed(board.receive(p.encode_request(p.GetMotorData()), 0.0))
    assert isinstance(p.decode_reply(frames[0], p.MotorData), p.MotorData)


def test_board_error_codes() -> None:
    board = SimulatedBoard()
    # Garbage: not synchronised.
    assert _error_of(board.receive(b"\x01\x02\x03\xaa", 0.0)) == p.ErrorCode.NOT_SYNCHRONISED
    # Checksum mismatch.
    bad = bytearray(p.encode_request(p.GetBaseStatus()))
    bad[-1] ^= 0xFF
    assert _error_of(board.receive(bytes(bad), 0.0)) == p.ErrorCode.CHECKSUM_MISMATCH
    # Longer than the board's 512-byte buffer.
    too_long = encode_frame(p.DEFAULT_CTRL_BUS, b"\xa9" + bytes(600), long=True)
    assert _error_of(board.receive(too_long, 0.0)) == p.ErrorCode.REQUEST_TOO_LONG
    # Unknown Control Bus command, unknown CMD.
    assert _error_of(board.receive(encode_frame(p.DEFAULT_CTRL_BUS, b"\x77"), 0.0)) == p.ErrorCode.NOT_SUPPORTED
    assert _error_of(board.receive(encode_frame(0x42, b"\x30"), 0.0)) == p.ErrorCode.NOT_SUPPORTED
    assert _error_of(board.receive(p.encode_request(p.ConnectBase(2)), 0.0)) == p.ErrorCode.NOT_SUPPORTED
    # Bad arguments.
    assert _error_of(board.receive(encode_frame(p.DEFAULT_CTRL_BUS, b"\x30\x00"), 0.0)) == p.ErrorCode.BAD_ARGUMENTS
    assert _error_of(board.receive(p.encode_request(p.SetVelocity(0.1, 0.1)), 0.0)) == p.ErrorCode.BAD_ARGUMENTS
    # Atomiser with an empty tank: the operation failed.
    board.drain_tank()
    assert _error_of(board.receive(p.encode_request(p.SetAtomiser(2)), 0.0)) == p.ErrorCode.OPERATION_FAILED
    assert board.state.atomiser == 0
    # ... and the board still serves a good request afterwards.
    frames = FrameDecoder(p.REPLY_CODES).feed(board.receive(p.encode_request(p.SetAtomiser(0)), 0.0))
    assert p.decode_reply(frames[0], p.Empty) == p.Empty()


def test_replies_are_named_tuples_and_decode_reply_matches_decode() -> None:
    """decode_reply's fast dispatch gives the same value and type as each class's ``decode``."""
    samples: dict[type, bytes] = {
        p.DeadReckon: struct.pack("<iiiB", 10 * 65536, -5 * 65536, 90 * 65536, 2),
        p.MotorData: struct.pack("<iiB", 1234, -50, 2),
        p.SensorData: struct.pack("<16I", *range(0, 16 * 65536000, 65536000)),
        p.BumperData: b"\xfe\xff\xff\xff",
        p.BaseStatus: b"\x57\x05",
        p.Health: b"\x01\x02",
        p.Buttons: b"\x0a",
        p.PowerData: struct.pack("<HhBB", 16800, -350, 100, 5),
        p.Empty: b"",
    }
    for cls, wire in samples.items():
        got = p.decode_reply(Frame(p.RESP_OK, wire, True), cls)
        assert type(got) is cls and isinstance(got, tuple) and hasattr(cls, "_fields")
        assert got == cls.decode(wire) and got.encode() == wire
    assert p.decode_reply(Frame(p.RESP_OK, samples[p.SensorData], True), p.SensorData).distances[:3] == (0.0, 1.0, 2.0)
    # Not a reply type: Malformed, not an exception.
    got = p.decode_reply(Frame(p.RESP_OK, b""), p.GetHealth)  # type: ignore[arg-type]
    assert isinstance(got, p.Malformed) and "GetHealth" in got.reason


def test_flag_enums() -> None:
    status = p.BaseStatus(87, p.PowerFlag.CHARGING | p.PowerFlag.ON_DOCK)
    assert status.encode() == b"\x57\x05" and status.charging and status.on_dock and not status.external_power
    assert p.MotorData.decode(struct.pack("<iiB", 0, 0, 2)).status & p.MotorStatus.STALL
    assert p.Health.decode(b"\x05\x01").flags == p.HealthFlag.WARNING | p.HealthFlag.FATAL
    assert p.Buttons.decode(b"\x0a").bitmap == p.Button.HOME | p.Button.ESTOP
    assert p.PendingBaseCommand.decode(b"\x01").command == p.PendingCommandCode.GO_HOME
    # Wrong sizes keep their wording.
    got = p.decode_reply(Frame(p.RESP_OK, b"\x00\x00"), p.Buttons)
    assert isinstance(got, p.Malformed) and got.reason == "Buttons: expected 1 byte, got 2"
    got = p.decode_reply(Frame(p.RESP_OK, bytes(12)), p.DeadReckon)
    assert isinstance(got, p.Malformed) and got.reason == "DeadReckon: expected 13 bytes, got 12"
