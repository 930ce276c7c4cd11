"""The wire contract: keys, header, schema, codec, registry and header stamping."""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import math
import threading
import types
import typing
from typing import Annotated, Any, ClassVar

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import BoardFault, BoardStatus, ControlPoint, Trajectory
from fleetlink.shared.wire import (
    WIRE,
    Header,
    HeaderCounter,
    Limits,
    Message,
    WireError,
    bounded,
    decode,
    decode_any,
    decode_key,
    encode,
    sized,
)

# --------------------------------------------------------------------------------------------------
# Fixtures and helpers

HEADER = Header(headerId=7, timestamp=1_767_225_600.25, version="1.0.0", robot="r1", sender="agent-r1")


def board(**overrides: Any) -> BoardStatus:
    fields: dict[str, Any] = {
        "header": HEADER,
        "connected": True,
        "model": "mbot-2",
        "firmware": "1.4.2",
        "battery_percent": 87.5,
        "battery_voltage_v": 12.1,
        "battery_current_a": -0.8,
        "charging": False,
        "on_dock": False,
        "temperature_c": 24.5,
        "humidity_percent": 41.0,
        "pm2_5_ug_m3": 8.5,
        "tvoc_ppb": 120,
        "uv_lamp": True,
        "atomiser_level": 2,
        "fan_level": 2,
        "has_payload": True,
        "tank_percent": 55.0,
        "estop_button": False,
        "health_flags": 0x21,
        "faults": (BoardFault(code=2, text="motor L overcurrent"), BoardFault(code=4, text="battery below 10 %")),
        "bumpers": 0b101,
        "sensors_m": (0.5, 1.25, 0.0),
        "watchdog_trips": 0,
    }
    fields.update(overrides)
    return BoardStatus(**fields)


def wire_dict(msg: Message) -> dict[str, Any]:
    """The msgpack map of a valid message, to mutate."""
    obj = msgpack.unpackb(encode(msg), raw=False)
    assert isinstance(obj, dict)
    return obj


def pack(obj: object) -> bytes:
    data = msgpack.packb(obj, use_bin_type=True)
    assert isinstance(data, bytes)
    return data


def rejects(cls: type[Message], data: bytes, *fragments: str) -> WireError:
    with pytest.raises(WireError) as info:
        decode(cls, data)
    err = info.value
    assert isinstance(err, ValueError)
    for fragment in fragments:
        assert fragment in err.reason, (fragment, err.reason)
    assert str(err) == err.reason
    return err


class Mode(enum.StrEnum):
    MANUAL = "manual"
    AUTO = "auto"


@dataclasses.dataclass(frozen=True, slots=True)
class Point:
    x: float
    y: Annotated[float, bounded(-10.0, 10.0)]


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class Sample(Message):
    """Unregistered test schema exercising every supported field kind."""

    TOPIC: ClassVar[str] = "test/sample"

    mode: Mode
    maybe: Annotated[int, bounded(0, 9)] | None
    blob: Annotated[bytes, sized(8)]
    where: Point
    path: Annotated[list[Point], sized(3)]
    tags: tuple[str, ...] = dataclasses.field(metadata={WIRE: sized(4, item=sized(5))})
    level: int = dataclasses.field(metadata={WIRE: bounded(-3, 3)})

    def __post_init__(self) -> None:
        if self.level == 2 and self.mode is Mode.AUTO:
            raise RuntimeError("level 2 is manual only")


def sample(**overrides: Any) -> Sample:
    fields: dict[str, Any] = {
        "header": HEADER,
        "mode": Mode.AUTO,
        "maybe": None,
        "blob": b"\x00\xff",
        "where": Point(1.0, -2.5),
        "path": [Point(0.0, 0.0), Point(3.0, 4.0)],
        "tags": ("a", "bc"),
        "level": -3,
    }
    fields.update(overrides)
    return Sample(**fields)


# --------------------------------------------------------------------------------------------------
# Keys

ids = st.from_regex(keys.ID_PATTERN, fullmatch=True).filter(lambda s: s != keys.SIM)
topics = st.lists(ids, min_size=1, max_size=keys.MAX_TOPIC_SEGMENTS).map("/".join)


@given(robot=ids, topic=topics.filter(lambda t: not t.endswith(keys.TRUTH_TOPIC)))
def test_key_round_trip(robot: str, topic: str) -> None:
    k = keys.key(robot, topic)
    assert k == f"fleetlink/v1/{robot}/{topic}"
    assert keys.parse_key(k) == (robot, topic)


def test_key_examples() -> None:
    assert keys.key("r1", "board") == "fleetlink/v1/r1/board"
    assert keys.parse_key("fleetlink/v1/r-2_x/map/updates") == ("r-2_x", "map/updates")
    assert keys.zenoh_all_robots("board") == "fleetlink/v1/*/board"
    assert keys.mqtt_all_robots("map/updates") == "fleetlink/v1/+/map/updates"
    assert keys.zenoh_robot("r1") == "fleetlink/v1/r1/**"
    assert keys.mqtt_robot("r1") == "fleetlink/v1/r1/#"
    assert keys.ZENOH_ALL == "fleetlink/v1/**"
    assert keys.MQTT_ALL == "fleetlink/v1/#"


@pytest.mark.parametrize(
    "robot",
    ["", "a/b", "a*", "a#", "a+", "$SYS", "a?", "a b", "ä", "x" * 65, "sim", "r1\n", None, 5],
)
def test_key_rejects_bad_robot(robot: Any) -> None:
    with pytest.raises(ValueError, match="robot id"):
        keys.key(robot, "board")
    assert not keys.is_valid_id(robot) or robot == "sim"


@pytest.mark.parametrize(
    "topic", ["", "/board", "board/", "map//updates", "a*", "#", "+", "a/**", "truth", "x/truth", None]
)
def test_key_rejects_bad_topic(topic: Any) -> None:
    with pytest.raises(ValueError, match="topic"):
        keys.key("r1", topic)


def test_topic_segment_limit() -> None:
    keys.check_topic("/".join(["a"] * keys.MAX_TOPIC_SEGMENTS))
    with pytest.raises(ValueError, match="segments"):
        keys.check_topic("/".join(["a"] * (keys.MAX_TOPIC_SEGMENTS + 1)))


@pytest.mark.parametrize(
    "bad",
    [
        "",
        "fleetlink/v1",
        "fleetlink/v1/",
        "fleetlink/v1/r1",
        "fleetlink/v1/r1/",
        "fleetlink/v2/r1/board",
        "fleetlink/v1//board",
        "fleetlink/v1/*/board",
        "fleetlink/v1/+/board",
        "fleetlink/v1/r1/#",
        "fleetlink/v1/r1/**",
        "fleetlink/v1/sim/r1/truth",
        "fleetlink/v1/r1/x/truth",
        "/fleetlink/v1/r1/board",
        "fleetlink/v1/r1/board\n",
        None,
    ],
)
def test_parse_key_rejects(bad: Any) -> None:
    with pytest.raises(ValueError, match="invalid key"):
        keys.parse_key(bad)


def test_truth_namespace() -> None:
    k = keys.truth_key("r1")
    assert k == "fleetlink/v1/sim/r1/truth"
    assert keys.is_truth_key(k) and not keys.is_truth_key("fleetlink/v1/r1/board")
    assert keys.parse_truth_key(k) == "r1"
    assert keys.ZENOH_ALL_TRUTH == "fleetlink/v1/sim/*/truth"
    assert keys.MQTT_ALL_TRUTH == "fleetlink/v1/sim/+/truth"
    for bad in ["fleetlink/v1/sim/r1", "fleetlink/v1/sim/r1/pose", "fleetlink/v1/sim/a*/truth", "x"]:
        with pytest.raises(ValueError, match="truth key"):
            keys.parse_truth_key(bad)
    with pytest.raises(ValueError, match="reserved"):
        keys.truth_key("sim")


@given(robot=ids)
def test_alive_key_round_trip(robot: str) -> None:
    k = keys.alive_key(robot)
    assert k == f"fleetlink/alive/v1/{robot}"
    assert keys.parse_alive_key(k) == robot


def test_alive_keys_are_off_the_robots_key_tree() -> None:
    # A token matched by fleetlink/v1/** cost zenoh 1.10's routers 4-6x the CPU (issue 18).
    from fleetlink.links.base import key_matches

    assert keys.ZENOH_ALL_ALIVE == "fleetlink/alive/v1/*"
    assert key_matches(keys.ZENOH_ALL_ALIVE, keys.alive_key("r1"))
    assert not key_matches(keys.ZENOH_ALL, keys.alive_key("r1"))
    with pytest.raises(ValueError, match="reserved"):
        keys.alive_key("sim")


@pytest.mark.parametrize(
    "bad",
    [
        "",
        "fleetlink/alive/v1",
        "fleetlink/alive/v1/",
        "fleetlink/alive/v1/r1/x",
        "fleetlink/alive/v1/a*",
        "fleetlink/alive/v1/sim",
        "fleetlink/alive/v1/r1\n",
        "fleetlink/alive/v2/r1",
        "fleetlink/alive/r1",
        "fleetlink/v1/r1/alive",
        None,
    ],
)
def test_parse_alive_key_rejects(bad: Any) -> None:
    with pytest.raises(ValueError, match="invalid token key"):
        keys.parse_alive_key(bad)


# --------------------------------------------------------------------------------------------------
# Round trips (generic over every registered message)


def strategy_for(tp: Any, limits: Limits) -> st.SearchStrategy[Any]:
    """Valid values for one schema type (mirrors wire's compiler)."""
    if tp is Header:
        return st.builds(
            Header,
            headerId=st.integers(0, 2**64 - 1),
            timestamp=st.floats(0.0, 4e9, allow_nan=False),
            version=st.sampled_from(["1.0.0", "1.2.3", "1.10.0"]),
            robot=ids,
            sender=ids,
        )
    if tp is Trajectory:  # its fields are checked together (__post_init__): clamped curves
        coord = st.floats(-1e5, 1e5, allow_nan=False, allow_infinity=False)

        def clamped(degree: int, pts: list[tuple[float, float]], weights: list[float]) -> Trajectory:
            n = len(pts)
            inner = [i / (n - degree) for i in range(1, n - degree)]
            return Trajectory(
                degree=degree,
                knotVector=(0.0,) * (degree + 1) + tuple(inner) + (1.0,) * (degree + 1),
                controlPoints=tuple(ControlPoint(x=x, y=y, weight=w) for (x, y), w in zip(pts, weights, strict=False)),
            )

        return st.integers(1, 3).flatmap(
            lambda d: st.builds(
                clamped,
                st.just(d),
                st.lists(st.tuples(coord, coord), min_size=d + 1, max_size=d + 4),
                st.lists(st.floats(0.1, 10.0), min_size=d + 4, max_size=d + 4),
            )
        )
    if typing.get_origin(tp) is typing.Annotated:
        base, *extras = typing.get_args(tp)
        for extra in extras:
            if isinstance(extra, Limits):
                limits = limits.over(extra)
        return strategy_for(base, limits)
    assert limits.check is None, f"write a strategy for {tp!r} with a custom check"
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        (inner,) = [a for a in typing.get_args(tp) if a is not type(None)]
        return st.none() | strategy_for(inner, limits)
    if origin in (list, tuple):
        assert limits.max_len is not None
        item = strategy_for(typing.get_args(tp)[0], limits.item or Limits())
        return st.lists(item, max_size=min(limits.max_len, 4)).map(origin)
    if tp is bool:
        return st.booleans()
    if tp is int:
        lo = -(2**63) if limits.ge is None else math.ceil(limits.ge)
        hi = 2**64 - 1 if limits.le is None else math.floor(limits.le)
        return st.integers(lo, hi)
    if tp is float:
        return st.floats(limits.ge, limits.le, allow_nan=False, allow_infinity=False)
    if tp is str:
        return st.text(max_size=min(limits.max_len or wire.DEFAULT_MAX_STR_LEN, 12))
    if tp is bytes:
        return st.binary(max_size=min(limits.max_len or 64, 64))
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return st.sampled_from(list(tp))
    assert dataclasses.is_dataclass(tp), tp
    return st.builds(tp, **{f.name: strategy_for(f.type, f.limits) for f in wire.schema(tp)})


def test_registry_has_board() -> None:
    assert wire.registered()["board"] is BoardStatus
    assert wire.message_type("board") is BoardStatus
    assert wire.schema(BoardStatus)[0].name == "header"


@pytest.mark.parametrize("topic", sorted(wire.registered()))
@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_round_trip_every_registered_message(topic: str, data: st.DataObject) -> None:
    cls = wire.registered()[topic]
    msg = data.draw(strategy_for(cls, Limits()))
    raw = encode(msg)
    back = decode(cls, raw)
    assert back == msg
    assert decode_any(topic, raw) == msg
    assert encode(back) == raw
    assert decode_key(wire.key_of(msg), raw) == msg


def test_board_round_trip_and_layout() -> None:
    msg = board()
    raw = encode(msg)
    assert decode(BoardStatus, raw) == msg
    obj = wire_dict(msg)
    assert list(obj) == [f.name for f in wire.schema(BoardStatus)]
    assert obj["header"] == {
        "headerId": 7,
        "timestamp": 1_767_225_600.25,
        "version": "1.0.0",
        "robot": "r1",
        "sender": "agent-r1",
    }
    assert obj["faults"] == [{"code": 2, "text": "motor L overcurrent"}, {"code": 4, "text": "battery below 10 %"}]
    assert wire.key_of(msg) == "fleetlink/v1/r1/board"


def test_board_decode_normalises() -> None:
    """Ints are accepted for floats; arrays come back as the declared tuple type."""
    obj = wire_dict(board())
    obj["battery_percent"] = 50
    obj["sensors_m"] = [1, 2.5]
    msg = decode(BoardStatus, pack(obj))
    assert type(msg.battery_percent) is float and msg.battery_percent == 50.0
    assert msg.sensors_m == (1.0, 2.5) and all(type(x) is float for x in msg.sensors_m)


def test_encode_accepts_lists_for_tuples() -> None:
    f = BoardFault(code=1, text="x")
    assert decode(BoardStatus, encode(board(faults=[f], sensors_m=[1.0]))) == board(faults=(f,), sensors_m=(1.0,))


def test_sample_round_trip() -> None:
    for msg in [sample(), sample(maybe=9, mode=Mode.MANUAL, level=2, path=[], tags=())]:
        back = decode(Sample, encode(msg))
        assert back == msg
        assert type(back.path) is list and type(back.tags) is tuple
        assert back.mode is msg.mode


def test_minor_version_accepted() -> None:
    obj = wire_dict(board())
    obj["header"]["version"] = "1.7.3"
    assert decode(BoardStatus, pack(obj)).header.version == "1.7.3"


# --------------------------------------------------------------------------------------------------
# Rejections: every reason names the field


def _locate(root: Any, path: str) -> tuple[Any, Any]:
    """The container holding the field at dotted ``path`` (list indexes are numbers), and its key."""
    *parents, last = path.split(".")
    target = root
    for part in parents:
        target = target[int(part)] if isinstance(target, list) else target[part]
    return target, int(last) if isinstance(target, list) else last


def mutated(path: str, value: Any, msg: Message | None = None) -> bytes:
    """Encoded ``msg`` (default: a BoardStatus) with the field at dotted ``path`` set to ``value``."""
    root = wire_dict(msg or board())
    target, last = _locate(root, path)
    target[last] = value
    return pack(root)


def without(path: str, msg: Message | None = None) -> bytes:
    """Encoded ``msg`` (default: a BoardStatus) with the field at dotted ``path`` removed."""
    root = wire_dict(msg or board())
    target, last = _locate(root, path)
    del target[last]
    return pack(root)


@pytest.mark.parametrize(
    ("version", "fragment"),
    [("2.0.0", "major"), ("0.9.0", "major"), ("1.0", "malformed"), ("v1.0.0", "malformed"), (1, "string")],
)
def test_rejects_unknown_or_bad_version(version: Any, fragment: str) -> None:
    rejects(BoardStatus, mutated("header.version", version), "header.version", fragment)


def test_version_checked_before_shape() -> None:
    """A message from another major version is reported as such, not as a shape mismatch."""
    obj = wire_dict(board())
    obj["header"]["version"] = "2.0.0"
    obj["new_in_v2"] = 1
    del obj["connected"]
    rejects(BoardStatus, pack(obj), "header.version", "major")


@pytest.mark.parametrize("path", ["battery_percent", "header", "header.headerId", "header.sender", "faults"])
def test_rejects_missing_field(path: str) -> None:
    rejects(BoardStatus, without(path), path, "missing field")


@pytest.mark.parametrize(
    ("path", "value"),
    [
        ("connected", 1),
        ("connected", None),
        ("battery_percent", True),
        ("battery_percent", "50"),
        ("battery_percent", None),
        ("health_flags", 3.0),
        ("health_flags", True),
        ("model", b"mbot"),
        ("model", 5),
        ("faults", "motor"),
        ("faults", {"a": 1}),
        ("faults.1", 5),
        ("sensors_m.0", "far"),
        ("header.headerId", "7"),
        ("header.timestamp", "now"),
        ("header.robot", 1),
        ("header", [1, 2]),
        ("header", None),
    ],
)
def test_rejects_wrong_type(path: str, value: Any) -> None:
    err = rejects(BoardStatus, mutated(path, value), "expected")
    shown = path.replace(".0", "[0]").replace(".1", "[1]")
    assert err.field == shown and err.reason.startswith(shown + ":")


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("path", ["temperature_c", "battery_percent", "sensors_m.2", "header.timestamp"])
def test_rejects_non_finite(path: str, value: float) -> None:
    shown = path.replace(".2", "[2]")
    rejects(BoardStatus, mutated(path, value), shown, "non-finite")


@pytest.mark.parametrize(
    ("path", "value"),
    [
        ("battery_percent", 100.001),
        ("battery_percent", -0.5),
        ("health_flags", 256),
        ("health_flags", -1),
        ("bumpers", -1),
        ("sensors_m.1", -0.01),
        ("header.headerId", -1),
        ("header.timestamp", -1.0),
    ],
)
def test_rejects_out_of_range(path: str, value: float) -> None:
    shown = path.replace(".1", "[1]")
    rejects(BoardStatus, mutated(path, value), shown, "out of range")


@pytest.mark.parametrize(
    ("path", "value", "fragment"),
    [
        ("header.robot", "a/b", "robot id"),
        ("header.robot", "sim", "reserved"),
        ("header.robot", "", "robot id"),
        ("header.sender", "op+1", "sender id"),
    ],
)
def test_rejects_bad_ids(path: str, value: str, fragment: str) -> None:
    rejects(BoardStatus, mutated(path, value), path, fragment)


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        ("faults", [{"code": 1, "text": "e"}] * 17, "faults"),
        ("sensors_m", [1.0] * 17, "sensors_m"),
        ("model", "m" * 65, "model"),
        ("faults.0.text", "e" * 65, "faults[0].text"),
    ],
)
def test_rejects_oversized_values(path: str, value: Any, field: str) -> None:
    rejects(BoardStatus, mutated(path, value), field + ":", "limit")


def test_limits_at_the_edge_are_accepted() -> None:
    msg = board(
        faults=(BoardFault(code=65_535, text="e" * 64),) * 16,
        sensors_m=(0.0,) * 16,
        model="m" * 64,
        battery_percent=100.0,
        health_flags=255,
    )
    assert decode(BoardStatus, encode(msg)) == msg


def test_rejects_oversized_payload_before_unpacking() -> None:
    # 0xc1 is never valid msgpack: the size check must fire first.
    rejects(BoardStatus, b"\xc1" * (wire.MAX_PAYLOAD + 1), "payload", "exceeds the limit")
    raw = encode(board())
    with pytest.raises(WireError, match=r"^payload: .*exceeds the limit"):
        decode(BoardStatus, raw, max_payload=len(raw) - 1)
    assert decode(BoardStatus, raw, max_payload=len(raw)) == board()
    with pytest.raises(WireError, match="payload: encoded size"):
        encode(board(), max_payload=10)


def test_unpack_limits_apply_inside_the_payload() -> None:
    """max_array_len/max_map_len are enforced by msgpack, far below the payload limit."""
    big_array = pack([None] * (wire.MAX_ARRAY_LEN + 1))
    assert len(big_array) < wire.MAX_PAYLOAD
    rejects(BoardStatus, big_array, "payload", "not valid msgpack")
    big_map = pack({str(i): 0 for i in range(wire.MAX_MAP_LEN + 1)})
    rejects(BoardStatus, big_map, "payload", "not valid msgpack")


@pytest.mark.parametrize("path", ["", "header"])
def test_rejects_unknown_fields(path: str) -> None:
    obj = wire_dict(board())
    target = obj[path] if path else obj
    target["bogus"] = 1
    field = f"{path}.bogus" if path else "bogus"
    err = rejects(BoardStatus, pack(obj), field, "unknown field")
    assert err.field == field


def test_rejects_several_unknown_fields() -> None:
    obj = wire_dict(board())
    obj.update({"a": 1, "b": 2})
    rejects(BoardStatus, pack(obj), "unknown field", "1 more")


def test_rejects_bytes_keys() -> None:
    obj = wire_dict(board())
    obj[b"connected"] = obj.pop("connected")
    rejects(BoardStatus, pack(obj), "connected: missing field")


@pytest.mark.parametrize("top", [[1, 2], 5, "board", None, b"\x00", 1.5, True])
def test_rejects_not_a_map(top: Any) -> None:
    rejects(BoardStatus, pack(top), "payload", "expected a map")


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\xc1",
        b"\x85",  # map of 5, truncated
        b"\xa5ab",  # str of 5, truncated
        pack({"a": 1}) + b"\x00",  # trailing data
        b"\xd9\x02\xff\xfe",  # invalid utf-8 str
        pack({1: 2}),  # non-string key
        b"\xd4\x01\x00",  # ext type
        b"\xd6\xff\x00\x00\x00\x00",  # msgpack timestamp ext
        b"\x91" * 5000,  # deeply nested arrays
    ],
)
def test_rejects_garbage_bytes(data: bytes) -> None:
    rejects(BoardStatus, data, "payload")


@pytest.mark.parametrize("data", ["text", None, 5, [1]])
def test_rejects_non_bytes_input(data: Any) -> None:
    rejects(BoardStatus, data, "payload", "expected bytes")


def test_accepts_bytearray_and_memoryview() -> None:
    raw = encode(board())
    assert decode(BoardStatus, bytearray(raw)) == board()
    assert decode(BoardStatus, memoryview(raw)) == board()


@pytest.mark.parametrize(
    ("path", "value", "fragments"),
    [
        ("mode", "turbo", ("mode:", "not one of", "'auto'")),
        ("mode", 1, ("mode:", "expected a string")),
        ("maybe", 10, ("maybe:", "out of range")),
        ("maybe", 1.0, ("maybe:", "expected an integer")),
        ("blob", "text", ("blob:", "expected bytes")),
        ("blob", b"123456789", ("blob:", "limit of 8")),
        ("where", [1, 2], ("where:", "expected a map")),
        ("where.y", 11.0, ("where.y:", "out of range")),
        ("where.z", 1.0, ("where.z:", "unknown field")),
        ("path.1.x", math.nan, ("path[1].x:", "non-finite")),
        ("path.0", None, ("path[0]:", "expected a map")),
        ("path", [{"x": 0.0, "y": 0.0}] * 4, ("path:", "limit of 3")),
        ("tags.1", "toolong", ("tags[1]:", "limit of 5")),
        ("level", 4, ("level:", "out of range")),
    ],
)
def test_sample_rejections(path: str, value: Any, fragments: tuple[str, ...]) -> None:
    rejects(Sample, mutated(path, value, sample()), *fragments)


def test_post_init_errors_become_wire_errors() -> None:
    obj = wire_dict(sample(mode=Mode.MANUAL, level=2))
    obj["mode"] = "auto"
    rejects(Sample, pack(obj), "rejected by Sample", "manual only")


def test_encode_validates() -> None:
    with pytest.raises(WireError, match=r"^battery_percent: 101.0 out of range"):
        encode(board(battery_percent=101.0))
    with pytest.raises(WireError, match=r"^sensors_m\[1\]: non-finite"):
        encode(board(sensors_m=(1.0, math.nan)))
    with pytest.raises(WireError, match=r"^connected: expected a bool"):
        encode(board(connected=1))
    with pytest.raises(WireError, match=r"^header.robot: .*reserved"):
        encode(board(header=dataclasses.replace(HEADER, robot="sim")))
    with pytest.raises(WireError, match=r"^mode: expected Mode"):
        encode(sample(mode="turbo"))
    with pytest.raises(WireError, match=r"^pm2_5_ug_m3: integer .* too large"):
        encode(board(pm2_5_ug_m3=10**400))
    with pytest.raises(WireError, match=r"^bumpers: .* out of range"):
        encode(board(bumpers=2**64))
    with pytest.raises(WireError, match="payload: expected a Message"):
        encode(HEADER)  # type: ignore[arg-type]


def test_decode_any_and_decode_key() -> None:
    raw = encode(board())
    assert decode_any("board", raw) == board()
    assert decode_key("fleetlink/v1/r1/board", raw) == board()
    with pytest.raises(WireError, match=r"^topic: no message registered"):
        decode_any("nope", raw)
    with pytest.raises(WireError, match=r"^header.robot: 'r1' does not match the key's robot 'r2'"):
        decode_key("fleetlink/v1/r2/board", raw)
    with pytest.raises(WireError, match=r"^key: invalid key"):
        decode_key("fleetlink/v1/r*/board", raw)
    # The simulation namespace carries Truth: a board payload there is refused, naming what is missing.
    with pytest.raises(WireError, match=r"^sim_time_s: missing field"):
        decode_key(keys.truth_key("r1"), raw)


# --------------------------------------------------------------------------------------------------
# Fuzz: nothing but WireError, ever

msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=20),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner, max_size=5),
    max_leaves=20,
)


def only_wire_errors(cls: type[Message], data: Any) -> None:
    try:
        decode(cls, data)
    except WireError as exc:
        assert exc.reason and "internal error" not in exc.reason, exc.reason
    with contextlib.suppress(WireError):
        decode_any(cls.TOPIC, data)


@settings(max_examples=300)
@given(data=st.binary(max_size=400))
def test_fuzz_random_bytes(data: bytes) -> None:
    only_wire_errors(BoardStatus, data)


@settings(max_examples=300)
@given(value=msgpack_values)
def test_fuzz_random_msgpack_objects(value: Any) -> None:
    only_wire_errors(BoardStatus, pack(value))


@settings(max_examples=400)
@given(
    cls_and_msg=st.sampled_from([(BoardStatus, board()), (Sample, sample())]),
    where=st.data(),
    value=msgpack_values,
)
def test_fuzz_one_field_replaced(cls_and_msg: tuple[type[Message], Message], where: st.DataObject, value: Any) -> None:
    """Structure-aware: a valid message with one field (top level or in the header) replaced."""
    cls, msg = cls_and_msg
    obj = wire_dict(msg)
    target = where.draw(st.sampled_from([obj, obj["header"]]))
    name = where.draw(st.sampled_from([*target, "extra"]))
    target[name] = value
    only_wire_errors(cls, pack(obj))


@settings(max_examples=200)
@given(raw=st.just(encode(board())), flips=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255))))
def test_fuzz_corrupted_valid_payload(raw: bytes, flips: list[tuple[int, int]]) -> None:
    data = bytearray(raw)
    for pos, byte in flips:
        data[pos % len(data)] = byte
    only_wire_errors(BoardStatus, bytes(data))


def test_validators_are_precompiled(monkeypatch: pytest.MonkeyPatch) -> None:
    raw = encode(board())
    decode(BoardStatus, raw)

    def boom(*_args: Any, **_kwargs: Any) -> Any:
        raise AssertionError("get_type_hints called per message")

    monkeypatch.setattr(typing, "get_type_hints", boom)
    for _ in range(3):
        assert decode(BoardStatus, encode(board())) == board()


# --------------------------------------------------------------------------------------------------
# Schema definition errors (programming errors: TypeError/ValueError at registration)


def test_schema_errors() -> None:
    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class NoMaxLen(Message):
        TOPIC: ClassVar[str] = "test/a"
        xs: list[int]

    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class BadLimit(Message):
        TOPIC: ClassVar[str] = "test/b"
        name: Annotated[str, bounded(0, 1)]

    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class BadUnion(Message):
        TOPIC: ClassVar[str] = "test/c"
        v: int | str

    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class BadTopic(Message):
        TOPIC: ClassVar[str] = "bad topic"

    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class Duplicate(Message):
        TOPIC: ClassVar[str] = "board"

    for cls, exc, match in [
        (NoMaxLen, TypeError, "max_len"),
        (BadLimit, TypeError, "does not apply"),
        (BadUnion, TypeError, "Optional"),
        (BadTopic, ValueError, "invalid topic"),
        (Duplicate, ValueError, "already registered"),
    ]:
        with pytest.raises(exc, match=match):
            wire.register(cls)
    assert wire.registered()["board"] is BoardStatus
    assert "test/a" not in wire.registered()


# --------------------------------------------------------------------------------------------------
# Header stamping


def test_header_counter_counts_per_topic() -> None:
    clock = SimClock(start=5.0)
    counter = HeaderCounter(clock, robot="r1", sender="agent-r1")
    assert [counter.header("board").headerId for _ in range(3)] == [0, 1, 2]
    assert counter.header("state").headerId == 0
    clock.advance(0.5)
    h = counter.header("board")
    assert h == Header(headerId=3, timestamp=clock.wall(), version=wire.WIRE_VERSION, robot="r1", sender="agent-r1")
    assert counter.header("board", robot="r2").headerId == 0
    assert counter.peek("board") == 4 and counter.peek("board", robot="r2") == 1


def test_header_counter_make_and_encode() -> None:
    counter = HeaderCounter(SimClock(), robot="r7", sender="agent-r7")
    fields = {f.name: getattr(board(), f.name) for f in dataclasses.fields(BoardStatus) if f.name != "header"}
    first = counter.make(BoardStatus, **fields)
    second = counter.make(BoardStatus, **fields)
    assert (first.header.headerId, second.header.headerId) == (0, 1)
    assert decode_key(wire.key_of(second), encode(second)) == second


def test_header_counter_validates() -> None:
    clock = SimClock()
    with pytest.raises(ValueError, match="robot id"):
        HeaderCounter(clock, robot="sim", sender="x")
    with pytest.raises(ValueError, match="sender id"):
        HeaderCounter(clock, robot="r1", sender="a/b")
    with pytest.raises(ValueError, match="major"):
        HeaderCounter(clock, robot="r1", sender="a", version="2.0.0")
    counter = HeaderCounter(clock, robot="r1", sender="a")
    with pytest.raises(ValueError, match="topic"):
        counter.header("a/#")
    with pytest.raises(ValueError, match="robot id"):
        counter.header("board", robot="x y")


def test_header_counter_is_thread_safe() -> None:
    counter = HeaderCounter(SimClock(), robot="r1", sender="a")
    seen: list[int] = []
    lock = threading.Lock()

    def work() -> None:
        ids = [counter.header("board").headerId for _ in range(500)]
        with lock:
            seen.extend(ids)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(seen) == list(range(2000))
