"""The BLAS kernels pinned before numpy loads (shared/blas.py): where, when not, and that OpenBLAS
takes them in a fresh ``fleetlink`` process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fleetlink.shared.blas import CORE_VARIABLE, PINNED_CORE, pin_blas_kernels

XEON = "processor\t: 0\nflags\t\t: fpu sse2 avx avx2 fma avx512f bmi2\n"
OLD_CPU = "processor\t: 0\nflags\t\t: fpu sse2 sse4_2 avx\n"


def _cpuinfo(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cpuinfo"
    path.write_text(text)
    return path


def test_pins_an_avx2_cpu_where_nothing_chose(tmp_path: Path) -> None:
    env: dict[str, str] = {}
    assert pin_blas_kernels(env, _cpuinfo(tmp_path, XEON), "x86_64", modules=()) == PINNED_CORE
    assert env == {CORE_VARIABLE: PINNED_CORE}


def test_a_choice_already_made_stands(tmp_path: Path) -> None:
    env = {CORE_VARIABLE: "SkylakeX"}
    assert pin_blas_kernels(env, _cpuinfo(tmp_path, XEON), "x86_64", modules=()) == "SkylakeX"
    assert env == {CORE_VARIABLE: "SkylakeX"}


@pytest.mark.parametrize(
    ("text", "machine", "modules"),
    [
        (OLD_CPU, "x86_64", ()),  # no AVX2: Haswell's kernels would stop it on an illegal instruction
        (XEON, "aarch64", ()),  # another architecture: other kernels altogether
        ("processor\t: 0\n", "x86_64", ()),  # no flags line
        (XEON, "x86_64", ("numpy",)),  # numpy's OpenBLAS already loaded: too late, and scipy's alone would differ
        (XEON, "x86_64", ("scipy",)),
    ],
)
def test_left_to_openblas(tmp_path: Path, text: str, machine: str, modules: tuple[str, ...]) -> None:
    env: dict[str, str] = {}
    assert pin_blas_kernels(env, _cpuinfo(tmp_path, text), machine, modules=modules) is None
    assert env == {}


def test_unreadable_cpu_flags_leave_it(tmp_path: Path) -> None:
    env: dict[str, str] = {}
    assert pin_blas_kernels(env, tmp_path / "missing", "x86_64", modules=()) is None
    assert env == {}


def _runs_haswell_kernels() -> bool:
    try:
        flags = next(line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags"))
    except (OSError, StopIteration):
        return False
    return os.uname().machine == "x86_64" and {"avx2", "fma"} <= set(flags.split())


def _openblas_cores(code: str, **extra: str) -> str:
    """What OpenBLAS says it loaded (``OPENBLAS_VERBOSE=2``) in a fresh interpreter running ``code``."""
    env = {k: v for k, v in os.environ.items() if k != CORE_VARIABLE}
    env.update(OPENBLAS_VERBOSE="2", **extra)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60, check=True)
    return done.stdout + done.stderr


@pytest.mark.skipif(not _runs_haswell_kernels(), reason="needs an x86-64 CPU with AVX2 and FMA")
def test_a_fleetlink_process_loads_the_pinned_kernels() -> None:
    # numpy's and scipy's OpenBLAS alike, as the CLI's package imports them after pinning.
    out = _openblas_cores("import fleetlink.cli, numpy, scipy.sparse.linalg")
    assert out.count(f"Core: {PINNED_CORE}") == 2, out
    # The user's choice stands.
    out = _openblas_cores("import fleetlink.cli, numpy", **{CORE_VARIABLE: "Sandybridge"})
    assert "Core: Sandybridge" in out and f"Core: {PINNED_CORE}" not in out, out
