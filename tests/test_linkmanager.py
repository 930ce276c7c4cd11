"""Link manager core: switching, hold-off, re-sends, health. Pure: time is passed in."""

from __future__ import annotations

import pytest

from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, Failed, LinkManager, LinkPolicy, Send, Switch

POLICY = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=2.0, max_attempts=3)


def _feed(lm: LinkManager, robot: str, links: tuple[str, ...], t0: float, t1: float, hz: float = 20.0) -> float:
    """The robot reports on ``links`` at ``hz`` from t0 to t1; poll after every message."""
    t, n = t0, int(t0 * hz)
    while t < t1:
        for link in links:
            lm.heard(robot, link, t)
        lm.poll(t)
        n += 1
        t = n / hz
    return t


def test_commands_use_primary_while_healthy() -> None:
    lm = LinkManager(POLICY)
    _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    sends, failed = lm.command("r1", "order", 0, b"x", 1.0)
    assert [s.link for s in sends] == [PRIMARY] and not failed
    assert lm.acked("r1", PRIMARY, "order", 0, 1.01)
    assert lm.pending("r1") == 0
    h = {x.link: x for x in lm.health("r1", 1.01)}
    assert h[PRIMARY].healthy and h[PRIMARY].rtt_s == pytest.approx(0.01)


def test_silent_primary_moves_commands_and_resends_unacked() -> None:
    lm = LinkManager(POLICY)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    lm.command("r1", "order", 7, b"goal", t)  # never acked: the primary is cut now
    out: list[object] = []
    switch_at = None
    while switch_at is None:
        t = round(t + 0.05, 3)
        lm.heard("r1", FALLBACK, t)
        out = lm.poll(t)
        if any(isinstance(o, Switch) for o in out):
            switch_at = t
    sw = next(o for o in out if isinstance(o, Switch))
    assert (sw.from_link, sw.to_link) == (PRIMARY, FALLBACK)
    assert switch_at - 1.0 <= 0.35 + 0.05
    resent = [o for o in out if isinstance(o, Send)]
    assert resent == [Send("r1", FALLBACK, "order", 7, b"goal", resend=True)]
    assert lm.active("r1") == FALLBACK
    # New commands follow the fallback.
    assert lm.command("r1", "order", 8, b"g2", t)[0][0].link == FALLBACK
    # The robot acks the re-send on the fallback: nothing left pending, nothing re-sent again.
    assert lm.acked("r1", FALLBACK, "order", 7, t + 0.01)
    assert lm.acked("r1", FALLBACK, "order", 8, t + 0.01)
    assert not [o for o in lm.poll(t + 0.5) if isinstance(o, Send)]


def test_ack_timeout_alone_switches() -> None:
    # The robot still talks on the primary (e.g. one-way loss), but commands go unanswered.
    lm = LinkManager(POLICY)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    lm.command("r1", "actions", 3, b"stop", t)
    switched = []
    for i in range(1, 10):
        now = t + i * 0.05
        switched += [o for o in lm.poll(now) if isinstance(o, Switch)]
    assert switched and "ack timeout" in switched[0].reason


def test_no_move_to_a_fallback_as_silent_as_the_primary() -> None:
    # The fallback was never heard (a console without MQTT, a broker down): a stall on the primary
    # keeps commands there, and re-sends on it are acked when it comes back.
    lm = LinkManager(POLICY)
    t = _feed(lm, "r1", (PRIMARY,), 0.0, 1.0)
    lm.command("r1", "teleop", 0, b"drive", t)
    resent: list[Send] = []
    for i in range(1, 8):  # 0.35 s of silence on the primary, nothing on the fallback either
        out = lm.poll(t + i * 0.05)
        assert not [o for o in out if isinstance(o, Switch)]
        resent += [o for o in out if isinstance(o, Send)]
    assert lm.active("r1") == PRIMARY and [s.link for s in resent] == [PRIMARY]
    t = _feed(lm, "r1", (PRIMARY,), t + 0.4, t + 0.5)
    assert lm.acked("r1", PRIMARY, "teleop", 0, t) and lm.pending("r1") == 0


def test_a_silent_fallback_hands_commands_back_to_a_healthy_primary_at_once() -> None:
    lm = LinkManager(POLICY)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    t = _feed(lm, "r1", (FALLBACK,), t, 1.5)
    assert lm.active("r1") == FALLBACK
    t = _feed(lm, "r1", (PRIMARY,), t, 2.0)  # the primary is back, the fallback falls silent
    assert lm.active("r1") == PRIMARY  # well before the 2 s hold-off
    assert lm.switches("r1") == 2


def test_failback_waits_for_holdoff() -> None:
    lm = LinkManager(POLICY)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    t = _feed(lm, "r1", (FALLBACK,), t, 2.0)
    assert lm.active("r1") == FALLBACK
    # The primary comes back; commands stay on the fallback until the hold-off has passed.
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), t, 3.5)
    assert lm.active("r1") == FALLBACK
    # A blip resets the hold-off.
    t = _feed(lm, "r1", (FALLBACK,), t, 4.0)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), t, 5.9)
    assert lm.active("r1") == FALLBACK
    _feed(lm, "r1", (PRIMARY, FALLBACK), t, 6.2)
    assert lm.active("r1") == PRIMARY
    assert lm.switches("r1") == 2


def test_unacked_command_gives_up_after_max_attempts() -> None:
    lm = LinkManager(POLICY)
    lm.heard("r1", PRIMARY, 0.0)
    lm.heard("r1", FALLBACK, 0.0)
    lm.command("r1", "order", 1, b"x", 0.0)
    events: list[object] = []
    for i in range(1, 40):
        events += lm.poll(i * 0.05)
    sends = [e for e in events if isinstance(e, Send)]
    failed = [e for e in events if isinstance(e, Failed)]
    assert len(sends) == POLICY.max_attempts - 1
    assert failed == [Failed("r1", "order", 1, f"no ack after {POLICY.max_attempts} sends")]
    assert lm.pending("r1") == 0


def test_fire_and_forget_is_never_resent() -> None:
    lm = LinkManager(POLICY)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    lm.command("r1", "teleop", 5, b"drive", t, expect_ack=False)
    out = []
    for i in range(1, 20):
        lm.heard("r1", FALLBACK, t + i * 0.05)
        out += lm.poll(t + i * 0.05)
    assert not [o for o in out if isinstance(o, Send)]


def test_loss_percent_counts_unacked_commands() -> None:
    lm = LinkManager(POLICY)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    for i in range(3):
        lm.command("r1", "order", i, b"x", t)
        lm.acked("r1", PRIMARY, "order", i, t + 0.01)
    lm.command("r1", "order", 3, b"x", t)  # never answered on the primary
    lm.heard("r1", PRIMARY, t + 0.3)
    lm.poll(t + 0.3)
    h = {x.link: x for x in lm.health("r1", t + 0.3)}
    assert h[PRIMARY].loss_pct == pytest.approx(25.0)
    assert h[FALLBACK].loss_pct == 0.0
    assert h[PRIMARY].age_s == pytest.approx(0.0)
    assert h[PRIMARY].rtt_s == pytest.approx(0.01)


def test_robots_are_independent() -> None:
    lm = LinkManager(POLICY)
    for i in range(40):
        t = i * 0.05
        lm.heard("r1", PRIMARY, t)
        lm.heard("r2", FALLBACK, t)
        if t < 1.0:
            lm.heard("r2", PRIMARY, t)
        lm.poll(t)
    assert lm.active("r1") == PRIMARY and lm.active("r2") == FALLBACK


def test_bad_link_name_rejected() -> None:
    with pytest.raises(ValueError, match="unknown link"):
        LinkManager().heard("r1", "carrier-pigeon", 0.0)
    with pytest.raises(ValueError, match="holdoff_s"):
        LinkPolicy(holdoff_s=0)


# -- redundant sending ---------------------------------------------------------------------------

BOTH_LINKS = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=2.0, max_attempts=3, redundant=True)


def test_redundant_sends_every_command_on_both_links_and_counts_who_came_first() -> None:
    lm = LinkManager(BOTH_LINKS)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    assert lm.route("r1") == "both"
    for i in range(10):
        sends, _ = lm.command("r1", "order", i, b"g", t)
        assert [s.link for s in sends] == [PRIMARY, FALLBACK] and {s.payload for s in sends} == {b"g"}
        assert lm.acked("r1", PRIMARY, "order", i, t + 0.002)  # the first ack settles it
        assert not lm.acked("r1", FALLBACK, "order", i, t + 0.005)  # the copy's ack: health only
    teleop, _ = lm.command("r1", "teleop", 99, b"drive", t, expect_ack=False)
    assert [s.link for s in teleop] == [PRIMARY, FALLBACK]  # a held key streams on both links
    h = {x.link: x for x in lm.health("r1", t + 0.01)}
    assert h[PRIMARY].first_pct == 100.0 and h[FALLBACK].first_pct == 0.0
    assert h[PRIMARY].lead_s == pytest.approx(0.003) and h[FALLBACK].lead_s is None
    assert h[PRIMARY].rtt_s == pytest.approx(0.002) and h[FALLBACK].rtt_p95_s == pytest.approx(0.005)
    assert h[PRIMARY].loss_pct == h[FALLBACK].loss_pct == 0.0
    assert not h[PRIMARY].degraded and not h[FALLBACK].degraded
    assert "first 100% by 3.0 ms" in h[PRIMARY].describe()


def test_redundant_never_switches_and_a_dead_primary_costs_nothing() -> None:
    lm = LinkManager(BOTH_LINKS)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    out: list[object] = []
    for i in range(20):  # the primary is dead from here on: only the fallback answers
        now = round(t + i * 0.05, 3)
        lm.heard("r1", FALLBACK, now)
        lm.command("r1", "order", i, b"g", now)
        assert lm.acked("r1", FALLBACK, "order", i, now + 0.003)
        out += lm.poll(now)
    assert not [o for o in out if isinstance(o, Switch | Send | Failed)]  # nothing moved, resent or lost
    h = {x.link: x for x in lm.health("r1", t + 1.2)}
    assert not h[PRIMARY].healthy and h[FALLBACK].healthy and not h[FALLBACK].degraded
    assert h[PRIMARY].loss_pct == 100.0 and "silent" in h[PRIMARY].degraded


def test_redundant_resends_on_both_links_when_neither_acks() -> None:
    lm = LinkManager(BOTH_LINKS)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    lm.command("r1", "actions", 4, b"stop", t)
    out = lm.poll(t + 0.3)
    assert sorted(s.link for s in out if isinstance(s, Send)) == [FALLBACK, PRIMARY]
    assert all(s.resend for s in out if isinstance(s, Send))


def test_a_late_link_is_degraded_and_says_why() -> None:
    lm = LinkManager(BOTH_LINKS)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    for i in range(20):  # MQTT delivers every copy, 150 ms late (over the 100 ms RTT threshold)
        now = t + i * 0.05
        lm.heard("r1", PRIMARY, now)
        lm.heard("r1", FALLBACK, now)
        lm.command("r1", "order", i, b"g", now)
        lm.acked("r1", PRIMARY, "order", i, now + 0.002)
        lm.acked("r1", FALLBACK, "order", i, now + 0.15)
        lm.poll(now)
    h = {x.link: x for x in lm.health("r1", t + 1.0)}
    assert not h[PRIMARY].degraded
    assert h[FALLBACK].healthy and h[FALLBACK].degraded.startswith("rtt p95 150 ms")
    assert "DEGRADED" in h[FALLBACK].describe()


def test_lost_copies_make_a_link_degraded_and_late_acks_still_give_rtt() -> None:
    lm = LinkManager(BOTH_LINKS)
    t = _feed(lm, "r1", (PRIMARY, FALLBACK), 0.0, 1.0)
    for i in range(10):  # MQTT answers half the copies, 300 ms late: past the ack timeout
        now = t + i * 0.05
        lm.command("r1", "order", i, b"g", now)
        lm.acked("r1", PRIMARY, "order", i, now + 0.002)
        lm.poll(now + 0.26)
        if i % 2 == 0:
            lm.acked("r1", FALLBACK, "order", i, now + 0.3)
    h = {x.link: x for x in lm.health("r1", t + 0.5)}
    assert h[FALLBACK].loss_pct == 100.0 and h[FALLBACK].degraded.startswith("loss")
    assert h[FALLBACK].rtt_s == pytest.approx(0.3)


def test_new_policy_values_are_checked() -> None:
    with pytest.raises(ValueError, match="degraded_rtt_s"):
        LinkPolicy(degraded_rtt_s=0)
    with pytest.raises(ValueError, match="degraded_loss_pct"):
        LinkPolicy(degraded_loss_pct=120.0)


def _states_as_health(lm: LinkManager, robot: str, now: float) -> None:
    """``link_states`` says what ``health`` says of each link's age and degradation."""
    assert lm.link_states(robot, now) == tuple((h.link, h.age_s, h.degraded) for h in lm.health(robot, now))


def test_link_states_are_health_s_ages_and_degradations() -> None:
    lm = LinkManager(BOTH_LINKS)
    _states_as_health(lm, "nobody", 0.0)
    t = _feed(lm, "r1", (PRIMARY,), 0.0, 1.0)  # heard on Zenoh only: MQTT never heard
    _states_as_health(lm, "r1", t)
    for i in range(12):  # MQTT: two copies lost (under min_samples at first), then late, then silent
        now = t + i * 0.05
        lm.heard("r1", PRIMARY, now)
        if i > 2:
            lm.heard("r1", FALLBACK, now)
        lm.command("r1", "order", i, b"g", now)
        lm.acked("r1", PRIMARY, "order", i, now + 0.002)
        if i > 2:
            lm.acked("r1", FALLBACK, "order", i, now + (0.15 if i > 6 else 0.01))
        lm.poll(now + 0.26)
        _states_as_health(lm, "r1", now + 0.26)
    for later in (0.5, 1.5, 5.0):  # silence grows
        _states_as_health(lm, "r1", t + 0.6 + later)
    assert {link: why for link, _, why in lm.link_states("r1", t + 0.7)}[FALLBACK]
