"""Every script of benchmarks/ starts: run as `python -m benchmarks.NAME --help` it exits 0, and its usage
names each option the script declares. Import time only: no script runs its work here."""

from __future__ import annotations

import argparse
import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
HELPERS = {"__init__", "common"}  # modules of the package, not scripts
SCRIPTS = sorted(p.stem for p in (REPO / "benchmarks").glob("*.py") if p.stem not in HELPERS)

# One fresh interpreter from the repository root runs every script as __main__ with --help (as `python -m`
# does), one after the other: their common imports (JAX, MuJoCo) load once, which keeps this test at a few
# seconds. Per script: the exit status (SystemExit's code; None if it ran to its end without exiting) and
# what it printed.
DRIVER = r"""
import contextlib, io, json, runpy, sys, traceback
names, results = sys.argv[1:], {}
for name in names:
    out, err = io.StringIO(), io.StringIO()
    sys.argv = [name, "--help"]
    code = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            runpy.run_module(f"benchmarks.{name}", run_name="__main__", alter_sys=True)
        except SystemExit as exc:
            code = exc.code
        except BaseException:
            traceback.print_exc()
            code = "raised"
    results[name] = {"code": code, "stdout": out.getvalue(), "stderr": err.getvalue()}
print(json.dumps(results))
"""


def declared_options(path: Path) -> list[str]:
    """The option strings ("--name") of the script's `add_argument` calls, those hidden from --help
    (help=argparse.SUPPRESS) left out."""
    options = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "add_argument"):
            continue
        hidden = any(k.arg == "help" and isinstance(k.value, ast.Attribute) and k.value.attr == "SUPPRESS"
                     for k in node.keywords)
        names = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
        options += [] if hidden else [n for n in names if n.startswith("--")]
    return options


def test_the_scripts_are_found():
    assert len(SCRIPTS) >= 10 and "bench_plan" in SCRIPTS and "replay_failures" in SCRIPTS
    assert argparse.SUPPRESS == "==SUPPRESS=="  # what declared_options recognises by name


@pytest.fixture(scope="module")
def helps() -> dict[str, dict]:
    done = subprocess.run([sys.executable, "-c", DRIVER, *SCRIPTS], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_help(helps, name):
    result = helps[name]
    assert result["code"] == 0, result["stderr"][-3000:]
    assert result["stdout"].startswith("usage:"), result["stdout"][:500]
    missing = [o for o in declared_options(REPO / "benchmarks" / f"{name}.py") if o not in result["stdout"]]
    assert not missing, f"{name} --help does not mention {missing}"
