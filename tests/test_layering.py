"""The layering contract ([tool.importlinter] in pyproject.toml) holds, and breaks on a bad import.

import-linter reads the fleetlink.* tree as ./dev lint builds it (links to the top-level folders);
the second test copies the sources, adds one import that climbs the layers, and expects the real
tool to refuse it, naming the offending import.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("shared", "devices", "links", "agent", "field", "positioning", "operator", "site", "cli")
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _tree(base: Path, copy: bool) -> Path:
    pkg = base / "fleetlink"
    pkg.mkdir(parents=True)
    for name in PACKAGES:
        if copy:
            shutil.copytree(ROOT / name, pkg / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            (pkg / name).symlink_to(ROOT / name)
    shutil.copy(ROOT / "pyproject.toml", base / "pyproject.toml")
    return base


def _lint(base: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(base)}
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"], cwd=base, env=env, capture_output=True, text=True, timeout=300
    )


def test_the_tree_keeps_its_layers(tmp_path: Path) -> None:
    result = _lint(_tree(tmp_path, copy=False))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "1 kept, 0 broken" in result.stdout


def test_a_bad_import_breaks_the_contract(tmp_path: Path) -> None:
    base = _tree(tmp_path, copy=True)
    # The wire contract reaching up into an agent: the very thing the layers forbid.
    (base / "fleetlink" / "shared" / "layering_probe.py").write_text("from fleetlink.agent import core  # noqa\n")
    result = _lint(base)
    assert result.returncode != 0
    assert "BROKEN" in result.stdout
    assert "fleetlink.shared.layering_probe -> fleetlink.agent.core" in result.stdout
