"""`sgjax baselines setup contact-graspnet`: build Contact-GraspNet's own Python environment.

Contact-GraspNet (`cgn-pytorch` 0.4.3, a third-party PyTorch re-implementation with its own checkpoint)
pins numpy < 2, torch-geometric 2.4.0 and a torch-cluster that PyPI has only as source, which clash
with sgjax's numpy 2 stack, so it lives in a virtual environment of its own, by default
`$SGJAX_CACHE/envs/contact-graspnet`, where `eval/contact_graspnet.py` finds it without any variable.

The recipe is the one measured on a 2-core CPU machine (/work/shared/notes/contact-graspnet-on-cpu.md),
step by step, each step skipped when what it installs is already there at the pinned version, so an
interrupted setup is resumed by running the command again:

    python3.11 -m venv PREFIX
    pip install torch==2.13.0                          # the CPU wheel (--torch-index for a CPU-only index)
    pip install "numpy<2" torch-geometric==2.4.0 scipy pyyaml trimesh meshcat importlib-resources tqdm wheel
    FORCE_ONLY_CPU=1 MAX_JOBS=2 pip install --no-build-isolation --no-deps torch-cluster==1.6.3   # ~10 min
    pip install --no-deps cgn-pytorch==0.4.3           # its own exact pins conflict
    probe: import cgn_pytorch and load its checkpoint on the CPU

(torch-geometric 2.8 ignores torch-cluster and needs pyg-lib, which PyPI lacks.) A finished setup
writes `PREFIX/sgjax-cgn.json` (the versions installed and the probe's result); only an environment
with that file is found by default.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from sgjax.utils.cache import cache_dir
from sgjax.utils.files import atomic_write_text

COMMAND = "sgjax baselines setup contact-graspnet"
MARKER = "sgjax-cgn.json"
PYTHON_VERSION = (3, 11)  # the version the recipe was measured with (torch 2.13.0's local CPU wheel is cp311)

# distribution -> (pip requirement, version that must be installed for the step to count as done;
# None: any version). Pinned where the note showed it matters.
TORCH = "torch==2.13.0"
DEPS = ("numpy<2", "torch-geometric==2.4.0", "scipy", "pyyaml", "trimesh", "meshcat", "importlib-resources", "tqdm",
        "wheel")  # wheel: torch-cluster is built with --no-build-isolation, in this venv
TORCH_CLUSTER = "torch-cluster==1.6.3"
CGN = "cgn-pytorch==0.4.3"

# The probe runs in the new environment's Python: the model is built and its shipped checkpoint loaded.
PROBE = """
import contextlib, json, sys, time
start = time.perf_counter()
with contextlib.redirect_stdout(sys.stderr):  # cgn_pytorch prints while loading
    import torch, numpy, torch_geometric, torch_cluster, cgn_pytorch
    from cgn_pytorch import from_pretrained
    model, _, _ = from_pretrained(device="cpu")
print(json.dumps({"torch": torch.__version__, "numpy": numpy.__version__,
                  "torch_geometric": torch_geometric.__version__, "torch_cluster": torch_cluster.__version__,
                  "parameters": sum(p.numel() for p in model.parameters()),
                  "load_s": round(time.perf_counter() - start, 2)}))
"""


class SetupError(RuntimeError):
    """A setup step failed; the message names the step and the command to rerun."""


def default_prefix() -> Path:
    """Where the environment goes by default: `$SGJAX_CACHE/envs/contact-graspnet`."""
    return cache_dir("envs", create=False) / "contact-graspnet"


def env_python(prefix: str | os.PathLike) -> Path:
    """The environment's interpreter (a venv's bin/python; Scripts/python.exe on Windows)."""
    prefix = Path(prefix)
    return prefix / "Scripts" / "python.exe" if os.name == "nt" else prefix / "bin" / "python"


def installed_python(prefix: str | os.PathLike | None = None) -> Path | None:
    """The interpreter of a FINISHED setup at `prefix` (default: `default_prefix()`), else None.

    Finished means the setup's last step (the probe) wrote its marker; a half-built environment is not
    returned, so that the method says to rerun the setup rather than failing inside it."""
    prefix = Path(prefix) if prefix is not None else default_prefix()
    python = env_python(prefix)
    return python if (prefix / MARKER).is_file() and python.is_file() else None


def state(prefix: str | os.PathLike | None = None) -> str:
    """'ready' | 'incomplete' (a venv without the marker: an interrupted setup) | 'absent'."""
    prefix = Path(prefix) if prefix is not None else default_prefix()
    if installed_python(prefix) is not None:
        return "ready"
    return "incomplete" if env_python(prefix).exists() else "absent"


def installed_versions(python: str | os.PathLike, names: Sequence[str]) -> dict[str, str | None]:
    """{distribution: version or None} as the environment of `python` sees them."""
    code = ("import importlib.metadata as m, json, sys\n"
            "def v(n):\n"
            "    try:\n        return m.version(n)\n"
            "    except m.PackageNotFoundError:\n        return None\n"
            "print(json.dumps({n: v(n) for n in sys.argv[1:]}))")
    done = subprocess.run([str(python), "-c", code, *names], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SetupError(f"{python} cannot list its packages: {done.stderr.strip()[-500:]}")
    return json.loads(done.stdout)


def satisfied(requirement: str, version: str | None) -> bool:
    """Whether an installed `version` (None: not installed) meets `requirement` ('name', 'name==V' or
    'name<V' with a plain numeric V) -- the only forms the recipe uses."""
    if version is None:
        return False
    if "==" in requirement:
        want = requirement.split("==", 1)[1]
        return version == want or version.split("+", 1)[0] == want  # 2.13.0+cpu is torch==2.13.0
    if "<" in requirement:
        bound = _numeric(requirement.split("<", 1)[1])
        return _numeric(version.split("+", 1)[0]) < bound
    return True


def _numeric(version: str) -> tuple[int, ...]:
    """The leading release numbers of a version: '1.26.4rc1' -> (1, 26, 4)."""
    match = re.match(r"\d+(?:\.\d+)*", version.strip())
    if match is None:
        raise SetupError(f"cannot read the version {version!r}")
    return tuple(int(x) for x in match.group(0).split("."))


def requirement_name(requirement: str) -> str:
    for sep in ("==", "<", ">", "["):
        requirement = requirement.split(sep, 1)[0]
    return requirement.strip()


@dataclasses.dataclass(frozen=True)
class Step:
    """One pip install: its requirements, pip's extra arguments and environment variables."""

    name: str
    requirements: tuple[str, ...]
    pip_args: tuple[str, ...] = ()
    env: tuple[tuple[str, str], ...] = ()


def steps(torch_index: str | None = None, max_jobs: int = 2) -> list[Step]:
    """The recipe's pip steps, in order (torch first: torch-cluster is built against it)."""
    torch_args = ("--extra-index-url", torch_index) if torch_index else ()
    return [
        Step("torch (CPU)", (TORCH,), torch_args),
        Step("numpy<2, torch-geometric 2.4.0 and cgn-pytorch's runtime dependencies", DEPS),
        Step("torch-cluster 1.6.3, built from source against the installed torch (~10 min on 2 cores)",
             (TORCH_CLUSTER,), ("--no-build-isolation", "--no-deps"),
             (("FORCE_ONLY_CPU", "1"), ("MAX_JOBS", str(max_jobs)))),
        Step("cgn-pytorch 0.4.3 (its exact pins conflict, hence --no-deps)", (CGN,), ("--no-deps",)),
    ]


def _run(command: list[str], env: dict[str, str] | None, what: str, log: Callable[[str], None]) -> None:
    log("  $ " + " ".join(command))
    done = subprocess.run(command, env=env, stdout=sys.stdout, stderr=sys.stderr, check=False)
    if done.returncode != 0:
        raise SetupError(f"{what} failed (exit {done.returncode}); fix the cause shown above and rerun `{COMMAND}` "
                         "(finished steps are skipped)")


def setup(prefix: str | os.PathLike | None = None, *, python: str = "python3.11", torch_index: str | None = None,
          max_jobs: int = 2, log: Callable[[str], None] = print) -> dict:
    """Create (or finish) the environment at `prefix` (default `default_prefix()`); returns the marker's
    content: {"python", "prefix", "versions", "probe", "seconds"}. Raises SetupError naming the failed step."""
    prefix = Path(prefix).expanduser().absolute() if prefix is not None else default_prefix()
    if max_jobs < 1:
        raise ValueError(f"max_jobs must be >= 1, got {max_jobs}")
    start = time.perf_counter()
    exe = env_python(prefix)
    if exe.exists():
        log(f"[skip] venv {prefix} exists")
    else:
        version = _python_version(python)
        if version[:2] != PYTHON_VERSION:
            raise SetupError(f"{python} is Python {'.'.join(map(str, version))}; the recipe was measured with "
                             f"Python {'.'.join(map(str, PYTHON_VERSION))} (pass --python PATH to one)")
        prefix.parent.mkdir(parents=True, exist_ok=True)
        log(f"[run ] venv {prefix} ({python})")
        _run([python, "-m", "venv", str(prefix)], None, "creating the venv", log)
    marker = prefix / MARKER
    if marker.exists():  # re-verified below; a stale marker must not survive a failed step
        marker.unlink()
    all_steps = steps(torch_index, max_jobs)
    names = [requirement_name(r) for step in all_steps for r in step.requirements]
    for step in all_steps:
        have = installed_versions(exe, names)
        if all(satisfied(r, have[requirement_name(r)]) for r in step.requirements):
            log(f"[skip] {step.name}: " + ", ".join(f"{requirement_name(r)} {have[requirement_name(r)]}"
                                                    for r in step.requirements))
            continue
        log(f"[run ] {step.name}")
        env = {**os.environ, **dict(step.env)} if step.env else None
        _run([str(exe), "-m", "pip", "install", *step.pip_args, *step.requirements], env, step.name, log)
    log("[run ] probe: import cgn_pytorch and load its checkpoint")
    done = subprocess.run([str(exe), "-c", PROBE], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SetupError(f"the probe (import cgn_pytorch, load its checkpoint) failed in {exe}:\n"
                         f"{done.stderr.strip()[-2000:]}\nrerun `{COMMAND}` after fixing it")
    probe = json.loads(done.stdout.strip().splitlines()[-1])
    record = {"python": str(exe), "prefix": str(prefix), "versions": installed_versions(exe, names), "probe": probe,
              "seconds": round(time.perf_counter() - start, 1), "recipe": [list(s.requirements) for s in all_steps]}
    atomic_write_text(marker, json.dumps(record, indent=1) + "\n")
    log(f"[done] {exe}: cgn_pytorch loads its checkpoint ({probe['parameters']:,} parameters, {probe['load_s']} s)")
    return record


def _python_version(python: str) -> tuple[int, ...]:
    try:
        done = subprocess.run([python, "-c", "import sys; print(*sys.version_info[:3])"], capture_output=True,
                              text=True, check=False)
    except OSError as exc:
        raise SetupError(f"cannot run {python!r} to create the venv ({exc}); pass --python PATH to a Python "
                         f"{'.'.join(map(str, PYTHON_VERSION))}") from None
    if done.returncode != 0:
        raise SetupError(f"{python} failed: {done.stderr.strip()[-300:]}")
    return tuple(int(x) for x in done.stdout.split())
