"""The report path: Table I on data no decision saw (`sgjax table-i`).

Every method of the paper's Table I (and the ablations `supergrasp-pointnetgpd` and `supergrasp-stage1`), three
settings, N scenes each, on the first reserved seed of `envs.sealed`: seen-10 and seen-20 on the seen
objects, and the unseen setting on the sealed objects ("unseen-sealed-10"). This module is the only
caller of `run_benchmark(..., for_report=True)`; development runs use `sgjax declutter` on other seeds
(seed 0 is the development seed of the docs).

Rows run one method after another in `METHODS` order (the methods the README compares first) so that
an interrupted report has whole rows; each run resumes from its logs. A method that cannot run here
(contact-graspnet without its environment) is skipped and named.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

from envs import sealed
from eval.benchmark import BenchmarkResult, run_benchmark
from eval.methods import MethodUnavailable, check_method

METHODS = (
    "supergrasp",
    "s1+pointnetgpd",
    "gpd+s2",
    "supergrasp-pointnetgpd",
    "supergrasp-stage1",
    "supergrasp-norefine",
    "pointnetgpd",
    "supergrasp@paper",
    "gpd",
    "contact-graspnet",
)
# (setting, object set replacing the setting's own: the unseen setting reports on the sealed objects)
SETTINGS = (("seen-10", None), ("seen-20", None), ("unseen-10", sealed.SEALED_OBJECT_SET))
SEED = sealed.RESERVED_SEEDS[0]


def run_table_i(
    out: str | os.PathLike,
    scenes: int = 30,
    methods: Sequence[str] = METHODS,
    progress: bool = True,
    say: Callable[[str], None] = print,
) -> tuple[list[BenchmarkResult], list[str]]:
    """Run (or continue) the report into `out` -> (results, methods skipped with the reason).
    An unknown method raises `eval.methods.UnknownMethod` before any run."""
    results, skipped, runnable = [], [], []
    for method in methods:  # every name checked first: a typo fails now, not after hours of runs
        try:
            check_method(method)
            runnable.append(method)
        except MethodUnavailable as exc:
            skipped.append(f"{method}: {exc}")
            say(f"skipped {method}: {exc}")
    for method in runnable:
        for setting, objects in SETTINGS:
            result = run_benchmark(method, setting=setting, scenes=scenes, seed=SEED, out=out, objects=objects,
                                   progress=progress, for_report=True)
            s = result.summary
            say(f"{result.method} {result.setting} (seed {SEED}, N = {s.scenes}): GSR {s.gsr:.2%} TSR {s.tsr:.2%} GA {s.ga}")
            results.append(result)
    return results, skipped
