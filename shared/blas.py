"""One BLAS kernel family on every x86-64 host, so a replay gives the same figures on every machine.

numpy and scipy call OpenBLAS (numpy's matrix products and small solves, scipy's SuperLU in the pose
graph's solve), and OpenBLAS picks its kernels for the CPU it finds: AVX-512 ones on one host, AVX2
ones on another. They sum in another order and round differently in the last bit, and a map is a
chain of matches, each seeded by the last: one bit became another closure accepted, and another
figure. Measured (2026-12-07): on one AVX-512 Xeon the published mit-csail log's worst revisit was
0.287 m under OpenBLAS's own choice of kernels and 0.226 m, as on the other hosts, under its AVX2
ones, every other input the same (docs/mapping.md, "The same figures on every host").

OpenBLAS reads ``OPENBLAS_CORETYPE`` once, when it is loaded, so ``pin_blas_kernels`` must run
before numpy or scipy is first imported: the CLI's package does it (every ``fleetlink`` command, the
agents the field starts among them), and so do the test suite (tests/conftest.py) and the benches
that run maps and missions (bench/mapping.py, sortie.py, coverage.py, field.py). It sets the
variable in the process's environment, so the processes it starts inherit it.

What it covers: OpenBLAS (numpy's and scipy's), on Linux x86-64 with AVX2 and FMA, the same numpy
and scipy versions. Not numpy's own vector loops (float64 ``exp``, ``log``, ``arctan2`` take AVX-512
paths where the CPU has them; they did not move mit-csail's poses), nor other systems. Stdlib only.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Container, MutableMapping
from pathlib import Path

PINNED_CORE = "Haswell"
"""OpenBLAS's AVX2 + FMA kernels: Intel's Core and Xeon CPUs since 2013 and AMD's since 2015 run them
(an AVX-512 CPU too); some Pentiums, Celerons and Atoms do not, and are left alone."""
NEEDED_FLAGS = frozenset({"avx2", "fma"})
CORE_VARIABLE = "OPENBLAS_CORETYPE"


def pin_blas_kernels(
    environ: MutableMapping[str, str] | None = None,
    cpuinfo: Path = Path("/proc/cpuinfo"),
    machine: str | None = None,
    modules: Container[str] | None = None,
) -> str | None:
    """Set ``OPENBLAS_CORETYPE`` to ``PINNED_CORE`` where the CPU runs those kernels and nothing has
    chosen yet. Returns the core type in force (None: OpenBLAS picks). Left alone: a value already
    set (the user's choice), a CPU that is not x86-64 or lacks AVX2 or FMA (forcing kernels it
    cannot run would stop the process on an illegal instruction), a host whose CPU flags cannot be
    read, and a process that has already imported numpy (its OpenBLAS is loaded: pinning scipy's
    alone would mix the two). The arguments are for tests: the process's environment, CPU and
    modules by default."""
    env = os.environ if environ is None else environ
    if env.get(CORE_VARIABLE):  # (empty is no choice: OpenBLAS says "Core not found" and picks)
        return env[CORE_VARIABLE]
    loaded = sys.modules if modules is None else modules
    if "numpy" in loaded or "scipy" in loaded:
        return None
    if (machine or platform.machine()).lower() not in ("x86_64", "amd64"):
        return None
    try:
        text = cpuinfo.read_text(errors="replace")
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith("flags"):
            flags = set(line.partition(":")[2].split())
            if flags >= NEEDED_FLAGS:
                env[CORE_VARIABLE] = PINNED_CORE
                return PINNED_CORE
            return None
    return None
