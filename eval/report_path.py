"""The report path: the paper's tables on data no decision saw (`sgjax table-i`, `sgjax table-ii`).

Table I: every method of the paper's Table I (and the ablations `supergrasp-pointnetgpd` and
`supergrasp-stage1`), three settings, N scenes each, on the first reserved seed of `envs.sealed`:
seen-10 and seen-20 on the seen objects, and the unseen setting on the sealed objects
("unseen-sealed-10"). Table II (simulated): the paper's real-world table re-created (the ag-105-145
gripper, stereo depth, segmented masks; `eval.declutter.SETTINGS`) for the methods of its Table II, on
the same seed: real-similar on the seen objects, real-novel on the sealed ones ("real-novel-unseen-sealed").
Table I through a sensor (`sgjax table-i --camera realsense --masks clusters`): the same runs, the
methods seeing the sensor model's depth through the front end of a user's frame (`eval.declutter`), so
that the sensor's cost is measured against Table I's own rows on data no decision saw. A table whose
settings fix their hardware (Table II) takes no other camera or masks. This module is the only caller of
`run_benchmark(..., for_report=True)`; development runs use `sgjax declutter` on other seeds (seed 0 is
the development seed of the docs).

Rows run one method after another in the table's order (the methods the README compares first) so that
an interrupted report has whole rows; each run resumes from its logs. A method that cannot run here
(contact-graspnet without its environment) is skipped and named. Each invocation's code commit and
shipped checkpoints are kept in DIR/provenance.json (`record_provenance`), so a report names what made it.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from envs import sealed
from sgjax.utils.files import atomic_write_text
from sgjax.utils.provenance import code_commit

# The benchmark, the method registry and the checkpoints are imported where used: the command line reads
# this module's tables to build its parser, and every command would pay for them.

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
PROVENANCE = "provenance.json"  # in the report's directory: what each invocation ran with


@dataclasses.dataclass(frozen=True)
class ReportTable:
    """One table of the report: its methods (in the order they run) and settings ((setting, object set
    replacing the setting's own or None), in order)."""

    name: str
    methods: tuple[str, ...]
    settings: tuple[tuple[str, str | None], ...]


TABLE_I = ReportTable("Table I", METHODS, SETTINGS)
# The paper's Table II compares these four on its real robot; novel objects are the sealed ones here too.
TABLE_II = ReportTable("Table II (simulated)", ("supergrasp", "s1+pointnetgpd", "pointnetgpd", "contact-graspnet"),
                       (("real-similar", None), ("real-novel", sealed.SEALED_OBJECT_SET)))


def shipped_networks() -> dict[str, Path]:
    """Every network shipped in `sgjax/models/` (a directory holding checkpoints) by its name."""
    from sgjax.stage2 import checkpoint

    return {d.name: d for d in sorted(checkpoint.MODELS_DIR.iterdir()) if (d / checkpoint.CHECKPOINT_DIR).is_dir()}


def provenance() -> dict[str, Any]:
    """What the report runs with now: {"commit": `code_commit()`, "checkpoints": {name: {"recipe_sha256",
    "trained_at"}}} for each shipped network (None where its meta records no recipe or commit)."""
    from sgjax.stage2 import checkpoint

    nets = {}
    for name, directory in shipped_networks().items():
        meta = checkpoint.read_meta(directory)
        nets[name] = {"recipe_sha256": (meta.get("recipe") or {}).get("sha256"),
                      "trained_at": (meta.get("commit") or {}).get("sha")}
    return {"commit": code_commit(), "checkpoints": nets}


def record_provenance(out: str | os.PathLike, say: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Append this invocation's `provenance()` to `out`/provenance.json when it differs from the last
    entry's (a resumed report at the same code adds nothing) -> every entry. Says which code it runs and
    warns when the report's runs come from more than one code or checkpoint state, or from uncommitted
    code: a report is as reproducible as the commits its directory names."""
    path = Path(out) / PROVENANCE
    entries = json.loads(path.read_text()) if path.exists() else []
    now = provenance()
    if not entries or {k: entries[-1][k] for k in now} != now:
        started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        entries.append({**now, "started": started})
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(entries, indent=1) + "\n")
    sha, dirty = now["commit"]["sha"], now["commit"]["dirty"]
    say(f"code {sha}" + (" with uncommitted changes: the report cannot name the code it ran" if dirty else ""))
    states = {json.dumps({k: e[k] for k in now}, sort_keys=True) for e in entries}
    if len(states) > 1:
        say(f"note: this report's runs come from {len(states)} code or checkpoint states ({path})")
    return entries


def run_table(
    out: str | os.PathLike,
    table: ReportTable = TABLE_I,
    scenes: int = 30,
    methods: Sequence[str] | None = None,
    progress: bool = True,
    say: Callable[[str], None] = print,
    camera: str | None = None,
    masks: str | None = None,
) -> tuple[list, list[str]]:
    """Run (or continue) the report's `table` into `out` -> (results: `eval.benchmark.BenchmarkResult`s, methods
    skipped with the reason).
    methods: a subset of the table's (None: all of them). camera (`envs.sensors`), masks ("truth" |
    "clusters"): how the methods see the scenes (`eval.declutter.DeclutterConfig`'s sensor and masks; None:
    the settings' own, exact depth and true masks for Table I).
    An unknown method, or a camera or masks that a setting fixes otherwise, raises (`eval.methods.UnknownMethod`,
    ValueError) before any run."""
    from eval.benchmark import run_benchmark
    from eval.declutter import DeclutterConfig, apply_setting, get_setting
    from eval.methods import MethodUnavailable, check_method

    config = DeclutterConfig(**{k: v for k, v in (("sensor", camera), ("masks", masks)) if v is not None})
    for setting, _ in table.settings:
        apply_setting(get_setting(setting), config)  # ValueError where the setting fixes another camera or masks

    results, skipped, runnable = [], [], []
    for method in table.methods if methods is None else methods:  # all checked first: a typo fails now, not hours on
        try:
            check_method(method)
            runnable.append(method)
        except MethodUnavailable as exc:
            skipped.append(f"{method}: {exc}")
            say(f"skipped {method}: {exc}")
    if runnable:
        record_provenance(out, say)
    for method in runnable:
        for setting, objects in table.settings:
            result = run_benchmark(method, setting=setting, scenes=scenes, seed=SEED, out=out, objects=objects,
                                   config=config, progress=progress, for_report=True)
            s = result.summary
            say(f"{result.method} {result.setting} (seed {SEED}, N = {s.scenes}): GSR {s.gsr:.2%} TSR {s.tsr:.2%} GA {s.ga}")
            results.append(result)
    return results, skipped
