"""End to end: the real console in tmux on the real-time field with real agents.

``fleetlink field --console on`` starts the demo field (simulated boards on TCP), an embedded
mosquitto, an agent per robot and the console. The test types into the terminal like a person:
the fleet table shows UWB ok (the UWB
simulator runs in the field); hold ``i`` and the selected robot's position on screen moves; type a goal and it arrives; quit
with ctrl+q and the process ends.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from tests.harness import wait_until

TMUX = shutil.which("tmux")
# .ci/install-tmux installs tmux, so under CI this test must run: there a missing tmux fails it.
pytestmark = pytest.mark.skipif(
    TMUX is None and not os.environ.get("CI"), reason="tmux not installed (./dev test installs it with apt-get)"
)

POSE = re.compile(r"(uvc-1) \S* ?pose ([+-]\d+\.\d+) ([+-]\d+\.\d+)")
UWB_OK = re.compile(r"uvc-1 .* ok +\S+ *│")  # the uwb column (health says "ok N%" then more)


def tmux(*args: str) -> str:
    return subprocess.run([TMUX or "tmux", *args], check=True, capture_output=True, text=True).stdout


def screen(session: str) -> str:
    return tmux("capture-pane", "-t", session, "-p")


def pose(session: str, shown: str | None = None) -> tuple[float, float] | None:
    m = POSE.search(screen(session) if shown is None else shown)
    return (float(m.group(2)), float(m.group(3))) if m else None


def test_drive_and_goal_in_the_real_console(tmp_path: Path) -> None:
    session = f"fl-e2e-{uuid.uuid4().hex[:8]}"
    fleetlink = Path(sys.executable).parent / "fleetlink"
    cmd = f"cd {tmp_path} && {fleetlink} field --console on --zenoh-listen none"
    tmux("new-session", "-d", "-s", session, "-x", "160", "-y", "48", cmd)
    pane_pid: int | None = None
    try:
        pane_pid = int(tmux("list-panes", "-t", session, "-F", "#{pane_pid}").split()[0])
        wait_until(lambda: pose(session) is not None, timeout=60, message="the console showing uvc-1's pose")
        wait_until(lambda: "zenoh" in screen(session), timeout=30, message="the link column")
        # The UWB simulator runs in the field: the fleet table says so for uvc-1.
        wait_until(lambda: UWB_OK.search(screen(session)) is not None, timeout=60, message="uvc-1's UWB ok")
        start = pose(session)
        assert start is not None

        def driven() -> bool:
            # Hold i (forward) like a key repeat, every 50 ms, until the position on screen moved.
            for _ in range(10):
                tmux("send-keys", "-t", session, "i")
                time.sleep(0.05)
            p = pose(session)
            return p is not None and math.dist(start, p) > 0.2

        wait_until(driven, timeout=60, message=f"uvc-1 moving on screen from {start} while i is held")
        # Let go: the console sends stop when the repeats end; wait until the robot stands still.
        last: list[tuple[float, float] | None] = [None]

        def still() -> bool:
            # Idle in the detail line (no command any more) and the same pose on two polls in a row.
            shown = screen(session)
            p, before = (pose(session, shown) if "uvc-1 idle pose" in shown else None), last[0]
            last[0] = p
            return p is not None and p == before

        wait_until(still, timeout=30, interval=0.25, message="uvc-1 stopping after the key was released")
        moved = pose(session)
        assert moved is not None
        # A typed goal half a metre further on; it must arrive (position on screen near it).
        gx, gy = round(moved[0] + 0.5, 2), round(moved[1], 2)
        tmux("send-keys", "-t", session, ":")
        tmux("send-keys", "-t", session, "-l", f"goal {gx} {gy}")
        tmux("send-keys", "-t", session, "Enter")
        wait_until(
            lambda: (p := pose(session)) is not None and math.dist(p, (gx, gy)) < 0.2,
            timeout=90,
            message=f"uvc-1 arriving at the goal ({gx}, {gy})",
        )
        tmux("send-keys", "-t", session, "C-q")
        wait_until(
            lambda: subprocess.run([TMUX or "tmux", "has-session", "-t", session], capture_output=True).returncode != 0,
            timeout=60,
            message="the field and console exiting on ctrl+q",
        )
        wait_until(lambda: not alive(pane_pid), timeout=30, message="the field process gone")
    except AssertionError as exc:
        try:
            shown = screen(session)
        except subprocess.CalledProcessError:
            shown = "(the tmux session has ended)"
        log = tmp_path / "field.log"
        tail = "\n".join(log.read_text().splitlines()[-20:]) if log.exists() else "(no field.log)"
        raise AssertionError(f"{exc}\n--- screen ---\n{shown}\n--- field.log ---\n{tail}") from None
    finally:
        subprocess.run([TMUX or "tmux", "kill-session", "-t", session], capture_output=True)
        if pane_pid is not None and alive(pane_pid):  # a hung field: kill what this test started
            with contextlib.suppress(ProcessLookupError):
                os.kill(pane_pid, signal.SIGKILL)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (exited, not yet reaped by tmux) counts as gone.
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split()[2] == "Z")
