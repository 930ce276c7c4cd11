"""The master's Control Bus connection, sans-I/O: bytes and times in, events out; no port, no clock."""

from __future__ import annotations

import pytest

from fleetlink.devices.controlbus import protocol as p
from fleetlink.devices.controlbus.connection import (
    Answered,
    BoardConnection,
    BoardProtocolError,
    BoardRefused,
    BoardTimeout,
    Echoed,
    Failed,
    Synced,
    Transmit,
    Waiting,
)
from fleetlink.field.board import SimulatedBoard

STATUS_OK = p.encode_ok(p.BaseStatus(87, 0))


def test_a_request_and_its_reply() -> None:
    conn = BoardConnection(timeout=0.1)
    data = conn.send(p.GetBaseStatus(), now=10.0)
    assert data == p.encode_request(p.GetBaseStatus()) and conn.busy
    assert conn.next_event(10.02) == Waiting(10.1)
    conn.receive_data(STATUS_OK[:3])  # any split
    assert conn.next_event(10.03) == Waiting(10.1)
    conn.receive_data(STATUS_OK[3:])
    event = conn.next_event(10.04)
    assert isinstance(event, Answered) and event.reply == p.BaseStatus(87, 0)
    assert event.request == p.GetBaseStatus() and event.rtt == pytest.approx(0.04)
    assert not conn.busy and conn.next_event(11.0) == Waiting(None)
    assert (conn.stats.requests, conn.stats.replies, conn.stats.timeouts) == (1, 1, 0)


def test_a_timeout_is_retried_after_a_sync_that_flushes_stale_replies() -> None:
    conn = BoardConnection(timeout=0.1, retries=2)
    request = conn.send(p.GetBaseStatus(), now=0.0)
    assert conn.next_event(0.05) == Waiting(0.1)
    # The deadline passes: the connection asks for a SYNC with a fresh nonce.
    sync = conn.next_event(0.1)
    assert isinstance(sync, Transmit)
    nonce = sync.data[3:-1]
    assert sync.data == p.encode_sync(nonce) and len(nonce) == 4
    # A late reply to the first attempt, then the SYNC's echo: the late one is discarded...
    conn.receive_data(p.encode_ok(p.BaseStatus(1, 0)) + sync.data)
    # ... and the request goes out again.
    assert conn.next_event(0.12) == Transmit(request)
    conn.receive_data(STATUS_OK)
    event = conn.next_event(0.13)
    assert isinstance(event, Answered) and event.reply == p.BaseStatus(87, 0)
    assert event.rtt == pytest.approx(0.01)  # from the attempt that was answered
    st = conn.stats
    assert (st.timeouts, st.retries, st.syncs, st.stale_replies, st.requests) == (1, 1, 1, 1, 2)


def test_retries_run_out() -> None:
    conn = BoardConnection(timeout=0.1, retries=1)
    conn.send(p.GetHealth(), now=0.0)
    sync = conn.next_event(0.1)
    assert isinstance(sync, Transmit)
    # The SYNC is not answered either: no attempts left.
    event = conn.next_event(0.2)
    assert isinstance(event, Failed) and isinstance(event.error, BoardTimeout)
    assert "SYNC" in str(event.error)
    assert not conn.busy and conn.stats.timeouts == 2


def test_a_refusal_is_final_and_a_protocol_error_is_retried() -> None:
    conn = BoardConnection()
    conn.send(p.SetAtomiser(2), now=0.0)
    conn.receive_data(p.encode_error(p.ErrorCode.OPERATION_FAILED))
    event = conn.next_event(0.01)
    assert isinstance(event, Failed) and isinstance(event.error, BoardRefused)
    assert event.error.code == p.ErrorCode.OPERATION_FAILED and event.error.request == p.SetAtomiser(2)
    assert conn.stats.retries == 0
    conn.send(p.GetBaseStatus(), now=1.0)
    conn.receive_data(p.encode_error(p.ErrorCode.CHECKSUM_MISMATCH))
    assert isinstance(conn.next_event(1.01), Transmit)  # the SYNC of a retry
    assert conn.stats.protocol_errors == 1 and conn.stats.retries == 1


def test_malformed_replies_end_as_protocol_errors() -> None:
    conn = BoardConnection(retries=0)
    conn.send(p.GetBaseStatus(), now=0.0)
    conn.receive_data(p.encode_ok(p.Health(0, 0)))  # the right size for a BaseStatus: accepted as one
    assert isinstance(conn.next_event(0.0), Answered)
    conn.send(p.GetBaseStatus(), now=0.0)
    conn.receive_data(p.encode_ok(p.Empty()))
    event = conn.next_event(0.0)
    assert isinstance(event, Failed) and isinstance(event.error, BoardProtocolError)


def test_sync_and_echo() -> None:
    conn = BoardConnection()
    sync = conn.sync(now=0.0)
    conn.receive_data(p.encode_echo(b"x") + sync)  # an echo nobody asked for is stale
    assert conn.next_event(0.0) == Synced()
    assert conn.stats.stale_replies == 1
    conn.echo(b"hello", now=0.0)
    conn.receive_data(p.encode_echo(b"hello"))
    assert conn.next_event(0.0) == Echoed(b"hello")
    conn.echo(b"again", now=0.0)
    event = conn.next_event(0.5)
    assert isinstance(event, Failed) and "ECHO" in str(event.error)


def test_one_exchange_at_a_time() -> None:
    conn = BoardConnection()
    conn.send(p.GetBaseStatus(), now=0.0)
    with pytest.raises(RuntimeError):
        conn.send(p.GetMotorData(), now=0.0)
    conn.abandon()  # the port failed: the next exchange may start; the late reply counts as stale
    conn.receive_data(STATUS_OK)
    conn.send(p.GetMotorData(), now=0.1)
    assert conn.stats.stale_replies == 1


def test_driving_a_simulated_board_without_any_port() -> None:
    """The whole handshake against the board's own sans-I/O side: bytes passed by hand."""
    board = SimulatedBoard(now=0.0)
    conn = BoardConnection()
    conn.receive_data(board.receive(conn.sync(now=0.0), 0.0))
    assert conn.next_event(0.0) == Synced()
    conn.receive_data(board.receive(conn.send(p.ConnectBase(), now=0.0), 0.0))
    event = conn.next_event(0.001)
    assert isinstance(event, Answered) and isinstance(event.reply, p.BaseInfo)
    assert event.reply.model == board.config.model and board.state.connected
