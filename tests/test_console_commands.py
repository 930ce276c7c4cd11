"""The console's typed commands (operator/commands.py): every command, every error."""

from __future__ import annotations

import math

import pytest

from fleetlink.operator.commands import (
    USAGE,
    CommandError,
    Goal,
    Home,
    MarkAt,
    Payload,
    Seek,
    Speed,
    StopAll,
    parse_command,
)


@pytest.mark.parametrize("line", ["", "   ", "\t"])
def test_a_blank_line_is_no_command(line: str) -> None:
    assert parse_command(line) is None


def test_goal_with_and_without_heading() -> None:
    assert parse_command("goal 3.5 -2") == Goal(3.5, -2.0, None)
    assert parse_command("  GOAL 1 2  ") == Goal(1.0, 2.0, None)  # the verb in any case, spaces ignored
    assert parse_command("g 1e1 0") == Goal(10.0, 0.0, None)  # g is short for goal
    cmd = parse_command("goal 3.5 -2 90")
    assert isinstance(cmd, Goal) and cmd.theta == pytest.approx(math.pi / 2)


@pytest.mark.parametrize(
    ("degrees", "radians"), [(270, -math.pi / 2), (-450, -math.pi / 2), (360, 0.0), (180, math.pi)]
)
def test_goal_heading_is_wrapped_into_minus_pi_pi(degrees: float, radians: float) -> None:
    cmd = parse_command(f"goal 0 0 {degrees}")
    assert isinstance(cmd, Goal) and cmd.theta is not None
    assert abs(math.remainder(cmd.theta - radians, 2 * math.pi)) < 1e-9
    assert -math.pi <= cmd.theta <= math.pi


def test_mark_with_and_without_label() -> None:
    assert parse_command("mark hazard 1 2 gas leak") == MarkAt("hazard", 1.0, 2.0, "gas leak")
    assert parse_command("mark casualty -1.5 0") == MarkAt("casualty", -1.5, 0.0, "")
    assert parse_command("mark hazard 1 2 gas:leak   here") == MarkAt("hazard", 1.0, 2.0, "gas:leak here")


def test_replay_seek_and_speed() -> None:
    assert parse_command("seek 120") == Seek(120.0, relative=False)
    assert parse_command("seek +30") == Seek(30.0, relative=True)
    assert parse_command("seek -5") == Seek(-5.0, relative=True)  # back
    assert parse_command("speed 4") == Speed(4.0)
    bad_seeks = ("seek --5", "seek +-5", "seek -+5", "seek x", "seek nan", "seek -nan", "seek inf", "seek 1e999")
    for bad in (*bad_seeks, "seek", "seek 1 2", "speed 0", "speed -1", "speed 1e9", "speed nan"):
        assert isinstance(parse_command(bad), CommandError), bad


def test_home_payload_stop() -> None:
    assert parse_command("home") == Home()
    assert parse_command("payload on") == Payload(True)
    assert parse_command("payload off") == Payload(False)
    assert parse_command("Stop") == StopAll()


@pytest.mark.parametrize(
    "line",
    [
        "fly 1 2",  # no such verb
        "goal 1",  # too few numbers
        "goal 1 2 3 4",  # too many
        "mark hazard 1",  # a mark needs KIND X Y
        "home now",  # home takes nothing
        "payload",  # payload needs on or off
        "payload maybe",
        "payload on off",
        "stop r1",  # stop takes nothing: it stops every robot
        "g",
    ],
)
def test_unknown_or_malformed_commands_show_the_usage(line: str) -> None:
    err = parse_command(line)
    assert err == CommandError(line, f"unknown command {line!r}: {USAGE}")


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        ("goal x 2", "could not convert string to float: 'x'"),
        ("goal 1 2 north", "could not convert string to float: 'north'"),
        ("mark hazard one 2", "could not convert string to float: 'one'"),
        ("mark hazard 1 two label", "could not convert string to float: 'two'"),
        ("goal nan 1", "coordinates must be finite numbers"),
        ("goal 1 inf", "coordinates must be finite numbers"),
        ("goal 1 1 -inf", "coordinates must be finite numbers"),
        ("mark hazard 1 nan", "coordinates must be finite numbers"),
    ],
)
def test_bad_numbers_say_which_and_why(line: str, reason: str) -> None:
    assert parse_command(line) == CommandError(line, f"bad command {line!r}: {reason}")


def test_a_mark_label_may_be_anything_even_a_number() -> None:
    assert parse_command("mark note 1 2 nan") == MarkAt("note", 1.0, 2.0, "nan")
