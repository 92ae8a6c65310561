"""How repeatable labelled outcomes are: a labelled directory's grasps replayed on their rebuilt scenes,
at the recorded pose and moved by a millimetre or a degree (`benchmarks/label_repeatability.py`).

Every scene of a labelling run depends only on its config, objects and index (`train.label.labelled_scene`),
so its grasps can be run again. Two questions, per candidate source:
  - same pose: does the replay give the recorded outcome (the simulator's determinism across runs
    and machines; anything below 100 % is a bug);
  - moved: with the pose moved by `shift` metres in a random direction and turned by `turn_deg` degrees
    about a random axis through the closing region's centre (`train.sources.perturb`), how often does
    a successful grasp stay successful and a failed one failed. A scorer cannot be surer of a label
    than the label is of a pose a millimetre away: this bounds what the judgement metrics
    (`sgjax score-data`, e.g. the top-scored grasp's success) can reach.
"""

from __future__ import annotations

import os

import numpy as np

from envs.outcome import Outcome
from envs.trial import run_trials
from train import dataset, sources
from train.label import labelled_scene, prepare_objects, read_config


def replay_directory(directory: str, scenes: tuple[int, int] | None = None, source_names: tuple[str, ...] = ("stage1",),
                     moves: int = 4, shift: float = 0.001, turn_deg: float = 1.0, seed: int = 0,
                     progress: bool = True) -> dict[str, np.ndarray]:
    """Replay the valid samples of `source_names` in scenes [first, last) of a labelled directory.

    -> columns over those samples [S]: scene_seed, source, label, outcome (recorded), replayed (the
    outcome at the recorded pose), moved [S, moves] (outcomes of the moved poses)."""
    if moves < 0 or shift < 0 or turn_deg < 0:
        raise ValueError(f"moves, shift and turn must be >= 0, got {moves}, {shift}, {turn_deg}")
    config = read_config(directory)
    codes = [sources.source_index(name) for name in source_names]
    objects, _ = prepare_objects(config, progress=False)
    rng = np.random.default_rng(seed)
    ranges = sources.Perturbation(translation=(shift, shift), angle_deg=(turn_deg, turn_deg))
    columns: dict[str, list] = {k: [] for k in ("scene_seed", "source", "label", "outcome", "replayed", "moved")}
    paths = dataset.shard_paths(directory)
    if not paths:
        raise dataset.DatasetError(f"{directory}: no label shards")
    for path in paths:
        samples, _ = dataset.read_label_shard(path)
        for index in np.unique(samples["scene_index"]):
            if scenes is not None and not scenes[0] <= index < scenes[1]:
                continue
            rows = np.flatnonzero((samples["scene_index"] == index) & samples["valid"] & np.isin(samples["source"], codes))
            if not len(rows):
                continue
            scene, _ = labelled_scene(int(index), objects, config)
            names = [a.name for a in scene.assets]
            targets = np.array([names.index(str(n)) for n in samples["object_name"][rows]])
            poses = samples["pose"][rows].astype(np.float64)
            tried = np.concatenate([poses] + [sources.perturb(poses, rng, config.spec, ranges) for _ in range(moves)])
            result = run_trials(scene, np.tile(targets, moves + 1), tried, np.tile(samples["width"][rows], moves + 1),
                                config=config.trial)
            outcome = result.outcome.reshape(moves + 1, len(rows)).T
            for key in ("scene_seed", "source", "label", "outcome"):
                columns[key].append(samples[key][rows])
            columns["replayed"].append(outcome[:, 0])
            columns["moved"].append(outcome[:, 1:])
        if progress:
            print(f"{os.path.basename(path)}: {sum(len(c) for c in columns['label'])} samples", flush=True)
    if not columns["label"]:
        raise dataset.DatasetError(f"{directory}: no valid samples of {list(source_names)} in the chosen scenes")
    return {k: np.concatenate(v) for k, v in columns.items()}


def table(replayed: dict[str, np.ndarray], moves: int, shift: float, turn_deg: float) -> str:
    """The markdown report of `replay_directory`'s columns."""
    ok = replayed["moved"] == Outcome.SUCCESS
    label = replayed["label"].astype(bool)
    lines = [f"Moved: {shift * 1000:g} mm and {turn_deg:g} deg, {moves} moves per sample.", "",
             "| source | samples | positive | same pose reproduces | positives stay successful | negatives stay failed |",
             "|---|---:|---:|---:|---:|---:|"]

    def pct(x):
        return "–" if x.size == 0 else f"{100 * x.mean():.1f} %"

    for code in np.unique(replayed["source"]):
        rows = replayed["source"] == code
        lines.append(f"| {sources.SOURCES[code]} | {rows.sum()} | {pct(label[rows])} | "
                     f"{pct(replayed['replayed'][rows] == replayed['outcome'][rows])} | "
                     f"{pct(ok[rows & label])} | {pct(~ok[rows & ~label])} |")
    stage1 = replayed["source"] == sources.source_index("stage1")
    if stage1.any() and moves:
        seeds = replayed["scene_seed"][stage1]
        robust = ok[stage1].all(1)
        ids = np.unique(seeds)
        some_label = np.mean([label[stage1][seeds == s].any() for s in ids])
        some_robust = np.mean([robust[seeds == s].any() for s in ids])
        lines += ["", f"Scenes: {len(ids)}; some Stage-1 grasp succeeds in {100 * some_label:.1f} %, "
                      f"some succeeds under every move in {100 * some_robust:.1f} %."]
    return "\n".join(lines)
