"""Control Bus messages: typed requests and replies with their exact byte layouts. No I/O.

Every Control Bus command of SLAMTEC's profile (docs/protocols/control-bus.md) has a request
class and, where the board answers with data, a reply class. Fixed-point fields (Q8, Q16, mm,
degrees) are converted to SI units (metres, m/s, radians) here and nowhere else.

Both roles use this module: the agent's link encodes requests and decodes replies against the
request it sent; the simulated board decodes requests and encodes replies. Decoding never raises:
it returns a typed value or a ``Rejected``/``Malformed`` value saying why.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import Any, ClassVar, NamedTuple, Protocol, TypeAlias, TypeVar, cast

from fleetlink.devices.controlbus.frames import Frame, encode_frame

__all__ = [
    "CMD_BASE",
    "CMD_ECHO",
    "CMD_SYNC",
    "DEFAULT_CTRL_BUS",
    "REPLY_CODES",
    "RESP_ECHO",
    "RESP_ERROR",
    "RESP_INVALID",
    "RESP_OK",
    "RESP_SYNC",
    "Button",
    "CtrlBus",
    "ErrorCode",
    "HealthFlag",
    "MotorStatus",
    "PendingCommandCode",
    "PowerFlag",
    "Profile",
]

# Request CMD values.
CMD_SYNC = 0x00
CMD_ECHO = 0x01
DEFAULT_CTRL_BUS = 0xF8  # SLAMTEC's CTRL_BUS; the thesis prints 0xA8 (a Profile setting)
CMD_BASE = 0xF9  # reference firmware only: 1 enter DFU, 2 reboot

# Response codes.
RESP_SYNC = 0x00
RESP_ECHO = 0x01
RESP_OK = 0x02
RESP_ERROR = 0x03
RESP_INVALID = 0xFF
REPLY_CODES = frozenset({RESP_SYNC, RESP_ECHO, RESP_OK, RESP_ERROR, RESP_INVALID})

Q8 = 256.0
Q16 = 65536.0
_DEG = math.pi / 180.0

_T = TypeVar("_T")


class ErrorCode(IntEnum):
    NOT_SYNCHRONISED = 0x0010  # first byte not a flag, or a new request before the last was handled
    REQUEST_TOO_LONG = 0x0020  # longer than the board's buffer
    CHECKSUM_MISMATCH = 0x0040
    NOT_SUPPORTED = 0x8000  # CMD or Control Bus command unknown; also a wrong protocol version
    BAD_ARGUMENTS = 0x8001
    OPERATION_FAILED = 0x8002

    @property
    def is_protocol_error(self) -> bool:
        """Codes below 0x8000 say the channel broke (we or the line), not that a command was refused."""
        return self.value < 0x8000

    @classmethod
    def describe(cls, code: int) -> str:
        try:
            return f"0x{code:04X} {cls(code).name.lower().replace('_', ' ')}"
        except ValueError:
            return f"0x{code:04X} unknown error"


class CtrlBus(IntEnum):
    """Control Bus command codes (payload[0] of a CTRL_BUS request)."""

    CONNECT_BASE = 0x10
    GET_BASE_CONF = 0x20
    GET_BINARY_CONF = 0x21
    GET_BASE_STATUS = 0x30
    GET_BASE_MOTOR_DATA = 0x31
    GET_BASE_SENSOR_DATA = 0x32
    GET_BASE_BUMPER_DATA = 0x33
    GET_AUTO_HOME_DATA = 0x34
    SET_BASE_MOTOR = 0x40
    SET_V_AND_GET_DEADRECKON = 0x41
    POLL_BASE_CMD = 0x50
    POLL_BASE_ANS_CMD = 0x5F
    SEND_EVENT = 0x60
    HEALTH_MGMT = 0x90
    # fleetlink extension for the disinfection robot's board (codes SLAMTEC leaves unused).
    SET_UV_LAMP = 0xA0
    SET_ATOMISER = 0xA1
    SET_FAN = 0xA2
    GET_PAYLOAD_STATUS = 0xA3
    GET_ENV_DATA = 0xA4
    GET_POWER_DATA = 0xA5
    GET_BUTTONS = 0xA6
    SET_LEDS = 0xA7
    BEEP = 0xA9
    GET_IMU_DATA = 0xAA
    GET_TELEMETRY = 0xAB


@dataclass(frozen=True, slots=True)
class Profile:
    """Settings of one board's dialect of the protocol."""

    ctrl_bus_cmd: int = DEFAULT_CTRL_BUS
    long_requests: bool = False  # the reference base accepts both; standard frames are shorter

    @property
    def request_codes(self) -> frozenset[int]:
        return frozenset({CMD_SYNC, CMD_ECHO, self.ctrl_bus_cmd, CMD_BASE})


DEFAULT_PROFILE = Profile()


class BadPayload(ValueError):
    """A payload whose layout does not match its command (raised only inside this module)."""


def _s32(x: float) -> int:
    v = round(x)
    if not -0x8000_0000 <= v <= 0x7FFF_FFFF:
        raise ValueError(f"{x} does not fit a signed 32-bit field")
    return v


def _u32(x: float) -> int:
    v = round(x)
    if not 0 <= v <= 0xFFFF_FFFF:
        raise ValueError(f"{x} does not fit an unsigned 32-bit field")
    return v


def _finite(name: str, *values: float) -> None:
    for v in values:
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v}")


def _unpack(st: struct.Struct, payload: bytes) -> tuple[int, ...]:
    if len(payload) != st.size:
        raise BadPayload(f"expected {st.size} bytes, got {len(payload)}")
    return st.unpack(payload)


# --------------------------------------------------------------------------------------------
# Replies (the OK payloads)
#
# Replies are NamedTuples: the master decodes tens of thousands a second, and a tuple built with
# the C-level ``tuple.__new__`` costs a fraction of a frozen dataclass's ``__init__``. Each reply
# type has a module-level ``_decode_<name>`` function (plain function, looked up by type in
# ``decode_reply``); ``Reply.decode`` classmethods wrap the same functions for other callers.
# Scaling to SI units is written out per field: ``x / 65536000.0`` is the same float as the
# former ``x / Q16 / 1000`` (dividing by a power of two is exact), so values are unchanged.
#
# Being tuples, two replies of different types with equal fields compare equal
# (``Health(0, 0) == BaseStatus(0, 0)``); compare ``type()`` too where that matters.
# --------------------------------------------------------------------------------------------


class _TupleNew(Protocol):
    def __call__(self, cls: type[_T], iterable: Iterable[Any], /) -> _T: ...


_new = cast(_TupleNew, tuple.__new__)  # builds a NamedTuple from a tuple without its Python __new__

_MM = 1000.0  # mm per m
_Q8_MM = Q8 * 1000  # mm Q8 per m
_Q16_MM = Q16 * 1000  # mm Q16 per m
_Q8_DEG = _DEG / Q8  # rad per deg Q8 (exact: Q8 is a power of two)
_Q16_DEG = _DEG / Q16  # rad per deg Q16


class PowerFlag(IntFlag):
    """Bits of ``BaseStatus.power_flags`` and ``PowerData.power_flags``."""

    CHARGING = 0x01
    EXTERNAL_POWER = 0x02
    ON_DOCK = 0x04


class MotorStatus(IntFlag):
    """Bits of ``MotorData.status``."""

    STALL = 0x02
    TRACTION_LOST = 0x04


class HealthFlag(IntFlag):
    """Bits of ``Health.flags``."""

    WARNING = 0x01
    ERROR = 0x02
    FATAL = 0x04


class Button(IntFlag):
    """Bits of ``Buttons.bitmap``."""

    POWER = 0x01
    HOME = 0x02
    START = 0x04
    ESTOP = 0x08  # emergency stop engaged


class PendingCommandCode(IntEnum):
    """Values of ``PendingBaseCommand.command``."""

    GO_HOME = 0x01


def _checked(decode: Callable[[bytes], _T], cls: type, payload: bytes) -> _T:
    """``decode(payload)``, with a wrong-size ``struct.error`` reported as ``BadPayload``."""
    try:
        return decode(payload)
    except struct.error:
        raise BadPayload(_size_problem(cls, payload)) from None


def _size_problem(cls: type | None, payload: bytes) -> str:
    size = _REPLY_SIZES.get(cls) if cls is not None else None
    if size is None:
        return f"payload of {len(payload)} bytes does not fit"
    return f"expected {size} byte{'s' if size != 1 else ''}, got {len(payload)}"


class Empty(NamedTuple):
    """An OK reply without data."""

    def encode(self) -> bytes:
        return b""

    @classmethod
    def decode(cls, payload: bytes) -> Empty:
        return _decode_empty(payload)


def _decode_empty(payload: bytes) -> Empty:
    if payload:
        raise BadPayload(f"expected an empty payload, got {len(payload)} bytes")
    return _new(Empty, ())


_BASE_INFO = struct.Struct("<12sHH3I")


class BaseInfo(NamedTuple):
    """CONNECT_BASE: model u8[12], firmware u16, hardware u16, serial u32[3]."""

    model: str
    firmware: int
    hardware: int
    serial: tuple[int, int, int]

    def encode(self) -> bytes:
        return _BASE_INFO.pack(self.model.encode("ascii")[:12], self.firmware, self.hardware, *self.serial)

    @classmethod
    def decode(cls, payload: bytes) -> BaseInfo:
        return _checked(_decode_base_info, cls, payload)

    @property
    def serial_text(self) -> str:
        return "".join(f"{s:08X}" for s in self.serial)

    @property
    def firmware_text(self) -> str:
        return f"{self.firmware >> 8}.{self.firmware & 0xFF}"


def _decode_base_info(payload: bytes) -> BaseInfo:
    model, fw, hw, s0, s1, s2 = _BASE_INFO.unpack(payload)
    text = bytes(model).split(b"\0", 1)[0].decode("ascii", "replace")
    return _new(BaseInfo, (text, fw, hw, (s0, s1, s2)))


_POSE = struct.Struct("<iiiI")


class MountPose(NamedTuple):
    """A sensor's or bumper's pose on the base: metres and radians (counter-clockwise)."""

    x: float
    y: float
    z: float
    angle: float

    def encode(self) -> bytes:
        return _POSE.pack(
            _s32(self.x * 1000 * Q8),
            _s32(self.y * 1000 * Q8),
            _s32(self.z * 1000 * Q8),
            _u32((math.degrees(self.angle) % 360.0) * Q8),
        )

    @classmethod
    def decode(cls, payload: bytes) -> MountPose:
        return _checked(_decode_mount_pose, cls, payload)


def _decode_mount_pose(payload: bytes) -> MountPose:
    x, y, z, a = _POSE.unpack(payload)
    return _new(MountPose, (x / _Q8_MM, y / _Q8_MM, z / _Q8_MM, a * _Q8_DEG))


_CONF_HEAD = struct.Struct("<BIBB")
_CONF_SIZE = _CONF_HEAD.size + 8 * _POSE.size + 1 + 8 * _POSE.size
_NO_POSE = MountPose(0.0, 0.0, 0.0, 0.0)


class BaseConf(NamedTuple):
    """GET_BASE_CONF: shape, radius, drive, and up to 8 range sensors and 8 bumpers."""

    base_type: int  # 0 circle, 1 square
    radius: float  # m
    motor_type: int  # 0 two-wheel differential
    sensors: tuple[MountPose, ...]
    bumpers: tuple[MountPose, ...]

    def encode(self) -> bytes:
        if len(self.sensors) > 8 or len(self.bumpers) > 8:
            raise ValueError("at most 8 sensors and 8 bumpers")
        out = bytearray(
            _CONF_HEAD.pack(self.base_type, _u32(self.radius * 1000 * Q8), self.motor_type, len(self.sensors))
        )
        for p in (*self.sensors, *[_NO_POSE] * (8 - len(self.sensors))):
            out += p.encode()
        out.append(len(self.bumpers))
        for p in (*self.bumpers, *[_NO_POSE] * (8 - len(self.bumpers))):
            out += p.encode()
        return bytes(out)

    @classmethod
    def decode(cls, payload: bytes) -> BaseConf:
        return _checked(_decode_base_conf, cls, payload)


def _decode_base_conf(payload: bytes) -> BaseConf:
    if len(payload) != _CONF_SIZE:
        raise BadPayload(f"expected {_CONF_SIZE} bytes, got {len(payload)}")
    base_type, radius, motor, n_sensors = _CONF_HEAD.unpack_from(payload)
    off = _CONF_HEAD.size
    sensors = [_decode_mount_pose(payload[off + i * 16 : off + i * 16 + 16]) for i in range(8)]
    off += 8 * 16
    n_bumpers = payload[off]
    off += 1
    bumpers = [_decode_mount_pose(payload[off + i * 16 : off + i * 16 + 16]) for i in range(8)]
    if n_sensors > 8 or n_bumpers > 8:
        raise BadPayload(f"{n_sensors} sensors / {n_bumpers} bumpers (at most 8 each)")
    return _new(BaseConf, (base_type, radius / _Q8_MM, motor, tuple(sensors[:n_sensors]), tuple(bumpers[:n_bumpers])))


class BinaryConf(NamedTuple):
    """GET_BINARY_CONF: an opaque blob."""

    blob: bytes

    def encode(self) -> bytes:
        return self.blob

    @classmethod
    def decode(cls, payload: bytes) -> BinaryConf:
        return _decode_binary_conf(payload)


def _decode_binary_conf(payload: bytes) -> BinaryConf:
    return _new(BinaryConf, (bytes(payload),))


_STATUS = struct.Struct("<BB")


class BaseStatus(NamedTuple):
    """GET_BASE_STATUS: battery percent and power flags (``PowerFlag`` bits)."""

    battery_percent: int
    power_flags: int  # bit 0 charging, bit 1 external power, bit 2 on dock

    @property
    def charging(self) -> bool:
        return bool(self.power_flags & PowerFlag.CHARGING)

    @property
    def external_power(self) -> bool:
        return bool(self.power_flags & PowerFlag.EXTERNAL_POWER)

    @property
    def on_dock(self) -> bool:
        return bool(self.power_flags & PowerFlag.ON_DOCK)

    def encode(self) -> bytes:
        return _STATUS.pack(self.battery_percent, self.power_flags)

    @classmethod
    def decode(cls, payload: bytes) -> BaseStatus:
        return _checked(_decode_base_status, cls, payload)


def _decode_base_status(payload: bytes) -> BaseStatus:
    fields = _STATUS.unpack(payload)
    if fields[0] > 100:
        raise BadPayload(f"battery {fields[0]} % is above 100")
    return _new(BaseStatus, fields)


_MOTOR = struct.Struct("<iiB")


class MotorData(NamedTuple):
    """GET_BASE_MOTOR_DATA: cumulative wheel distances (m) and status bits (``MotorStatus``)."""

    left: float
    right: float
    status: int  # bit 1 stall, bit 2 traction lost

    def encode(self) -> bytes:
        return _MOTOR.pack(_wrap32(self.left * 1000), _wrap32(self.right * 1000), self.status)

    @classmethod
    def decode(cls, payload: bytes) -> MotorData:
        return _checked(_decode_motor_data, cls, payload)


def _decode_motor_data(payload: bytes) -> MotorData:
    left, right, status = _MOTOR.unpack(payload)
    return _new(MotorData, (left / _MM, right / _MM, status))


def _wrap32(x: float) -> int:
    """Cumulative counters wrap like the board's s32 (after ~2,147 km)."""
    v = round(x) & 0xFFFF_FFFF
    return v - 0x1_0000_0000 if v & 0x8000_0000 else v


_SENSORS = struct.Struct("<16I")


_RANGE_TOP = 0xFFFF_FFFF / Q16 / 1000  # the largest u32 Q16 mm reading (65.536 m), in metres


def _range_q16(d: float) -> int:
    """A range reading (m) as mm Q16 u32, clamped to the field; 0 (no echo) for d <= 0."""
    return _u32(min(d, _RANGE_TOP) * 1000 * Q16) if d > 0 else 0


class SensorData(NamedTuple):
    """GET_BASE_SENSOR_DATA: 16 range readings in metres (configured order; unused = 0)."""

    distances: tuple[float, ...]

    def encode(self) -> bytes:
        vals = list(self.distances)[:16] + [0.0] * (16 - len(self.distances))
        return _SENSORS.pack(*map(_range_q16, vals))

    @classmethod
    def decode(cls, payload: bytes) -> SensorData:
        return _checked(_decode_sensor_data, cls, payload)


def _decode_sensor_data(payload: bytes) -> SensorData:
    # Written out: about 3x faster than a comprehension or map() over the 16 values.
    v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11, v12, v13, v14, v15 = _SENSORS.unpack(payload)
    s = _Q16_MM
    distances = (
        v0 / s, v1 / s, v2 / s, v3 / s, v4 / s, v5 / s, v6 / s, v7 / s,
        v8 / s, v9 / s, v10 / s, v11 / s, v12 / s, v13 / s, v14 / s, v15 / s,
    )  # fmt: skip
    return _new(SensorData, (distances,))


class BumperData(NamedTuple):
    """GET_BASE_BUMPER_DATA: a bitmap, bumpers from bit 0 then cliff sensors; a 0 bit = triggered.

    Firmwares differ in width (u8 or u32); ``width`` records which was received.
    """

    bitmap: int
    width: int = 4

    def triggered(self, bit: int) -> bool:
        return not (self.bitmap >> bit) & 1

    def encode(self) -> bytes:
        return self.bitmap.to_bytes(self.width, "little")

    @classmethod
    def decode(cls, payload: bytes) -> BumperData:
        return _decode_bumper_data(payload)


def _decode_bumper_data(payload: bytes) -> BumperData:
    n = len(payload)
    if n != 4 and n != 1:
        raise BadPayload(f"expected 1 or 4 bytes, got {n}")
    return _new(BumperData, (int.from_bytes(payload, "little"), n))


class AutoHomeData(NamedTuple):
    """GET_AUTO_HOME_DATA: docking beacon probes."""

    beacon_count: int
    probes: bytes

    def encode(self) -> bytes:
        return bytes((self.beacon_count, len(self.probes))) + self.probes

    @classmethod
    def decode(cls, payload: bytes) -> AutoHomeData:
        return _decode_auto_home_data(payload)


def _decode_auto_home_data(payload: bytes) -> AutoHomeData:
    if len(payload) < 2 or len(payload) != 2 + payload[1]:
        raise BadPayload("beacon count, probe count and that many probes expected")
    return _new(AutoHomeData, (payload[0], bytes(payload[2:])))


_DEADRECKON = struct.Struct("<iiiB")


class DeadReckon(NamedTuple):
    """SET_V_AND_GET_DEADRECKON reply: motion since the previous call, in the base frame."""

    dx: float  # m
    dy: float  # m
    dtheta: float  # rad, counter-clockwise
    status: int

    def encode(self) -> bytes:
        return _DEADRECKON.pack(
            _s32(self.dx * 1000 * Q16), _s32(self.dy * 1000 * Q16), _s32(math.degrees(self.dtheta) * Q16), self.status
        )

    @classmethod
    def decode(cls, payload: bytes) -> DeadReckon:
        return _checked(_decode_dead_reckon, cls, payload)


def _decode_dead_reckon(payload: bytes) -> DeadReckon:
    dx, dy, dth, status = _DEADRECKON.unpack(payload)
    return _new(DeadReckon, (dx / _Q16_MM, dy / _Q16_MM, dth * _Q16_DEG, status))


class PendingBaseCommand(NamedTuple):
    """POLL_BASE_CMD reply: a pending command from the base (``PendingCommandCode``), or None."""

    command: int | None

    def encode(self) -> bytes:
        return b"" if self.command is None else bytes((self.command,))

    @classmethod
    def decode(cls, payload: bytes) -> PendingBaseCommand:
        return _decode_pending_base_command(payload)


def _decode_pending_base_command(payload: bytes) -> PendingBaseCommand:
    if len(payload) > 1:
        raise BadPayload(f"expected 0 or 1 byte, got {len(payload)}")
    return _new(PendingBaseCommand, (payload[0] if payload else None,))


_HEALTH = struct.Struct("<BB")


class Health(NamedTuple):
    """HEALTH_MGMT 1 (get health): flags (``HealthFlag`` bits) and error count."""

    flags: int  # bit 0 warning, 1 error, 2 fatal
    error_count: int

    def encode(self) -> bytes:
        return _HEALTH.pack(self.flags, self.error_count)

    @classmethod
    def decode(cls, payload: bytes) -> Health:
        return _checked(_decode_health_reply, cls, payload)


def _decode_health_reply(payload: bytes) -> Health:
    return _new(Health, _HEALTH.unpack(payload))


_HEALTH_ERROR = struct.Struct("<I32s")


class HealthError(NamedTuple):
    """HEALTH_MGMT 2 (get error): code u32 and a 32-byte message."""

    code: int
    message: str

    def encode(self) -> bytes:
        return _HEALTH_ERROR.pack(self.code, self.message.encode("ascii", "replace")[:32])

    @classmethod
    def decode(cls, payload: bytes) -> HealthError:
        return _checked(_decode_health_error, cls, payload)


def _decode_health_error(payload: bytes) -> HealthError:
    code, msg = _HEALTH_ERROR.unpack(payload)
    return _new(HealthError, (code, bytes(msg).split(b"\0", 1)[0].decode("ascii", "replace")))


class HealthErrorCode(IntEnum):
    """fleetlink board error codes reported through HEALTH_MGMT."""

    CORE_DISCONNECTED = 0x0001  # the link watchdog fired
    MOTOR_STALL = 0x0002
    TANK_EMPTY = 0x0003
    BATTERY_LOW = 0x0004


_PAYLOAD_STATUS = struct.Struct("<BBBB")


class PayloadStatus(NamedTuple):
    """GET_PAYLOAD_STATUS (extension): UV-C lamp, atomiser level, fan, tank level %."""

    uv_lamp: bool
    atomiser_level: int  # 0-3
    fan: bool
    tank_percent: int

    def encode(self) -> bytes:
        return _PAYLOAD_STATUS.pack(int(self.uv_lamp), self.atomiser_level, int(self.fan), self.tank_percent)

    @classmethod
    def decode(cls, payload: bytes) -> PayloadStatus:
        return _checked(_decode_payload_status, cls, payload)


def _decode_payload_status(payload: bytes) -> PayloadStatus:
    uv, level, fan, tank = _PAYLOAD_STATUS.unpack(payload)
    if level > 3 or tank > 100 or uv > 1 or fan > 1:
        raise BadPayload(f"payload status out of range: uv={uv} level={level} fan={fan} tank={tank}")
    return _new(PayloadStatus, (uv == 1, level, fan == 1, tank))


_ENV = struct.Struct("<BhHHH")


class EnvData(NamedTuple):
    """GET_ENV_DATA (extension): disinfectant level, temperature, humidity, air quality."""

    disinfectant_percent: int
    temperature_c: float  # 0.01 °C on the wire
    humidity_percent: float  # 0.01 % on the wire
    pm2_5: float  # µg/m³, 0.1 on the wire
    tvoc_ppb: int

    def encode(self) -> bytes:
        return _ENV.pack(
            self.disinfectant_percent,
            round(self.temperature_c * 100),
            round(self.humidity_percent * 100),
            round(self.pm2_5 * 10),
            self.tvoc_ppb,
        )

    @classmethod
    def decode(cls, payload: bytes) -> EnvData:
        return _checked(_decode_env_data, cls, payload)


def _decode_env_data(payload: bytes) -> EnvData:
    level, t, h, pm, tvoc = _ENV.unpack(payload)
    if level > 100 or h > 10000:
        raise BadPayload(f"environment reading out of range: level={level} humidity={h / 100}")
    return _new(EnvData, (level, t / 100, h / 100, pm / 10, tvoc))


_POWER = struct.Struct("<HhBB")


class PowerData(NamedTuple):
    """GET_POWER_DATA (extension): battery voltage and current, percent, power flags."""

    voltage: float  # V (mV on the wire)
    current: float  # A, positive when charging (mA on the wire)
    battery_percent: int
    power_flags: int  # ``PowerFlag`` bits, as BaseStatus

    def encode(self) -> bytes:
        return _POWER.pack(
            round(self.voltage * 1000), round(self.current * 1000), self.battery_percent, self.power_flags
        )

    @classmethod
    def decode(cls, payload: bytes) -> PowerData:
        return _checked(_decode_power_data, cls, payload)


def _decode_power_data(payload: bytes) -> PowerData:
    mv, ma, pct, flags = _POWER.unpack(payload)
    return _new(PowerData, (mv / _MM, ma / _MM, pct, flags))


_BUTTONS = struct.Struct("<B")


class Buttons(NamedTuple):
    """GET_BUTTONS (extension): ``Button`` bits: 0 power, 1 home, 2 start/pause, 3 emergency stop engaged."""

    bitmap: int

    def encode(self) -> bytes:
        return bytes((self.bitmap,))

    @classmethod
    def decode(cls, payload: bytes) -> Buttons:
        return _checked(_decode_buttons, cls, payload)


def _decode_buttons(payload: bytes) -> Buttons:
    return _new(Buttons, _BUTTONS.unpack(payload))


_IMU = struct.Struct("<iiI")
_Q16_TO_RAD = 1.0 / Q16 * _DEG


class ImuData(NamedTuple):
    """GET_IMU_DATA (extension): the gyro's yaw rate and integrated yaw, and a sample counter.

    yaw_rate (rad/s) and yaw (rad, wrapped to [-pi, pi)) travel as degrees Q16 s32, like
    SET_V_AND_GET_DEADRECKON's dtheta; samples u32 counts gyro updates since power-on.
    """

    yaw_rate: float
    yaw: float
    samples: int

    def encode(self) -> bytes:
        return _IMU.pack(
            _s32(math.degrees(self.yaw_rate) * Q16), _s32(math.degrees(self.yaw) * Q16), self.samples & 0xFFFF_FFFF
        )

    @classmethod
    def decode(cls, payload: bytes) -> ImuData:
        return _checked(_decode_imu, cls, payload)


def _decode_imu(payload: bytes) -> ImuData:
    rate, yaw, samples = _IMU.unpack(payload)
    return _new(ImuData, (rate * _Q16_TO_RAD, yaw * _Q16_TO_RAD, samples))


_TELEMETRY_HEAD = struct.Struct("<BiiBiiIIB")
_TELEMETRY_GYRO = 0x01  # flags bit 0: a gyro is fitted (else the IMU fields are zero and mean nothing)


class Telemetry(NamedTuple):
    """GET_TELEMETRY (extension): what the master polls at its sensor rate, in one exchange.

    One reading of the wheels, the gyro, the range sensors and the bumper/cliff bitmap, sampled
    together: the same fields as GET_BASE_MOTOR_DATA, GET_IMU_DATA, GET_BASE_SENSOR_DATA and
    GET_BASE_BUMPER_DATA (u32 bitmap), each in its own reply type. Layout: flags u8 (bit 0 gyro
    fitted), left mm s32, right mm s32, motor status u8, yaw rate deg Q16 s32, yaw deg Q16 s32,
    gyro samples u32, bumper bitmap u32, sensor count u8 (0-16), count x distance mm Q16 u32.
    ``imu`` is None for a board without a gyro; ``sensors`` holds only the fitted sensors.
    """

    motor: MotorData
    imu: ImuData | None
    sensors: SensorData
    bumpers: BumperData

    def encode(self) -> bytes:
        m, imu, d = self.motor, self.imu, self.sensors.distances
        if len(d) > 16:
            raise ValueError(f"at most 16 range sensors, got {len(d)}")
        gyro = imu or ImuData(0.0, 0.0, 0)
        head = _TELEMETRY_HEAD.pack(
            _TELEMETRY_GYRO if imu is not None else 0,
            _wrap32(m.left * 1000),
            _wrap32(m.right * 1000),
            m.status,
            _s32(math.degrees(gyro.yaw_rate) * Q16),
            _s32(math.degrees(gyro.yaw) * Q16),
            gyro.samples & 0xFFFF_FFFF,
            self.bumpers.bitmap & 0xFFFF_FFFF,
            len(d),
        )
        return head + struct.pack(f"<{len(d)}I", *map(_range_q16, d))

    @classmethod
    def decode(cls, payload: bytes) -> Telemetry:
        return _decode_telemetry(payload)


def _decode_telemetry(payload: bytes) -> Telemetry:
    n = len(payload) - _TELEMETRY_HEAD.size
    if n < 0:
        raise BadPayload(f"expected at least {_TELEMETRY_HEAD.size} bytes, got {len(payload)}")
    flags, left, right, status, rate, yaw, samples, bumpers, count = _TELEMETRY_HEAD.unpack_from(payload)
    if count > 16:
        raise BadPayload(f"{count} range sensors (at most 16)")
    if n != 4 * count:
        raise BadPayload(f"{count} range sensors need {_TELEMETRY_HEAD.size + 4 * count} bytes, got {len(payload)}")
    s = _Q16_MM
    distances = tuple(v / s for v in struct.unpack_from(f"<{count}I", payload, _TELEMETRY_HEAD.size))
    return _new(
        Telemetry,
        (
            _new(MotorData, (left / _MM, right / _MM, status)),
            _new(ImuData, (rate * _Q16_TO_RAD, yaw * _Q16_TO_RAD, samples)) if flags & _TELEMETRY_GYRO else None,
            _new(SensorData, (distances,)),
            _new(BumperData, (bumpers, 4)),
        ),
    )


Reply: TypeAlias = (
    Empty
    | BaseInfo
    | BaseConf
    | BinaryConf
    | BaseStatus
    | MotorData
    | SensorData
    | BumperData
    | AutoHomeData
    | DeadReckon
    | PendingBaseCommand
    | Health
    | HealthError
    | PayloadStatus
    | EnvData
    | PowerData
    | Buttons
    | ImuData
    | Telemetry
)

# decode_reply's dispatch: reply type -> decoder of its OK payload.
_REPLY_DECODERS: dict[type[Reply] | None, Callable[[bytes], Reply]] = {
    Empty: _decode_empty,
    BaseInfo: _decode_base_info,
    BaseConf: _decode_base_conf,
    BinaryConf: _decode_binary_conf,
    BaseStatus: _decode_base_status,
    MotorData: _decode_motor_data,
    SensorData: _decode_sensor_data,
    BumperData: _decode_bumper_data,
    AutoHomeData: _decode_auto_home_data,
    DeadReckon: _decode_dead_reckon,
    PendingBaseCommand: _decode_pending_base_command,
    Health: _decode_health_reply,
    HealthError: _decode_health_error,
    PayloadStatus: _decode_payload_status,
    EnvData: _decode_env_data,
    PowerData: _decode_power_data,
    Buttons: _decode_buttons,
    ImuData: _decode_imu,
    Telemetry: _decode_telemetry,
}

# Fixed payload sizes, for the message when a payload has the wrong size.
_REPLY_SIZES: dict[type, int] = {
    BaseInfo: _BASE_INFO.size,
    MountPose: _POSE.size,
    BaseConf: _CONF_SIZE,
    BaseStatus: _STATUS.size,
    MotorData: _MOTOR.size,
    SensorData: _SENSORS.size,
    DeadReckon: _DEADRECKON.size,
    Health: _HEALTH.size,
    HealthError: _HEALTH_ERROR.size,
    PayloadStatus: _PAYLOAD_STATUS.size,
    EnvData: _ENV.size,
    PowerData: _POWER.size,
    Buttons: _BUTTONS.size,
    ImuData: _IMU.size,
}


# --------------------------------------------------------------------------------------------
# Requests (a CTRL_BUS frame's payload: command code, then arguments)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ConnectBase:
    protocol_version: int = 1

    CODE: ClassVar[int] = CtrlBus.CONNECT_BASE
    REPLY: ClassVar[type[Reply]] = BaseInfo

    def encode_args(self) -> bytes:
        return bytes((self.protocol_version,))

    @classmethod
    def decode_args(cls, args: bytes) -> ConnectBase:
        if len(args) != 1:
            raise BadPayload(f"expected protocol version u8, got {len(args)} bytes")
        return cls(args[0])


@dataclass(frozen=True, slots=True)
class GetBaseConf:
    CODE: ClassVar[int] = CtrlBus.GET_BASE_CONF
    REPLY: ClassVar[type[Reply]] = BaseConf

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetBaseConf:
        _expect_empty(args)
        return cls()


def _expect_empty(args: bytes) -> None:
    if args:
        raise BadPayload(f"expected no arguments, got {len(args)} bytes")


@dataclass(frozen=True, slots=True)
class GetBinaryConf:
    CODE: ClassVar[int] = CtrlBus.GET_BINARY_CONF
    REPLY: ClassVar[type[Reply]] = BinaryConf

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetBinaryConf:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetBaseStatus:
    CODE: ClassVar[int] = CtrlBus.GET_BASE_STATUS
    REPLY: ClassVar[type[Reply]] = BaseStatus

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetBaseStatus:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetMotorData:
    CODE: ClassVar[int] = CtrlBus.GET_BASE_MOTOR_DATA
    REPLY: ClassVar[type[Reply]] = MotorData

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetMotorData:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetSensorData:
    CODE: ClassVar[int] = CtrlBus.GET_BASE_SENSOR_DATA
    REPLY: ClassVar[type[Reply]] = SensorData

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetSensorData:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetBumperData:
    CODE: ClassVar[int] = CtrlBus.GET_BASE_BUMPER_DATA
    REPLY: ClassVar[type[Reply]] = BumperData

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetBumperData:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetAutoHomeData:
    data_type: int = 0  # 0 beacon

    CODE: ClassVar[int] = CtrlBus.GET_AUTO_HOME_DATA
    REPLY: ClassVar[type[Reply]] = AutoHomeData

    def encode_args(self) -> bytes:
        return bytes((self.data_type,))

    @classmethod
    def decode_args(cls, args: bytes) -> GetAutoHomeData:
        if len(args) != 1:
            raise BadPayload(f"expected data_type u8, got {len(args)} bytes")
        return cls(args[0])


_WHEELS = struct.Struct("<4i")


@dataclass(frozen=True, slots=True)
class SetBaseMotor:
    """Wheel speeds in m/s (mm/s s32 on the wire): [0] left, [1] right, [2], [3] unused here."""

    speeds: tuple[float, float, float, float]

    CODE: ClassVar[int] = CtrlBus.SET_BASE_MOTOR
    REPLY: ClassVar[type[Reply]] = Empty

    @classmethod
    def wheels(cls, left: float, right: float) -> SetBaseMotor:
        return cls((left, right, 0.0, 0.0))

    def encode_args(self) -> bytes:
        _finite("wheel speed", *self.speeds)
        return _WHEELS.pack(*(_s32(s * 1000) for s in self.speeds))

    @classmethod
    def decode_args(cls, args: bytes) -> SetBaseMotor:
        a, b, c, d = _unpack(_WHEELS, args)
        return cls((a / 1000, b / 1000, c / 1000, d / 1000))


_VELOCITY = struct.Struct("<iii")


@dataclass(frozen=True, slots=True)
class SetVelocity:
    """SET_V_AND_GET_DEADRECKON: body velocity in, motion since the last call out.

    vx, vy in m/s and omega in rad/s (Q16 s32 on the wire). The master sends this every motion
    poll, which is also what keeps the board's link watchdog fed.
    """

    vx: float
    vy: float = 0.0
    omega: float = 0.0

    CODE: ClassVar[int] = CtrlBus.SET_V_AND_GET_DEADRECKON
    REPLY: ClassVar[type[Reply]] = DeadReckon

    def encode_args(self) -> bytes:
        _finite("velocity", self.vx, self.vy, self.omega)
        return _VELOCITY.pack(_s32(self.vx * Q16), _s32(self.vy * Q16), _s32(self.omega * Q16))

    @classmethod
    def decode_args(cls, args: bytes) -> SetVelocity:
        vx, vy, w = _unpack(_VELOCITY, args)
        return cls(vx / Q16, vy / Q16, w / Q16)


@dataclass(frozen=True, slots=True)
class PollBaseCommand:
    CODE: ClassVar[int] = CtrlBus.POLL_BASE_CMD
    REPLY: ClassVar[type[Reply]] = PendingBaseCommand

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> PollBaseCommand:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class AnswerBaseCommand:
    """POLL_BASE_ANS_CMD: clears the pending base command."""

    CODE: ClassVar[int] = CtrlBus.POLL_BASE_ANS_CMD
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> AnswerBaseCommand:
        _expect_empty(args)
        return cls()


class BaseEvent(IntEnum):
    LIDAR_CONNECT_FAILED = 0x61
    SYSTEM_UP = 0x63
    CORE_DISCONNECTED = 0x65


@dataclass(frozen=True, slots=True)
class SendEvent:
    event: int

    CODE: ClassVar[int] = CtrlBus.SEND_EVENT
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        return bytes((self.event,))

    @classmethod
    def decode_args(cls, args: bytes) -> SendEvent:
        if len(args) != 1:
            raise BadPayload(f"expected event u8, got {len(args)} bytes")
        return cls(args[0])


@dataclass(frozen=True, slots=True)
class GetHealth:
    """HEALTH_MGMT sub-command 1."""

    CODE: ClassVar[int] = CtrlBus.HEALTH_MGMT
    REPLY: ClassVar[type[Reply]] = Health

    def encode_args(self) -> bytes:
        return b"\x01"


@dataclass(frozen=True, slots=True)
class GetHealthError:
    """HEALTH_MGMT sub-command 2: the error at ``index``."""

    index: int

    CODE: ClassVar[int] = CtrlBus.HEALTH_MGMT
    REPLY: ClassVar[type[Reply]] = HealthError

    def encode_args(self) -> bytes:
        return bytes((2, self.index))


@dataclass(frozen=True, slots=True)
class ClearHealthError:
    """HEALTH_MGMT sub-command 3: clear the error with ``code``."""

    code: int

    CODE: ClassVar[int] = CtrlBus.HEALTH_MGMT
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        return b"\x03" + struct.pack("<I", self.code)


def _decode_health(args: bytes) -> GetHealth | GetHealthError | ClearHealthError:
    if args == b"\x01":
        return GetHealth()
    if len(args) == 2 and args[0] == 2:
        return GetHealthError(args[1])
    if len(args) == 5 and args[0] == 3:
        return ClearHealthError(struct.unpack_from("<I", args, 1)[0])
    raise BadPayload("HEALTH_MGMT expects 01, 02 index, or 03 code")


@dataclass(frozen=True, slots=True)
class SetUvLamp:
    on: bool

    CODE: ClassVar[int] = CtrlBus.SET_UV_LAMP
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        return bytes((int(self.on),))

    @classmethod
    def decode_args(cls, args: bytes) -> SetUvLamp:
        return cls(_flag(args))


def _flag(args: bytes) -> bool:
    if len(args) != 1 or args[0] > 1:
        raise BadPayload("expected one byte, 0 (off) or 1 (on)")
    return bool(args[0])


@dataclass(frozen=True, slots=True)
class SetAtomiser:
    """Atomiser level 0 (off) to 3; the board refuses levels above 0 with an empty tank."""

    level: int

    CODE: ClassVar[int] = CtrlBus.SET_ATOMISER
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        if not 0 <= self.level <= 3:
            raise ValueError(f"atomiser level {self.level} is not 0-3")
        return bytes((self.level,))

    @classmethod
    def decode_args(cls, args: bytes) -> SetAtomiser:
        if len(args) != 1 or args[0] > 3:
            raise BadPayload("expected atomiser level 0-3")
        return cls(args[0])


@dataclass(frozen=True, slots=True)
class SetFan:
    on: bool

    CODE: ClassVar[int] = CtrlBus.SET_FAN
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        return bytes((int(self.on),))

    @classmethod
    def decode_args(cls, args: bytes) -> SetFan:
        return cls(_flag(args))


@dataclass(frozen=True, slots=True)
class GetPayloadStatus:
    CODE: ClassVar[int] = CtrlBus.GET_PAYLOAD_STATUS
    REPLY: ClassVar[type[Reply]] = PayloadStatus

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetPayloadStatus:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetEnvData:
    CODE: ClassVar[int] = CtrlBus.GET_ENV_DATA
    REPLY: ClassVar[type[Reply]] = EnvData

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetEnvData:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetPowerData:
    CODE: ClassVar[int] = CtrlBus.GET_POWER_DATA
    REPLY: ClassVar[type[Reply]] = PowerData

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetPowerData:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetButtons:
    CODE: ClassVar[int] = CtrlBus.GET_BUTTONS
    REPLY: ClassVar[type[Reply]] = Buttons

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetButtons:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetImuData:
    CODE: ClassVar[int] = CtrlBus.GET_IMU_DATA
    REPLY: ClassVar[type[Reply]] = ImuData

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetImuData:
        _expect_empty(args)
        return cls()


@dataclass(frozen=True, slots=True)
class GetTelemetry:
    CODE: ClassVar[int] = CtrlBus.GET_TELEMETRY
    REPLY: ClassVar[type[Reply]] = Telemetry

    def encode_args(self) -> bytes:
        return b""

    @classmethod
    def decode_args(cls, args: bytes) -> GetTelemetry:
        _expect_empty(args)
        return cls()


_LEDS = struct.Struct("<BBBB")


@dataclass(frozen=True, slots=True)
class SetLeds:
    """mode 0 off, 1 solid, 2 blink, 3 breathe; colour as 8-bit RGB."""

    mode: int
    red: int = 0
    green: int = 0
    blue: int = 0

    CODE: ClassVar[int] = CtrlBus.SET_LEDS
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        return _LEDS.pack(self.mode, self.red, self.green, self.blue)

    @classmethod
    def decode_args(cls, args: bytes) -> SetLeds:
        mode, r, g, b = _unpack(_LEDS, args)
        if mode > 3:
            raise BadPayload(f"LED mode {mode} is not 0-3")
        return cls(mode, r, g, b)


_BEEP = struct.Struct("<HH")


@dataclass(frozen=True, slots=True)
class Beep:
    frequency_hz: int
    duration_s: float  # ms on the wire

    CODE: ClassVar[int] = CtrlBus.BEEP
    REPLY: ClassVar[type[Reply]] = Empty

    def encode_args(self) -> bytes:
        return _BEEP.pack(self.frequency_hz, round(self.duration_s * 1000))

    @classmethod
    def decode_args(cls, args: bytes) -> Beep:
        f, ms = _unpack(_BEEP, args)
        return cls(f, ms / 1000)


Request: TypeAlias = (
    ConnectBase
    | GetBaseConf
    | GetBinaryConf
    | GetBaseStatus
    | GetMotorData
    | GetSensorData
    | GetBumperData
    | GetAutoHomeData
    | SetBaseMotor
    | SetVelocity
    | PollBaseCommand
    | AnswerBaseCommand
    | SendEvent
    | GetHealth
    | GetHealthError
    | ClearHealthError
    | SetUvLamp
    | SetAtomiser
    | SetFan
    | GetPayloadStatus
    | GetEnvData
    | GetPowerData
    | GetButtons
    | GetImuData
    | GetTelemetry
    | SetLeds
    | Beep
)

REQUEST_TYPES: tuple[type, ...] = (
    ConnectBase,
    GetBaseConf,
    GetBinaryConf,
    GetBaseStatus,
    GetMotorData,
    GetSensorData,
    GetBumperData,
    GetAutoHomeData,
    SetBaseMotor,
    SetVelocity,
    PollBaseCommand,
    AnswerBaseCommand,
    SendEvent,
    GetHealth,
    GetHealthError,
    ClearHealthError,
    SetUvLamp,
    SetAtomiser,
    SetFan,
    GetPayloadStatus,
    GetEnvData,
    GetPowerData,
    GetButtons,
    GetImuData,
    GetTelemetry,
    SetLeds,
    Beep,
)

_DECODERS: dict[int, Callable[[bytes], IncomingRequest]] = {
    cls.CODE: cls.decode_args  # type: ignore[attr-defined]
    for cls in REQUEST_TYPES
    if hasattr(cls, "decode_args")
}
_DECODERS[CtrlBus.HEALTH_MGMT] = _decode_health


# --------------------------------------------------------------------------------------------
# Whole frames, both directions
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Sync:
    """SYNC request or reply: the board sends the whole request frame back unchanged."""

    data: bytes


@dataclass(frozen=True, slots=True)
class Echo:
    """ECHO request or reply."""

    data: bytes


@dataclass(frozen=True, slots=True)
class BaseCommand:
    """0xF9 base/UI command (reference firmware): 1 enter DFU, 2 reboot."""

    command: int


@dataclass(frozen=True, slots=True)
class Rejected:
    """A request the board cannot serve, with the error code it must answer."""

    error: int
    reason: str


@dataclass(frozen=True, slots=True)
class ErrorReply:
    """An ERROR response from the board."""

    code: int

    def __str__(self) -> str:
        return ErrorCode.describe(self.code)


@dataclass(frozen=True, slots=True)
class InvalidReply:
    """An INVALID response (packet incomplete or malformed)."""

    payload: bytes


@dataclass(frozen=True, slots=True)
class Malformed:
    """A reply whose code or payload does not fit what was asked."""

    reason: str


IncomingRequest: TypeAlias = Request | Sync | Echo | BaseCommand | Rejected
IncomingReply: TypeAlias = Reply | Sync | Echo | ErrorReply | InvalidReply | Malformed


def encode_request(req: Request, profile: Profile = DEFAULT_PROFILE) -> bytes:
    """The CTRL_BUS frame for one typed request."""
    return encode_frame(profile.ctrl_bus_cmd, bytes((req.CODE,)) + req.encode_args(), long=profile.long_requests)


def encode_sync(data: bytes = b"", profile: Profile = DEFAULT_PROFILE) -> bytes:
    return encode_frame(CMD_SYNC, data, long=profile.long_requests)


def encode_echo(data: bytes = b"", profile: Profile = DEFAULT_PROFILE) -> bytes:
    return encode_frame(CMD_ECHO, data, long=profile.long_requests)


def decode_request(frame: Frame, profile: Profile = DEFAULT_PROFILE) -> IncomingRequest:
    """Board side: a typed request, or ``Rejected`` with the error code to answer."""
    code = frame.code
    payload = frame.payload
    if code == profile.ctrl_bus_cmd:
        if not payload:
            return Rejected(ErrorCode.BAD_ARGUMENTS, "CTRL_BUS request without a command byte")
        decoder = _DECODERS.get(payload[0])
        if decoder is None:
            return Rejected(ErrorCode.NOT_SUPPORTED, f"Control Bus command 0x{payload[0]:02X} not supported")
        try:
            return decoder(payload[1:])
        except (BadPayload, struct.error) as exc:
            return Rejected(ErrorCode.BAD_ARGUMENTS, f"{CtrlBus(payload[0]).name}: {exc}")
    if code == CMD_SYNC:
        return Sync(payload)
    if code == CMD_ECHO:
        return Echo(payload)
    if code == CMD_BASE:
        if len(payload) != 1:
            return Rejected(ErrorCode.BAD_ARGUMENTS, "base command expects one byte")
        return BaseCommand(payload[0])
    return Rejected(ErrorCode.NOT_SUPPORTED, f"request CMD 0x{code:02X} not supported")


def decode_reply(frame: Frame, expected: type[Reply] | None) -> IncomingReply:
    """Master side: decode a reply against the reply type of the request that was sent.

    The OK path is the master's hot loop (tens of thousands of replies a second): one dict
    lookup by type, then the type's plain decoder function (struct unpack, SI scaling, C-level
    tuple construction). Failures, including a payload of the wrong size, become ``Malformed``.
    """
    code, payload, _ = frame
    if code == RESP_OK:
        try:
            return _REPLY_DECODERS[expected](payload)
        except (BadPayload, struct.error, UnicodeError) as exc:
            reason = _size_problem(expected, payload) if isinstance(exc, struct.error) else str(exc)
            return Malformed(f"{getattr(expected, '__name__', expected)}: {reason}")
        except KeyError:
            if expected is None:
                return Malformed("OK reply without a request in flight")
            return Malformed(f"{getattr(expected, '__name__', expected)}: not a reply type")
    if code == RESP_ERROR:
        if len(payload) != 2:
            return Malformed(f"ERROR reply with {len(payload)} payload bytes (u16 expected)")
        return ErrorReply(payload[0] | (payload[1] << 8))
    if code == RESP_SYNC:
        return Sync(payload)
    if code == RESP_ECHO:
        return Echo(payload)
    if code == RESP_INVALID:
        return InvalidReply(payload)
    return Malformed(f"unknown response code 0x{code:02X}")


def encode_ok(reply: Reply) -> bytes:
    """Board side: the OK frame (always long, like the reference base)."""
    return encode_frame(RESP_OK, reply.encode(), long=True)


def encode_error(code: int) -> bytes:
    return encode_frame(RESP_ERROR, struct.pack("<H", code), long=True)
