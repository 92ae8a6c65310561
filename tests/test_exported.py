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

scale = float(sys.argv[1])
def fn(x, tree):
    keep = x > 0
    return {"result": FilterResult(keep, ~keep, keep, keep, keep, keep, keep, x.astype(jnp.int32)),
            "sum": (x * x * scale).sum() + tree["b"].sum()}
out = exported.call("toy", fn, (jnp.arange(-2.0, 3.0), {"b": np.ones(2, np.float32)}), static=(scale,))
assert isinstance(out["result"], FilterResult)
print(json.dumps({"keep": np.asarray(out["result"].keep).tolist(), "sum": float(out["sum"]), "traced": exported.traced_programs(),
                  **exported.stats}))
"""


def _run(env: dict, scale: float = 2.0) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, str(scale)], env=env, capture_output=True, text=True)
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
    assert (again["exported"], again["loaded"]) == (1, 0) and again["sum"] == first["sum"]


def test_off_exports_nothing(tmp_path):
    env = {**os.environ, "SGJAX_CACHE": str(tmp_path), "SGJAX_COMPILE_CACHE": "0"}
    out = _run(env)
    assert (out["exported"], out["loaded"], out["jitted"], out["traced"]) == (0, 0, 1, 1) and out["sum"] == 2.0 * 10 + 2
    assert not (tmp_path / "exported").exists()
