"""How a grasp trial ended (`envs.rollout`'s judge decides it; see that module for each case).

Its own module, without MuJoCo: labels, datasets and the training judgement name outcomes on machines
that train but do not simulate (e.g. a GPU box without the simulator installed).
"""

from __future__ import annotations

import enum


class Outcome(enum.IntEnum):
    SUCCESS = 0
    COLLISION_PREGRASP = 1
    COLLISION_APPROACH = 2
    DROPPED_LIFT = 3
    DROPPED_REORIENT = 4
    DROPPED_DISTURBANCE = 5
    INVALID = 6
