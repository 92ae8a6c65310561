"""The sealed split: objects and benchmark seeds that no decision may touch, kept for reporting only.

Every default of this project was chosen on some scenes and objects (docs/decisions.md lists which).
Numbers reported on them flatter the method, so the headline results are run on data that no decision
has seen and none ever will:

  * `SEALED_OBJECT_SET` ("unseen-sealed"): `SEALED_COUNT` procedural objects of every kind
    (`envs.procedural`: superquadrics, blends, extrusions) drawn from a generator seed that no other
    set, test or experiment uses. Never labelled, never trained on; the unseen setting of the report.
  * `RESERVED_SEEDS`: benchmark seeds for the report only, far from every seed used so far (the seeds
    decisions were made on: docs/decisions.md).

Only the report path (`eval.report_path`, `sgjax table-i` and `table-ii`) runs them: `check_benchmark`
refuses a benchmark run on a reserved seed or the sealed set unless it is the report, and
`check_labelling` refuses to label the sealed objects or on a reserved seed at all. tests/test_sealed.py fails when any other file
of the repository names them.
"""

from __future__ import annotations

SEALED_OBJECT_SET = "unseen-sealed"
SEALED_PREFIX = "sealed"  # object names "sealed/<kind>_<index>"
SEALED_COUNT = 15  # five of each procedural kind
SEALED_GENERATOR_SEED = 4099  # the procedural family; families 0 (seen) and 1 (procedural-unseen) are in use
RESERVED_SEEDS = (1000, 1001, 1002)
REPORT_COMMAND = "sgjax table-i"


class SealedDataError(ValueError):
    """A run outside the report path named the sealed objects or a reserved seed."""


def check_benchmark(seed: int, object_set: str | None, *, report: bool = False) -> None:
    """Refuse a benchmark run on a reserved seed or the sealed objects unless it is the report's."""
    if report:
        return
    if int(seed) in RESERVED_SEEDS:
        raise SealedDataError(
            f"seed {seed} is reserved for reporting ({', '.join(map(str, RESERVED_SEEDS))}): develop on other "
            f"seeds; `{REPORT_COMMAND}` alone runs the reserved ones"
        )
    if object_set == SEALED_OBJECT_SET:
        raise SealedDataError(
            f"object set {SEALED_OBJECT_SET!r} is sealed for reporting: develop on the 'unseen' set; "
            f"`{REPORT_COMMAND}` alone runs it"
        )


def check_labelling(object_set: str, seed: int) -> None:
    """Refuse to label the sealed objects (never trained on) or scenes of a reserved seed."""
    if object_set == SEALED_OBJECT_SET:
        raise SealedDataError(f"object set {SEALED_OBJECT_SET!r} is sealed: it is never labelled or trained on")
    if int(seed) in RESERVED_SEEDS:
        raise SealedDataError(
            f"seed {seed} is reserved for reporting ({', '.join(map(str, RESERVED_SEEDS))}): label with another seed"
        )
