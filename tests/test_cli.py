"""The command line as a person uses it: subprocesses, real sockets, real output."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FLEETLINK = [sys.executable, "-m", "fleetlink.cli.main"]


def run(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*FLEETLINK, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def test_stdlib_operator_is_not_shadowed_from_the_repo_root() -> None:
    # Python started in the repo root has the root on sys.path; operator/ must stay a namespace portion.
    assert not (ROOT / "operator" / "__init__.py").exists()
    out = subprocess.run(
        [sys.executable, "-c", "import collections, operator, fleetlink.operator; print(operator.itemgetter)"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert out.returncode == 0, out.stderr
    assert "itemgetter" in out.stdout


@pytest.mark.parametrize("args", [[], ["field"], ["board"], ["board", "serve"], ["board", "probe"]])
def test_every_subcommand_has_help(args: list[str]) -> None:
    out = run(*args, "--help")
    assert out.returncode == 0, out.stderr
    assert "usage: fleetlink" in out.stdout
    assert len(out.stdout.splitlines()) > 4


def test_no_subcommand_prints_help_and_fails() -> None:
    out = run()
    assert out.returncode == 2
    assert "field" in out.stdout and "board" in out.stdout


def test_probe_talks_to_a_served_board_and_drives_it() -> None:
    serve = subprocess.Popen(
        [*FLEETLINK, "board", "serve", "--port", "0"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert serve.stdout is not None
        line = serve.stdout.readline()
        match = re.search(r"socket://127\.0\.0\.1:(\d+)", line)
        assert match, line
        out = run("board", "probe", match.group(0), "--drive", "0.2", "--seconds", "1")
        assert out.returncode == 0, out.stderr
        assert "model     FLK-UVC-01" in out.stdout
        assert "battery" in out.stdout and "tank 100 %" in out.stdout
        dist = re.search(r"dead reckoning: x=\+(\d+\.\d+) m", out.stdout)
        assert dist and 0.1 < float(dist.group(1)) < 0.3, out.stdout
        assert "stopped" in out.stdout
    finally:
        serve.terminate()
        serve.wait(10)


def test_probe_reports_an_unreachable_board_clearly() -> None:
    out = run("board", "probe", "socket://127.0.0.1:9", "--timeout", "0.05")
    assert out.returncode == 1
    assert "error: cannot open socket://127.0.0.1:9" in out.stderr


def test_field_demo_shows_live_board_status() -> None:
    start = time.monotonic()
    out = run("field", "--duration", "2", "--refresh", "2", "--zenoh-listen", "tcp/127.0.0.1:0")
    assert out.returncode == 0, out.stderr
    assert time.monotonic() - start < 25
    assert "demo on apartment" in out.stdout
    assert "uvc-1" in out.stdout and "uvc-2" in out.stdout
    assert "link up" in out.stdout and "lidar socket://127.0.0.1:" in out.stdout
    assert "battery    100 %" in out.stdout
    assert "Traceback" not in out.stderr


def test_field_runs_a_scenario_in_lockstep_and_writes_truth(tmp_path: Path) -> None:
    out = run("field", "run", "office-drill", "--lockstep", "--duration", "12", "--out", str(tmp_path), timeout=120)
    assert out.returncode == 0, out.stderr
    assert "door room-3 closes" in out.stdout and "x real time" in out.stdout
    rows = (tmp_path / "truth" / "scout-1.csv").read_text().splitlines()
    assert rows[0] == "t_s,x_m,y_m,theta_rad,v_m_per_s,omega_rad_per_s"
    assert len(rows) == 1 + 12 * 20 + 1
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["seed"] == 7 and summary["robots"] == ["scout-1", "scout-2"]


def test_field_run_reports_bad_scenarios_clearly(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('plan = "office"\n[[robots]]\nname = "a"\nstart = "attic"\n')
    out = run("field", "run", str(bad), "--lockstep", "--out", str(tmp_path / "o"))
    assert out.returncode == 2
    assert "no start 'attic'" in out.stderr
    out = run("field", "run", "no-such-scenario", "--lockstep", "--out", str(tmp_path / "o"))
    assert out.returncode == 2 and "built-in:" in out.stderr


def test_probe_works_over_a_pty() -> None:
    if not os.path.exists("/dev/ptmx"):
        pytest.fail("this machine has no pseudo-terminals")
    serve = subprocess.Popen(
        [*FLEETLINK, "board", "serve", "--pty"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert serve.stdout is not None
        line = serve.stdout.readline()
        match = re.search(r"on (/dev/pts/\d+)", line)
        assert match, line
        out = run("board", "probe", match.group(1))
        assert out.returncode == 0, out.stderr
        assert "FLK-UVC-01" in out.stdout
    finally:
        serve.terminate()
        serve.wait(10)
