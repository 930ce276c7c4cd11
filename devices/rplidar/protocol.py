"""The RPLIDAR A1 serial protocol, both roles, with no I/O.

Master side (the agent): ``encode_request`` builds requests; ``LidarDecoder.feed(bytes)`` turns the
lidar's answers, in any split, into typed events; ``RevolutionAssembler`` groups measurement nodes
into revolutions. Slave side (``field.rplidar``'s simulated lidar): ``RequestDecoder`` splits
requests, and the ``encode_*`` answer helpers build descriptors, answers and nodes.

Wire format (SLAMTEC's SDK, ``sl_lidar_cmd.h`` / ``sl_lidar_protocol.h``):

* Request: ``A5 cmd``; a command with bit 0x80 set adds ``size payload... checksum``, the checksum
  being the XOR of every byte sent, ``A5`` included.
* Response descriptor, 7 bytes: ``A5 5A``, a little-endian u32 whose low 30 bits are the answer's
  size and whose top 2 bits are the send mode (0 single answer, 1 a stream of ``size``-byte
  answers until STOP), then the answer type.
* Measurement node (type 0x81, size 5): byte 0 = quality << 2 | !S << 1 | S (S: first node of a
  new revolution); bytes 1-2 LE u16 = angle_q6 << 1 | 1 (the check bit); bytes 3-4 LE u16 =
  distance in 1/4 mm, 0 for no return.

Units in events: ``Node`` carries the angle as the wire has it, *degrees, clockwise* seen from
above (SLAMTEC's convention), and the distance in metres. ``Revolution`` converts to what the rest
of fleetlink uses: radians, counter-clockwise, in [0, 2 pi), sorted.

``LidarDecoder`` never raises. Outside an answer it looks for ``A5 5A`` (bytes before it are
``garbage_bytes``); a false descriptor (a size above ``MAX_ANSWER`` or a reserved send mode) is
skipped a byte at a time. In a node stream it applies SLAMTEC's resynchronisation rule: a node
whose S and !S bits agree, or whose check bit is 0, is out of step, so one byte is skipped
(``resync_bytes``) and the next position tried. Since a real node's byte 1 always has its check
bit set, ``A5 5A`` can never start a node; where a node is rejected and a valid descriptor starts,
the decoder takes it (a new answer after a STOP the master did not tell it about). Streams of
other answer types cannot be resynchronised and are cut into ``Response`` events of ``size``
bytes. What stays buffered is at most one incomplete descriptor or answer (``MAX_ANSWER`` bytes).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from functools import reduce
from operator import xor
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

__all__ = [
    "CAPSULE_LEN",
    "DESCRIPTOR_LEN",
    "EXPRESS_DESCRIPTOR",
    "HEALTH_ERROR",
    "HEALTH_GOOD",
    "HEALTH_WARNING",
    "MAX_ANSWER",
    "NODE_LEN",
    "SCAN_DESCRIPTOR",
    "SEND_MODE_MULTI",
    "SEND_MODE_SINGLE",
    "SYNC",
    "SYNC2",
    "AnswerType",
    "AssemblerStats",
    "CapsuleEncoder",
    "Command",
    "ConfType",
    "DecoderStats",
    "Descriptor",
    "DeviceHealth",
    "DeviceInfo",
    "Event",
    "LidarConf",
    "LidarDecoder",
    "Node",
    "NodeBatch",
    "Request",
    "RequestDecoder",
    "RequestStats",
    "Response",
    "Revolution",
    "RevolutionAssembler",
    "SampleRate",
    "ScanMode",
    "checksum",
    "decode_capsule_angles",
    "device_deg_to_rad",
    "encode_capsules",
    "encode_conf_request",
    "encode_descriptor",
    "encode_device_info",
    "encode_express_request",
    "encode_health",
    "encode_lidar_conf",
    "encode_node",
    "encode_nodes",
    "encode_request",
    "encode_samplerate",
    "parse_conf_request",
    "rad_to_device_deg",
    "split_requests",
]

SYNC = 0xA5  # first byte of every request and every descriptor
SYNC2 = 0x5A  # second byte of a descriptor
DESCRIPTOR_LEN = 7
NODE_LEN = 5
CAPSULE_LEN = 84  # express scan (answer 0x82): 4 header bytes + 16 cabins of 5 bytes, 32 samples
CAPSULE_SAMPLES = 32
MAX_ANSWER = 1024  # largest answer we accept (real ones are at most 84 bytes: express capsules)
MAX_REQUEST_PAYLOAD = 255  # the size field of a request is one byte

SEND_MODE_SINGLE = 0
SEND_MODE_MULTI = 1

HEALTH_GOOD = 0
HEALTH_WARNING = 1
HEALTH_ERROR = 2

ANGLE_Q = 64.0  # angle units per degree (q6)
DIST_Q = 4000.0  # distance units per metre (1/4 mm)

FloatArray = npt.NDArray[np.float64]
U8Array = npt.NDArray[np.uint8]
BoolArray = npt.NDArray[np.bool_]


class Command(IntEnum):
    STOP = 0x25
    RESET = 0x40
    SCAN = 0x20
    FORCE_SCAN = 0x21
    EXPRESS_SCAN = 0x82
    GET_INFO = 0x50
    GET_HEALTH = 0x52
    GET_SAMPLERATE = 0x59
    GET_LIDAR_CONF = 0x84  # firmware 1.24 and later
    SET_MOTOR_PWM = 0xF0
    GET_ACC_BOARD_FLAG = 0xFF  # A2/A3: does an accessory board drive the motor? (A1: no answer)


class AnswerType(IntEnum):
    DEVICE_INFO = 0x04
    DEVICE_HEALTH = 0x06
    SAMPLE_RATE = 0x15
    LIDAR_CONF = 0x20
    MEASUREMENT = 0x81
    MEASUREMENT_CAPSULED = 0x82  # express scan, legacy capsule format


class ConfType(IntEnum):
    """GET_LIDAR_CONF entries (``sl_lidar_cmd.h``'s ``SL_LIDAR_CONF_*``) that fleetlink speaks.

    The request payload is the type as a little-endian u32, followed for the per-mode entries by
    the scan mode's id as a u16; the answer (type 0x20) echoes the u32 type, then the value."""

    SCAN_MODE_COUNT = 0x70  # u16
    SCAN_MODE_US_PER_SAMPLE = 0x71  # u32, Q8 fixed point microseconds (per mode)
    SCAN_MODE_MAX_DISTANCE = 0x74  # u32, Q8 fixed point metres (per mode)
    SCAN_MODE_ANS_TYPE = 0x75  # u8, the answer type the mode streams (per mode)
    SCAN_MODE_TYPICAL = 0x7C  # u16, the id of the mode SLAMTEC recommends for the model
    SCAN_MODE_NAME = 0x7F  # NUL-terminated ASCII (per mode)


PER_MODE_CONF = frozenset(
    {
        ConfType.SCAN_MODE_US_PER_SAMPLE,
        ConfType.SCAN_MODE_MAX_DISTANCE,
        ConfType.SCAN_MODE_ANS_TYPE,
        ConfType.SCAN_MODE_NAME,
    }
)


# -- events ---------------------------------------------------------------------------------------


class Descriptor(NamedTuple):
    size: int
    mode: int  # SEND_MODE_SINGLE or SEND_MODE_MULTI
    type: int

    @property
    def continuous(self) -> bool:
        return self.mode == SEND_MODE_MULTI

    def encode(self) -> bytes:
        return encode_descriptor(self.size, self.mode, self.type)


SCAN_DESCRIPTOR = Descriptor(NODE_LEN, SEND_MODE_MULTI, AnswerType.MEASUREMENT)
EXPRESS_DESCRIPTOR = Descriptor(CAPSULE_LEN, SEND_MODE_MULTI, AnswerType.MEASUREMENT_CAPSULED)


class DeviceInfo(NamedTuple):
    model: int
    firmware: tuple[int, int]  # (major, minor)
    hardware: int
    serial: bytes  # 16 bytes

    @property
    def firmware_str(self) -> str:
        return f"{self.firmware[0]}.{self.firmware[1]:02d}"

    @property
    def serial_hex(self) -> str:
        return self.serial.hex().upper()


class DeviceHealth(NamedTuple):
    status: int  # HEALTH_GOOD, HEALTH_WARNING or HEALTH_ERROR
    error_code: int

    @property
    def ok(self) -> bool:
        return self.status == HEALTH_GOOD

    @property
    def status_name(self) -> str:
        return {HEALTH_GOOD: "good", HEALTH_WARNING: "warning", HEALTH_ERROR: "error"}.get(
            self.status, f"status {self.status}"
        )


class SampleRate(NamedTuple):
    standard_us: int  # microseconds per sample in SCAN mode
    express_us: int  # ... in express mode


class LidarConf(NamedTuple):
    """A GET_LIDAR_CONF answer: the entry's type and its value bytes (see ``ConfType``)."""

    type: int
    value: bytes

    def u8(self) -> int:
        return self._int(1)

    def u16(self) -> int:
        return self._int(2)

    def u32(self) -> int:
        return self._int(4)

    def q8(self) -> float:
        """A u32 in Q8 fixed point (microseconds per sample, metres)."""
        return self._int(4) / 256.0

    def text(self) -> str:
        """A NUL-terminated string (a scan mode's name)."""
        return self.value.split(b"\x00", 1)[0].decode("ascii", "replace")

    def _int(self, size: int) -> int:
        if len(self.value) < size:
            raise ValueError(f"conf 0x{self.type:02X}: {len(self.value)} value bytes, need {size}")
        return int.from_bytes(self.value[:size], "little")


class ScanMode(NamedTuple):
    """One scan mode as GET_LIDAR_CONF describes it."""

    id: int
    name: str
    us_per_sample: float
    max_distance_m: float
    answer_type: int  # 0x81 standard nodes, 0x82 express capsules (others: not decoded by fleetlink)

    @property
    def samples_per_second(self) -> float:
        return 1e6 / self.us_per_sample


class Node(NamedTuple):
    """One measurement as the wire has it: angle in degrees clockwise, distance in metres (0: none)."""

    start: bool
    quality: int  # 0-63
    angle_deg: float
    distance_m: float


@dataclass(frozen=True, slots=True, eq=False)
class NodeBatch:
    """Consecutive nodes as arrays (``LidarDecoder(batch=True)``): cheaper than one ``Node`` each."""

    start: BoolArray
    quality: U8Array
    angle_deg: FloatArray
    distance_m: FloatArray

    def __len__(self) -> int:
        return int(self.start.size)

    def nodes(self) -> list[Node]:
        return [
            Node(bool(s), int(q), float(a), float(d))
            for s, q, a, d in zip(
                self.start.tolist(),
                self.quality.tolist(),
                self.angle_deg.tolist(),
                self.distance_m.tolist(),
                strict=True,
            )
        ]


class Response(NamedTuple):
    """An answer this decoder does not interpret (an unknown type, a wrong size, express capsules)."""

    type: int
    payload: bytes


Event = Descriptor | DeviceInfo | DeviceHealth | SampleRate | LidarConf | Node | NodeBatch | Response


# -- encoders -------------------------------------------------------------------------------------


def checksum(data: bytes | bytearray | memoryview) -> int:
    return reduce(xor, data, 0)


def encode_request(cmd: int, payload: bytes = b"") -> bytes:
    """``A5 cmd``, plus ``size payload checksum`` for commands with bit 0x80 (raises ValueError if
    the request cannot be encoded: a payload on a command without bit 0x80, or over 255 bytes)."""
    if not 0 <= cmd <= 0xFF:
        raise ValueError(f"command {cmd} is not a byte")
    if not cmd & 0x80:
        if payload:
            raise ValueError(f"command 0x{cmd:02X} carries no payload (bit 0x80 is clear)")
        return bytes((SYNC, cmd))
    if len(payload) > MAX_REQUEST_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes does not fit a request")
    body = bytes((SYNC, cmd, len(payload))) + bytes(payload)
    return body + bytes((checksum(body),))


def encode_descriptor(size: int, mode: int, answer_type: int) -> bytes:
    if not (0 <= size < 1 << 30 and 0 <= mode <= 3 and 0 <= answer_type <= 0xFF):
        raise ValueError(f"bad descriptor: size {size}, mode {mode}, type {answer_type}")
    return bytes((SYNC, SYNC2)) + (size | mode << 30).to_bytes(4, "little") + bytes((answer_type,))


def encode_device_info(info: DeviceInfo) -> bytes:
    """The 20-byte GET_INFO answer (without its descriptor)."""
    serial = bytes(info.serial[:16]).ljust(16, b"\x00")
    major, minor = info.firmware
    return bytes((info.model & 0xFF, minor & 0xFF, major & 0xFF, info.hardware & 0xFF)) + serial


def encode_health(health: DeviceHealth) -> bytes:
    return bytes((health.status & 0xFF,)) + (health.error_code & 0xFFFF).to_bytes(2, "little")


def encode_samplerate(rate: SampleRate) -> bytes:
    return (rate.standard_us & 0xFFFF).to_bytes(2, "little") + (rate.express_us & 0xFFFF).to_bytes(2, "little")


def encode_node(start: bool, quality: int, angle_deg: float, distance_m: float) -> bytes:
    """One node; the angle is wrapped into [0, 360) and the values clipped to their fields."""
    return encode_nodes(np.array([angle_deg]), np.array([distance_m]), np.array([quality]), start_first=start)


def encode_nodes(
    angles_deg: npt.ArrayLike,
    distances_m: npt.ArrayLike,
    qualities: npt.ArrayLike,
    start_first: bool = True,
) -> bytes:
    """Nodes in the order given; only the first carries the start flag (if ``start_first``)."""
    ang = np.mod(np.asarray(angles_deg, dtype=np.float64), 360.0)
    q6 = np.rint(ang * ANGLE_Q).astype(np.int64) % int(360 * ANGLE_Q)
    q2 = np.clip(np.rint(np.asarray(distances_m, dtype=np.float64) * DIST_Q), 0, 0xFFFF).astype(np.int64)
    q = np.clip(np.asarray(qualities, dtype=np.int64), 0, 63)
    n = q6.size
    out = np.empty((n, NODE_LEN), dtype=np.uint8)
    s = np.zeros(n, dtype=np.int64)
    if n and start_first:
        s[0] = 1
    out[:, 0] = (q << 2) | ((1 - s) << 1) | s
    a = (q6 << 1) | 1
    out[:, 1] = a & 0xFF
    out[:, 2] = a >> 8
    out[:, 3] = q2 & 0xFF
    out[:, 4] = q2 >> 8
    return out.tobytes()


def encode_conf_request(conf: int, mode: int | None = None) -> bytes:
    """GET_LIDAR_CONF: ``A5 84 size type(u32) [mode(u16)] checksum``."""
    payload = (conf & 0xFFFF_FFFF).to_bytes(4, "little")
    if mode is not None:
        payload += (mode & 0xFFFF).to_bytes(2, "little")
    return encode_request(Command.GET_LIDAR_CONF, payload)


def parse_conf_request(payload: bytes) -> tuple[int, int | None] | None:
    """The lidar's reading of a GET_LIDAR_CONF payload: (type, scan mode id or None), or None if
    the payload is too short to hold a type."""
    if len(payload) < 4:
        return None
    conf = int.from_bytes(payload[:4], "little")
    mode = int.from_bytes(payload[4:6], "little") if len(payload) >= 6 else None
    return conf, mode


def encode_lidar_conf(conf: int, value: bytes) -> bytes:
    """A GET_LIDAR_CONF answer with its descriptor: type 0x20, the u32 type echoed, then ``value``."""
    body = (conf & 0xFFFF_FFFF).to_bytes(4, "little") + bytes(value)
    return encode_descriptor(len(body), SEND_MODE_SINGLE, AnswerType.LIDAR_CONF) + body


def encode_express_request(working_mode: int = 0) -> bytes:
    """EXPRESS_SCAN: payload working_mode (u8), working_flags (u16), param (u16). Working mode 0 is
    the legacy express scan; SLAMTEC's SDK puts the scan mode's id there on firmware with
    GET_LIDAR_CONF (1 for an A1's "Express")."""
    return encode_request(Command.EXPRESS_SCAN, bytes((working_mode & 0xFF, 0, 0, 0, 0)))


_Q6_TURN = 360 * 64  # a turn in 1/64 degree
_MAX_MM = 0x3FFF  # 14 bits of distance in a cabin
_CAPSULE_J = np.arange(CAPSULE_SAMPLES, dtype=np.int64)[None, :]
_PY_CAPSULES = 8  # up to this many capsules at once, plain Python is quicker than NumPy


def encode_capsules(
    start_q6: npt.ArrayLike,
    next_q6: npt.ArrayLike,
    angles_q6: npt.ArrayLike,
    distances_m: npt.ArrayLike,
    new_scan: bool = False,
) -> bytes:
    """K express capsules (``CAPSULE_LEN`` bytes each) in one pass.

    ``start_q6[k]`` is capsule k's start angle and ``next_q6[k]`` the start angle of the capsule
    after it (the decoder interpolates capsule k's 32 sample angles between the two, as SLAMTEC's
    SDK does); ``angles_q6`` (K*32, wire angles in 1/64 degree) are what each sample's angle should
    decode to, which the per-sample compensation offsets (6 bits of 1/8 degree, subtracted) bring
    about as nearly as they can; ``distances_m`` travel in whole millimetres (0: no return).
    ``new_scan`` sets the start flag on the first capsule (a new scan session)."""
    s = np.asarray(start_q6, dtype=np.int64).reshape(-1) % _Q6_TURN
    nxt = np.asarray(next_q6, dtype=np.int64).reshape(-1) % _Q6_TURN
    k = s.size
    t = np.asarray(angles_q6, dtype=np.int64).reshape(k, CAPSULE_SAMPLES) % _Q6_TURN
    mm = np.rint(np.asarray(distances_m, dtype=np.float64).reshape(k, CAPSULE_SAMPLES) * 1000.0).astype(np.int64)
    np.clip(mm, 0, _MAX_MM, out=mm)
    # The SDK's arithmetic: the increment per sample in Q16 degrees (Q8 difference << 3), sample j
    # at start + j * increment; then the offset (1/8 degree = 8192 in Q16) that lands the floored
    # Q6 angle on the sample's, taken against the copy of the sample's angle nearest the raw one.
    inc_q16 = ((nxt - s) % _Q6_TURN) << 5
    raw = (s << 10)[:, None] + _CAPSULE_J * inc_q16[:, None]
    tu = t + ((raw >> 10) - t + _Q6_TURN // 2) // _Q6_TURN * _Q6_TURN
    off = (raw - (tu << 10) - 512 + 4096) >> 13
    np.clip(off, 0, 63, out=off)
    # Never let a sample decode across the 0/360 line from the side it is on (a turn's boundary).
    dec = t + ((raw - (off << 13)) >> 10) - tu
    if (dec < 0).any() or (dec >= _Q6_TURN).any():
        off = np.where(dec < 0, off - (-dec + 7) // 8, off)
        off = np.where(dec >= _Q6_TURN, off + (dec - _Q6_TURN + 8) // 8, off)
        np.clip(off, 0, 63, out=off)
    d = (mm << 2) | (off >> 4)
    cab = np.empty((k, 16, 5), dtype=np.int64)
    cab[:, :, 0] = d[:, 0::2]
    cab[:, :, 1] = d[:, 0::2] >> 8
    cab[:, :, 2] = d[:, 1::2]
    cab[:, :, 3] = d[:, 1::2] >> 8
    cab[:, :, 4] = (off[:, 0::2] & 0xF) | ((off[:, 1::2] & 0xF) << 4)
    out = np.empty((k, CAPSULE_LEN), dtype=np.uint8)
    start_field = s.copy()
    if k and new_scan:
        start_field[0] |= 0x8000
    out[:, 2] = start_field & 0xFF
    out[:, 3] = start_field >> 8
    out[:, 4:] = (cab & 0xFF).reshape(k, 80)
    cs = np.bitwise_xor.reduce(out[:, 2:], axis=1)
    out[:, 0] = 0xA0 | (cs & 0xF)
    out[:, 1] = 0x50 | (cs >> 4)
    return out.tobytes()


def _encode_capsule(
    start_q6: int, next_q6: int, angles_q6: Sequence[int], distances_m: Sequence[float], new_scan: bool
) -> bytes:
    """One capsule, as ``encode_capsules`` makes it (the same bytes), in plain Python: about four
    times quicker than NumPy for the one or two capsules a stream produces per step."""
    turn = _Q6_TURN
    s = start_q6 % turn
    inc = ((next_q6 % turn - s) % turn) << 5
    raw = s << 10
    body = bytearray(CAPSULE_LEN)
    sf = s | (0x8000 if new_scan else 0)
    body[2] = sf & 0xFF
    body[3] = sf >> 8
    offs = [0] * CAPSULE_SAMPLES
    words = [0] * CAPSULE_SAMPLES
    for j in range(CAPSULE_SAMPLES):
        t = angles_q6[j] % turn
        tu = t + ((raw >> 10) - t + turn // 2) // turn * turn
        off = min(63, max(0, (raw - (tu << 10) - 512 + 4096) >> 13))
        dec = t + ((raw - (off << 13)) >> 10) - tu
        if dec < 0:
            off = max(0, off - (-dec + 7) // 8)
        elif dec >= turn:
            off = min(63, off + (dec - turn + 8) // 8)
        mm = min(_MAX_MM, max(0, round(distances_m[j] * 1000.0)))
        offs[j] = off
        words[j] = (mm << 2) | (off >> 4)
        raw += inc
    p = 4
    for c in range(0, CAPSULE_SAMPLES, 2):
        d1 = words[c]
        d2 = words[c + 1]
        body[p] = d1 & 0xFF
        body[p + 1] = d1 >> 8
        body[p + 2] = d2 & 0xFF
        body[p + 3] = d2 >> 8
        body[p + 4] = (offs[c] & 0xF) | ((offs[c + 1] & 0xF) << 4)
        p += 5
    cs = checksum(memoryview(body)[2:])
    body[0] = 0xA0 | (cs & 0xF)
    body[1] = 0x50 | (cs >> 4)
    return bytes(body)


class CapsuleEncoder:
    """The lidar's express-scan stream: samples in, capsules out, as samples become due.

    ``push(angles_q6, distances_m, new_turn, next_q6)`` adds consecutive samples of one turn (wire
    angles in 1/64 degree, as the turn is sent) and returns the capsules they complete. A capsule's
    start angle is committed when the capsule before it is sent: the angle of the sample that will
    follow, ``margin_q6`` ahead, so that the decoder's interpolated angles run a little ahead of the
    samples' and the (subtracted, non-negative) offsets bring them back. Where the following sample
    is the first of the next turn, not yet cast, it is predicted ``step_q6`` on; the offsets absorb
    the difference. ``next_q6`` is the sample after the pushed ones when it is in the same turn
    (None at the turn's end). The output depends only on the samples, not on how they were pushed.
    """

    def __init__(self, step_q6: float) -> None:
        self.step_q6 = float(step_q6)
        # A whole number of offset units (1/8 degree = 8 q6) above one sample step.
        self.margin_q6 = int(min(8 * 48, 8 * math.ceil((self.step_q6 + 4.0) / 8.0)))
        self.capsules = 0
        self._angles: list[int] = []
        self._dist: list[float] = []
        self._first_of_turn: list[bool] = []
        self._tail_next: int | None = None
        self._start: int | None = None  # committed start angle of the next capsule

    @property
    def pending(self) -> int:
        return len(self._angles)

    def reset(self) -> None:
        """A new scan session: the next capsule carries the start flag."""
        self._angles.clear()
        self._dist.clear()
        self._first_of_turn.clear()
        self._tail_next = None
        self._start = None

    def push(
        self,
        angles_q6: npt.ArrayLike,
        distances_m: npt.ArrayLike,
        new_turn: bool = False,
        next_q6: int | None = None,
    ) -> bytes:
        a = np.asarray(angles_q6, dtype=np.int64).reshape(-1).tolist()
        d = np.asarray(distances_m, dtype=np.float64).reshape(-1).tolist()
        if not a:
            return b""
        self._angles += a
        self._dist += d
        self._first_of_turn += [new_turn] + [False] * (len(a) - 1)
        self._tail_next = next_q6
        n_caps = len(self._angles) // CAPSULE_SAMPLES
        if n_caps == 0:
            return b""
        used = n_caps * CAPSULE_SAMPLES
        angles = self._angles
        new_scan = self._start is None
        starts = np.empty(n_caps, dtype=np.int64)
        nexts = np.empty(n_caps, dtype=np.int64)
        start = angles[0] + self.margin_q6 if self._start is None else self._start
        for c in range(n_caps):
            last = (c + 1) * CAPSULE_SAMPLES - 1
            if last + 1 < len(angles):
                follow = None if self._first_of_turn[last + 1] else angles[last + 1]
            else:
                follow = self._tail_next
            if follow is None:
                follow = round(angles[last] + self.step_q6)
            starts[c] = start
            start = (follow + self.margin_q6) % _Q6_TURN
            nexts[c] = start
        self._start = start
        if n_caps <= _PY_CAPSULES:
            parts = []
            for c in range(n_caps):
                lo, hi = c * CAPSULE_SAMPLES, (c + 1) * CAPSULE_SAMPLES
                parts.append(
                    _encode_capsule(
                        int(starts[c]), int(nexts[c]), angles[lo:hi], self._dist[lo:hi], new_scan and c == 0
                    )
                )
            out = b"".join(parts)
        else:
            out = encode_capsules(starts, nexts, angles[:used], self._dist[:used], new_scan=new_scan)
        del self._angles[:used]
        del self._dist[:used]
        del self._first_of_turn[:used]
        self.capsules += n_caps
        return out


def rad_to_device_deg(angles_rad: npt.ArrayLike) -> FloatArray:
    """Sensor-frame angles (rad, counter-clockwise) to the RPLIDAR's degrees clockwise in [0, 360)."""
    return np.mod(-np.degrees(np.asarray(angles_rad, dtype=np.float64)), 360.0)


def device_deg_to_rad(angles_deg: npt.ArrayLike) -> FloatArray:
    """The RPLIDAR's degrees (clockwise) to sensor-frame radians, counter-clockwise, in [0, 2 pi)."""
    return np.mod(-np.radians(np.asarray(angles_deg, dtype=np.float64)), 2.0 * math.pi)


# -- master side: answers -------------------------------------------------------------------------


@dataclass(slots=True)
class DecoderStats:
    descriptors: int = 0
    answers: int = 0  # single answers and stream units other than nodes
    nodes: int = 0
    garbage_bytes: int = 0  # skipped while looking for a descriptor
    bad_descriptors: int = 0  # A5 5A followed by an impossible size or mode
    resync_bytes: int = 0  # skipped in a node stream to get back in step
    wrong_size: int = 0  # answers of a known type with an unexpected size (delivered as Response)
    capsules: int = 0  # express capsules that passed their sync nibbles and checksum
    bad_capsules: int = 0  # capsules with good sync nibbles and a bad checksum (dropped)
    capsule_resets: int = 0  # a capsule with the start flag in the middle of a stream

    @property
    def dropped_bytes(self) -> int:
        return self.garbage_bytes + self.resync_bytes


_IDLE, _SINGLE, _STREAM = "idle", "answer", "stream"

# Angle continuity, the second resync check. The two check bits of a node pass at a wrong byte
# offset about one time in four, and because a real turn's angle bytes change slowly, a stream
# read one byte out of step can pass them for many nodes in a row. In step, each node's angle
# advances by well under a degree (a little backward jitter allowed); out of step, the "angle"
# is made of distance bytes and jumps about at random. A node that breaks continuity with the
# last one emitted is taken only if it starts a run of RESYNC_RUN nodes continuous among
# themselves (a genuine jump, e.g. after a burst of lost bytes); otherwise the decoder slips a byte.
# A stream's first node has nothing to continue and is taken on its check bits alone.
MAX_ANGLE_STEP_DEG = 20.0
ANGLE_JITTER_DEG = 5.0
RESYNC_RUN = 4

_KNOWN_SIZES: dict[int, int] = {AnswerType.DEVICE_INFO: 20, AnswerType.DEVICE_HEALTH: 3, AnswerType.SAMPLE_RATE: 4}


class LidarDecoder:
    """Sans-I/O decoder of the lidar's answers; see the module docstring for the rules.

    ``batch=True`` delivers runs of nodes as ``NodeBatch`` arrays instead of one ``Node`` each.
    """

    def __init__(self, batch: bool = False) -> None:
        self.batch = batch
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._state = _IDLE
        self._desc: Descriptor | None = None
        self._last_angle: float | None = None  # degrees, of the last node emitted in this stream
        self._cap_prev: bytes | None = None  # the last good capsule, decoded once the next one comes
        self._cap_last_q6: int | None = None  # angle of the last sample decoded from capsules

    # -- public ----------------------------------------------------------------------------------

    @property
    def state(self) -> str:
        """ "idle" (waiting for a descriptor), "answer" (one answer due) or "stream"."""
        return self._state

    @property
    def descriptor(self) -> Descriptor | None:
        """The descriptor of the answer being received, if any."""
        return self._desc if self._state != _IDLE else None

    @property
    def buffered(self) -> int:
        return len(self._buf)

    @property
    def held_samples(self) -> int:
        """Samples received but not yet emitted: a capsule is decoded once the next one comes (its
        samples' angles lie between the two capsules' start angles)."""
        return CAPSULE_SAMPLES if self._cap_prev is not None else 0

    def reset(self) -> None:
        """Forget everything buffered and wait for a descriptor (after a STOP, before a request)."""
        self._buf.clear()
        self._state = _IDLE
        self._desc = None
        self._last_angle = None
        self._cap_prev = None
        self._cap_last_q6 = None

    def assume(self, descriptor: Descriptor) -> None:
        """Continue as if ``descriptor`` had just been received (joining a lidar already streaming)."""
        self._buf.clear()
        self._enter(descriptor)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Event]:
        """Take bytes in; return the events they complete (possibly none). Never raises."""
        out: list[Event] = []
        if data:
            self._buf += data
            buf = bytes(self._buf)
            pos = self._scan(buf, out)
            if pos:
                del self._buf[:pos]
        return out

    # -- internals -------------------------------------------------------------------------------

    def _enter(self, desc: Descriptor) -> None:
        self._desc = desc
        self._last_angle = None
        self._cap_prev = None
        self._cap_last_q6 = None
        if desc.size == 0:
            self._state = _IDLE
        elif desc.mode == SEND_MODE_MULTI:
            self._state = _STREAM
        else:
            self._state = _SINGLE

    def _scan(self, data: bytes, out: list[Event]) -> int:
        pos = 0
        n = len(data)
        while pos < n:
            state = self._state
            if state == _IDLE:
                pos, progressed = self._seek_descriptor(data, pos, out)
                if not progressed:
                    break
            elif state == _SINGLE:
                desc = self._desc
                assert desc is not None
                if n - pos < desc.size:
                    break
                out.append(_answer(desc, data[pos : pos + desc.size], self.stats))
                self.stats.answers += 1
                pos += desc.size
                self._state = _IDLE
            else:
                desc = self._desc
                assert desc is not None
                if desc.type == AnswerType.MEASUREMENT and desc.size == NODE_LEN:
                    pos, progressed = self._nodes(data, pos, out)
                    if not progressed:
                        break
                elif desc.type == AnswerType.MEASUREMENT_CAPSULED and desc.size == CAPSULE_LEN:
                    pos, progressed = self._capsules(data, pos, out)
                    if not progressed:
                        break
                else:
                    if n - pos < desc.size:
                        break
                    out.append(Response(desc.type, data[pos : pos + desc.size]))
                    self.stats.answers += 1
                    pos += desc.size
        return pos

    def _seek_descriptor(self, data: bytes, pos: int, out: list[Event]) -> tuple[int, bool]:
        """Skip to the next A5 5A and take the descriptor there. Returns (pos, progressed)."""
        n = len(data)
        start = pos
        while True:
            i = data.find(b"\xa5\x5a", pos)
            if i < 0:
                # Keep a trailing A5: it may be the first half of a descriptor.
                keep = 1 if data[n - 1] == SYNC else 0
                self.stats.garbage_bytes += n - keep - pos
                return n - keep, n - keep > start
            self.stats.garbage_bytes += i - pos
            if n - i < DESCRIPTOR_LEN:
                return i, i > start
            desc = _parse_descriptor(data, i)
            if desc is None:
                self.stats.bad_descriptors += 1
                self.stats.garbage_bytes += 1
                pos = i + 1
                continue
            self.stats.descriptors += 1
            out.append(desc)
            self._enter(desc)
            return i + DESCRIPTOR_LEN, True

    def _nodes(self, data: bytes, pos: int, out: list[Event]) -> tuple[int, bool]:
        """Nodes from ``pos`` while in step; resynchronise a byte at a time when not."""
        n = len(data)
        start = pos
        st = self.stats
        while n - pos >= NODE_LEN:
            b0 = data[pos]
            b1 = data[pos + 1]
            if ((b0 ^ (b0 >> 1)) & 1) and (b1 & 1):
                last = self._last_angle
                # In step, the whole chunk is most likely good: check it in one pass. Out of step
                # (hunting for a node boundary), start small so a false start costs little.
                m = _valid_run(data, pos, n, 8 if last is None else 4096)
                if last is not None and not _continuous(last, _angle_at(data, pos)) and m < RESYNC_RUN:
                    if m == (n - pos) // NODE_LEN:
                        return pos, pos > start  # too few bytes yet to tell a jump from a slip: wait
                    st.resync_bytes += 1
                    pos += 1
                    continue
                self._emit_nodes(data, pos, m, out)
                self._last_angle = _angle_at(data, pos + NODE_LEN * (m - 1))
                st.nodes += m
                pos += NODE_LEN * m
                continue
            if b0 == SYNC and b1 == SYNC2:
                if n - pos < DESCRIPTOR_LEN:
                    return pos, pos > start  # wait: it may be a descriptor
                desc = _parse_descriptor(data, pos)
                if desc is not None:
                    st.descriptors += 1
                    out.append(desc)
                    self._enter(desc)
                    return pos + DESCRIPTOR_LEN, True
            st.resync_bytes += 1
            pos += 1
        return pos, pos > start

    def _capsules(self, data: bytes, pos: int, out: list[Event]) -> tuple[int, bool]:
        """Express capsules from ``pos``: runs of good ones are decoded in one pass; a position whose
        sync nibbles are wrong is skipped a byte at a time, a capsule whose checksum is wrong is
        dropped (``bad_capsules``) and the hunt goes on at its next byte. Either breaks the chain of
        capsules, as in SLAMTEC's SDK: the capsule before it is not decoded."""
        n = len(data)
        start = pos
        st = self.stats
        while n - pos >= 2:
            b0 = data[pos]
            b1 = data[pos + 1]
            if (b0 >> 4) != 0xA or (b1 >> 4) != 0x5:
                st.resync_bytes += 1
                self._cap_prev = None
                pos += 1
                continue
            if n - pos < CAPSULE_LEN:
                break  # wait for the whole capsule
            k = min((n - pos) // CAPSULE_LEN, 1024)
            arr = np.frombuffer(data, dtype=np.uint8, count=CAPSULE_LEN * k, offset=pos).reshape(k, CAPSULE_LEN)
            good = ((arr[:, 0] >> 4) == 0xA) & ((arr[:, 1] >> 4) == 0x5)
            cs = np.bitwise_xor.reduce(arr[:, 2:], axis=1)
            good &= cs == ((arr[:, 0] & 0xF) | ((arr[:, 1] & 0xF) << 4))
            m = k if bool(good.all()) else int(np.argmin(good))
            if m == 0:
                if b0 == SYNC and b1 == SYNC2:
                    desc = _parse_descriptor(data, pos)
                    if desc is not None:  # a new answer after a STOP the decoder was not told about
                        st.descriptors += 1
                        out.append(desc)
                        self._enter(desc)
                        return pos + DESCRIPTOR_LEN, True
                st.bad_capsules += 1
                st.resync_bytes += 1
                self._cap_prev = None
                pos += 1
                continue
            self._emit_capsules(arr[:m], out)
            st.capsules += m
            pos += CAPSULE_LEN * m
        return pos, pos > start

    def _emit_capsules(self, caps: U8Array, out: list[Event]) -> None:
        """Decode each capsule whose successor is known: the one held from before, then these."""
        st = self.stats
        starts = (caps[:, 2].astype(np.int64) | (caps[:, 3].astype(np.int64) << 8)).tolist()
        chain: list[bytes] = [] if self._cap_prev is None else [self._cap_prev]
        pairs_prev: list[bytes] = []
        pairs_next: list[int] = []
        for i, sf in enumerate(starts):
            if sf & 0x8000:  # a new scan session: what came before is not continued
                if chain:
                    st.capsule_resets += 1
                chain = []
            elif chain:
                pairs_prev.append(chain[-1])
                pairs_next.append(sf & 0x7FFF)
            chain = [bytes(caps[i])]
        self._cap_prev = chain[-1] if chain else None
        if not pairs_prev:
            return
        prev = np.frombuffer(b"".join(pairs_prev), dtype=np.uint8).reshape(-1, CAPSULE_LEN)
        angle_q6, dist_q2 = decode_capsule_angles(prev, np.array(pairs_next, dtype=np.int64))
        last = self._cap_last_q6
        before = np.concatenate(([angle_q6[0] if last is None else last], angle_q6[:-1]))
        start = angle_q6 + _Q6_TURN // 2 < before  # the angle wraps: a new revolution
        angle_deg = angle_q6 / ANGLE_Q
        distance_m = dist_q2 / DIST_Q
        quality = np.where(dist_q2 > 0, CAPSULE_QUALITY, 0).astype(np.uint8)
        self._cap_last_q6 = int(angle_q6[-1])
        st.nodes += int(angle_q6.size)
        batch = NodeBatch(start, quality, angle_deg, distance_m)
        if self.batch:
            out.append(batch)
        else:
            out.extend(batch.nodes())

    def _emit_nodes(self, data: bytes, pos: int, m: int, out: list[Event]) -> None:
        if m == 1 and not self.batch:
            s0 = data[pos]
            q6 = (data[pos + 1] | data[pos + 2] << 8) >> 1
            q2 = data[pos + 3] | data[pos + 4] << 8
            out.append(Node(bool(s0 & 1), s0 >> 2, q6 / ANGLE_Q, q2 / DIST_Q))
            return
        arr = np.frombuffer(data, dtype=np.uint8, count=NODE_LEN * m, offset=pos).reshape(m, NODE_LEN)
        b0 = arr[:, 0]
        start = (b0 & 1).astype(np.bool_)
        quality = (b0 >> 2).astype(np.uint8)
        angle = ((arr[:, 1].astype(np.uint16) | (arr[:, 2].astype(np.uint16) << 8)) >> 1) / ANGLE_Q
        dist = (arr[:, 3].astype(np.uint16) | (arr[:, 4].astype(np.uint16) << 8)) / DIST_Q
        batch = NodeBatch(start, quality, angle, dist)
        if self.batch:
            out.append(batch)
        else:
            out.extend(batch.nodes())


CAPSULE_QUALITY = 47  # capsules carry no quality; SLAMTEC's SDK reports 47 (0x2F) for a return


def decode_capsule_angles(caps: U8Array, next_start_q6: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], FloatArray]:
    """The samples of K capsules (K, 84) given the start angle of the capsule after each: angles in
    1/64 degree within [0, 360) and distances in 1/4 mm, K * 32 of each, in stream order.

    SLAMTEC's SDK arithmetic, integer for integer: the capsule's start angle and the next one's in
    Q8 degrees, their difference (plus 360 if the next is lower) shifted into a Q16 increment per
    sample; sample j sits at start + j * increment, minus its 6-bit offset in 1/8 degree (four bits
    in the cabin's last byte, two in the low bits of its distance word), floored to Q6."""
    caps = np.asarray(caps, dtype=np.uint8).reshape(-1, CAPSULE_LEN)
    k = caps.shape[0]
    start_q8 = ((caps[:, 2].astype(np.int64) | (caps[:, 3].astype(np.int64) << 8)) & 0x7FFF) << 2
    next_q8 = (np.asarray(next_start_q6, dtype=np.int64).reshape(-1) & 0x7FFF) << 2
    diff_q8 = next_q8 - start_q8
    diff_q8 = np.where(start_q8 > next_q8, diff_q8 + (360 << 8), diff_q8)
    inc_q16 = diff_q8 << 3
    cab = caps[:, 4:].reshape(k, 16, 5).astype(np.int64)
    d1 = cab[:, :, 0] | (cab[:, :, 1] << 8)
    d2 = cab[:, :, 2] | (cab[:, :, 3] << 8)
    off1 = (cab[:, :, 4] & 0xF) | ((d1 & 0x3) << 4)
    off2 = (cab[:, :, 4] >> 4) | ((d2 & 0x3) << 4)
    dist = np.empty((k, CAPSULE_SAMPLES), dtype=np.int64)
    dist[:, 0::2] = d1 & 0xFFFC
    dist[:, 1::2] = d2 & 0xFFFC
    off = np.empty((k, CAPSULE_SAMPLES), dtype=np.int64)
    off[:, 0::2] = off1
    off[:, 1::2] = off2
    j = np.arange(CAPSULE_SAMPLES, dtype=np.int64)
    raw = (start_q8[:, None] << 8) + j[None, :] * inc_q16[:, None]
    angle = ((raw - (off << 13)) >> 10) % _Q6_TURN
    return angle.reshape(-1), dist.reshape(-1).astype(np.float64)


def _angle_at(data: bytes, pos: int) -> float:
    return ((data[pos + 1] | data[pos + 2] << 8) >> 1) / ANGLE_Q


def _continuous(prev_deg: float, next_deg: float) -> bool:
    return (next_deg - prev_deg + ANGLE_JITTER_DEG) % 360.0 < MAX_ANGLE_STEP_DEG + ANGLE_JITTER_DEG


def _valid_run(data: bytes, pos: int, n: int, window: int = 8) -> int:
    """How many consecutive in-step nodes start at ``pos`` (the first passes the check bits):
    each further node passes the check bits and continues the previous node's angle. Checked in
    windows of ``window`` nodes, growing eightfold while they pass (the answer does not depend on it)."""
    total = 0
    prev: float | None = None
    while True:
        k = min(window, (n - pos) // NODE_LEN)
        if k <= 0:
            return total
        arr = np.frombuffer(data, dtype=np.uint8, count=NODE_LEN * k, offset=pos).reshape(k, NODE_LEN)
        b0 = arr[:, 0]
        ok = ((b0 ^ (b0 >> 1)) & arr[:, 1] & 1).astype(np.bool_)
        angle = ((arr[:, 1].astype(np.int32) | (arr[:, 2].astype(np.int32) << 8)) >> 1) / ANGLE_Q
        step = np.diff(angle, prepend=angle[0] if prev is None else prev)
        ok &= (step + ANGLE_JITTER_DEG) % 360.0 < MAX_ANGLE_STEP_DEG + ANGLE_JITTER_DEG
        if ok.all():
            total += k
            pos += NODE_LEN * k
            prev = float(angle[-1])
            window = min(window * 8, 4096)
            continue
        return total + int(np.argmin(ok))


def _parse_descriptor(data: bytes, i: int) -> Descriptor | None:
    word = int.from_bytes(data[i + 2 : i + 6], "little")
    size = word & 0x3FFF_FFFF
    mode = word >> 30
    if mode > SEND_MODE_MULTI or size > MAX_ANSWER:
        return None
    return Descriptor(size, mode, data[i + 6])


def _answer(desc: Descriptor, payload: bytes, stats: DecoderStats) -> Event:
    t = desc.type
    if t == AnswerType.LIDAR_CONF:
        if len(payload) < 4:
            stats.wrong_size += 1
            return Response(t, payload)
        return LidarConf(int.from_bytes(payload[:4], "little"), payload[4:])
    expected = _KNOWN_SIZES.get(t)
    if expected is None:
        return Response(t, payload)
    if len(payload) != expected:
        stats.wrong_size += 1
        return Response(t, payload)
    if t == AnswerType.DEVICE_INFO:
        return DeviceInfo(payload[0], (payload[2], payload[1]), payload[3], payload[4:20])
    if t == AnswerType.DEVICE_HEALTH:
        return DeviceHealth(payload[0], int.from_bytes(payload[1:3], "little"))
    return SampleRate(int.from_bytes(payload[0:2], "little"), int.from_bytes(payload[2:4], "little"))


# -- revolutions ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class Revolution:
    """One turn: nodes from a start flag up to the next, converted and sorted.

    ``angles_rad``: sensor frame, counter-clockwise, [0, 2 pi), increasing. ``distances_m``: 0.0 for
    no return. ``stamp``: when the master completed it (set by the driver; None from the assembler).
    """

    angles_rad: FloatArray
    distances_m: FloatArray
    qualities: U8Array
    stamp: float | None = None

    def __len__(self) -> int:
        return int(self.angles_rad.size)

    @property
    def valid(self) -> BoolArray:
        return self.distances_m > 0.0

    def points(self) -> FloatArray:
        """(K, 2) x, y in the sensor frame of the samples with a return."""
        v = self.valid
        a = self.angles_rad[v]
        d = self.distances_m[v]
        return np.column_stack((d * np.cos(a), d * np.sin(a)))


@dataclass(slots=True)
class AssemblerStats:
    revolutions: int = 0
    orphan_nodes: int = 0  # nodes before the first start flag (the tail of a turn we did not see begin)
    overflow_nodes: int = 0  # dropped: a "revolution" longer than ``max_nodes`` (no start flags)
    false_starts: int = 0  # start flags ignored because the angle did not wrap (``check_wrap``)


class RevolutionAssembler:
    """Groups nodes between start flags into ``Revolution`` values.

    A revolution is complete when the next start flag arrives. With ``check_wrap`` (the default) a
    start flag counts only where the angle wraps, i.e. falls by more than 180 degrees from the
    previous node's, as it does at a real turn's first node: a node decoded out of step after line
    noise may carry a false start flag in the middle of a turn, and would otherwise split it.
    ``push`` takes ``Node`` and ``NodeBatch`` events (anything else is ignored, so a decoder's whole
    output can be passed).
    """

    def __init__(self, max_nodes: int = 8192, check_wrap: bool = True) -> None:
        self.max_nodes = max_nodes
        self.check_wrap = check_wrap
        self.stats = AssemblerStats()
        self._chunks: list[tuple[FloatArray, FloatArray, U8Array]] = []
        self._pending: list[tuple[float, float, int]] = []  # single Nodes not yet in a chunk
        self._count = 0
        self._started = False
        self._last_angle: float | None = None

    @property
    def partial(self) -> int:
        """Nodes of the revolution in progress."""
        return self._count

    @property
    def started(self) -> bool:
        """A turn's start has been seen (nodes before it are the tail of a turn not seen begin)."""
        return self._started

    def reset(self) -> None:
        """Drop the revolution in progress (after a STOP or a resynchronisation)."""
        self._chunks.clear()
        self._pending.clear()
        self._count = 0
        self._started = False
        self._last_angle = None

    def push(self, event: object) -> list[Revolution]:
        if isinstance(event, Node):
            return self._push_node(event)
        if isinstance(event, NodeBatch):
            return self.add(event.start, event.quality, event.angle_deg, event.distance_m)
        return []

    def push_all(self, events: Iterable[object]) -> list[Revolution]:
        out: list[Revolution] = []
        for ev in events:
            out.extend(self.push(ev))
        return out

    def add(
        self,
        start: npt.ArrayLike,
        quality: npt.ArrayLike,
        angle_deg: npt.ArrayLike,
        distance_m: npt.ArrayLike,
    ) -> list[Revolution]:
        """Arrays of consecutive nodes (the wire's units)."""
        s = np.asarray(start, dtype=np.bool_).reshape(-1)
        q = np.asarray(quality, dtype=np.uint8).reshape(-1)
        a = np.asarray(angle_deg, dtype=np.float64).reshape(-1)
        d = np.asarray(distance_m, dtype=np.float64).reshape(-1)
        if a.size == 0:
            return []
        self._flush_pending()
        out: list[Revolution] = []
        cuts: list[int] = []
        for c in np.flatnonzero(s).tolist():
            prev = float(a[c - 1]) if c > 0 else self._last_angle
            if self._is_start(float(a[c]), prev):
                cuts.append(c)
        prev_cut = 0
        for c in [*cuts, a.size]:
            if c > prev_cut:
                self._append(a[prev_cut:c], d[prev_cut:c], q[prev_cut:c])
            if c < a.size:  # a start flag: the turn in progress is complete
                rev = self._finish()
                if rev is not None:
                    out.append(rev)
                self._started = True
            prev_cut = c
        self._last_angle = float(a[-1])
        return out

    # -- internals -------------------------------------------------------------------------------

    def _is_start(self, angle: float, prev: float | None) -> bool:
        if not self.check_wrap or prev is None or angle + 180.0 < prev:
            return True
        self.stats.false_starts += 1
        return False

    def _push_node(self, node: Node) -> list[Revolution]:
        out: list[Revolution] = []
        prev = self._last_angle
        self._last_angle = node.angle_deg
        if node.start and self._is_start(node.angle_deg, prev):
            rev = self._finish()
            if rev is not None:
                out.append(rev)
            self._started = True
        if not self._started:
            self.stats.orphan_nodes += 1
            return out
        if self._count >= self.max_nodes:
            self.stats.overflow_nodes += 1
            return out
        self._pending.append((node.angle_deg, node.distance_m, node.quality))
        self._count += 1
        return out

    def _flush_pending(self) -> None:
        if self._pending:
            arr = np.array(self._pending, dtype=np.float64).reshape(-1, 3)
            self._chunks.append((arr[:, 0].copy(), arr[:, 1].copy(), arr[:, 2].astype(np.uint8)))
            self._pending.clear()

    def _append(self, a: FloatArray, d: FloatArray, q: U8Array) -> None:
        if not self._started:
            self.stats.orphan_nodes += a.size
            return
        room = self.max_nodes - self._count
        if a.size > room:
            self.stats.overflow_nodes += a.size - max(room, 0)
            a, d, q = a[:room], d[:room], q[:room]
            if a.size == 0:
                return
        self._chunks.append((a, d, q))
        self._count += a.size

    def _finish(self) -> Revolution | None:
        self._flush_pending()
        if not self._started or not self._chunks:
            self._chunks.clear()
            self._count = 0
            return None
        a = np.concatenate([c[0] for c in self._chunks])
        d = np.concatenate([c[1] for c in self._chunks])
        q = np.concatenate([c[2] for c in self._chunks])
        self._chunks.clear()
        self._count = 0
        rad = device_deg_to_rad(a)
        order = np.argsort(rad, kind="stable")
        self.stats.revolutions += 1
        return Revolution(rad[order], d[order], q[order])


# -- slave side: requests -------------------------------------------------------------------------


class Request(NamedTuple):
    cmd: int
    payload: bytes = b""


@dataclass(slots=True)
class RequestStats:
    requests: int = 0
    garbage_bytes: int = 0
    bad_checksum: int = 0


@dataclass(slots=True)
class RequestDecoder:
    """The lidar's request parser: ``A5 cmd [size payload checksum]``; never raises.

    Bytes that are not ``A5`` are skipped; a request with a bad checksum is dropped (the firmware
    ignores it) and scanning resumes at the byte after its ``A5``.
    """

    stats: RequestStats = field(default_factory=RequestStats)
    _buf: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Request]:
        out: list[Request] = []
        if not data:
            return out
        self._buf += data
        buf = bytes(self._buf)
        n = len(buf)
        pos = 0
        st = self.stats
        while pos < n:
            if buf[pos] != SYNC:
                i = buf.find(b"\xa5", pos)
                nxt = n if i < 0 else i
                st.garbage_bytes += nxt - pos
                pos = nxt
                continue
            if n - pos < 2:
                break
            cmd = buf[pos + 1]
            if not cmd & 0x80:
                out.append(Request(cmd))
                st.requests += 1
                pos += 2
                continue
            if n - pos < 3:
                break
            size = buf[pos + 2]
            end = pos + 3 + size + 1
            if end > n:
                break
            if checksum(buf[pos:end]) != 0:
                st.bad_checksum += 1
                pos += 1
                continue
            out.append(Request(cmd, buf[pos + 3 : end - 1]))
            st.requests += 1
            pos = end
        if pos:
            del self._buf[:pos]
        return out

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def reset(self) -> None:
        self._buf.clear()


def split_requests(chunks: Sequence[bytes]) -> list[Request]:
    """Convenience for tests: decode requests from a stream given as chunks."""
    dec = RequestDecoder()
    out: list[Request] = []
    for c in chunks:
        out.extend(dec.feed(c))
    return out
