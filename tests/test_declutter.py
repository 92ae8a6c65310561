"""Decluttering benchmark: metrics on hand-made logs, the episode rules on real MuJoCo scenes of the tiny
set (oracle, GPD baseline and, when installed, the SuperGrasp planner), seeds, resume, bad input."""

from __future__ import annotations

import dataclasses
import importlib.util
import json

import numpy as np
import pytest

from envs.camera import CameraConfig
from envs.objects import tiny_object_set
from eval import declutter, metrics, report
from eval.numerics import code_flags, numerics_label, vector_isa
from eval.benchmark import run_benchmark, run_key
from eval.declutter import DeclutterConfig, run_scene
from eval.methods import METHODS, MethodUnavailable, UnknownMethod, make_method
from eval.protocol import Decision, near_grasps
from sgjax.geometry.gripper import GripperSpec
from sgjax_cli import main

# Small camera images keep each observation at ~60 ms; 3-4 objects keep a scene at a few seconds.
CONFIG = DeclutterConfig(camera=CameraConfig(width=320, height=240), nthread=1)
N_OBJECTS = 4


@pytest.fixture(scope="module")
def objects():
    return tiny_object_set()


@pytest.fixture(scope="module")
def oracle_run(objects):
    return run_scene(make_method("oracle-topdown"), objects, N_OBJECTS, seed=0, index=0, config=CONFIG, setting="tiny-4")


@pytest.fixture(scope="module")
def gpd_run(objects):
    return run_scene(make_method("gpd"), objects, N_OBJECTS, seed=0, index=0, config=CONFIG, setting="tiny-4")


def timing(total: float = 0.1) -> dict:
    return {"stage1_s": total / 2, "stage2_s": total / 2, "total_s": total}


class Never:
    """Returns no grasp."""

    name = "never"

    def __init__(self):
        self.calls = 0

    def plan(self, points, labels, viewpoint, seed=0):
        self.calls += 1
        return Decision(None, 0.0, 0.0, "nothing to do", timing())


class InTheAir:
    """A top-down grasp far from every object: nothing between the fingers, every time."""

    name = "in-the-air"

    def plan(self, points, labels, viewpoint, seed=0):
        pose = np.eye(4)
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
        pose[:3, 3] = [0.2, 0.2, 0.3]
        return Decision(pose, 0.2, 0.5, "", timing())  # width above max_opening: clipped by the harness


class InTheAirRemembering(InTheAir):
    """InTheAir with the harness's memory: it does not try its one grasp again once it failed."""

    name = "in-the-air-remembering"

    def __init__(self):
        self.avoid_seen = []

    def plan(self, points, labels, viewpoint, seed=0, avoid=None):
        self.avoid_seen.append(np.array(avoid))
        decision = super().plan(points, labels, viewpoint, seed)
        if near_grasps(decision.pose[None], avoid, GripperSpec())[0]:
            return Decision(None, 0.0, 0.0, "my only grasp failed", timing())
        return decision


# ---------------------------------------------------------------------------------------------
# Metrics on hand-made logs.


def log(objects: int, outcomes: str, **extra) -> dict:
    """A scene log: 's' = successful attempt, 'f' = failed attempt."""
    attempts = [{"success": c == "s", "timing": timing(0.2 if c == "s" else 0.4)} for c in outcomes]
    return {"objects": objects, "attempts": attempts, **extra}


def test_scene_indices_of_the_benchmark_scripts():
    from eval.benchmark import scene_indices

    assert scene_indices("0-3") == [0, 1, 2, 3] and scene_indices("7") == [7]
    assert scene_indices("0,4,7-9") == [0, 4, 7, 8, 9]
    with pytest.raises(ValueError, match="scene indices"):
        scene_indices("0:5")


def test_metrics_are_ratios_of_totals_as_in_the_paper():
    logs = [log(10, "s" * 9 + "f"), log(10, "sfsfs"), log(5, "")]
    summary = metrics.summarize(logs)
    assert (summary.scenes, summary.objects, summary.successes, summary.attempts) == (3, 25, 12, 15)
    assert summary.gsr == pytest.approx(12 / 15) and summary.tsr == pytest.approx(12 / 25)
    assert summary.ga == 15 and summary.cleared == 0
    assert summary.as_dict() == {"GSR": 0.8, "TSR": 0.48, "GA": 15, "scenes": 3, "objects": 25, "successes": 12,
                                 "attempts": 15, "cleared": 0}
    assert metrics.summarize([log(2, "fss")]).cleared == 1
    # Zero denominators: no attempts -> GSR undefined; no objects -> TSR undefined.
    empty = metrics.summarize([log(3, ""), log(0, "")])
    assert empty.gsr is None and empty.tsr == 0.0 and empty.ga == 0
    assert metrics.summarize([]).tsr is None and metrics.summarize([]).gsr is None
    with pytest.raises(ValueError, match="3 successful grasps"):
        metrics.summarize([log(2, "sss")])


def test_scene_intervals_resample_whole_scenes():
    # Scenes alike: every draw gives the same rates, the interval is the point.
    same = metrics.scene_intervals([log(4, "ssf")] * 6)
    assert same["GSR"] == pytest.approx((2 / 3, 2 / 3)) and same["TSR"] == pytest.approx((0.5, 0.5))
    # Scenes that differ: the interval holds the estimate, stays within [0, 1], and repeats for a seed.
    logs = [log(5, "sssss"), log(5, "sfsfs"), log(5, "ffsss"), log(5, "s"), log(5, "ssssf")] * 3
    out = metrics.scene_intervals(logs)
    summary = metrics.summarize(logs)
    assert 0 <= out["GSR"][0] < summary.gsr < out["GSR"][1] <= 1 and out["TSR"][0] < summary.tsr < out["TSR"][1]
    assert metrics.scene_intervals(logs) == out and metrics.scene_intervals(logs, seed=1) != out
    # More scenes of the same kind: narrower.
    wide, narrow = metrics.scene_intervals(logs[:5])["TSR"], metrics.scene_intervals(logs * 4)["TSR"]
    assert narrow[1] - narrow[0] < wide[1] - wide[0]
    # Undefined rates: no scenes, or no attempts in any draw.
    assert metrics.scene_intervals([]) == {"GSR": None, "TSR": None}
    assert metrics.scene_intervals([log(3, "")])["GSR"] is None


def test_timing_summary_is_per_executed_grasp():
    times = metrics.timing_summary([log(3, "ssf"), log(1, "")])
    mean, std, n = times["total_s"]
    assert n == 3 and mean == pytest.approx(0.8 / 3) and std == pytest.approx(np.std([0.2, 0.2, 0.4]))
    assert times["stage1_s"][0] == pytest.approx(0.4 / 3)
    assert np.isnan(metrics.timing_summary([log(1, "")])["total_s"][0])
    # A plan call that compiled a program is compilation time, not planning time: left out.
    slow = log(2, "ss")
    slow["attempts"][1].update(timing=timing(30.0), info={"compiled": True})
    mean, _, n = metrics.timing_summary([slow])["total_s"]
    assert n == 1 and mean == pytest.approx(0.2)


def test_harness_costs_are_means_per_attempt_and_scene():
    a, b = log(3, "sf", wall_s=10.0, method="gpd"), log(2, "f", wall_s=4.0, method="gpd")
    for attempt, (observe, trial, settle) in zip(a["attempts"] + b["attempts"], [(0.1, 0.3, 0.5), (0.2, 0.5, 0.7), (0.3, 0.0, None)]):
        attempt.update(observe_s=observe, trial_s=trial, target=None if settle is None else 0)
        if settle is not None:
            attempt["settle_s"] = settle
    h = metrics.harness_summary([a, b])
    assert h["observe_s"] == pytest.approx((0.2, 3)) and h["trial_s"] == pytest.approx((0.4, 2))  # simulated only
    assert h["settle_s"] == pytest.approx((0.6, 2)) and h["scene_s"] == pytest.approx((7.0, 2))
    assert h["plan_s"] == pytest.approx(((0.2 + 0.4 + 0.4) / 3, 3))
    assert np.isnan(metrics.harness_summary([log(1, "")])["trial_s"][0])
    assert "| gpd | 0.200 | 0.333 | 0.400 | 0.600 | 7.0 | 3 |" in report.harness_markdown([a, b])


def test_failures_are_counted_by_phase_and_by_why_scenes_ended():
    cap = log(3, "ff", method="gpd", setting="seen-10", seed=0, end="attempt_cap", remaining=3)
    stage1 = log(3, "sf", method="gpd", setting="seen-10", seed=0, end="no_grasp", remaining=2,
                 final_reason="no candidates: object 2: all 810 transferred candidates were removed")
    stage2 = log(4, "s", method="gpd", setting="seen-10", seed=0, end="no_grasp", remaining=3,
                 final_reason="best eval 0.52 <= 0.7 and best refine 0.24 <= 0.7")
    other = log(4, "s", method="gpd", setting="seen-10", seed=0, end="no_grasp", remaining=3,
                final_reason="best eval 0.1 <= 0.7 and best refine 0.43 <= 0.7")
    clear = log(1, "s", method="gpd", setting="seen-10", seed=0, end="cleared", remaining=0)
    for one, outcome in zip(cap["attempts"] + stage1["attempts"][1:], ["collision_approach", "dropped_lift", "dropped_lift"]):
        one["outcome"] = outcome
    b = metrics.failure_breakdown([cap, stage1, stage2, other, clear])
    assert b["failed"] == {"dropped_lift": 2, "collision_approach": 1}
    assert b["unfinished"] == {"attempt cap": 1, "no grasp: no candidates": 1,
                               "no grasp: best eval N <= N and best refine N <= N": 2}
    assert b["left"]["no grasp: best eval N <= N and best refine N <= N"] == 6 and b["left"]["attempt cap"] == 3
    assert metrics.why_unfinished(clear) is None
    table = report.failures_markdown([cap, stage1, stage2, other, clear])
    assert ("| gpd | seen-10 | 5 | dropped_lift 2, collision_approach 1 | no grasp: best eval N <= N and best refine "
            "N <= N (2, 6); attempt cap (1, 3); no grasp: no candidates (1, 2) |") in table


def test_objects_not_grasped_and_failed_on_are_counted_by_name():
    a = log(3, "fsfs", method="gpd", setting="seen-10", seed=0, object_names=["box", "lens", "lens"])
    b = log(2, "sf", method="gpd", setting="seen-10", seed=1, object_names=["box", "lens"])
    for attempt, (name, outcome) in zip(a["attempts"] + b["attempts"],
                                        [("lens", "dropped_lift"), ("box", "success"), (None, "no_object"),
                                         ("lens", "success"), ("box", "success"), ("lens", "collision_approach")]):
        attempt.update(target_name=name, outcome=outcome)
    counts = metrics.object_breakdown([a, b])
    assert (counts["box"].scenes, counts["box"].grasped, counts["box"].not_grasped, counts["box"].attempts) == (2, 2, 0, 2)
    lens = counts["lens"]
    assert (lens.scenes, lens.grasped, lens.not_grasped, lens.attempts) == (3, 1, 2, 3)
    assert lens.failed == {"dropped_lift": 1, "collision_approach": 1}
    table = report.object_outcomes_markdown([a, b, {**b, "method": "oracle-topdown", "attempts": b["attempts"][:1]}])
    assert "| object | gpd | oracle-topdown |" in table  # methods in the report's order
    assert "| lens | 2 / 3, 2 | 1 / 1, 0 |" in table and "box" not in table  # never missed nor failed on


def test_attempts_are_broken_down_by_how_chosen_score_and_tilt(tmp_path):
    infos = [{"kind": "evaluated", "robust_rank": 0}, {"kind": "refined", "fallback": True, "fit_grasp": True}, {}]
    assert [metrics.how_chosen({"info": i}) for i in infos] == [
        "first plan, evaluated, transferred, robust choice", "second plan, refined, on the fit, alone", "-"]
    edges = metrics.SCORE_EDGES
    assert [metrics.bin_label(v, edges) for v in (0.7, 0.75, 0.8, 0.81, 0.5, None, float("nan"), 1.2)] == [
        "0.7-0.8", "0.7-0.8", "0.7-0.8", "0.8-0.85", "< 0.7", "none", "none", "> 1"]
    down = np.diag([1.0, -1.0, -1.0, 1.0])  # approach (z column) straight down
    tilted = np.eye(4)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    tilted[:3, :3] = down[:3, :3] @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])  # 30 deg about the closing axis
    side = np.eye(4)[[0, 2, 1, 3]]  # approach along world y
    assert [round(metrics.approach_tilt(p), 6) for p in (down, tilted, side, np.eye(4))] == [0.0, 30.0, 90.0, 180.0]
    a, b = log(3, "sfs"), log(2, "ff")
    for attempt, score, outcome in zip(a["attempts"] + b["attempts"], [0.9, 0.75, 0.95, 0.72, 0.99],
                                       ["success", "dropped_lift", "success", "collision_approach", "dropped_lift"]):
        attempt.update(score=score, outcome=outcome)
    by = metrics.outcomes_by([a, b], lambda t: metrics.bin_label(t["score"], edges))
    assert by == {"0.85-0.9": {"success": 1}, "0.7-0.8": {"dropped_lift": 1, "collision_approach": 1},
                  "0.93-0.95": {"success": 1}, "0.97-1": {"dropped_lift": 1}}
    # The stop rule: each scene ends at its first grasp scored <= the bar, the attempts before it unchanged.
    assert metrics.stopped_at([a, b], 0.7) == metrics.summarize([a, b])
    stopped = metrics.stopped_at([a, b], 0.8)  # a keeps its first attempt, b none
    assert (stopped.attempts, stopped.successes, stopped.objects, stopped.gsr) == (1, 1, 5, 1.0)
    assert metrics.stopped_at([a, b], 0.99).attempts == 0 and metrics.stopped_at([a, b], 0.99).gsr is None
    # Logs found at any depth; other JSON beside them (e.g. scene_007.states.json) is not a scene log.
    report.write_scene_log(tmp_path / "x" / "seed3" / "scene_007.json", a)
    (tmp_path / "x" / "seed3" / "scene_007.states.json").write_text("[]")
    assert report.logs_under(tmp_path) == [a] and report.logs_under(tmp_path / "none") == []


def test_tables_follow_table_i_and_table_iii():
    logs = [
        log(10, "ssff", method="gpd", setting="seen-10", seed=0),
        log(10, "s", method="supergrasp", setting="seen-10", seed=0),
        log(20, "ss", method="supergrasp", setting="seen-20", seed=0),
    ]
    rows = report.result_rows(logs)
    assert [(r["method"], r["setting"]) for r in rows] == [("supergrasp", "seen-10"), ("supergrasp", "seen-20"), ("gpd", "seen-10")]
    table = report.table_i_markdown(rows)
    assert "| Method | seen-10 GSR | seen-10 TSR | seen-10 GA | seen-10 N | seen-20 GSR" in table
    assert "| gpd | 50.00% | 20.00% | 4 | 1 |  |  |  |  |" in table
    assert "| supergrasp | 100.00% | 10.00% | 1 | 1 | 100.00% | 10.00% | 2 | 1 |" in table
    timing_table = report.table_iii_markdown(report.timing_rows(logs))
    assert "| gpd | 0.150 ± 0.050 | 0.150 ± 0.050 | 0.300 ± 0.100 | 4 |" in timing_table


# ---------------------------------------------------------------------------------------------
# Episodes on real scenes.


def test_oracle_clears_the_tiny_scene_and_the_log_follows_the_rules(oracle_run):
    log_ = oracle_run.log
    attempts = log_["attempts"]
    assert log_["objects"] == N_OBJECTS and len(log_["object_names"]) == N_OBJECTS
    assert len(attempts) <= log_["objects"] + 5
    successes = [a for a in attempts if a["success"]]
    assert len(successes) >= N_OBJECTS - 1  # the oracle clears (nearly) every object
    targets = [a["target"] for a in successes]
    assert len(set(targets)) == len(targets)  # a grasped object is gone from the scene
    assert log_["remaining"] == log_["objects"] - len(successes) - len(log_["fell_out"])
    if log_["end"] == "cleared":
        assert log_["remaining"] == 0
    for a in attempts:
        assert a["outcome"] in {"success", "collision_pregrasp", "collision_approach", "dropped_lift",
                                "dropped_reorient", "dropped_disturbance", "invalid"}
        assert set(a["timing"]) >= set(metrics.TIMING_KEYS)
        assert np.asarray(a["pose"]).shape == (4, 4) and 0 < a["width"] <= 0.08
        assert a["points_in_gripper"][str(a["target"])] == max(a["points_in_gripper"].values())
        assert a["settle_s"] > 0 and a["trial_s"] > 0 and a["observe_s"] > 0
    json.dumps(log_)  # JSON-able


def test_gpd_baseline_runs_a_tiny_scene(gpd_run):
    log_ = gpd_run.log
    assert log_["method"] == "gpd" and log_["objects"] == N_OBJECTS
    assert 1 <= len(log_["attempts"]) <= N_OBJECTS + 5
    assert sum(a["success"] for a in log_["attempts"]) >= 1
    for a in log_["attempts"]:
        pose = np.asarray(a["pose"])
        np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
        assert pose[2, 2] < -0.4  # approach within 60 deg of straight down (z of the approach axis)
        assert a["timing"]["total_s"] == pytest.approx(a["timing"]["stage1_s"] + a["timing"]["stage2_s"])
    assert log_["end"] in ("cleared", "attempt_cap", "no_grasp")


def test_a_scene_log_replays_attempt_by_attempt(objects, gpd_run):
    """eval.replay re-executes the logged grasps without the method: the same outcomes, the same contacts
    as the harness logged for failed trials, and each grasp also with the Panda hand; a log that does not
    match the simulation stops the replay where it diverges."""
    from eval.replay import collision_cause, replay_scene
    from sgjax.geometry.gripper import PANDA_HAND

    log_ = gpd_run.log
    simulated = [a for a in log_["attempts"] if a["target"] is not None]
    assert any(not a["success"] for a in simulated) and any(a["success"] for a in simulated)
    replayed = replay_scene(log_, objects, CONFIG, other=PANDA_HAND)
    assert [r.outcome for r in replayed] == [a["outcome"] for a in log_["attempts"]]
    assert all(r.reproduced for r in replayed)
    for r, a in zip(replayed, log_["attempts"]):
        if a["target"] is None:
            assert r.other_outcome == "" and "contacts" not in a
        elif a["success"]:
            assert r.contacts == {} and "contacts" not in a
        else:
            assert r.contacts == a["contacts"]
            assert a["contacts"]["phase"] in ("pregrasp", "approach", "close", "lift", "hold", "disturb")
        if a["target"] is not None:
            assert r.other_outcome in {"success", "collision_pregrasp", "collision_approach", "dropped_lift",
                                       "dropped_reorient", "dropped_disturbance", "invalid"}
            assert np.isfinite(r.com_depth) and abs(r.com_depth) < 0.2
        if r.outcome.startswith("collision"):
            assert collision_cause(r) in ("table", "table + neighbour", "target only") or collision_cause(r).startswith("neighbour")
    # A changed outcome in the log: the replay stops at that attempt.
    k = next(i for i, a in enumerate(log_["attempts"]) if a["target"] is not None)
    changed = json.loads(json.dumps(log_))
    changed["attempts"][k]["outcome"] = "dropped_reorient" if log_["attempts"][k]["success"] else "success"
    diverged = replay_scene(changed, objects, CONFIG)
    assert len(diverged) == k + 1 and not diverged[-1].reproduced
    wrong = dict(log_, object_names=log_["object_names"][::-1])
    with pytest.raises(ValueError, match="other objects"):
        replay_scene(wrong, objects, CONFIG)


def test_same_seed_same_scene_for_every_method(objects, oracle_run, gpd_run):
    first, second = oracle_run.first_observation, gpd_run.first_observation
    np.testing.assert_array_equal(first.points, second.points)
    np.testing.assert_array_equal(first.point_labels, second.point_labels)
    assert oracle_run.log["scene_seed"] == gpd_run.log["scene_seed"] == declutter.scene_seed(0, 0)
    assert oracle_run.log["object_names"] == gpd_run.log["object_names"]
    # Another index or run seed gives another scene.
    seeds = {declutter.scene_seed(s, i) for s in range(3) for i in range(3)}
    assert len(seeds) == 9
    other = declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 1, CONFIG)
    assert not np.array_equal(other.state, declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 0, CONFIG).state)


def test_attempts_are_capped_at_objects_plus_five(objects):
    run = run_scene(InTheAir(), objects, 3, seed=0, index=0, config=CONFIG)
    attempts = run.log["attempts"]
    assert run.log["end"] == "attempt_cap" and len(attempts) == run.log["objects"] + 5
    assert all(a["outcome"] == declutter.NO_OBJECT and a["target"] is None for a in attempts)
    assert all(a["width"] == 0.08 for a in attempts)  # clipped to max_opening
    assert run.log["remaining"] == run.log["objects"]
    fewer = run_scene(InTheAir(), objects, 3, seed=0, index=0, config=dataclasses.replace(CONFIG, extra_attempts=1))
    assert len(fewer.log["attempts"]) == fewer.log["objects"] + 1


def test_the_harness_remembers_failed_grasps(objects):
    """Each plan call gets the poses that failed so far in the scene; a method without `avoid` runs
    without the memory; remember_failures=False turns it off."""
    method = InTheAirRemembering()
    run = run_scene(method, objects, 3, seed=0, index=0, config=CONFIG)
    assert run.log["memory"] and run.log["end"] == "no_grasp" and run.log["final_reason"] == "my only grasp failed"
    assert [a["outcome"] for a in run.log["attempts"]] == [declutter.NO_OBJECT]
    assert [a.shape for a in method.avoid_seen] == [(0, 4, 4), (1, 4, 4)]
    np.testing.assert_array_equal(method.avoid_seen[1][0], run.log["attempts"][0]["pose"])
    off = run_scene(InTheAirRemembering(), objects, 3, seed=0, index=0,
                    config=dataclasses.replace(CONFIG, remember_failures=False))
    assert not off.log["memory"] and off.log["end"] == "attempt_cap"
    assert not run_scene(InTheAir(), objects, 3, seed=0, index=0, config=dataclasses.replace(CONFIG, extra_attempts=0)).log["memory"]
    assert declutter.takes_avoid(method) and not declutter.takes_avoid(InTheAir())


@pytest.mark.parametrize("name, options", [("oracle-topdown", {"order": "highest"}), ("gpd", {})])
def test_methods_leave_out_the_grasps_to_avoid(objects, name, options):
    method = make_method(name, **options)
    scene = declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 0, CONFIG)
    obs = declutter.camera_lib.observe(scene, CONFIG.camera)
    if getattr(method, "uses_ground_truth", False):
        method.set_scene(scene)
    first = method.plan(obs.points, obs.point_labels, CONFIG.camera.position, 0)
    again = method.plan(obs.points, obs.point_labels, CONFIG.camera.position, 0, avoid=np.zeros((0, 4, 4)))
    np.testing.assert_array_equal(again.pose, first.pose)  # nothing to avoid: the same plan
    other = method.plan(obs.points, obs.point_labels, CONFIG.camera.position, 0, avoid=first.pose[None])
    assert other.pose is not None and not near_grasps(other.pose[None], first.pose[None], GripperSpec())[0]


def test_no_grasp_ends_the_scene(objects):
    method = Never()
    run = run_scene(method, objects, 3, seed=0, index=0, config=CONFIG)
    assert method.calls == 1 and run.log["attempts"] == []
    assert run.log["end"] == "no_grasp" and run.log["final_reason"] == "nothing to do"
    summary = metrics.summarize([run.log])
    assert summary.gsr is None and summary.tsr == 0.0 and summary.ga == 0


# ---------------------------------------------------------------------------------------------
# Output directory, resume, CLI.


def test_benchmark_resumes_and_writes_tables_and_pictures(tmp_path, objects):
    args = {"setting": "seen-10", "seed": 0, "out": tmp_path, "objects": "tiny", "object_assets": objects,
            "n_objects": 2, "config": CONFIG, "pictures": 1, "progress": False}
    first = run_benchmark("oracle-topdown", scenes=1, **args)
    assert (first.ran, first.resumed, first.setting) == (1, 0, "tiny-2")
    path = report.scene_log_path(tmp_path, "oracle-topdown", "tiny-2", 0, 0)
    stamp = path.stat().st_mtime_ns
    second = run_benchmark("oracle-topdown", scenes=2, **args)
    assert (second.ran, second.resumed) == (1, 1) and second.summary.scenes == 2
    assert path.stat().st_mtime_ns == stamp  # the finished scene was not rerun
    assert second.logs[0] == json.loads(path.read_text())
    assert report.picture_path(tmp_path, "oracle-topdown", "tiny-2", 0, 0).stat().st_size > 0
    assert not report.picture_path(tmp_path, "oracle-topdown", "tiny-2", 0, 1).exists()  # pictures=1
    csv_text = (tmp_path / "results.csv").read_text()
    assert csv_text.startswith("method,setting,seed,GSR,TSR,GA,scenes") and "oracle-topdown,tiny-2,0," in csv_text
    assert "| oracle-topdown |" in (tmp_path / "results.md").read_text()
    # Every table says which objects it ran on.
    identity = second.logs[0]["object_set"]
    assert identity["size"] == len(objects) and identity["name"] == "tiny"
    assert f"tiny-2: object set `tiny`, {len(objects)} objects, names hash `{identity['hash']}`" in (
        tmp_path / "results.md").read_text()
    assert f",tiny,{len(objects)},{identity['hash']}," in csv_text
    # ... and which numerics (vector ISA, versions) its outcomes repeat under.
    assert second.logs[0]["numerics"] == numerics_label()
    assert f"- tiny-2: {numerics_label()} (2 scenes)" in (tmp_path / "results.md").read_text()
    assert "| oracle-topdown | tiny-2 | 0 |" in (tmp_path / "results.md").read_text()  # the intervals table
    assert "GSR_lo,GSR_hi,TSR_lo,TSR_hi" in csv_text.splitlines()[0]
    assert second.as_dict()["GA"] == second.summary.attempts
    # README's form of the same numbers (`python -m benchmarks.readme_table DIR`).
    from benchmarks.readme_table import table

    s = second.summary
    assert f"| oracle-topdown | {100 * s.gsr:.2f} % / {100 * s.tsr:.2f} % / {s.ga} |" in table(str(tmp_path))
    # A log written under other settings is not silently reused.
    with pytest.raises(ValueError, match="different configuration"):
        run_benchmark("oracle-topdown", scenes=1, **{**args, "config": dataclasses.replace(CONFIG, extra_attempts=2)})


def test_resume_key_covers_the_methods_own_settings(objects):
    """A method's changed settings (its defaults included) must not resume logs written under the old ones."""
    from sgjax.samplers.gpd import GPDConfig

    key = lambda cfg: run_key("gpd", {}, 2, objects, CONFIG, cfg)
    assert key(GPDConfig()) == key(GPDConfig())
    other = GPDConfig(voxel_size=0.008)
    assert key(other)["method_config"] != key(GPDConfig())["method_config"]
    assert {k for k in key(other) if key(other)[k] != key(GPDConfig())[k]} == {"method_config"}


def test_bad_input_is_reported_clearly(tmp_path, objects, capsys, monkeypatch):
    with pytest.raises(UnknownMethod, match="expected one of supergrasp, supergrasp-norefine, supergrasp-pointnetgpd, supergrasp-stage1, gpd"):
        make_method("gdp")
    with monkeypatch.context() as m, pytest.raises(MethodUnavailable, match="not available yet"):
        m.delenv("SGJAX_CGN_PYTHON", raising=False)
        m.setenv("SGJAX_CACHE", str(tmp_path / "no-cgn"))  # no Contact-GraspNet environment there
        make_method("contact-graspnet")
    with pytest.raises(ValueError, match="does not take option"):
        make_method("gpd", model="runs/x")
    with pytest.raises(ValueError, match="unknown setting 'seen-30'"):
        run_benchmark("gpd", setting="seen-30", out=tmp_path, object_assets=objects, progress=False)
    with pytest.raises(ValueError, match="scenes must be >= 1"):
        run_benchmark("gpd", scenes=0, out=tmp_path, object_assets=objects, progress=False)
    assert main(["declutter", "--method", "gdp", "--out", str(tmp_path)]) == 2
    assert "unknown method 'gdp'" in capsys.readouterr().err
    assert main(["declutter", "--method", "gpd", "--setting", "seen-30", "--out", str(tmp_path)]) == 2
    assert "unknown setting" in capsys.readouterr().err
    assert not (tmp_path / "logs").exists()


def test_cli_runs_on_a_user_mesh_folder_and_prints_json(tmp_path, capsys):
    import trimesh

    folder = tmp_path / "my_meshes"
    folder.mkdir()
    trimesh.creation.box((0.04, 0.05, 0.06)).export(folder / "block.obj")
    trimesh.creation.cylinder(radius=0.025, height=0.08, sections=16).export(folder / "can.stl")
    code = main(["declutter", "--method", "oracle-topdown", "--objects", str(folder), "--n-objects", "2",
                 "--scenes", "1", "--out", str(tmp_path / "out"), "--json", "--quiet", "--pictures", "0"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert {"GSR", "TSR", "GA", "scenes"} <= set(result) and result["scenes"] == 1
    assert result["setting"] == "my_meshes-2" and result["GA"] >= 1
    log_ = json.loads(report.scene_log_path(tmp_path / "out", "oracle-topdown", "my_meshes-2", 0, 0).read_text())
    assert set(log_["object_names"]) <= {"my_meshes/block", "my_meshes/can"} and log_["memory"]
    assert log_["object_set"]["size"] == 2 and log_["object_set"]["skipped"] == []
    # --no-memory is another configuration: it refuses to resume into the same folder.
    code = main(["declutter", "--method", "oracle-topdown", "--objects", str(folder), "--n-objects", "2",
                 "--scenes", "1", "--out", str(tmp_path / "out"), "--quiet", "--pictures", "0", "--no-memory"])
    assert code != 0 and "config differ" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# SuperGrasp adapters (when the planner is installed).


@pytest.fixture(scope="module")
def rigged():
    """(model, config): a tiny E-RNet rigged to rate every candidate 0.98, so the planner always executes
    a grasp, and a small planner config for it."""
    import jax.numpy as jnp
    from flax import nnx

    from sgjax.stage2.ernet import ERNet, ERNetConfig
    from sgjax.planner import PlannerConfig
    from sgjax.stage2.scene_cloud import SceneCloudConfig

    tiny = ERNetConfig.tiny(backbone=dataclasses.replace(ERNetConfig.tiny().backbone, sampler="random"))
    model = ERNet(tiny, rngs=nnx.Rngs(0))
    last = model.eval_head.layers[-1]
    last.kernel[...] = jnp.zeros_like(last.kernel[...])
    last.bias[...] = jnp.asarray([-2.0, 2.0], jnp.float32)
    return model, PlannerConfig(max_stage2_candidates=64, scene_cloud=SceneCloudConfig(max_points=4096), stage1_batch_sizes=(1,))


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("sgjax.planner") is None, reason="sgjax.planner is not installed")
def test_supergrasp_methods_run_a_tiny_scene(objects, small_db, rigged):
    model, config = rigged
    for name in ("supergrasp", "supergrasp-norefine"):
        assert METHODS[name].unavailable_reason() is None
        method = make_method(name, model=model, db=small_db, config=config)
        assert method.name == name and method.planner.config.use_refinement == (name == "supergrasp")
        run = run_scene(method, objects, 2, seed=0, index=0, config=CONFIG, setting="tiny-2")
        attempts = run.log["attempts"]
        assert 1 <= len(attempts) <= run.log["objects"] + 5
        assert all(a["info"]["kind"] in ("evaluated", "refined") for a in attempts)
        assert all(a["score"] == pytest.approx(0.982, abs=1e-3) for a in attempts)
        assert all(set(a["timing"]) == set(metrics.TIMING_KEYS) for a in attempts)
    # The planner keeps Stage-1 results over a scene's plans; the harness starts each scene afresh
    # (`begin_scene`), so the same scene run again by the same method object plays out the same.
    assert method.memory.entries and method.memory.computed >= 1
    again = run_scene(method, objects, 2, seed=0, index=0, config=CONFIG, setting="tiny-2")
    strip = lambda log: [{**{k: v for k, v in a.items() if k not in ("timing", "observe_s", "trial_s", "settle_s")},
                          "info": {k: v for k, v in a["info"].items() if k != "compiled"}} for a in log["attempts"]]
    assert strip(again.log) == strip(run.log)


@pytest.fixture(scope="module")
def supergrasp_run(objects, small_db, rigged):
    """(method, run): the rigged SuperGrasp planner's run of a tiny 3-object scene."""
    model, config = rigged
    method = make_method("supergrasp", model=model, db=small_db, config=config)
    return method, run_scene(method, objects, 3, seed=0, index=0, config=CONFIG, setting="tiny-3")


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("sgjax.planner") is None, reason="sgjax.planner is not installed")
def test_every_finalist_is_simulated_from_the_logged_states(objects, small_db, rigged, supergrasp_run):
    from eval.counterfactual import RULES, oracle_successes, replay_choices, rule_successes

    model, config = rigged
    method, run = supergrasp_run
    states, reproduced = replay_choices(run.log, objects, method, CONFIG)
    assert reproduced and states
    logged = {a["attempt"]: a for a in run.log["attempts"]}
    for state in states:
        chosen = [f for f in state.finalists if f.chosen]
        assert len(chosen) == 1 and len(state.finalists) >= 2
        # the executed finalist, simulated in the batch, is the logged trial
        assert chosen[0].outcome == state.logged == logged[state.attempt]["outcome"]
        assert chosen[0].target == logged[state.attempt]["target"]
        # the robust score is the mean of the own and the five perturbed scores
        for f in state.finalists:
            assert len(f.perturbed) == 5
            assert f.robust_score == pytest.approx((f.eval_prob + sum(f.perturbed)) / 6, abs=1e-5)
    executed = rule_successes(states, RULES["executed"])
    assert executed == sum(logged[s.attempt]["success"] for s in states)
    assert executed <= oracle_successes(states) <= len(states)
    # a log the planner does not reproduce stops the replay there, and says so
    changed = json.loads(json.dumps(run.log))
    changed["attempts"][0]["pose"][0][3] += 0.01
    assert replay_choices(changed, objects, method, CONFIG) == ([], False)
    with pytest.raises(ValueError, match="robust"):
        replay_choices(run.log, objects, make_method("supergrasp", model=model, db=small_db,
                                                      config=dataclasses.replace(config, robust=None)), CONFIG)


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("sgjax.planner") is None, reason="sgjax.planner is not installed")
def test_another_planner_is_measured_on_the_logged_states(objects, small_db, rigged, supergrasp_run):
    """`replay_alternative`: another planner plans each logged state; its grasp, where it differs, is
    executed from that very state (its first one is the initial scene, so the alternative's own run
    must agree there), the same planner agrees everywhere, and a planner that finds nothing says so."""
    from eval.counterfactual import replay_alternative

    model, config = rigged
    method, run = supergrasp_run
    logged = {a["attempt"]: a for a in run.log["attempts"]}
    twin = make_method("supergrasp", model=model, db=small_db, config=config)
    states, reproduced = replay_alternative(run.log, objects, method, twin, CONFIG)
    assert reproduced and [s.attempt for s in states] == [k for k, a in logged.items() if a["target"] is not None]
    assert all(s.same and s.outcome == s.logged == logged[s.attempt]["outcome"] and s.kind == s.logged_kind
               for s in states)
    assert {s.logged_kind for s in states} <= {"compared", "lone", "refined", "compared, second plan",
                                               "lone, second plan", "refined, second plan"}
    # Without the grasps on the fits (offered first) the planner chooses other grasps.
    other_config = dataclasses.replace(config, fit_grasps=None)
    other = make_method("supergrasp", model=model, db=small_db, config=other_config)
    states, reproduced = replay_alternative(run.log, objects, method, other, CONFIG)
    assert reproduced and len(states) == len([a for a in logged.values() if a["target"] is not None])
    own = run_scene(make_method("supergrasp", model=model, db=small_db, config=other_config), objects, 3, seed=0,
                    index=0, config=CONFIG, setting="tiny-3")
    first, own_first = states[0], own.log["attempts"][0]
    assert first.attempt == 0 and not first.same
    assert not np.allclose(own_first["pose"], logged[0]["pose"])
    assert first.outcome == own_first["outcome"]
    assert first.kind.split(",")[0] in {"evaluated": ("compared", "lone"), "refined": ("refined",)}[own_first["info"]["kind"]]
    assert first.kind.endswith("second plan") == bool(own_first["info"].get("fallback"))
    # A planner whose bar nothing passes plans no grasp anywhere.
    bar = dataclasses.replace(config, eval_threshold=0.99, refine_threshold=0.99, fallback_filter=None)
    none, reproduced = replay_alternative(run.log, objects, method, make_method("supergrasp", model=model, db=small_db,
                                                                                 config=bar), CONFIG)
    assert reproduced and none and all(s.outcome == "none" and s.kind == "none" and not s.same for s in none)
    with pytest.raises(ValueError, match="alternative"):
        replay_alternative(run.log, objects, method, make_method("oracle-topdown"), CONFIG)


@pytest.mark.skipif(METHODS["contact-graspnet"].unavailable_reason() is not None,
                    reason="Contact-GraspNet's environment is not set up: run `sgjax baselines setup contact-graspnet`")
def test_contact_graspnet_runs_a_tiny_scene(objects):
    """The real cgn-pytorch model, out of process: a tiny scene runs by the rules (outcomes are its own)."""
    method = make_method("contact-graspnet")
    try:
        run = run_scene(method, objects, N_OBJECTS, seed=0, index=0, config=CONFIG, setting=f"tiny-{N_OBJECTS}")
    finally:
        method.close()
    log_ = run.log
    assert log_["method"] == "contact-graspnet" and log_["end"] in ("cleared", "attempt_cap", "no_grasp")
    assert len(log_["attempts"]) <= log_["objects"] + 5
    for a in log_["attempts"]:
        pose = np.asarray(a["pose"])
        np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
        assert a["info"]["grasps"] >= 1 and 0.5 <= a["score"] <= 1.0
    if not log_["attempts"]:
        assert "no grasp above confidence" in log_["final_reason"]


def test_vector_isa_is_the_cpus_widest_capped_by_xla_flags():
    avx512 = {"sse4_2", "avx", "avx2", "avx512f"}
    assert vector_isa(avx512, "") == "AVX512"
    assert vector_isa(avx512, "--xla_cpu_max_isa=AVX2 --other") == "AVX2"
    assert vector_isa({"sse4_2", "avx", "avx2"}, "--xla_cpu_max_isa=AVX512") == "AVX2"  # a cap cannot widen
    assert vector_isa({"sse4_2"}, "") == "SSE4_2"
    label = numerics_label()
    assert "jaxlib" in label and "mujoco" in label
    # XLA's code-generation flags are named (the suite sets some: tests/conftest.py), the ISA cap and the
    # host device count are not.
    assert code_flags("--xla_cpu_max_isa=AVX2 --xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 "
                      "--xla_force_host_platform_device_count=2") == (
        "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false")
    assert code_flags("") == "" and code_flags("--xla_cpu_max_isa=AVX2") == ""
    assert label.endswith(f", XLA_FLAGS {code_flags()}") if code_flags() else "XLA_FLAGS" not in label


# ---------------------------------------------------------------------------------------------
# Through a sensor: the method sees what the front end of a real frame makes of the sensor's depth.


class Recorder(InTheAir):
    """InTheAir that keeps what it was shown."""

    name = "recorder"

    def __init__(self):
        self.seen = []

    def plan(self, points, labels, viewpoint, seed=0):
        self.seen.append((np.array(points), np.array(labels)))
        return super().plan(points, labels, viewpoint, seed)


@pytest.mark.parametrize("masks", ["truth", "clusters"])
def test_through_a_sensor_the_method_sees_the_front_ends_frame(objects, masks):
    from envs.camera import observe

    config = dataclasses.replace(CONFIG, sensor="realsense", masks=masks, extra_attempts=0)
    assert config.through_sensor and config.view == f"realsense+{masks}"
    assert repr(config) == repr(dataclasses.replace(CONFIG, extra_attempts=0))  # the resume key names the view instead
    method = Recorder()
    run = run_scene(method, objects, N_OBJECTS, seed=0, index=0, config=config, setting="tiny-4")
    assert run.log["view"] == f"realsense+{masks}" and len(method.seen) == len(run.log["attempts"]) >= 1
    points, labels = method.seen[0]
    assert set(np.unique(labels)) <= {-1, *range(1, 100)} and (labels == -1).any() and (labels > 0).any()
    seen = run.log["attempts"][0]["seen"]
    assert seen["objects_found"] == len(np.unique(labels[labels > 0]))
    np.testing.assert_allclose(seen["table"], (0, 0, 1, 0), atol=2e-3)  # the fitted table: z = 0, up
    # The scene is the same one (the surroundings only seen), its depth another: not the exact render's cloud.
    scene = declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 0, config)
    exact = observe(scene, config.camera)
    assert "robot_stand" in [scene.model.geom(i).name for i in range(scene.model.ngeom)]
    assert np.array_equal(scene.state, declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 0, CONFIG).state)
    assert len(points) != len(exact.points) or not np.array_equal(points, exact.points)
    if masks == "truth":  # the instance ids of the exact render: object index + 1
        visible = {int(i) + 1 for i, c in zip(*np.unique(exact.point_labels, return_counts=True)) if i >= 0 and c > 20}
        assert visible <= set(np.unique(labels[labels > 0]).tolist())


class SecondPlan(Recorder):
    """Recorder that finds no grasp on every first plan of an observation and InTheAir's on the second."""

    name = "second-plan"

    def plan(self, points, labels, viewpoint, seed=0):
        self.seen.append((np.array(points), np.array(labels)))
        if len(self.seen) % 2:
            return Decision(None, 0.0, 0.0, "first plan: none", timing())
        return InTheAir.plan(self, points, labels, viewpoint, seed)


def test_with_clusters_a_method_without_a_grasp_plans_again_on_the_other_hypotheses(objects):
    """Through the stereo model with clusters (tiny-4, scene 2: a crease cuts an object in two), a method
    that finds no grasp is shown the frame's next hypothesis (the clusters as segmented where the parted
    one came first, else the joined fragments); the grasp it finds there is executed and logged as such;
    with true masks there is no second plan."""
    config = dataclasses.replace(CONFIG, sensor="stereo", masks="clusters", extra_attempts=0)
    scene = declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 2, config)
    view = declutter.observe(scene, config, declutter.scene_seed(0, 2))
    hypotheses = list(declutter.hypotheses(view))
    names = [h[0].split()[0] for h in hypotheses]
    first_labels = view.info.get("labels", "clusters")
    assert first_labels in ("parted", "clusters") and names[:1] == (["clusters"] if first_labels == "parted" else ["joined"])
    joined = hypotheses[names.index("joined")][1:]
    assert view.info["objects_found"] > len(np.unique(joined[1][joined[1] > 0]))  # the crease-cut object joined
    method = SecondPlan()
    run = run_scene(method, objects, N_OBJECTS, seed=0, index=2, config=config, setting="tiny-4")
    first = run.log["attempts"][0]
    assert len(method.seen) >= 2 and first["seen"]["labels"] == names[0] and first["outcome"] == "no_object"
    np.testing.assert_array_equal(method.seen[0][1], view.labels)
    np.testing.assert_array_equal(method.seen[1][0], hypotheses[0][1])
    np.testing.assert_array_equal(method.seen[1][1], hypotheses[0][2])
    assert first["timing"]["total_s"] == pytest.approx(2 * timing()["total_s"])  # both plans' time
    never = Never()
    run = run_scene(never, objects, N_OBJECTS, seed=0, index=2, config=config, setting="tiny-4")
    # Every hypothesis in turn (each where it differs from those before), each plan's reason in the scene's.
    assert names in (["joined"], ["joined", "finer"], ["clusters", "joined"], ["clusters", "joined", "finer"])
    assert never.calls == 1 + len(hypotheses) and run.log["end"] == "no_grasp"
    assert run.log["final_reason"] == "nothing to do" + "".join(f"; on the {h[0]}: nothing to do" for h in hypotheses)
    never = Never()
    run_scene(never, objects, N_OBJECTS, seed=0, index=2, config=dataclasses.replace(config, masks="truth"), setting="tiny-4")
    assert never.calls == 1


def test_the_exact_camera_keeps_todays_cloud_and_key(objects):
    method = Recorder()
    run = run_scene(method, objects, N_OBJECTS, seed=0, index=0, config=dataclasses.replace(CONFIG, extra_attempts=0),
                    setting="tiny-4")
    from envs.camera import observe

    obs = observe(declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 0, CONFIG), CONFIG.camera, seed=run.log["scene_seed"])
    np.testing.assert_array_equal(method.seen[0][0], obs.points)
    np.testing.assert_array_equal(method.seen[0][1], obs.point_labels)
    assert "view" not in run.log and "seen" not in run.log["attempts"][0]
    key = run_key("m", {}, 4, objects, CONFIG)
    assert "view" not in key and run_key("m", {}, 4, objects, dataclasses.replace(CONFIG, sensor="kinect"))["view"] == "kinect+truth"


def test_sensor_and_mask_choices_are_checked_and_the_cli_offers_each_sensor():
    from envs.sensors import SENSORS
    from sgjax_cli.commands import MASKS as CLI_MASKS
    from sgjax_cli.commands import SENSORS as CLI_SENSORS

    assert tuple(SENSORS) == CLI_SENSORS and declutter.MASKS == CLI_MASKS
    with pytest.raises(ValueError, match="exact, kinect, realsense, stereo"):
        DeclutterConfig(sensor="lidar")
    with pytest.raises(ValueError, match="unknown masks 'sam'"):
        DeclutterConfig(masks="sam")


def test_the_exact_sensors_frame_is_the_exact_render_cloud(objects):
    """Through the front end with the exact sensor, every point the method gets is a point of the exact
    render (the pixel convention of `CameraConfig.pixel_intrinsic` is the user's)."""
    from envs.camera import observe

    config = dataclasses.replace(CONFIG, sensor="exact", masks="clusters", extra_attempts=0)
    method = Recorder()
    run = run_scene(method, objects, N_OBJECTS, seed=0, index=0, config=config, setting="tiny-4")
    exact = observe(declutter.make_benchmark_scene(objects, N_OBJECTS, 0, 0, config), config.camera,
                    seed=run.log["scene_seed"])
    points = method.seen[0][0]
    from scipy.spatial import cKDTree

    assert cKDTree(exact.points).query(points)[0].max() < 1e-5


def test_the_real_world_settings_fix_their_gripper_sensor_and_masks(tmp_path):
    """Table II re-created: real-similar / real-novel bring the AG-105-145, stereo depth and segmented masks;
    a config that asks for another of them is refused, and Table I's settings change nothing."""
    from eval.declutter import apply_setting, get_setting
    from sgjax.geometry.gripper_files import load_gripper

    for name, objects in (("real-similar", "seen"), ("real-novel", "unseen")):
        setting = get_setting(name)
        config = apply_setting(setting, DeclutterConfig())
        assert setting.object_set == objects and setting.n_objects == 10
        assert config.gripper == load_gripper("ag-105-145") and config.gripper.max_opening == pytest.approx(0.145)
        assert (config.sensor, config.masks, config.view) == ("stereo", "clusters", "stereo+clusters")
        with pytest.raises(ValueError, match=f"setting '{name}' fixes the sensor"):
            apply_setting(setting, DeclutterConfig(sensor="kinect"))
        with pytest.raises(ValueError, match="fixes the gripper"):
            apply_setting(setting, DeclutterConfig(gripper=load_gripper("robotiq-2f85")))
    assert apply_setting(get_setting("seen-10"), DeclutterConfig(sensor="kinect")) == DeclutterConfig(sensor="kinect")


def test_a_run_is_named_after_its_setting_objects_and_view():
    """Logs and tables name a run "<objects>-<n>[@<view>]"; a setting that fixes its hardware keeps its name,
    with the object set after it when the set replaces its own (the report's real-novel on the sealed set)."""
    from eval.declutter import get_setting

    assert get_setting("seen-10").label("seen", 10) == "seen-10"
    assert get_setting("unseen-10").label("mymeshes", 10, replaced=True) == "mymeshes-10"
    assert get_setting("seen-10").label("seen", 10, "realsense+clusters") == "seen-10@realsense+clusters"
    real = get_setting("real-novel")
    assert real.label("unseen", 10, "stereo+clusters") == "real-novel"
    assert real.label("mymeshes", 10, "stereo+clusters", replaced=True) == "real-novel-mymeshes"
    assert real.label("unseen", 4, "stereo+clusters", custom=True) == "unseen-4@stereo+clusters"  # not its scenes


def test_cluster_grade_tells_clean_merged_and_split_clusters_apart():
    """The cluster a grasp was planned on, graded against the true objects: a grasp at the origin
    (closing along x, approaching along +z) on cluster 1 of 100 points; true object 0 holds 90 of them and
    has 100 points in the frame: clean; the same cluster 70 % object 0: merged; one of object 0's 400
    points: split; a grasp on no cluster's points: None."""
    spec = GripperSpec()
    pose = np.eye(4)
    rng = np.random.default_rng(0)
    inside = rng.uniform([-0.01, -0.005, 0.005], [0.01, 0.005, 0.03], (100, 3))  # in the closing region
    far = inside + [0.5, 0.0, 0.0]
    points = np.concatenate([inside, far])
    labels = np.r_[np.ones(100, int), np.full(100, 2)]  # cluster 1 under the grasp, 2 far away
    truth = np.r_[np.zeros(90, int), np.ones(10, int), np.full(100, 2)]
    grade = declutter.cluster_grade(points, labels, truth, np.array([100, 10, 100]), pose, 0.04, spec)
    assert grade == {"cluster": 1, "points": 100, "object": 0, "purity": 0.9, "coverage": 0.9, "grade": "clean"}
    truth[:30] = 1  # 70 % object 0
    assert declutter.cluster_grade(points, labels, truth, np.array([100, 40, 100]), pose, 0.04, spec)["grade"] == "merged"
    truth[:30] = 0
    split = declutter.cluster_grade(points, labels, truth, np.array([400, 10, 100]), pose, 0.04, spec)
    assert split["grade"] == "split" and split["coverage"] == pytest.approx(90 / 400)
    moved = np.eye(4)
    moved[:3, 3] = [0.0, 0.3, 0.0]  # nothing there
    assert declutter.cluster_grade(points, labels, truth, np.array([100, 10, 100]), moved, 0.04, spec) is None


class OnCluster(Recorder):
    """A top-down grasp through the middle of the largest cluster (label 1), the hand open."""

    name = "on-cluster"

    def plan(self, points, labels, viewpoint, seed=0):
        self.seen.append((np.array(points), np.array(labels)))
        mine = np.asarray(points)[np.asarray(labels) == 1]
        if not len(mine):
            return Decision(None, 0.0, 0.0, "no cluster", timing())
        pose = np.eye(4)
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # approach straight down
        pose[:3, 3] = [*np.median(mine[:, :2], 0), mine[:, 2].max() + 0.005]
        return Decision(pose, 0.08, 0.5, "", timing())


def test_with_clusters_the_log_grades_the_cluster_each_grasp_was_planned_on(objects):
    """Through the RealSense model with clusters, each attempt's "segment" grades the cluster planned on
    against the exact render (`cluster_grade`): the largest cluster, mostly the object the grasp was
    judged to be on; with true masks there is no grade."""
    config = dataclasses.replace(CONFIG, sensor="realsense", masks="clusters", extra_attempts=0)
    run = run_scene(OnCluster(), objects, N_OBJECTS, seed=0, index=0, config=config, setting="tiny-4")
    first = run.log["attempts"][0]
    segment = first["segment"]
    assert segment["cluster"] == 1 and segment["grade"] in ("clean", "merged", "split")
    assert segment["object"] == first["target"] and 0.5 < segment["purity"] <= 1 and 0 < segment["coverage"] <= 1
    json.dumps(run.log)  # the log stays JSON
    run = run_scene(OnCluster(), objects, N_OBJECTS, seed=0, index=0, config=dataclasses.replace(config, masks="truth"),
                    setting="tiny-4")
    assert "segment" not in run.log["attempts"][0]


def test_attempts_are_counted_by_the_grade_of_the_cluster_they_were_planned_on():
    a = log(4, "sffs", method="supergrasp", setting="seen-10@realsense+clusters", seed=0)
    b = log(2, "sf", method="supergrasp", setting="seen-10@realsense+clusters", seed=0)
    for attempt, grade in zip(a["attempts"] + b["attempts"], ["clean", "merged", None, "clean", "split", "clean"]):
        attempt["segment"] = None if grade is None else {"grade": grade}
    assert metrics.segment_breakdown([a, b]) == {"clean": (3, 2), "merged": (1, 0), "split": (1, 1), "none": (1, 0)}
    assert metrics.segment_breakdown([log(2, "sf", method="m", setting="seen-10", seed=0)]) is None  # true masks
    table = report.segments_markdown([a, b, log(2, "sf", method="gpd", setting="seen-10", seed=0)])
    assert "| supergrasp | seen-10@realsense+clusters | 2 | 3, 66.67% | 1, 0.00% | 1, 100.00% | 1, 0.00% |" in table
    assert "gpd" not in table and report.segments_markdown([log(2, "sf", method="m", setting="s", seed=0)]) == ""
