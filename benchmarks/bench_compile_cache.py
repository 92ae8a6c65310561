"""A new process's first plan, with JAX's persistent compilation cache cold, warm, and off (run by hand).

    python -m benchmarks.bench_compile_cache [--repeats 1]

Each measurement is a fresh Python process that builds the default planner (shipped database and
E-RNet) and plans one synthetic single-view cloud (`sgjax example`'s superquadric) twice: the first
call pays tracing and compilation (or loads both from the cache: `exported/` and `jax/`), the second is
the steady time. Rows: the caches off (`SGJAX_COMPILE_CACHE=0`), cold (an empty `$SGJAX_CACHE`, which
the run fills) and warm (the same directory again). Prints a markdown table; compare rows of one run, since these machines are shared.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

CHILD = r"""
import json, os, tempfile, time
t0 = time.perf_counter()
import numpy as np
import sgjax
from sgjax_cli import main
path = os.path.join(tempfile.mkdtemp(), "object.npy")
main(["example", path])
cloud = np.load(path)
planner = sgjax.Planner()
t1 = time.perf_counter()
plan = planner.plan_target(cloud, cloud, viewpoint=np.zeros(3))
t2 = time.perf_counter()
planner.plan_target(cloud, cloud, viewpoint=np.zeros(3), seed=1)
t3 = time.perf_counter()
print(json.dumps({"setup": t1 - t0, "first": t2 - t1, "second": t3 - t2, "kind": plan.kind}))
"""


def run(env: dict) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    rows = []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as cache:
            base = {k: v for k, v in os.environ.items() if k not in ("SGJAX_COMPILE_CACHE", "SGJAX_JAX_CACHE_DIR")}
            # A private, empty data cache: its jax/ (compiled) and exported/ (traced programs) start empty;
            # the planner needs nothing else from it (the database and E-RNet ship in the package).
            env = {**base, "SGJAX_CACHE": cache}
            rows.append(("off", run({**env, "SGJAX_COMPILE_CACHE": "0"})))
            rows.append(("cold", run(env)))
            rows.append(("warm", run(env)))
    print("| compilation cache | import + planner (s) | first plan (s) | second plan (s) |")
    print("|---|---:|---:|---:|")
    for name, r in rows:
        print(f"| {name} | {r['setup']:.2f} | {r['first']:.2f} | {r['second']:.2f} |")


if __name__ == "__main__":
    main()
