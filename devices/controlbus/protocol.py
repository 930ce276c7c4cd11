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
from dataclasses import dataclass, field, fields
from enum import IntEnum, IntFlag
from operator import attrgetter
from typing import Any, ClassVar, NamedTuple, Protocol, TypeAlias, TypeVar, cast, get_args

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
        return is_protocol_error(self.value)

    @classmethod
    def describe(cls, code: int) -> str:
        try:
            return f"0x{code:04X} {cls(code).name.lower().replace('_', ' ')}"
        except ValueError:
            return f"0x{code:04X} unknown error"


def is_protocol_error(code: int) -> bool:
    """An ERROR code below 0x8000 (known or not) says the exchange broke; 0x8000 and up, a refusal."""
    return code < 0x8000


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
    size = _PAYLOAD_SIZES.get(cls) if cls is not None else None
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

    @property
    def triggered_bits(self) -> int:
        """Bit i set when sensor i is triggered (the bitmap inverted within its width)."""
        return ~self.bitmap & ((1 << (8 * self.width)) - 1)

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
    """GET_PAYLOAD_STATUS (extension): UV-C lamp, atomiser level, fan level, tank level %."""

    uv_lamp: bool
    atomiser_level: int  # 0-3
    fan_level: int  # 0 (off) - 3
    tank_percent: int

    def encode(self) -> bytes:
        return _PAYLOAD_STATUS.pack(int(self.uv_lamp), self.atomiser_level, self.fan_level, self.tank_percent)

    @classmethod
    def decode(cls, payload: bytes) -> PayloadStatus:
        return _checked(_decode_payload_status, cls, payload)


def _decode_payload_status(payload: bytes) -> PayloadStatus:
    uv, level, fan, tank = _PAYLOAD_STATUS.unpack(payload)
    if level > 3 or tank > 100 or uv > 1 or fan > 3:
        raise BadPayload(f"payload status out of range: uv={uv} level={level} fan={fan} tank={tank}")
    return _new(PayloadStatus, (uv == 1, level, fan, tank))


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


# --------------------------------------------------------------------------------------------
# Request arguments: a few field kinds, from which each command's layout is composed
# --------------------------------------------------------------------------------------------

_INT_RANGE = {"B": (0, 0xFF), "H": (0, 0xFFFF), "I": (0, 0xFFFF_FFFF), "i": (-0x8000_0000, 0x7FFF_FFFF)}


@dataclass(frozen=True, slots=True)
class Field:
    """One request argument: a little-endian integer on the wire (``fmt``, a ``struct`` code).

    ``scale``: the SI value times ``scale``, rounded, is the wire integer (and the value must be
    finite); ``high``: the largest value allowed, checked in both directions; ``flag``: a bool
    carried as 0 or 1; ``count``: the argument is a tuple of that many values. ``what`` names it
    in error messages.
    """

    fmt: str
    scale: float | None = None
    high: int | None = None
    flag: bool = False
    count: int = 1
    what: str = "argument"

    def to_wire(self, value: Any) -> int:
        if self.scale is not None:
            if not math.isfinite(value):
                raise ValueError(f"{self.what} must be finite, got {value}")
            v: int = round(value * self.scale)
        else:
            v = int(value)
        low, high = _INT_RANGE[self.fmt]
        if self.high is not None:
            high = self.high
        if not low <= v <= high:
            raise ValueError(f"{self.what} {value} does not fit its field ({low}-{high} on the wire)")
        return v

    def from_wire(self, v: int) -> Any:
        if self.high is not None and v > self.high:
            raise BadPayload(f"{self.what} {v} is not 0-{self.high}")
        if self.flag:
            if v > 1:
                raise BadPayload(f"{self.what} must be 0 (off) or 1 (on), got {v}")
            return v == 1
        return v if self.scale is None else v / self.scale


U8 = Field("B")
U16 = Field("H")
U32 = Field("I")
ON_OFF = Field("B", flag=True, what="on/off flag")


class Args:
    """A request's argument layout: an optional sub-command byte, then ``fields`` in the order of
    the request's dataclass fields."""

    __slots__ = ("fields", "prefix", "size", "struct")

    def __init__(self, *fields: Field, sub: int | None = None) -> None:
        self.fields = fields
        self.prefix = b"" if sub is None else bytes((sub,))
        self.struct = struct.Struct("<" + "".join(f"{f.count}{f.fmt}" if f.count > 1 else f.fmt for f in fields))
        self.size = len(self.prefix) + self.struct.size

    @property
    def sub(self) -> int | None:
        return self.prefix[0] if self.prefix else None

    def encode(self, values: tuple[Any, ...]) -> bytes:
        if not self.fields:
            return self.prefix
        wire: list[int] = []
        for f, value in zip(self.fields, values, strict=True):
            if f.count == 1:
                wire.append(f.to_wire(value))
            elif len(value) != f.count:
                raise ValueError(f"{f.what}: {f.count} values expected, got {len(value)}")
            else:
                wire += map(f.to_wire, value)
        return self.prefix + self.struct.pack(*wire)

    def decode(self, args: bytes) -> list[Any]:
        n = len(self.prefix)
        if len(args) != self.size or args[:n] != self.prefix:
            if not self.fields:
                raise BadPayload(f"expected no arguments, got {_bytes(len(args) - n)}")
            raise BadPayload(f"expected {_bytes(self.struct.size)} of arguments, got {len(args) - n}")
        wire = self.struct.unpack_from(args, n)
        values: list[Any] = []
        i = 0
        for f in self.fields:
            if f.count == 1:
                values.append(f.from_wire(wire[i]))
            else:
                values.append(tuple(map(f.from_wire, wire[i : i + f.count])))
            i += f.count
        return values


NO_ARGS = Args()

_Req = TypeVar("_Req", bound="_Request")


class _Request:
    """What every request has; ``COMMANDS`` fills in each class's row (code, reply type, layout)."""

    __slots__ = ()
    CODE: ClassVar[int]
    REPLY: ClassVar[type[Reply]]
    COMMAND: ClassVar[Command]

    def encode_args(self) -> bytes:
        return self.COMMAND.args.encode(self.COMMAND.values(self))

    @classmethod
    def decode_args(cls: type[_Req], args: bytes) -> _Req:
        return cls(*cls.COMMAND.args.decode(args))


# --------------------------------------------------------------------------------------------
# Requests (a CTRL_BUS frame's payload: command code, then arguments). Their codes, layouts and
# replies are in the command table below.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)  # no slots: a frozen slotted dataclass's __setattr__ breaks in subclasses
class _NoArgs(_Request):
    """A request without arguments: one declaration for all of them (each subclass is its own
    type, equal only to itself)."""


class GetBaseConf(_NoArgs):
    """GET_BASE_CONF: the base's shape and sensor poses."""


class GetBinaryConf(_NoArgs):
    """GET_BINARY_CONF: an opaque configuration blob."""


class GetBaseStatus(_NoArgs):
    """GET_BASE_STATUS: battery and power flags."""


class GetMotorData(_NoArgs):
    """GET_BASE_MOTOR_DATA: cumulative wheel distances."""


class GetSensorData(_NoArgs):
    """GET_BASE_SENSOR_DATA: range sensors."""


class GetBumperData(_NoArgs):
    """GET_BASE_BUMPER_DATA: bumper and cliff bitmap."""


class PollBaseCommand(_NoArgs):
    """POLL_BASE_CMD: a command the base asks the master to run (go home)."""


class AnswerBaseCommand(_NoArgs):
    """POLL_BASE_ANS_CMD: clears the pending base command."""


class GetHealth(_NoArgs):
    """HEALTH_MGMT sub-command 1: flags and error count."""


class GetPayloadStatus(_NoArgs):
    """GET_PAYLOAD_STATUS (extension): lamp, atomiser, fan, tank."""


class GetEnvData(_NoArgs):
    """GET_ENV_DATA (extension): disinfectant, temperature, humidity, air."""


class GetPowerData(_NoArgs):
    """GET_POWER_DATA (extension): battery voltage and current."""


class GetButtons(_NoArgs):
    """GET_BUTTONS (extension): the buttons, the emergency stop among them."""


class GetImuData(_NoArgs):
    """GET_IMU_DATA (extension): the gyro."""


class GetTelemetry(_NoArgs):
    """GET_TELEMETRY (extension): wheels, gyro, range sensors and bumpers in one exchange."""


@dataclass(frozen=True, slots=True)
class ConnectBase(_Request):
    protocol_version: int = 1


@dataclass(frozen=True, slots=True)
class GetAutoHomeData(_Request):
    data_type: int = 0  # 0 beacon


@dataclass(frozen=True, slots=True)
class SetBaseMotor(_Request):
    """Wheel speeds in m/s (mm/s s32 on the wire): [0] left, [1] right, [2], [3] unused here."""

    speeds: tuple[float, float, float, float]

    @classmethod
    def wheels(cls, left: float, right: float) -> SetBaseMotor:
        return cls((left, right, 0.0, 0.0))


@dataclass(frozen=True, slots=True)
class SetVelocity(_Request):
    """SET_V_AND_GET_DEADRECKON: body velocity in, motion since the last call out.

    vx, vy in m/s and omega in rad/s (Q16 s32 on the wire). The master sends this every motion
    poll, which is also what keeps the board's link watchdog fed.
    """

    vx: float
    vy: float = 0.0
    omega: float = 0.0


class BaseEvent(IntEnum):
    LIDAR_CONNECT_FAILED = 0x61
    SYSTEM_UP = 0x63
    CORE_DISCONNECTED = 0x65


@dataclass(frozen=True, slots=True)
class SendEvent(_Request):
    event: int  # ``BaseEvent``


@dataclass(frozen=True, slots=True)
class GetHealthError(_Request):
    """HEALTH_MGMT sub-command 2: the error at ``index``."""

    index: int


@dataclass(frozen=True, slots=True)
class ClearHealthError(_Request):
    """HEALTH_MGMT sub-command 3: clear the error with ``code``."""

    code: int


@dataclass(frozen=True, slots=True)
class SetUvLamp(_Request):
    on: bool


@dataclass(frozen=True, slots=True)
class SetAtomiser(_Request):
    """Atomiser level 0 (off) to 3; the board refuses levels above 0 with an empty tank."""

    level: int


@dataclass(frozen=True, slots=True)
class SetFan(_Request):
    """HEPA fan level 0 (off) to 3 (a first-generation board took 0/1: the same bytes)."""

    level: int


@dataclass(frozen=True, slots=True)
class SetLeds(_Request):
    """mode 0 off, 1 solid, 2 blink, 3 breathe; colour as 8-bit RGB."""

    mode: int
    red: int = 0
    green: int = 0
    blue: int = 0


@dataclass(frozen=True, slots=True)
class Beep(_Request):
    frequency_hz: int
    duration_s: float  # ms on the wire


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


# --------------------------------------------------------------------------------------------
# The command table: every Control Bus command, once
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Command:
    """One Control Bus command: its code, its request type and argument layout, its reply type."""

    code: CtrlBus
    request: type[Request]
    args: Args
    reply: type[Reply]
    values: Callable[[Any], tuple[Any, ...]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        names = [f.name for f in fields(self.request)]
        if len(names) != len(self.args.fields):
            raise TypeError(f"{self.request.__name__}: {len(names)} fields, {len(self.args.fields)} in its layout")
        # A request's field values as a tuple, in layout order (C-level, for the encoder).
        getter = attrgetter(*names) if names else (lambda req: ())
        values = (lambda req: (getter(req),)) if len(names) == 1 else getter
        object.__setattr__(self, "values", values)


class ReplyLayout(NamedTuple):
    """A reply type, the decoder of its OK payload (plain function: the master's hot path) and
    its fixed payload size (None when it varies)."""

    type: type[Reply]
    decode: Callable[[bytes], Reply]
    size: int | None


_VELOCITY = Field("i", scale=Q16, what="velocity")  # m/s or rad/s, Q16

#: Every command of the profile and fleetlink's extension, in protocol order.
COMMANDS: tuple[Command, ...] = (
    Command(CtrlBus.CONNECT_BASE, ConnectBase, Args(U8), BaseInfo),
    Command(CtrlBus.GET_BASE_CONF, GetBaseConf, NO_ARGS, BaseConf),
    Command(CtrlBus.GET_BINARY_CONF, GetBinaryConf, NO_ARGS, BinaryConf),
    Command(CtrlBus.GET_BASE_STATUS, GetBaseStatus, NO_ARGS, BaseStatus),
    Command(CtrlBus.GET_BASE_MOTOR_DATA, GetMotorData, NO_ARGS, MotorData),
    Command(CtrlBus.GET_BASE_SENSOR_DATA, GetSensorData, NO_ARGS, SensorData),
    Command(CtrlBus.GET_BASE_BUMPER_DATA, GetBumperData, NO_ARGS, BumperData),
    Command(CtrlBus.GET_AUTO_HOME_DATA, GetAutoHomeData, Args(U8), AutoHomeData),
    Command(CtrlBus.SET_BASE_MOTOR, SetBaseMotor, Args(Field("i", scale=1000, count=4, what="wheel speed")), Empty),
    Command(CtrlBus.SET_V_AND_GET_DEADRECKON, SetVelocity, Args(_VELOCITY, _VELOCITY, _VELOCITY), DeadReckon),
    Command(CtrlBus.POLL_BASE_CMD, PollBaseCommand, NO_ARGS, PendingBaseCommand),
    Command(CtrlBus.POLL_BASE_ANS_CMD, AnswerBaseCommand, NO_ARGS, Empty),
    Command(CtrlBus.SEND_EVENT, SendEvent, Args(U8), Empty),
    Command(CtrlBus.HEALTH_MGMT, GetHealth, Args(sub=1), Health),
    Command(CtrlBus.HEALTH_MGMT, GetHealthError, Args(U8, sub=2), HealthError),
    Command(CtrlBus.HEALTH_MGMT, ClearHealthError, Args(U32, sub=3), Empty),
    Command(CtrlBus.SET_UV_LAMP, SetUvLamp, Args(ON_OFF), Empty),
    Command(CtrlBus.SET_ATOMISER, SetAtomiser, Args(Field("B", high=3, what="atomiser level")), Empty),
    Command(CtrlBus.SET_FAN, SetFan, Args(Field("B", high=3, what="fan level")), Empty),
    Command(CtrlBus.GET_PAYLOAD_STATUS, GetPayloadStatus, NO_ARGS, PayloadStatus),
    Command(CtrlBus.GET_ENV_DATA, GetEnvData, NO_ARGS, EnvData),
    Command(CtrlBus.GET_POWER_DATA, GetPowerData, NO_ARGS, PowerData),
    Command(CtrlBus.GET_BUTTONS, GetButtons, NO_ARGS, Buttons),
    Command(CtrlBus.GET_IMU_DATA, GetImuData, NO_ARGS, ImuData),
    Command(CtrlBus.GET_TELEMETRY, GetTelemetry, NO_ARGS, Telemetry),
    Command(CtrlBus.SET_LEDS, SetLeds, Args(Field("B", high=3, what="LED mode"), U8, U8, U8), Empty),
    Command(CtrlBus.BEEP, Beep, Args(U16, Field("H", scale=1000, what="beep duration")), Empty),
)

#: Every reply type: how its OK payload decodes, and its size.
REPLIES: tuple[ReplyLayout, ...] = (
    ReplyLayout(Empty, _decode_empty, 0),
    ReplyLayout(BaseInfo, _decode_base_info, _BASE_INFO.size),
    ReplyLayout(BaseConf, _decode_base_conf, _CONF_SIZE),
    ReplyLayout(BinaryConf, _decode_binary_conf, None),
    ReplyLayout(BaseStatus, _decode_base_status, _STATUS.size),
    ReplyLayout(MotorData, _decode_motor_data, _MOTOR.size),
    ReplyLayout(SensorData, _decode_sensor_data, _SENSORS.size),
    ReplyLayout(BumperData, _decode_bumper_data, None),  # u8 or u32
    ReplyLayout(AutoHomeData, _decode_auto_home_data, None),
    ReplyLayout(DeadReckon, _decode_dead_reckon, _DEADRECKON.size),
    ReplyLayout(PendingBaseCommand, _decode_pending_base_command, None),  # empty or one byte
    ReplyLayout(Health, _decode_health_reply, _HEALTH.size),
    ReplyLayout(HealthError, _decode_health_error, _HEALTH_ERROR.size),
    ReplyLayout(PayloadStatus, _decode_payload_status, _PAYLOAD_STATUS.size),
    ReplyLayout(EnvData, _decode_env_data, _ENV.size),
    ReplyLayout(PowerData, _decode_power_data, _POWER.size),
    ReplyLayout(Buttons, _decode_buttons, _BUTTONS.size),
    ReplyLayout(ImuData, _decode_imu, _IMU.size),
    ReplyLayout(Telemetry, _decode_telemetry, None),
)


# -- derived from the table -------------------------------------------------------------------

REQUEST_TYPES: tuple[type[Request], ...] = tuple(c.request for c in COMMANDS)
REPLY_TYPES: tuple[type[Reply], ...] = tuple(r.type for r in REPLIES)

# decode_reply's dispatch: reply type -> decoder of its OK payload.
_REPLY_DECODERS: dict[type[Reply] | None, Callable[[bytes], Reply]] = {r.type: r.decode for r in REPLIES}

# Fixed payload sizes, for the message when a payload has the wrong size (a MountPose is part of
# BaseConf and decodes on its own too).
_PAYLOAD_SIZES: dict[type, int] = {r.type: r.size for r in REPLIES if r.size is not None} | {MountPose: _POSE.size}


def _bind_and_check() -> dict[int, Callable[[bytes], IncomingRequest]]:
    """Give each request class its row, check the table against the unions, and build the board's
    request decoders by command code (HEALTH_MGMT dispatches on its sub-command byte)."""
    if len(set(REQUEST_TYPES)) != len(REQUEST_TYPES):
        raise TypeError("a request type appears twice in COMMANDS")
    if set(REQUEST_TYPES) != set(get_args(Request)):
        raise TypeError(f"COMMANDS and the Request union differ: {set(REQUEST_TYPES) ^ set(get_args(Request))}")
    if set(REPLY_TYPES) != set(get_args(Reply)) or len(REPLY_TYPES) != len(REPLIES):
        raise TypeError(f"REPLIES and the Reply union differ: {set(REPLY_TYPES) ^ set(get_args(Reply))}")
    if not {c.reply for c in COMMANDS} <= set(REPLY_TYPES):
        raise TypeError("a command's reply type has no layout in REPLIES")
    by_code: dict[int, list[Command]] = {}
    for c in COMMANDS:
        c.request.CODE = c.code
        c.request.REPLY = c.reply
        c.request.COMMAND = c
        by_code.setdefault(c.code, []).append(c)
    decoders: dict[int, Callable[[bytes], IncomingRequest]] = {}
    for code, rows in by_code.items():
        subs = [c.args.sub for c in rows]
        if len(rows) == 1 and subs[0] is None:
            decoders[code] = rows[0].request.decode_args
        elif None in subs or len(set(subs)) != len(subs):
            raise TypeError(f"{CtrlBus(code).name}: commands sharing a code need distinct sub-command bytes")
        else:
            decoders[code] = _sub_command_decoder({c.args.sub: c.request for c in rows if c.args.sub is not None})
    return decoders


def _sub_command_decoder(by_sub: dict[int, type[Request]]) -> Callable[[bytes], IncomingRequest]:
    expected = ", ".join(f"{s:02X}" for s in by_sub)

    def decode(args: bytes) -> IncomingRequest:
        cls = by_sub.get(args[0]) if args else None
        if cls is None:
            raise BadPayload(f"expected sub-command {expected}")
        return cls.decode_args(args)

    return decode


_DECODERS = _bind_and_check()


def _bytes(n: int) -> str:
    return f"{n} byte{'s' if n != 1 else ''}"


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

    @property
    def is_protocol_error(self) -> bool:
        return is_protocol_error(self.code)


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
