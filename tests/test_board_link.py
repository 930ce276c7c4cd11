"""The master's Control Bus client against the simulated board, over real bytes.

One suite, three transports: a real TCP socket and a pty (both through pyserial's
``serial_for_url``, the board served by ``DeviceServer`` in real time) and the in-process port under
a ``SimClock`` (lockstep: simulated time moves only while the client waits).
"""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, ClassVar

import pytest

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.client import BoardClient, BoardProtocolError, BoardRefused
from fleetlink.devices.controlbus.frames import (
    BOARD_BUFFER,
    FLAG_LONG,
    FLAG_STANDARD,
    Frame,
    FrameDecoder,
    encode_frame,
)
from fleetlink.devices.ports import Port, PortClosed, SerialPort
from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.shared.clock import Clock, SimClock, SystemClock

TRANSPORTS = ["tcp", "pty", "inproc"]


@contextlib.contextmanager
def serve_board(kind: str, board: SimulatedBoard | None = None) -> Iterator[tuple[DeviceServer, str]]:
    """A simulated board served in real time on TCP or a pty: yields (server, url); stops it after."""
    server = DeviceServer(board or SimulatedBoard(), SystemClock(), name="board")
    try:
        url = f"socket://127.0.0.1:{server.serve_tcp()}" if kind == "tcp" else server.serve_pty()
        yield server, url
    finally:
        server.stop()


@pytest.fixture(params=["tcp", "pty"])
def served_board(request: pytest.FixtureRequest) -> Iterator[tuple[DeviceServer, str]]:
    with serve_board(request.param) as served:
        yield served


class Tamper:
    """A port wrapper that lets a test mangle the next write (line noise, a flipped bit)."""

    def __init__(self, port: Port) -> None:
        self.port = port
        self.mangle: Callable[[bytes], bytes] | None = None

    def write(self, data: bytes) -> None:
        if self.mangle is not None:
            data, self.mangle = self.mangle(data), None
        self.port.write(data)

    def read_some(self, clock: Clock, deadline: float) -> bytes:
        return self.port.read_some(clock, deadline)

    def close(self) -> None:
        self.port.close()


@dataclass
class Rig:
    kind: str
    board: SimulatedBoard
    clock: Clock
    port: Tamper
    client: BoardClient
    server: DeviceServer | None = None

    def locked(self) -> contextlib.AbstractContextManager[Any]:
        """Hold the server's lock while touching the board from the test thread."""
        return self.server.lock if self.server is not None else contextlib.nullcontext()

    def raw(self, data: bytes, quiet: float = 0.05, timeout: float = 1.0) -> list[Frame]:
        """Write raw bytes past the client; collect reply frames until the line has been quiet a while."""
        self.port.port.write(data)
        decoder = FrameDecoder(valid_codes=p.REPLY_CODES)
        frames: list[Frame] = []
        end = self.clock.now() + timeout
        while self.clock.now() < end:
            chunk = self.port.port.read_some(self.clock, min(end, self.clock.now() + quiet))
            if not chunk:
                if frames:
                    break
                continue
            frames += [f for f in decoder.feed(chunk) if isinstance(f, Frame)]
        assert decoder.buffered == 0, "a reply frame was cut short"
        return frames


@pytest.fixture(autouse=True)
def _no_close_sleep_in_pyserial_sockets(monkeypatch: pytest.MonkeyPatch) -> None:
    """pyserial's socket:// ``close()`` sleeps 0.3 s "in case of quick reconnects"; these tests never
    reconnect, and a dozen TCP tests would otherwise spend ~4 s in it. (The session tests keep it.)"""
    from serial.urlhandler import protocol_socket

    monkeypatch.setattr(protocol_socket, "time", SimpleNamespace(sleep=lambda seconds: None))


@pytest.fixture(params=TRANSPORTS)
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    kind = request.param
    if kind == "inproc":
        clock = SimClock(start=100.0)
        board = SimulatedBoard(now=clock.now())
        port = Tamper(board.in_process_port(clock))
        client = BoardClient(port, clock)
        yield Rig(kind, board, clock, port, client)
        client.close()
        return
    with serve_board(kind) as (server, url):
        clock = SystemClock()
        port = Tamper(SerialPort(url))
        client = BoardClient(port, clock, timeout=0.2)
        try:
            yield Rig(kind, server.device, clock, port, client, server)
        finally:
            client.close()


# ---------------------------------------------------------------------------------------------
# Handshake and every command
# ---------------------------------------------------------------------------------------------


def test_served_board_fixture_gives_a_reachable_url(served_board: tuple[DeviceServer, str]) -> None:
    server, url = served_board
    client = BoardClient(SerialPort(url), SystemClock(), timeout=0.2)
    try:
        info = client.connect()
        assert info.model == "FLK-UVC-01"
        assert client.echo(b"hello") == b"hello"
        with server.lock:
            assert server.device.state.connected
    finally:
        client.close()


def test_handshake(rig: Rig) -> None:
    info = rig.client.connect()
    assert isinstance(info, p.BaseInfo)
    assert info.model == "FLK-UVC-01"
    assert info.firmware_text == "1.2"
    assert info.serial_text == "464C4B000000000100000001"
    assert rig.board.state.connected
    assert rig.client.stats.syncs >= 1
    assert rig.client.stats.timeouts == 0


Check = Callable[[Any], bool]

# One example per Control Bus command: the request, then the reply type and a sanity check on it,
# or the error code the board must refuse it with.
COMMANDS: dict[type, tuple[Any, type | int, Check]] = {
    p.ConnectBase: (p.ConnectBase(1), p.BaseInfo, lambda r: r.model == "FLK-UVC-01"),
    p.GetBaseConf: (
        p.GetBaseConf(),
        p.BaseConf,
        lambda r: r.radius == pytest.approx(0.17, abs=1e-3) and len(r.sensors) == 1 and len(r.bumpers) == 2,
    ),
    p.GetBinaryConf: (p.GetBinaryConf(), p.BinaryConf, lambda r: b"track=0.22" in r.blob),
    p.GetBaseStatus: (p.GetBaseStatus(), p.BaseStatus, lambda r: r.battery_percent == 100 and not r.charging),
    p.GetMotorData: (p.GetMotorData(), p.MotorData, lambda r: r.status == 0),
    p.GetSensorData: (p.GetSensorData(), p.SensorData, lambda r: len(r.distances) == 16),
    p.GetBumperData: (p.GetBumperData(), p.BumperData, lambda r: r.bitmap == 0xFFFF_FFFF),
    p.GetAutoHomeData: (p.GetAutoHomeData(0), p.AutoHomeData, lambda r: r.probes == b""),
    p.SetBaseMotor: (p.SetBaseMotor.wheels(0.0, 0.0), p.Empty, lambda r: True),
    p.SetVelocity: (p.SetVelocity(0.0, 0.0, 0.0), p.DeadReckon, lambda r: r.status == 0),
    p.PollBaseCommand: (p.PollBaseCommand(), p.PendingBaseCommand, lambda r: r.command is None),
    p.AnswerBaseCommand: (p.AnswerBaseCommand(), p.Empty, lambda r: True),
    p.SendEvent: (p.SendEvent(p.BaseEvent.SYSTEM_UP), p.Empty, lambda r: True),
    p.GetHealth: (p.GetHealth(), p.Health, lambda r: r.error_count == 0),
    p.GetHealthError: (p.GetHealthError(99), p.ErrorCode.BAD_ARGUMENTS, lambda r: True),
    p.ClearHealthError: (p.ClearHealthError(0x7777), p.ErrorCode.BAD_ARGUMENTS, lambda r: True),
    p.SetUvLamp: (p.SetUvLamp(True), p.Empty, lambda r: True),
    p.SetAtomiser: (p.SetAtomiser(1), p.Empty, lambda r: True),
    p.SetFan: (p.SetFan(2), p.Empty, lambda r: True),
    p.GetPayloadStatus: (
        p.GetPayloadStatus(),
        p.PayloadStatus,
        lambda r: r.uv_lamp and r.atomiser_level == 1 and r.fan_level == 2 and r.tank_percent == 100,
    ),
    p.GetEnvData: (p.GetEnvData(), p.EnvData, lambda r: r.disinfectant_percent == 100 and r.humidity_percent > 0),
    p.GetPowerData: (
        p.GetPowerData(),
        p.PowerData,
        lambda r: r.voltage == pytest.approx(16.8, abs=0.05) and r.current < 0 and r.battery_percent == 100,
    ),
    p.GetButtons: (p.GetButtons(), p.Buttons, lambda r: r.bitmap == 0),
    p.GetImuData: (p.GetImuData(), p.ImuData, lambda r: r.yaw_rate == 0.0 and r.yaw == 0.0 and r.samples >= 0),
    p.GetTelemetry: (
        p.GetTelemetry(),
        p.Telemetry,
        lambda r: r.imu is not None and len(r.sensors.distances) == 1 and r.bumpers.bitmap == 0xFFFF_FFFF,
    ),
    p.SetLeds: (p.SetLeds(1, 255, 0, 0), p.Empty, lambda r: True),
    p.Beep: (p.Beep(880, 0.1), p.Empty, lambda r: True),
}

# Documented refusals beyond the table above.
REFUSALS: list[tuple[Any, int]] = [
    (p.ConnectBase(2), p.ErrorCode.NOT_SUPPORTED),  # wrong protocol version
    (p.GetAutoHomeData(1), p.ErrorCode.BAD_ARGUMENTS),  # only beacon data (0)
    (p.SetVelocity(0.1, 0.1, 0.0), p.ErrorCode.BAD_ARGUMENTS),  # a differential base cannot go sideways
]


def test_command_table_covers_every_request_type() -> None:
    assert set(COMMANDS) == set(p.REQUEST_TYPES)


def test_every_command_gets_a_typed_reply_or_the_documented_refusal(rig: Rig) -> None:
    rig.client.connect()
    for req_type in p.REQUEST_TYPES:  # in protocol order: the payload setters come before the status read
        req, expected, check = COMMANDS[req_type]
        if isinstance(expected, int):
            with pytest.raises(BoardRefused) as info:
                rig.client.request(req)
            assert info.value.code == expected, req
            assert info.value.request == req
        else:
            reply = rig.client.request(req)
            assert type(reply) is expected, f"{req} -> {reply}"
            assert check(reply), f"{req} -> {reply}"
    for req, code in REFUSALS:
        with pytest.raises(BoardRefused) as info:
            rig.client.request(req)
        assert info.value.code == code, req
    stats = rig.client.stats
    assert stats.refusals == 2 + len(REFUSALS)
    assert stats.retries == 0 and stats.timeouts == 0 and stats.protocol_errors == 0
    assert rig.board.state.leds == (1, 255, 0, 0)
    assert any("beep 880 Hz" in e for e in rig.board.events)
    assert any("event 0x63" in e for e in rig.board.events)


def test_sync_and_echo_do_not_feed_the_watchdog(rig: Rig) -> None:
    rig.client.connect()
    with rig.locked():
        last = rig.board.state.last_ctrl_bus
    rig.client.sync()
    assert rig.client.echo(b"\x10\x50 not a frame") == b"\x10\x50 not a frame"
    with rig.locked():
        assert rig.board.state.last_ctrl_bus == last


# ---------------------------------------------------------------------------------------------
# Error replies, as the master sees them, and recovery
# ---------------------------------------------------------------------------------------------


def error_codes(frames: list[Frame]) -> list[int]:
    out = []
    for f in frames:
        reply = p.decode_reply(f, None)
        assert isinstance(reply, p.ErrorReply), f"expected an ERROR frame, got {reply}"
        out.append(reply.code)
    return out


def assert_recovers(rig: Rig) -> None:
    status = rig.client.request(p.GetBaseStatus())
    assert isinstance(status, p.BaseStatus)
    assert status.battery_percent == 100


def test_garbage_gets_not_synchronised(rig: Rig) -> None:
    rig.client.connect()
    garbage = b"\x01\x02\x03garbage\xff"
    assert FLAG_STANDARD not in garbage and FLAG_LONG not in garbage
    frames = rig.raw(garbage)
    assert error_codes(frames) == [p.ErrorCode.NOT_SYNCHRONISED]
    assert frames[0].long  # the board always answers with long frames
    assert_recovers(rig)


def test_request_longer_than_the_board_buffer(rig: Rig) -> None:
    rig.client.connect()
    frame = encode_frame(p.DEFAULT_CTRL_BUS, bytes((p.CtrlBus.GET_BASE_STATUS,)) + bytes(600), long=True)
    assert len(frame) > BOARD_BUFFER
    assert FLAG_STANDARD not in frame[1:] and FLAG_LONG not in frame[1:]
    codes = error_codes(rig.raw(frame))
    assert codes[0] == p.ErrorCode.REQUEST_TOO_LONG
    # If the transport split the frame, the tail arrives as garbage; nothing else may come back.
    assert set(codes[1:]) <= {p.ErrorCode.NOT_SYNCHRONISED}
    assert_recovers(rig)


def test_bad_checksum(rig: Rig) -> None:
    rig.client.connect()
    frame = bytearray(p.encode_request(p.GetBaseStatus()))
    assert bytes(frame) == bytes.fromhex("10 02 F8 30 DA")  # the worked example in the reference note
    frame[-1] ^= 0x01
    assert error_codes(rig.raw(bytes(frame))) == [p.ErrorCode.CHECKSUM_MISMATCH]
    assert_recovers(rig)


def test_unknown_control_bus_command(rig: Rig) -> None:
    rig.client.connect()
    frames = rig.raw(encode_frame(p.DEFAULT_CTRL_BUS, b"\x7e"))
    assert error_codes(frames) == [p.ErrorCode.NOT_SUPPORTED]
    assert frames[0] == Frame(p.RESP_ERROR, b"\x00\x80", True)  # 50 03 00 03 00 80 D0
    assert_recovers(rig)


def test_unknown_request_cmd(rig: Rig) -> None:
    rig.client.connect()
    assert error_codes(rig.raw(encode_frame(0x42, b"\x01"))) == [p.ErrorCode.NOT_SUPPORTED]
    assert_recovers(rig)


@dataclass(frozen=True)
class UnknownCommand:
    """A Control Bus command the board does not have."""

    CODE: ClassVar[int] = 0x7E
    REPLY: ClassVar[type] = p.Empty

    def encode_args(self) -> bytes:
        return b""


@dataclass(frozen=True)
class Oversized:
    """A well-formed request that cannot fit the board's 512-byte receive buffer."""

    CODE: ClassVar[int] = p.CtrlBus.SEND_EVENT
    REPLY: ClassVar[type] = p.Empty

    def encode_args(self) -> bytes:
        return bytes(BOARD_BUFFER)


def test_refusals_raise_board_refused_with_code_and_are_not_retried(rig: Rig) -> None:
    rig.client.connect()
    with pytest.raises(BoardRefused) as info:
        rig.client.request(UnknownCommand())
    assert info.value.code == p.ErrorCode.NOT_SUPPORTED
    with pytest.raises(BoardRefused) as info:
        rig.client.request(p.GetHealthError(99))
    assert info.value.code == p.ErrorCode.BAD_ARGUMENTS
    assert "0x8001" in str(info.value)
    assert rig.client.stats.retries == 0
    assert rig.client.stats.refusals == 2
    assert_recovers(rig)


def test_operation_failed_on_an_empty_tank(rig: Rig) -> None:
    rig.client.connect()
    with rig.locked():
        rig.board.drain_tank()
    with pytest.raises(BoardRefused) as info:
        rig.client.request(p.SetAtomiser(2))
    assert info.value.code == p.ErrorCode.OPERATION_FAILED
    assert rig.board.state.atomiser == 0
    # The failure is in the health list, readable and clearable by the master.
    health = rig.client.request(p.GetHealth())
    assert isinstance(health, p.Health)
    assert health.error_count == 1 and health.flags & p.HealthFlag.WARNING
    err = rig.client.request(p.GetHealthError(0))
    assert err == p.HealthError(p.HealthErrorCode.TANK_EMPTY, "disinfectant tank empty")
    assert rig.client.request(p.ClearHealthError(p.HealthErrorCode.TANK_EMPTY)) == p.Empty()
    assert rig.client.request(p.GetHealth()) == p.Health(0, 0)
    assert_recovers(rig)


def test_protocol_error_replies_raise_board_protocol_error(rig: Rig) -> None:
    """0x0020 through the client: retried (after a SYNC) and then reported as a protocol error."""
    rig.client.connect()
    with pytest.raises(BoardProtocolError, match="0x0020"):
        rig.client.request(Oversized())
    stats = rig.client.stats
    assert stats.protocol_errors == rig.client.retries + 1
    assert stats.retries == rig.client.retries
    assert_recovers(rig)


@pytest.mark.parametrize(
    ("mangle", "code"),
    [
        (lambda frame: frame[:-1] + bytes((frame[-1] ^ 0x40,)), p.ErrorCode.CHECKSUM_MISMATCH),
        (lambda frame: b"noise" + frame, p.ErrorCode.NOT_SYNCHRONISED),
    ],
    ids=["checksum", "noise"],
)
def test_client_retries_through_a_garbled_request(rig: Rig, mangle: Callable[[bytes], bytes], code: int) -> None:
    rig.client.connect()
    with rig.locked():
        errors_before = rig.board.state.error_replies
    rig.port.mangle = mangle
    assert_recovers(rig)
    stats = rig.client.stats
    assert stats.protocol_errors == 1, f"the board's 0x{code:04X} reply should have been seen once"
    assert stats.retries == 1
    with rig.locked():
        assert rig.board.state.error_replies == errors_before + 1


# ---------------------------------------------------------------------------------------------
# SerialPort.read_some: everything available in one call, deadlines honoured
# ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def raw_peer(kind: str) -> Iterator[tuple[SerialPort, Callable[[bytes], None], Callable[[], None]]]:
    """A SerialPort on a TCP socket or a pty whose other end the test drives: (port, send, hang_up)."""
    if kind == "tcp":
        listener = socket.create_server(("127.0.0.1", 0))
        port = SerialPort(f"socket://127.0.0.1:{listener.getsockname()[1]}")
        conn, _ = listener.accept()
        listener.close()
        try:
            yield port, conn.sendall, conn.close
        finally:
            port.close()
            conn.close()
    else:
        master, slave = os.openpty()
        port = SerialPort(os.ttyname(slave))
        open_fds = [master, slave]

        def send(data: bytes) -> None:
            os.write(master, data)

        def hang_up() -> None:
            while open_fds:
                os.close(open_fds.pop())

        try:
            yield port, send, hang_up
        finally:
            port.close()
            hang_up()


@pytest.mark.parametrize("kind", ["tcp", "pty"])
def test_read_some_returns_everything_available_in_one_call(kind: str) -> None:
    clock = SystemClock()
    replies = b"".join(p.encode_ok(p.DeadReckon(0.01, 0.0, 0.02, 0)) for _ in range(10))  # 180 bytes
    with raw_peer(kind) as (port, send, _):
        send(replies)
        time.sleep(0.05)  # all of it has arrived
        got = port.read_some(clock, clock.now() + 1.0)
        assert got == replies  # one call (pyserial's socket in_waiting alone would give 1 byte)
        # Nothing more: returns empty at the deadline, not much later.
        t0 = time.perf_counter()
        assert port.read_some(clock, clock.now() + 0.03) == b""
        assert 0.025 <= time.perf_counter() - t0 < 0.5


@pytest.mark.parametrize("kind", ["tcp", "pty"])
def test_read_some_returns_as_soon_as_bytes_arrive(kind: str) -> None:
    clock = SystemClock()
    with raw_peer(kind) as (port, send, _):
        timer = threading.Timer(0.05, send, (b"\x50\x01\x00\x02\x53",))
        timer.start()
        t0 = time.perf_counter()
        got = port.read_some(clock, clock.now() + 2.0)
        elapsed = time.perf_counter() - t0
        timer.join()
        assert got == b"\x50\x01\x00\x02\x53"
        assert elapsed < 1.0  # woken by the bytes, not by the deadline


def test_read_some_on_a_closed_tcp_peer_raises_port_closed() -> None:
    clock = SystemClock()
    with raw_peer("tcp") as (port, _, hang_up):
        hang_up()
        with pytest.raises(PortClosed):
            port.read_some(clock, clock.now() + 1.0)


def test_read_some_without_a_descriptor_loop_url() -> None:
    clock = SystemClock()
    port = SerialPort("loop://")
    try:
        port.write(b"hello board")
        assert port.read_some(clock, clock.now() + 1.0) == b"hello board"
        t0 = time.perf_counter()
        assert port.read_some(clock, clock.now() + 0.03) == b""
        assert time.perf_counter() - t0 < 0.5
    finally:
        port.close()
