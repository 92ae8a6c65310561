"""Traced programs kept on disk (sgjax.utils.exported): a new process loads them instead of tracing.

Each case runs in fresh interpreters, as a user's new notebook kernel or shell command would.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

CHILD = r"""
import json, sys
import jax.numpy as jnp, numpy as np
from sgjax.stage1.filters import FilterResult
from sgjax.utils import exported

import threading
import jax
compiled = []  # (thread, function) of each compilation or persistent-cache load of this process
jax.monitoring.register_event_duration_secs_listener(
    lambda event, _, fun_name="", **kw: compiled.append((threading.current_thread().name, fun_name))
    if event == "/jax/core/compile/backend_compile_duration" else None)
scale = float(sys.argv[1])
if len(sys.argv) > 2:
    exported.prefetch(sys.argv[2])
if len(sys.argv) > 3:
    exported.end_group()
def fn(x, tree):
    keep = x > 0
    return {"result": FilterResult(keep, ~keep, keep, keep, keep, keep, keep, x.astype(jnp.int32)),
            "sum": (x * x * scale).sum() + tree["b"].sum()}
out = exported.call("toy", fn, (jnp.arange(-2.0, 3.0), {"b": np.ones(2, np.float32)}), static=(scale,))
assert isinstance(out["result"], FilterResult)
print(json.dumps({"keep": np.asarray(out["result"].keep).tolist(), "sum": float(out["sum"]), "traced": exported.traced_programs(),
                  "calls_compiled": [t for t, f in compiled if f == "jit(call)"], **exported.stats}))
"""


def _run(env: dict, scale: float = 2.0, group: str | None = None, end: bool = False) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, str(scale), *([group] if group else []), *(["end"] if end else [])],
                          env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_second_process_loads_the_exported_program(tmp_path):
    env = {**os.environ, "SGJAX_CACHE": str(tmp_path)}
    env.pop("SGJAX_COMPILE_CACHE", None)
    first = _run(env)
    assert first["keep"] == [False, False, False, True, True] and first["sum"] == 2.0 * 10 + 2
    assert (first["exported"], first["loaded"], first["traced"]) == (1, 0, 1)
    files = sorted(p.name for p in (tmp_path / "exported").iterdir())
    assert len(files) == 1 and files[0].startswith("toy-") and files[0].endswith(".jaxexport")
    second = _run(env)
    # A load is not a trace (`traced_programs`: what the planner's never-recompiles test counts).
    assert (second["exported"], second["loaded"], second["traced"]) == (0, 1, 0) and second["keep"] == first["keep"] and second["sum"] == first["sum"]
    # Another static setting is another program; a damaged file is exported again, not trusted.
    other = _run(env, scale=3.0)
    assert other["exported"] == 1 and other["sum"] == 3.0 * 10 + 2
    assert len(list((tmp_path / "exported").iterdir())) == 2
    (tmp_path / "exported" / files[0]).write_bytes(b"not a program")
    again = _run(env)
    assert (again["exported"], again["loaded"], again["unreadable"]) == (1, 0, 1) and again["sum"] == first["sum"]


def test_off_exports_nothing(tmp_path):
    env = {**os.environ, "SGJAX_CACHE": str(tmp_path), "SGJAX_COMPILE_CACHE": "0"}
    out = _run(env)
    assert (out["exported"], out["loaded"], out["jitted"], out["traced"]) == (0, 0, 1, 1) and out["sum"] == 2.0 * 10 + 2
    assert not (tmp_path / "exported").exists()


def test_prefetch_loads_the_last_run_s_programs_on_another_thread(tmp_path):
    env = {**os.environ, "SGJAX_CACHE": str(tmp_path)}
    env.pop("SGJAX_COMPILE_CACHE", None)
    first = _run(env, group="toy command")
    # Nothing to prefetch yet: the program is exported and compiled on the calling thread, and listed.
    assert first["exported"] == 1 and first["calls_compiled"] == ["MainThread"]
    lists = list((tmp_path / "exported").glob("*.keys"))
    assert len(lists) == 1 and len(json.loads(lists[0].read_text())["keys"]) == 1
    second = _run(env, group="toy command")
    # The next run of the group loads it on the prefetch thread; the call then compiles nothing.
    assert second["loaded"] == 1 and second["exported"] == 0 and second["traced"] == 0
    assert len(second["calls_compiled"]) == 1 and second["calls_compiled"][0].startswith("sgjax-prefetch")
    assert (second["keep"], second["sum"]) == (first["keep"], first["sum"])
    listed = json.loads(lists[0].read_text())["keys"]
    # Calls after the group ended (`end_group`: `sgjax_cli.main` ends each command's) are not listed.
    later = _run(env, scale=4.0, group="toy command", end=True)
    assert later["exported"] == 1 and json.loads(lists[0].read_text())["keys"] == listed
    # A run that calls another program (another setting) lists that one instead.
    other = _run(env, scale=3.0, group="toy command")
    assert other["exported"] == 1 and other["sum"] == 3.0 * 10 + 2
    now = json.loads(lists[0].read_text())["keys"]
    assert len(now) == 1 and now != listed and now[0].startswith("toy-")
    # A listed program whose file is damaged: the prefetch fails on it once, the call exports it again
    # without reading the file a second time.
    (tmp_path / "exported" / (now[0] + ".jaxexport")).write_bytes(b"not a program")
    damaged = _run(env, scale=3.0, group="toy command")
    assert (damaged["unreadable"], damaged["loaded"], damaged["exported"]) == (1, 0, 1) and damaged["sum"] == other["sum"]
