"""What a benchmark's floating-point results depend on beyond the code and the seeds.

XLA compiles the planner's JAX programs for the CPU it runs on, using the widest vector instructions
the CPU has (or `XLA_FLAGS=--xla_cpu_max_isa=...` allows). Different instructions round differently in
the last bits; where a plan is near a tie (two candidates scored alike, a point on a filter's
threshold) the choice changes, and a scene's later attempts differ from there on. Measured on unseen-10,
N = 30 (docs/benchmark.md, "Same seeds, another CPU"): the same code and seeds compiled for AVX2 instead
of AVX-512 gave GSR 92.91 % instead of 90.67 %, 28 of the 30 scenes taking another grasp at some point.
XLA's own code-generation flags in `XLA_FLAGS` (e.g. `--xla_cpu_use_fusion_emitters=false`, which
halves compile time) change the compiled programs as well: the same scenes then take other grasps after
a few attempts (docs/experiments.md, 2026-12-06). Outcomes repeat attempt for attempt only between runs
whose `numerics_label` is equal; the benchmark records it in every scene log and lists it in results.md.
"""

from __future__ import annotations

import functools
import os
import platform
import re
from importlib import metadata

# The x86 ISA levels XLA's CPU backend targets (its --xla_cpu_max_isa names), widest first, with the
# /proc/cpuinfo flag that means the CPU has it.
_X86_LEVELS = (("AVX512", "avx512f"), ("AVX2", "avx2"), ("AVX", "avx"), ("SSE4_2", "sse4_2"))


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "absent"


def vector_isa(cpu_flags: set[str] | None = None, xla_flags: str | None = None) -> str:
    """The widest vector ISA XLA compiles for here: the CPU's widest x86 level (`cpu_flags`, default read
    from /proc/cpuinfo), capped by --xla_cpu_max_isa in `xla_flags` (default $XLA_FLAGS); on CPUs
    that are not x86 or without /proc/cpuinfo, the machine name."""
    if cpu_flags is None:
        cpu_flags = _cpu_flags()
    if xla_flags is None:
        xla_flags = os.environ.get("XLA_FLAGS", "")
    levels = [name for name, flag in _X86_LEVELS]
    have = next((name for name, flag in _X86_LEVELS if flag in cpu_flags), None)
    if have is None:
        return platform.machine() or "unknown"
    cap = re.search(r"--xla_cpu_max_isa=(\w+)", xla_flags)
    if cap and cap.group(1).upper() in levels and levels.index(cap.group(1).upper()) > levels.index(have):
        return cap.group(1).upper()
    return have


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def code_flags(xla_flags: str | None = None) -> str:
    """The XLA flags in `xla_flags` (default $XLA_FLAGS) that may change the compiled code, sorted, one
    space apart: every --xla_* flag but the ISA cap, which `vector_isa` reports, and the host device count,
    which splits the host rather than changing a program; "" for none."""
    if xla_flags is None:
        xla_flags = os.environ.get("XLA_FLAGS", "")
    skipped = ("--xla_cpu_max_isa=", "--xla_force_host_platform_device_count=")
    return " ".join(sorted(f for f in xla_flags.split() if f.startswith("--xla_") and not f.startswith(skipped)))


@functools.lru_cache(maxsize=1)
def numerics_label() -> str:
    """One line naming what the results' rounding depends on: vector ISA, jaxlib and MuJoCo versions, and
    XLA's code-generation flags when any are set (`code_flags`)."""
    flags = code_flags()
    return f"{vector_isa()}, jaxlib {_version('jaxlib')}, mujoco {_version('mujoco')}" + (f", XLA_FLAGS {flags}" if flags else "")
