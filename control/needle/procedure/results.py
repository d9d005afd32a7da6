"""What a needle procedure step answers: the steps' order, a step's result, the failure
that ends a step, and the Monte Carlo's success rates over many trials' results."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

#: The steps in their order (seed 002 §IV.B, Table I).
STEPS = ("NG", "NH", "ND", "NR", "NP")


@dataclass
class StepResult:
    """One step's outcome.

    ``ok``: the procedure's own verdict (what it saw); ``refused``: it stopped before
    moving toward the needle; ``cause``: a short code when not ok (``refused_*`` for
    refusals, e.g. ``refused_not_converged``, ``refused_out_of_reach``,
    ``refused_bad_suture``; ``grasp_missed``, ``move_stopped``, ``lost_track`` ...),
    ``detail`` the sentence; ``figures``: what was measured (mm, deg); ``truth_ok`` /
    ``truth_detail``: the check against the cell's ground truth (``None`` without a
    ``truth_check``); ``seconds``: wall time of the step.
    """

    step: str
    ok: bool
    refused: bool = False
    cause: str = ""
    detail: str = ""
    figures: dict[str, Any] = field(default_factory=dict)
    truth_ok: bool | None = None
    truth_detail: str = ""
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


class StepFailed(Exception):
    """Raised inside a step: ends it with ``cause`` and the message."""

    def __init__(self, cause: str, detail: str, refused: bool = False) -> None:
        super().__init__(detail)
        self.cause, self.detail, self.refused = cause, detail, refused


def _refuse(cause: str, detail: str) -> StepFailed:
    """A refusal (``refused_<cause>``): the step stopped before moving toward the needle."""
    return StepFailed(f"refused_{cause}", detail, refused=True)


def step_rates(outcomes: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Table I/II figures from per-trial outcomes (``{"steps": {step: truth_ok or None}}``):
    overall rates (a step not reached counts as failed) and individual rates (of the
    trials that reached the step)."""
    n = len(outcomes)
    overall, individual = {}, {}
    for st in STEPS:
        ok = sum(1 for o in outcomes if o["steps"].get(st) is True)
        reached = sum(1 for o in outcomes if o["steps"].get(st) is not None)
        overall[st] = ok / n if n else 0.0
        individual[st] = ok / reached if reached else None
    done = sum(1 for o in outcomes if all(o["steps"].get(st) is True for st in STEPS))
    return {"trials": n, "overall": done / n if n else 0.0, "steps": overall,
            "individual": individual}
