"""Stage 1's filters on and off, and the second plan, with today's E-RNet (issue "Stage 2, part 2": keep
each filter beyond the paper's only where the benchmark shows it helps).

    python benchmarks/filter_ablation.py [--setting seen-10] [--scenes 30] [--seed 0]
                                         [--variants default no-fallback ...] [--out filter_ablation_out]
                                         [--model RUN_DIR] [--method supergrasp|supergrasp-norefine]
                                         [--reuse RUN_WITHOUT_FALLBACK]

Each variant is `supergrasp` (or --method) with one change to today's planner (`VARIANTS`: a
`FilterConfig` change, the second plan's filter, a `MatchConfig`, `Stage1Config` or `PlannerConfig` change), run on the same scenes (same seed) through
`eval.benchmark.run_benchmark` into its own folder OUT/<variant> (resumable: rerun the same command
after an interrupt). Prints, per variant: GSR / TSR / GA, the unfinished scenes by why they ended
(Stage 1 kept no candidate; Stage 2 scored every candidate <= the threshold; the memory of failed grasps
left none; the attempt cap), the failed grasps by outcome (phase), Stage-1 candidates per plan and the
planning time per grasp."""

from __future__ import annotations

import argparse
import collections
import dataclasses

import numpy as np

from eval import report
from envs.scene import stage2_scene_cloud
from eval.benchmark import run_benchmark
from eval.methods import make_method
from sgjax.planner import PlannerConfig, RobustChoice
from sgjax.stage1.filters import FilterConfig
from sgjax.stage1.fit_grasps import FitGraspConfig
from sgjax.stage1.neighbours import NeighbourFitConfig

# The filters beyond the paper's (i)-(iii) and the table (v), each switched to the paper's reading (or,
# for the obstacle margin, back to the default it had before 2026-12-02); and the second plan when the
# first finds nothing (`PlannerConfig.fallback_filter`): "fallback" gives its filter as changes to
# FilterConfig(), None for no second plan; without the key a variant keeps the default `FALLBACK_FILTER`.
VARIANTS = {
    "default": {},
    "no-fallback": {"fallback": None},  # the planner before 2026-12-02 evening: one plan
    "margin-5mm": {"obstacle_margin": 0.005},  # (iv) with the hand boxes grown by 5 mm (the old default)
    "no-shadows": {"shadow_depth": 0.0},  # (iv) tests the observed obstacle points only
    "shadow-8cm": {"shadow_depth": 0.08},  # (iv) with each obstacle point hiding twice as deep a shadow
    "hidden-accept": {"hidden_contacts": "accept"},  # (iii) does not judge a finger whose contacts are hidden
    "hidden-reject": {"hidden_contacts": "reject"},  # (iii) the paper's strict reading
    "paper": {"shadow_depth": 0.0, "obstacle_margin": 0.0, "hidden_contacts": "accept"},  # = labelling's stage1_paper, with (iv)
    # A second plan with only the filters beyond the paper's off (the default also loosens (ii), (iii)).
    "fallback-paper": {"fallback": {"shadow_depth": 0.0, "hidden_contacts": "accept"}},
    # the second plan's looser (ii), (iii) and hidden contacts, with the first plan's camera-ray shadows kept
    "fallback-shadows": {"fallback": {"hidden_contacts": "accept", "max_normal_angle_deg": 30.0, "min_points": 25}},
    # Not a filter: the matching also tries the fit's axes relabelled (`MatchConfig.relabel_axes`).
    "relabel-axes": {"match": {"relabel_axes": True}},
    "relabel-extra": {"match": {"relabel_extra": 5}},  # ... only as 5 extra matches after the paper's K2
    # ... only in the second plan (the first finds nothing): `PlannerConfig.fallback_match`.
    "fallback-relabel": {"fallback_match": {"relabel_extra": 5}},
    # Not Stage 1: refinements scored by the refine head alone, the paper's rule (`PlannerConfig.refine_rescore`).
    "refine-head": {"planner": {"refine_rescore": 0}},
    # Not Stage 1's: the planner's test of the hand against the neighbours' fitted superquadrics
    # (`PlannerConfig.neighbour_fits`): off (the planner before 2026-12-03 evening), with a 5 mm margin,
    # in the second plan too, or with the closing region between the fingers tested too.
    "no-neighbour-fits": {"planner": {"neighbour_fits": None}},
    "neighbour-fits-5mm": {"planner": {"neighbour_fits": NeighbourFitConfig(margin=0.005)}},
    "neighbour-fits-both": {"planner": {"neighbour_fits": NeighbourFitConfig(in_fallback=True)}},  # in the second plan too
    "neighbour-fits-closing": {"planner": {"neighbour_fits": NeighbourFitConfig(closing=True)}},
    # ... and in the second plan as a preference: the candidates that pass it, else all of them (the
    # default since 2026-12-05); "neighbour-fits-first-only": the first plan only (the default before).
    "neighbour-fits-prefer": {"planner": {"neighbour_fits": NeighbourFitConfig(in_fallback="prefer")}},
    "neighbour-fits-first-only": {"planner": {"neighbour_fits": NeighbourFitConfig(in_fallback=False)}},
    # Not a filter: on the chosen object, the passing candidate with the shortest lever arm preferred
    # (`PlannerConfig.lever_weight`; 2 per metre was the best of 1-4 on the labelled mix-v5 + v6).
    "lever": {"planner": {"lever_weight": 2.0}},
    # Not a filter: Stage 1's top-down grasps on each object's fit (`PlannerConfig.fit_grasps`,
    # `sgjax.stage1.fit_grasps`; default: in both plans) off, or only in the second plan.
    "no-fit-grasps": {"planner": {"fit_grasps": None}},
    "fit-grasps-second": {"planner": {"fit_grasps": FitGraspConfig(first_plan=False)}},
    # ... only straight across the fit's horizontal axes (no ±15° turns): on the lone lens the grasps
    # 0-10° off its short axis held 90 %, 10-20° off 62 % (docs/benchmark.md, "Grasps on the fit itself").
    # The default since 2026-12-05; "fit-grasps-turned" is the default before it (also turned by ±15°).
    "fit-grasps-straight": {"planner": {"fit_grasps": FitGraspConfig(yaws_deg=(0.0,))}},
    "fit-grasps-turned": {"planner": {"fit_grasps": FitGraspConfig(yaws_deg=(-15.0, 0.0, 15.0))}},
    # ... and chosen first: among the passing grasps on the fits when any passes (`PlannerConfig.prefer_fit_grasps`).
    "prefer-fit-grasps": {"planner": {"prefer_fit_grasps": True}},
    # ... only in the second plan, whose transferred grasps are the marginal ones (the first plan: E-RNet's order).
    "prefer-fit-grasps-second": {"planner": {"prefer_fit_grasps": "second"}},
    # Not a filter: the best-evaluated candidate executed, not the one among the 12 best whose score holds
    # up at small perturbations of its pose (`PlannerConfig.robust`, `RobustChoice`; default since
    # 2026-12-03 night); "robust" names the default's choice explicitly (the runs that measured it).
    "no-robust": {"planner": {"robust": None}},
    "robust": {"planner": {"robust": RobustChoice()}},
    # Not a filter: after a failed grasp, the other objects first (`PlannerConfig.failed_last`: a failed
    # grasp counts for the object with an observed point within 2 cm of its closing region's centre).
    "failed-last": {"planner": {"failed_last": 0.02}},
    # Filter (iv) on twice the obstacle points: in 20-object scenes an object's obstacle crop holds 10-18k
    # camera points and the default 4,096-point subsample keeps a quarter, so a neighbour's sliver between
    # the fingers can vanish from it (`Stage1Config.max_scene_points`).
    "obstacles-8192": {"stage1": {"max_scene_points": 8192}},
    # The default before 2026-12-04: a crop over 4,096 points subsampled at random, without the 4 mm
    # grid that first keeps a point in every occupied cell (`Stage1Config.obstacle_voxel`).
    "obstacles-random": {"stage1": {"obstacle_voxel": 0.0}},
    # ... and a perturbed pose that meets a neighbour's fitted superquadric counts 0 (`RobustChoice.fits`).
    "robust-fits": {"planner": {"robust": RobustChoice(fits=True)}},
    # ... and the mean must pass the evaluation bar too, a lone passing candidate judged as well
    # (`RobustChoice.must_pass`; eval.counterfactual: lone candidates succeeded 61 % on dense states; off: it trades TSR for GSR).
    "robust-must-pass": {"planner": {"robust": RobustChoice(must_pass=True)}},
    # The second plan also when the first plan's grasp was chosen without a comparison (a lone passing
    # candidate; and refinements): its choice replaces the first's when it compared two or more.
    # ... and among the robust choice's judged candidates, those clear of the obstacles and the neighbours'
    # fits by 5 mm (the old filter margin, as a preference) first (`RobustChoice.prefer_clearance`).
    "robust-prefer-clear": {"planner": {"robust": RobustChoice(prefer_clearance=0.005)}},
    "fallback-for-lone": {"planner": {"fallback_for": ("lone",)}},
    "fallback-for-uncompared": {"planner": {"fallback_for": ("lone", "refined")}},
}


def variant_config(name: str):
    """The planner config of a variant: the benchmark's (`eval.supergrasp` default) with its changes."""
    if name not in VARIANTS:
        raise ValueError(f"unknown variant {name!r}; known: {', '.join(VARIANTS)}")
    base = PlannerConfig(scene_cloud=stage2_scene_cloud())
    changes = dict(VARIANTS[name])
    fallback = changes.pop("fallback", "default")
    matching = dataclasses.replace(base.stage1.match, **changes.pop("match", {}))
    fallback_match = changes.pop("fallback_match", None)
    planner = changes.pop("planner", {})
    stage1 = changes.pop("stage1", {})
    fallback_match = None if fallback_match is None else dataclasses.replace(base.stage1.match, **fallback_match)
    if fallback == "default":
        fallback_filter = base.fallback_filter
    else:
        fallback_filter = None if fallback is None else dataclasses.replace(FilterConfig(), **fallback)
    filt = dataclasses.replace(FilterConfig(), **changes)
    return dataclasses.replace(base, stage1=dataclasses.replace(base.stage1, filter=filt, match=matching, **stage1),
                               fallback_filter=fallback_filter, fallback_match=fallback_match, **planner)


def differs_only_by_fallback(name: str) -> bool:
    """Whether variant `name` is the default filters with a second plan (so `--reuse` applies)."""
    return set(VARIANTS[name]) <= {"fallback"} and VARIANTS[name].get("fallback", "default") is not None


def reuse_unaffected(source, out, setting: str, scenes: int, seed: int, objects, options: dict, method) -> int:
    """Copy into `out` the scene logs of `source` (a run of the same filters without a fallback) that
    cannot change with a fallback: the fallback only acts on a plan that finds no grasp, and such a plan
    ends a scene ("no_grasp"), so every scene that ended otherwise runs identically. Their resume key is
    rewritten to this variant's. -> scenes copied."""
    from eval import declutter, report
    from eval.benchmark import resolve_objects, run_key
    from eval.declutter import DeclutterConfig

    chosen = declutter.get_setting(setting)
    assets, label, _ = resolve_objects(chosen, objects)
    key = run_key(method.name, options, chosen.n_objects, assets, DeclutterConfig(), method.config)
    copied = 0
    for index in range(scenes):
        log = report.read_scene_log(report.scene_log_path(source, method.name, f"{label}-{chosen.n_objects}", seed, index))
        target = report.scene_log_path(out, method.name, f"{label}-{chosen.n_objects}", seed, index)
        if log is None or log["end"] == "no_grasp" or target.exists():
            continue
        report.write_scene_log(target, {**log, "key": key})
        copied += 1
    return copied


def why_unfinished(log: dict) -> str | None:
    """Why a scene ended with objects left: None when cleared, else stage1 / stage2 / memory / cap."""
    if log["end"] == "cleared" or not log.get("remaining"):
        return None
    if log["end"] == "attempt_cap":
        return "cap"
    reason = log.get("final_reason", "")
    if reason.startswith("no candidates") or reason.startswith("no object"):
        return "stage1"
    if "of the" in reason and "pose(s) to avoid" in reason:
        return "memory"
    return "stage2"


def summary_row(name: str, result) -> dict:
    s = result.summary
    causes = [(why, int(log["remaining"])) for log in result.logs if (why := why_unfinished(log))]
    ends, left = collections.Counter(), collections.Counter()
    for why, remaining in causes:
        ends[why] += 1
        left[why] += remaining
    attempts = [a for log in result.logs for a in log["attempts"]]
    failed = collections.Counter(a["outcome"] for a in attempts if not a["success"])
    plan_s = [a["timing"].get("total_s", 0.0) for a in attempts]
    n_cand = [a["info"].get("n_candidates", 0) for a in attempts]
    causes_of = lambda counter: "/".join(str(counter[k]) for k in ("stage1", "stage2", "memory", "cap"))
    return {
        "variant": name,
        "GSR": report.percent(s.gsr),
        "TSR": report.percent(s.tsr),
        "GA": s.ga,
        "unfinished (stage1/stage2/memory/cap)": causes_of(ends),
        "objects left (stage1/stage2/memory/cap)": causes_of(left),
        "failed grasps": ", ".join(f"{k} {v}" for k, v in failed.most_common()) or "-",
        "candidates per plan": f"{np.mean(n_cand):.0f}" if n_cand else "-",
        "plan s/grasp": f"{np.mean(plan_s):.2f}" if plan_s else "-",
    }


def markdown(rows: list[dict]) -> str:
    return report.markdown_table(list(rows[0]), [list(r.values()) for r in rows])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--setting", default="seen-10")
    parser.add_argument("--scenes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--objects", help="object set or mesh folder instead of the setting's")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", default="filter_ablation_out")
    parser.add_argument("--model", help="E-RNet run directory (default: the shipped checkpoint)")
    parser.add_argument("--judge", help="a second E-RNet run directory that makes the robust choice (Planner(judge=))")
    parser.add_argument("--method", default="supergrasp", choices=["supergrasp", "supergrasp-norefine"])
    parser.add_argument("--reuse", help="for the variants that add a second plan to the default filters (default, "
                        "fallback-*): the output folder of a run without it (the no-fallback variant, or `sgjax "
                        "declutter` of a planner without one; same setting, seed, model); its scenes that did not "
                        "end for want of a grasp are taken from there, since a second plan cannot change them")
    args = parser.parse_args()

    rows = []
    for name in args.variants:
        options = {"model": args.model, "config": variant_config(name), **({"judge": args.judge} if args.judge else {})}
        method = make_method(args.method, **options)
        if args.reuse and differs_only_by_fallback(name):
            copied = reuse_unaffected(args.reuse, f"{args.out}/{name}", args.setting, args.scenes, args.seed,
                                      args.objects, options, method)
            print(f"{name}: {copied} scenes taken from {args.reuse}", flush=True)
        result = run_benchmark(method, setting=args.setting, scenes=args.scenes, seed=args.seed,
                               out=f"{args.out}/{name}", objects=args.objects, method_options=options, pictures=0)
        rows.append(summary_row(name, result))
        print(markdown(rows[-1:]), flush=True)
    print(f"\n{args.setting}, N = {args.scenes}, seed {args.seed}:\n")
    print(markdown(rows))


if __name__ == "__main__":
    main()
