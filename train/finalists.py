"""Finalist labels: what a judge of the planner's finalists learns from (issue "Stage 2, part 2").

The planner's robust choice ends with a dozen near-equal candidates, its finalists, and executes the one
E-RNet scores highest on average over its own and five perturbed poses. Labelled scenes (`train.label`)
draw candidates from several sources on 5-object scenes; they rarely hold the planner's own finalists on
the states a decluttering episode meets (dense, half-cleared, after failed grasps). Replaying benchmark
scenes state by state and executing every finalist with its refinements
(`eval.counterfactual.replay_finalist_trials`, `sgjax label-finalists`) gives exactly those: this module
turns a replayed scene into a label shard (`train.dataset.write_label_shard`, source "finalist"), one
Stage-2 cloud per state, so `sgjax train --data` reads it like any labelled directory.

Beside each shard a JSON sidecar keeps, per state, the planner's scores of its finalists in shard order
(eval_prob, robust_score, chosen), so a new judge's choice can be compared offline with the executed one
(`finalist_choices`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from envs.outcome import Outcome
from train.dataset import LABEL_FIELDS, read_label_shard, write_label_shard
from train.sources import source_index
from sgjax.utils.files import atomic_write_text

SIDECAR_SUFFIX = ".states.json"


def state_seed(scene_seed: int, attempt: int) -> int:
    """The seed a finalist shard gives a state: the benchmark scene's seed and the attempt, in one int64
    (attempts stay below 1,000: a scene of n objects allows n + 5)."""
    if not 0 <= attempt < 1000:
        raise ValueError(f"attempt {attempt} outside [0, 1000)")
    return int(scene_seed) * 1000 + int(attempt)


def finalist_samples(states: Sequence, scene_seed: int, scene_index: int,
                     held_out: Sequence[str] = ()) -> tuple[dict[str, np.ndarray], list[np.ndarray]]:
    """One replayed scene's finalist trials -> (LABEL_FIELDS columns, the states' clouds).

    states: `eval.counterfactual.FinalistTrials` (attempt, cloud [C, 3], pose [M, 4, 4], width [M],
    target_name [M], outcome and label [M, 1 + K], ...); held_out: names of objects no run trains on
    (`train.label.LabelConfig.held_out_objects`). Every state is a scene of its own: its samples point at
    its own cloud (`cloud_row`) and carry its own seed (`state_seed`), so that a within-scene ranking
    loss (`sgjax train --rank-weight`) ranks one state's finalists against each other (the train /
    held-out split of `sgjax train` is then per state); scene_index is the benchmark scene's."""
    parts = []
    for row, state in enumerate(states):
        m = len(state.pose)
        names = np.array(state.target_name, dtype=str)
        outcome = np.asarray(state.outcome, np.int8)
        label = np.asarray(state.label, np.int8)
        parts.append({
            "pose": np.asarray(state.pose, np.float32), "width": np.asarray(state.width, np.float32),
            "label": label[:, 0], "refine_labels": label[:, 1:], "outcome": outcome[:, 0],
            "refine_outcomes": outcome[:, 1:], "source": np.full(m, source_index("finalist"), np.int8),
            "scene_seed": np.full(m, state_seed(scene_seed, state.attempt), np.int64),
            "scene_index": np.full(m, scene_index, np.int32),
            "cloud_row": np.full(m, row, np.int32), "object_name": names,
            "held_out_object": np.isin(names, list(held_out)),
            # An invalid trial (the simulation refused the grasp) says nothing about it.
            "valid": ~(outcome == Outcome.INVALID).any(axis=1),
        })
    if not parts:
        return {k: np.zeros((0, *f.shape), f.dtype) for k, f in LABEL_FIELDS.items()}, []
    clouds = [np.asarray(s.cloud, np.float32) for s in states]
    return {k: np.concatenate([p[k] for p in parts]) for k in LABEL_FIELDS}, clouds


def write_finalist_shard(path: str | os.PathLike, states: Sequence, scene_seed: int, scene_index: int,
                         held_out: Sequence[str] = ()) -> str | None:
    """Write one replayed scene's finalist trials as a label shard at `path` (.npz) and its sidecar
    (`SIDECAR_SUFFIX`: per state the attempt and the planner's eval_prob, robust_score and chosen of its
    finalists, in shard order), both atomically, the sidecar last (a shard without one is unfinished).
    No state: only the sidecar (an empty list), so a resumed run knows the scene is done. -> the shard's
    path, or None."""
    path = os.fspath(path)
    samples, clouds = finalist_samples(states, scene_seed, scene_index, held_out)
    written = write_label_shard(path, samples, clouds) if clouds else None
    sidecar = [{"attempt": int(s.attempt), "eval_prob": np.asarray(s.eval_prob, float).round(6).tolist(),
                "robust_score": np.asarray(s.robust_score, float).round(6).tolist(),
                "chosen": np.asarray(s.chosen, bool).tolist()} for s in states]
    atomic_write_text(sidecar_path(path), json.dumps({"scene_seed": int(scene_seed), "scene_index": int(scene_index),
                                                      "states": sidecar}))
    return written


def sidecar_path(shard: str | os.PathLike) -> str:
    """The sidecar of a finalist shard: its name with .npz replaced by SIDECAR_SUFFIX."""
    shard = os.fspath(shard)
    return (shard[: -len(".npz")] if shard.endswith(".npz") else shard) + SIDECAR_SUFFIX


class Choice(NamedTuple):
    """One state of a finalist shard judged offline: whether the executed finalist succeeded, whether the
    one a judge picks does, and whether any / all of the state's finalists do."""

    executed: bool
    picked: bool
    any: bool
    all: bool


def finalist_choices(shard: str | os.PathLike, scores: np.ndarray, samples: dict | None = None) -> list[Choice]:
    """Offline: per state of a finalist shard, a `Choice` for the finalist with the highest `scores` (one
    per sample of the shard, e.g. a new judge's). Ties go to the better robust score of the logged plan,
    then the earlier finalist. samples: the shard's columns when the caller has read them already
    (`read_label_shard`; None: read here). Raises ValueError when scores do not match the shard's samples."""
    if samples is None:
        samples, _ = read_label_shard(shard)
    with open(sidecar_path(shard)) as fh:
        states = json.load(fh)["states"]
    scores = np.asarray(scores, np.float64)
    if scores.shape != samples["label"].shape:
        raise ValueError(f"{shard}: {samples['label'].shape[0]} samples but {scores.shape} scores")
    out, start = [], 0
    for state in states:
        m = len(state["chosen"])
        label = samples["label"][start:start + m].astype(bool)
        chosen = np.asarray(state["chosen"], bool)
        executed = bool(label[chosen].any()) if chosen.any() else bool(label[int(np.argmax(state["robust_score"]))])
        key = np.lexsort((-np.arange(m), np.asarray(state["robust_score"]), scores[start:start + m]))
        out.append(Choice(executed, bool(label[key[-1]]), bool(label.any()), bool(label.all())))
        start += m
    return out
