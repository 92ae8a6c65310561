"""A resumable decluttering benchmark run: N scenes of one setting with one method, logged to OUT.

`run_benchmark` loads the setting's objects (or a user folder), builds the method, runs the scenes that
have no log yet (`eval.declutter.run_scene`), writes each scene's log and picture as it finishes, and
recomputes OUT's tables (`eval.report`). Rerunning the same command continues an interrupted run; a log
left by a different configuration (other objects, camera, trial settings, method options) is an error,
so one OUT never mixes incomparable scenes under one label.

The method plans for the simulated gripper (`DeclutterConfig.gripper`, recorded whole in every scene log
as "gripper"): a registered method is built for it (`eval.methods.takes_gripper`), and a method instance or
a `gripper` method option planning for another gripper is refused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path

from envs import sealed
from eval import declutter, metrics, report
from eval.declutter import DeclutterConfig
from eval.methods import check_method, make_method, method_gripper, takes_gripper
from eval.protocol import Method
from sgjax.geometry.gripper_files import gripper_to_dict


@dataclasses.dataclass
class BenchmarkResult:
    """What a run produced: metrics over all its scenes (also those of earlier, resumed runs)."""

    method: str
    setting: str
    seed: int
    summary: metrics.Summary
    timing: dict
    logs: list[dict]
    ran: int  # scenes simulated now
    resumed: int  # scenes whose logs were already there
    warmup_s: float
    tables: dict[str, Path]
    out: Path

    def as_dict(self) -> dict:
        """{"GSR", "TSR", "GA", "scenes", ..., "method", "setting", "seed", "timing", "ran", "resumed", "out"}."""
        return {
            **self.summary.as_dict(),
            "method": self.method,
            "setting": self.setting,
            "seed": self.seed,
            "timing": {k: {"mean": m, "std": s, "n": n} for k, (m, s, n) in self.timing.items()},
            "ran": self.ran,
            "resumed": self.resumed,
            "warmup_s": self.warmup_s,
            "out": str(self.out),
        }


def resolve_objects(setting: declutter.Setting, objects: str | None = None, progress: bool = False):
    """(assets, set label, identity) for a setting: its object split, or the set / folder `objects`.

    A named set that lost a member raises `envs.objects.ObjectSetError`; a folder may skip bad meshes,
    and identity (`envs.objects.object_set_identity`) lists them so the results say so.
    """
    from envs.objects import OBJECT_SETS, load_object_set_report, object_set_identity

    name = setting.object_set if objects is None else objects
    # One process per core: preparing meshes (CoACD) is most of a first run's cache fill.
    report = load_object_set_report(name, progress=progress, workers=os.cpu_count() or 1)
    if not report.assets:
        raise ValueError(f"object set {name!r} has no usable object (see `sgjax objects prepare`)")
    label = name if name in OBJECT_SETS else Path(os.path.expanduser(name)).resolve().name or "user"
    identity = object_set_identity(label, report.assets, [f.name for f in report.failures])
    return report.assets, label, identity


def scene_indices(text: str) -> list[int]:
    """Scene indices written as on the benchmark scripts' command lines: "0-5", "3" or "0,4,7-9" ->
    [0, 1, 2, 3, 4, 5] ...; ValueError naming the text when it is not of that form."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.strip().partition("-")
        if not lo.isdigit() or not (hi == "" or hi.isdigit()):
            raise ValueError(f"scene indices must look like 0-5 or 0,3,7, got {text!r}")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


def machine_label() -> str:
    """A short description of this machine for the timing table (CPU, cores, JAX backend)."""
    import jax

    cpu = platform.processor() or platform.machine()
    return f"{cpu}, {os.cpu_count()} cores, JAX {jax.default_backend()}"


def _describe(value) -> str:
    """A stable text for an option value (objects without a stable repr by their type)."""
    if isinstance(value, (str, int, float, bool, os.PathLike)) or dataclasses.is_dataclass(value):
        return repr(value)
    return type(value).__name__


def run_key(method: str, options: dict, n_objects: int, assets: Sequence, config: DeclutterConfig,
            method_config: object = None) -> dict:
    """What must match for a resumed scene log to belong to this run. method_config: the method's own
    settings (its `config`, defaults included), so that changed defaults do not resume older logs."""
    from envs.objects import object_set_identity

    objects = object_set_identity("", assets)["hash"]  # the same names hash the tables show
    # nthread changes speed, not results.
    relevant = dataclasses.replace(config, nthread=0)
    key = {
        "method": method,
        "options": {k: _describe(v) for k, v in sorted(options.items()) if v is not None and v is not False},
        "n_objects": int(n_objects),
        "objects": objects,
        "config": hashlib.sha1(repr(relevant).encode()).hexdigest()[:12],
        "method_config": hashlib.sha1(repr(method_config).encode()).hexdigest()[:12],
    }
    if config.view:  # through a sensor (outside the config's repr, so that exact runs keep their key)
        key["view"] = config.view
    return key


def _check_key(path: Path, log: dict, key: dict) -> None:
    if log.get("key") != key:
        theirs = log.get("key") or {}
        diff = sorted(k for k in set(key) | set(theirs) if key.get(k) != theirs.get(k))
        raise ValueError(
            f"{path} was written by a different configuration ({', '.join(diff)} differ): "
            "use another --out directory, or delete that run's logs to redo it"
        )


def _warm_up(method: Method, assets, n_objects: int, seed: int, index: int, config: DeclutterConfig) -> float:
    """One discarded plan call on the first scene's observation, so timings exclude JIT compilation."""

    start = time.perf_counter()
    scene = declutter.make_benchmark_scene(assets, n_objects, seed, index, config)
    _, points, labels, *_ = declutter.observe(scene, config, 0)
    if getattr(method, "uses_ground_truth", False):
        method.set_scene(scene)
    if len(points):
        method.plan(points, labels, config.camera.position, 0)
    return time.perf_counter() - start


def run_benchmark(
    method: str | Method,
    setting: str = "seen-10",
    scenes: int = 30,
    seed: int = 0,
    out: str | os.PathLike = "declutter_results",
    objects: str | None = None,
    object_assets: Sequence | None = None,
    n_objects: int | None = None,
    method_options: dict | None = None,
    config: DeclutterConfig | None = None,
    pictures: int = 3,
    progress: bool = True,
    for_report: bool = False,
) -> BenchmarkResult:
    """Run (or continue) `scenes` scenes of `setting` with `method` into `out`; see the module doc.

    method: a registered name (`eval.methods.METHODS`) or a Method instance.
    objects: an object set name or a mesh folder replacing the setting's objects; object_assets: the
        assets themselves (tests). n_objects: objects per scene instead of the setting's.
    The setting's label in logs and tables: `declutter.Setting.label` (seen-10, seen-10@realsense+clusters,
    real-similar, real-novel-mymeshes).
    pictures: draw the first this many scenes. for_report: the report path's run (`envs.sealed`); other runs
    may not use a reserved seed or the sealed objects (SealedDataError).
    Raises ValueError / UnknownMethod / MethodUnavailable.
    """
    chosen = declutter.get_setting(setting)
    config = declutter.apply_setting(chosen, config or DeclutterConfig())
    sealed.check_benchmark(seed, chosen.object_set if objects is None else objects, report=for_report)
    if scenes < 1:
        raise ValueError(f"scenes must be >= 1, got {scenes}")
    n = chosen.n_objects if n_objects is None else int(n_objects)
    if n < 1:
        raise ValueError(f"n_objects must be >= 1, got {n}")
    options = dict(method_options or {})
    # The method plans for the simulated gripper: never another one (`eval.methods.takes_gripper`).
    given = options.pop("gripper", None)
    if given is not None and given != config.gripper:
        from sgjax.stage2.checkpoint import describe_gripper

        raise ValueError(f"method_options gripper {describe_gripper(given, config.gripper)} is not the benchmark's "
                         f"simulated gripper {describe_gripper(config.gripper, given)} (DeclutterConfig.gripper): "
                         "set the gripper there")
    if isinstance(method, str):
        check_method(method, **options)  # unknown, unavailable or a wrong option: fail before any work
        instance, name = None, method
    else:
        instance, name = method, method.name
        planned = method_gripper(instance)
        if planned is not None and planned != config.gripper:
            from sgjax.stage2.checkpoint import describe_gripper

            raise ValueError(f"method {name!r} plans for gripper {describe_gripper(planned, config.gripper)} but the "
                             f"benchmark simulates gripper {describe_gripper(config.gripper, planned)} "
                             "(DeclutterConfig.gripper): build the method for that gripper")
    if object_assets is not None:
        from envs.objects import object_set_identity

        assets, label = list(object_assets), objects or "objects"
        identity = object_set_identity(label, assets)
    else:
        assets, label, identity = resolve_objects(chosen, objects, progress)
    setting_label = chosen.label(label, n, config.view, replaced=objects is not None,
                                 custom=object_assets is not None or n_objects is not None)
    # Built before the logs are read: its settings are part of the resume key. The gripper is not among
    # the key's options: the config's part of the key holds it (DeclutterConfig.gripper).
    if instance is None:
        instance = make_method(name, **options, **({"gripper": config.gripper} if takes_gripper(name) else {}))
    key = run_key(name, options, n, assets, config, getattr(instance, "config", None))
    out = Path(out)

    todo, logs = [], {}
    for index in range(scenes):
        path = report.scene_log_path(out, name, setting_label, seed, index)
        log = report.read_scene_log(path)
        if log is None:
            todo.append(index)
        else:
            _check_key(path, log, key)
            logs[index] = log
    warmup_s = 0.0
    if todo:
        warmup_s = _warm_up(instance, assets, n, seed, todo[0], config)
    from tqdm import tqdm

    bar = tqdm(todo, desc=f"{name} {setting_label}", unit="scene", disable=not progress)
    for index in bar:
        run = declutter.run_scene(instance, assets, n, seed, index, config, setting_label)
        run.log["key"] = key
        run.log["object_set"] = identity  # which objects, how many, and any skipped: shown in the tables
        run.log["gripper"] = gripper_to_dict(config.gripper)  # the simulated gripper, the method's too
        if index < pictures:  # before the log: a scene with a log is finished, picture included
            path = report.picture_path(out, name, setting_label, seed, index)
            report.draw_scene(path, run.first_observation, run.log, config.gripper, config.scene.workspace_size)
        report.write_scene_log(report.scene_log_path(out, name, setting_label, seed, index), run.log)
        logs[index] = run.log
        so_far = metrics.summarize(logs.values())
        bar.set_postfix_str(f"GSR {report.percent(so_far.gsr)} TSR {report.percent(so_far.tsr)} GA {so_far.ga}")
    bar.close()
    ordered = [logs[i] for i in range(scenes)]
    tables = report.write_tables(out, machine_label())
    return BenchmarkResult(
        method=name,
        setting=setting_label,
        seed=seed,
        summary=metrics.summarize(ordered),
        timing=metrics.timing_summary(ordered),
        logs=ordered,
        ran=len(todo),
        resumed=scenes - len(todo),
        warmup_s=warmup_s,
        tables=tables,
        out=out,
    )


def result_json(result: BenchmarkResult) -> str:
    return json.dumps(result.as_dict())
