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


def test_pins_on_windows_machine_names_too(tmp_path: Path) -> None:
    env: dict[str, str] = {}
    assert pin_blas_kernels(env, _cpuinfo(tmp_path, XEON), "AMD64", modules=()) == PINNED_CORE


def test_a_choice_already_made_stands(tmp_path: Path) -> None:
    env = {CORE_VARIABLE: "SkylakeX"}
    assert pin_blas_kernels(env, _cpuinfo(tmp_path, XEON), "x86_64", modules=()) == "SkylakeX"
    assert env == {CORE_VARIABLE: "SkylakeX"}
    # An empty value is no choice (OpenBLAS would say "Core not found" and pick for itself).
    env = {CORE_VARIABLE: ""}
    assert pin_blas_kernels(env, _cpuinfo(tmp_path, XEON), "x86_64", modules=()) == PINNED_CORE


@pytest.mark.parametrize(
    ("text", "machine", "modules"),
    [
        (OLD_CPU, "x86_64", ()),  # no AVX2: Haswell's kernels would stop it on an illegal instruction
        ("flags\t: sse2 avx avx2\n", "x86_64", ()),  # AVX2 without FMA: likewise
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
    """This host's CPU read apart from ``pin_blas_kernels``: a pin that wrongly declined here would
    otherwise skip the test below instead of failing it."""
    try:
        flags = next(line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags"))
    except (OSError, StopIteration):
        return False
    return os.uname().machine == "x86_64" and {"avx2", "fma"} <= set(flags.split())


def _openblas_cores(code: str, **extra: str) -> tuple[list[str], str]:
    """What OpenBLAS says it loaded (``OPENBLAS_VERBOSE=2``: its "Core:" lines, numpy's and scipy's
    each) in a fresh interpreter running ``code``, and what ``code`` printed."""
    env = {k: v for k, v in os.environ.items() if k != CORE_VARIABLE}
    env.update(OPENBLAS_VERBOSE="2", **extra)
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60, check=True)
    cores = [line for line in (done.stdout + done.stderr).splitlines() if line.startswith("Core:")]
    printed = [line for line in done.stdout.splitlines() if not line.startswith("Core:")]
    return cores, printed[-1] if printed else ""


PINNING = "import fleetlink.cli, numpy, scipy.sparse.linalg, os; print(os.environ.get('OPENBLAS_CORETYPE'))"


@pytest.mark.skipif(not _runs_haswell_kernels(), reason="needs an x86-64 CPU with AVX2 and FMA")
def test_a_fleetlink_process_loads_the_pinned_kernels() -> None:
    if not _openblas_cores("import numpy")[0]:
        pytest.skip("this numpy's BLAS does not say which kernels it loaded (not OpenBLAS)")
    # The CLI's package pins before numpy and scipy load theirs, whatever this CPU would have chosen.
    cores, printed = _openblas_cores(PINNING)
    assert printed == PINNED_CORE
    assert cores and all(line == f"Core: {PINNED_CORE}" for line in cores), cores
    # The user's choice stands.
    cores, printed = _openblas_cores(PINNING, **{CORE_VARIABLE: "Sandybridge"})
    assert printed == "Sandybridge" and cores and all(line == "Core: Sandybridge" for line in cores), cores
