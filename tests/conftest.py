"""Shared fixtures: see tests/harness.

Fixtures:
  mosquitto                      a started private broker (MosquittoBroker), stopped at teardown
  mosquitto_factory(extra_conf)  -> started MosquittoBroker with extra config lines
  zenoh_peers(n=2)               -> ZenohPeers: n connected loopback zenoh sessions, closed at teardown
  rig                            a started console rig (tests/harness/console_rig.py), closed at teardown
  _no_thread_leaks (autouse)     fails a test that leaves a non-daemon thread running

The suite runs on two pytest-xdist workers (addopts in pyproject.toml). Tests marked ``slow`` are
collected first, so each worker starts on a long one and the short ones fill in around them: the
run does not end with one worker idle while another finishes a long test it picked up last.
Tests that share a module-scoped fixture carry an ``xdist_group`` mark (one worker, one set-up); so
do the console's real-time tmux tests (one at a time: tests/e2e/test_console_field.py).
"""

# ruff: noqa: E402 -- first, before anything imports numpy: the BLAS kernels every fleetlink command
# runs (shared/blas.py), so the suite computes alike on every host.
from __future__ import annotations

from fleetlink.shared.blas import pin_blas_kernels

pin_blas_kernels()

import signal
import threading
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, settings

from tests.harness import leaked_threads
from tests.harness.console_rig import rig
from tests.harness.mosquitto import mosquitto, mosquitto_factory
from tests.harness.zenoh_peers import zenoh_peers

__all__ = ["mosquitto", "mosquitto_factory", "rig", "zenoh_peers"]

THREAD_GRACE_S = 2.0

# Hypothesis times every example (a 200 ms deadline) and its data generation (the too_slow health
# check): on two workers sharing two cores with other work, those are timings of the machine, not
# behaviour of the code, and fail now and then. The properties are checked without them.
settings.register_profile("fleetlink", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("fleetlink")


def pytest_configure(config: pytest.Config) -> None:
    # A run started with SIGINT ignored (a background job of a non-interactive shell, as a CI runner
    # may start it) hands that on to every process a test starts, and Python then leaves it ignored:
    # SIGINT (Ctrl-C) would not stop a command under test (tests/test_uwb_mqtt.py), depending on
    # which earlier test of the same worker happened to install a handler. Take it back, as a
    # terminal has it: children then start with SIGINT at its default.
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    # Stable: the slow tests first, each part in collection order (the same on every worker).
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(autouse=True)
def _no_thread_leaks() -> Iterator[None]:
    # Autouse and function-scoped, so it is set up before the test's other function-scoped
    # fixtures and torn down after them: their cleanup (closing zenoh sessions, stopping paho
    # loops) has already run when the check happens.
    before = set(threading.enumerate())
    yield
    leaked = leaked_threads(before, grace=THREAD_GRACE_S)
    if leaked:
        names = ", ".join(f"{t.name!r} (target={getattr(t, '_target', None)!r})" for t in leaked)
        pytest.fail(
            f"test left {len(leaked)} non-daemon thread(s) running {THREAD_GRACE_S}s after teardown: "
            f"{names}. Close zenoh sessions / stop clients / join worker threads.",
            pytrace=False,
        )
