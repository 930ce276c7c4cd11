"""The generated decoders (shared/wire.py ``_generate``) accept and refuse exactly what the generic
field-by-field path does, with the same reasons.

Every decode here is run twice: as receivers run it (the decoder generated for the class, falling
back to the generic path for anything it does not accept) and under ``wire.generic_decoding()``
(the generic path alone, the decoder as it was before). The two must give the same message, field
types included, or the same ``WireError`` reason. And the generated function itself must refuse
every malformed input (raise), so no refusal depends on the generic path catching what the
generated code let through.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from typing import Annotated, Any, ClassVar

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetlink.shared import keys, wire
from fleetlink.shared.messages import BoardStatus, Pose, State
from fleetlink.shared.wire import Limits, Message, WireError, bounded, decode, decode_key, encode, sized
from tests.harness.messages import state_fields
from tests.test_wire import (
    HEADER,
    Sample,
    board,
    msgpack_values,
    mutated,
    pack,
    sample,
    strategy_for,
    wire_dict,
    without,
)

Outcome = tuple[str, str]


def outcome(cls: type[Message], data: bytes) -> Outcome:
    """``("ok", repr of the message)`` (repr tells 1 from 1.0 and a tuple from a list) or
    ``("refused", reason)``."""
    try:
        return "ok", repr(decode(cls, data))
    except WireError as exc:
        return "refused", exc.reason


def same_as_generic(cls: type[Message], data: bytes) -> Outcome:
    got = outcome(cls, data)
    with wire.generic_decoding():
        reference = outcome(cls, data)
    assert got == reference
    return got


def generated_refuses(cls: type[Message], data: bytes) -> None:
    """The generated decoder raises on ``data`` by itself (the generic path is not asked)."""
    import msgpack

    obj = msgpack.unpackb(data, raw=False)
    with pytest.raises(Exception):  # noqa: B017 (_Fallback, a KeyError or a check's WireError)
        wire._struct(cls).fast(obj)


def pose() -> Pose:
    return Pose(
        header=HEADER, x=1.0, y=-2.0, theta=0.5, sd_x_m=0.1, sd_y_m=0.1, sd_theta_rad=0.01,
        odom_x=1.0, odom_y=-2.0, odom_theta=0.5, vx=0.2, omega=0.0, uwbStale=False,
    )  # fmt: skip


def state() -> State:
    return State(header=HEADER, **state_fields())


# -- what receivers are sent: the generated decoder takes it without the generic path ---------------


@pytest.mark.parametrize("topic", sorted(wire.registered()))
@settings(max_examples=40, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_every_registered_message_is_decoded_by_its_generated_decoder(topic: str, data: st.DataObject) -> None:
    cls = wire.registered()[topic]
    msg = data.draw(strategy_for(cls, Limits()))
    raw = encode(msg)
    decoded = wire._struct(cls).fast(wire_dict(msg))  # raises if it would fall back
    assert decoded == msg and repr(decoded) == repr(msg)
    assert same_as_generic(cls, raw) == ("ok", repr(msg))


def test_the_generated_decoder_makes_the_message_its_class_makes() -> None:
    for cls, msg in ((Pose, pose()), (State, state()), (BoardStatus, board()), (Sample, sample())):
        decoded = wire._struct(cls).fast(wire_dict(msg))
        assert type(decoded) is cls and decoded == msg
        if cls is not Sample:  # (Sample holds a list)
            assert hash(decoded) == hash(msg)
        with pytest.raises(dataclasses.FrozenInstanceError):
            decoded.header = HEADER  # type: ignore[misc]
    # ints where floats are declared come out as floats, as the generic path makes them
    obj = wire_dict(pose())
    obj["x"], obj["header"]["timestamp"] = 3, 17
    got = decode(Pose, pack(obj))
    assert type(got.x) is float and type(got.header.timestamp) is float and got.x == 3.0


def test_the_source_is_kept_for_reading() -> None:
    source = wire._struct(Pose).source
    assert source.startswith("def decode_Pose(value):") and "-100000.0 <= f1 <= 100000.0" in source


# -- what the contract refuses: the same reason, and the generated decoder refuses it itself --------

MALFORMED_BOARD: list[tuple[str, Any]] = [
    # NaN and the infinities, in a field, an optional field, a list item, the header
    *[(path, v) for path in ("battery_percent", "temperature_c", "sensors_m.1", "header.timestamp")
      for v in (math.nan, math.inf, -math.inf)],
    # wrong types: bool for a number, float for an int, str for a number, bytes for str, nil
    ("battery_percent", True), ("battery_percent", "50"), ("battery_percent", None), ("health_flags", 3.0),
    ("health_flags", True), ("connected", 1), ("connected", None), ("model", b"mbot"), ("faults", "motor"),
    ("faults", {"a": 1}), ("faults.1", 5), ("faults.0.code", 1.0), ("sensors_m.0", "far"), ("header", [1, 2]),
    ("header", None), ("header.headerId", "7"), ("header.robot", 1), ("tvoc_ppb", 1.5),
    # out of range
    ("battery_percent", 100.001), ("battery_percent", -0.5), ("health_flags", 256), ("health_flags", -1),
    ("bumpers", -1), ("sensors_m.1", -0.01), ("header.headerId", -1), ("header.timestamp", -1.0),
    ("faults.0.code", 65_536), ("pm2_5_ug_m3", -1e-300),
    # oversized strings and lists
    ("model", "m" * 65), ("faults.0.text", "e" * 65), ("faults", [{"code": 1, "text": "e"}] * 17),
    ("sensors_m", [1.0] * 17),
    # bad ids and versions: malformed, another major version
    ("header.robot", "a/b"), ("header.robot", "sim"), ("header.robot", ""), ("header.sender", "op+1"),
    ("header.version", "2.0.0"), ("header.version", "0.9.0"), ("header.version", "1.0"), ("header.version", 1),
]  # fmt: skip


@pytest.mark.parametrize(("path", "value"), MALFORMED_BOARD)
def test_malformed_values_are_refused_with_the_generic_reason(path: str, value: Any) -> None:
    data = mutated(path, value)
    verdict, reason = same_as_generic(BoardStatus, data)
    assert verdict == "refused"
    assert reason.startswith(path.split(".")[0]), reason
    generated_refuses(BoardStatus, data)


@pytest.mark.parametrize("path", ["header", "connected", "header.sender", "faults.0.text"])
def test_missing_fields_are_refused_with_the_generic_reason(path: str) -> None:
    data = without(path)
    assert same_as_generic(BoardStatus, data)[0] == "refused"
    generated_refuses(BoardStatus, data)


@pytest.mark.parametrize("where", ["", "header", "faults.0"])
def test_unknown_fields_are_refused_with_the_generic_reason(where: str) -> None:
    obj = wire_dict(board())
    target = obj
    for part in where.split(".") if where else []:
        target = target[int(part)] if isinstance(target, list) else target[part]
    target["bogus"] = 1
    verdict, reason = same_as_generic(BoardStatus, pack(obj))
    assert verdict == "refused" and "bogus: unknown field" in reason
    # the same number of fields, one of them unknown
    del target[next(k for k in target if k != "bogus")]
    assert same_as_generic(BoardStatus, pack(obj))[0] == "refused"
    generated_refuses(BoardStatus, pack(obj))


def test_another_major_version_is_refused_before_the_shape() -> None:
    obj = wire_dict(pose())
    obj["header"]["version"] = "2.0.0"
    obj["new_in_v2"] = 1
    del obj["x"]
    assert same_as_generic(Pose, pack(obj)) == (
        "refused",
        "header.version: unknown major version in '2.0.0' (this side speaks 1.x.y)",
    )


def test_a_message_of_an_earlier_minor_version_without_a_field_added_since_is_read_with_its_default() -> None:
    """1.2.0 added ``Pose.map_began`` (default 0): a 1.1.0 agent's pose, or one in a recording made
    before, is still read, the field at its default; a required field left out is still refused, as is
    a field this side does not know."""
    obj = wire_dict(dataclasses.replace(pose(), map_began=12.5))
    assert decode(Pose, pack(obj)).map_began == 12.5
    obj["header"]["version"] = "1.1.0"
    del obj["map_began"]
    assert same_as_generic(Pose, pack(obj))[0] == "ok"
    assert decode(Pose, pack(obj)).map_began == 0.0
    obj["later"] = 1
    assert same_as_generic(Pose, pack(obj)) == ("refused", "later: unknown field in Pose")
    del obj["later"], obj["x"]
    assert same_as_generic(Pose, pack(obj)) == ("refused", "x: missing field")


def test_oversized_payloads_and_keys_are_refused_with_the_generic_reason() -> None:
    raw = encode(pose())
    for data, max_payload in ((b"\xc1" * (wire.MAX_PAYLOAD + 1), wire.MAX_PAYLOAD), (raw, len(raw) - 1)):
        results = []
        for generic in (False, True):
            with wire.generic_decoding() if generic else contextlib.nullcontext():
                with pytest.raises(WireError) as info:
                    decode_key("fleetlink/v1/r1/pose", data, max_payload=max_payload)
                results.append(info.value.reason)
        assert results[0] == results[1] and "exceeds the limit" in results[0]
    for key, fragment in (("fleetlink/v1/r2/pose", "does not match the key's robot"), ("fleetlink/v1/r*/pose", "key")):
        reasons = []
        for generic in (False, True):
            with wire.generic_decoding() if generic else contextlib.nullcontext():
                with pytest.raises(WireError) as info:
                    decode_key(key, raw)
                reasons.append(info.value.reason)
        assert reasons[0] == reasons[1] and fragment in reasons[0]


@pytest.mark.parametrize(
    ("path", "value"),
    [
        ("mode", "turbo"), ("mode", 1), ("maybe", 10), ("maybe", 1.0), ("blob", "text"), ("blob", b"123456789"),
        ("where", [1, 2]), ("where.y", 11.0), ("where.z", 1.0), ("path.1.x", math.nan), ("path.0", None),
        ("path", [{"x": 0.0, "y": 0.0}] * 4), ("path", (1, 2)), ("tags.1", "toolong"), ("tags.0", None),
        ("level", 4), ("level", -4),
    ],
)  # fmt: skip
def test_every_kind_of_field_refuses_as_the_generic_path(path: str, value: Any) -> None:
    """Enums, optional ints, bytes, nested structs, lists and tuples of them (tests/test_wire.py's
    Sample)."""
    data = mutated(path, value, sample())
    assert same_as_generic(Sample, data)[0] == "refused"
    generated_refuses(Sample, data)


def test_a_post_init_refusal_is_the_generic_one() -> None:
    obj = wire_dict(sample(level=-3))
    obj["level"] = 2  # level 2 is manual only: Sample.__post_init__ refuses it
    assert same_as_generic(Sample, pack(obj)) == ("refused", "rejected by Sample: level 2 is manual only")
    generated_refuses(Sample, pack(obj))


# -- fuzz: one value anywhere in a valid message replaced, removed or added ------------------------

NASTY = st.sampled_from(
    [math.nan, math.inf, -math.inf, -0.0, 1e308, -1e308, 5e-324, True, False, 0, 1, -1, 2**63 - 1, -(2**63),
     2**64 - 1, 1.5, "", "x" * 2000, "sim", "2.0.0", "1.0.0", "r1", b"", b"\x00" * 300, [], {}, None,
     "manual", "AUTOMATIC", [None], {"x": 1.0, "y": 2.0}]
)  # fmt: skip


def _paths(obj: Any, here: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [here]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, (*here, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _paths(v, (*here, i))
    return out


def _mutate(obj: Any, path: tuple[Any, ...], action: str, value: Any) -> Any:
    if not path:
        return value if action == "replace" else obj
    parent = obj
    for part in path[:-1]:
        parent = parent[part]
    last = path[-1]
    if action == "replace":
        parent[last] = value
    elif action == "remove":
        del parent[last]
    elif isinstance(parent, dict):
        parent["extra" if action == "add" else last] = value
    return obj


MESSAGES: list[tuple[type[Message], Message]] = [(Pose, pose()), (State, state()), (BoardStatus, board()),
                                                 (Sample, sample())]  # fmt: skip


@settings(max_examples=600, suppress_health_check=[HealthCheck.too_slow])
@given(
    which=st.integers(0, len(MESSAGES) - 1),
    where=st.data(),
    action=st.sampled_from(["replace", "remove", "add"]),
    value=NASTY | msgpack_values,
)
def test_fuzz_the_generated_decoders_agree_with_the_generic_path(
    which: int, where: st.DataObject, action: str, value: Any
) -> None:
    cls, msg = MESSAGES[which]
    obj = wire_dict(msg)
    path = where.draw(st.sampled_from(_paths(obj)))
    same_as_generic(cls, pack(_mutate(obj, path, action, value)))


@pytest.mark.parametrize("topic", sorted(wire.registered()))
@settings(max_examples=25, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), action=st.sampled_from(["replace", "remove", "add"]), value=NASTY)
def test_fuzz_every_registered_message(topic: str, data: st.DataObject, action: str, value: Any) -> None:
    cls = wire.registered()[topic]
    obj = wire_dict(data.draw(strategy_for(cls, Limits())))
    path = data.draw(st.sampled_from(_paths(obj)))
    same_as_generic(cls, pack(_mutate(obj, path, action, value)))


# -- classes the generated decoder cannot fill slot by slot: it calls them ---------------------------


@dataclasses.dataclass
class Loose:  # not frozen, not slotted
    a: int
    b: Annotated[str, sized(4)] = "x"


@dataclasses.dataclass(frozen=True, slots=True)
class Normalised:
    """A ``__post_init__`` that changes the value (and one that refuses)."""

    v: Annotated[float, bounded(-10.0, 10.0)]

    def __post_init__(self) -> None:
        if self.v == 9.0:
            raise ValueError("nine is refused")
        object.__setattr__(self, "v", round(self.v, 1))


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class Odd(Message):
    TOPIC: ClassVar[str] = "test/odd"
    loose: Loose
    norm: Normalised
    many: Annotated[tuple[Normalised, ...], sized(3)]
    opt: Annotated[str, Limits(max_len=64, check=keys.check_robot_id)] | None


def odd(**overrides: Any) -> Odd:
    fields: dict[str, Any] = {"header": HEADER, "loose": Loose(1, "ab"), "norm": Normalised(1.26),
                              "many": (Normalised(2.0),), "opt": "r2"}  # fmt: skip
    fields.update(overrides)
    return Odd(**fields)


def test_classes_of_every_shape_decode_as_the_generic_path() -> None:
    assert "Loose(" in wire._struct(Loose).source and "_set" not in wire._struct(Loose).source
    msg = odd()
    assert msg.norm.v == 1.3
    assert same_as_generic(Odd, encode(msg)) == ("ok", repr(msg))
    for path, value in [("norm.v", 9.0), ("many.0.v", 9.0), ("norm.v", 1.24), ("loose.a", True), ("loose.b", "abcde"),
                        ("opt", "sim"), ("opt", None), ("opt", "r3"), ("many", [])]:  # fmt: skip
        same_as_generic(Odd, mutated(path, value, msg))


def test_generic_decoding_is_restored_after_the_block() -> None:
    with pytest.raises(RuntimeError), wire.generic_decoding():
        raise RuntimeError
    assert wire._generated
