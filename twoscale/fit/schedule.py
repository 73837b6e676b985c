"""The fit's schedule: coarse-to-fine stages of random cell subsamples (docs/model.md §8)."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of the schedule.

    Attributes:
        n_cells: cells fitted (a uniform random subsample of the fitted cells; None = all).
        keep: how many of the best solutions go on to the next stage (per material type).
        max_steps: solver steps allowed per start: a safety net, not the usual end (see
            ``round_steps``).
        round_steps: the solver runs in rounds of this many steps (the first step of a round
            evaluates its starting point; at least 2); a start has converged when
            the solver's own tests say so, or when a round lowers the RMS by less than
            :func:`~twoscale.fit.solver.stall_rtol` (relative; 1e-4, or less than a tenth of
            the subsample's own resolution ``1/√m`` on ``m`` residuals where that is larger):
            further steps would not change the fit, or not measurably on these cells.
    """

    n_cells: int | None
    keep: int
    max_steps: int
    round_steps: int = 10

    def __post_init__(self):
        if self.max_steps < 1 or self.round_steps < 1 or self.keep < 1:
            raise ValueError(f"Stage needs keep, max_steps, round_steps ≥ 1, got {self}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: Default: every start on ≈ 4 096 cells, the best 2 (per material type) on ≈ 32 768, the best
#: one on 262 144 (rounds of 5 steps there: each step is a pass over those cells). Refining on
#: all ≈ 1.1 M valid cells instead ("full") changed the log RMSE on all cells by < 1e-4 on the
#: stand-ins measured (campaigns/RESULTS.md) at 4× the cost of that stage.
#:
#: The last stage's cap, :data:`LAST_STAGE_MAX_STEPS`, is a safety net: its rounds end a start
#: once the RMS stops falling. It was 25, which every fit of the 60 stand-ins ends below, but
#: which cut two held-out mixtures while their RMS was still falling by 0.05–4 % per round
#: (white-fabric + pvc and black-oxidized-steel + specular-yellow-phenolic, campaigns/MIXTURES.md:
#: converged after 75 and 35 steps instead, log RMSE 2 % and 3 % lower, ≈ 0.2 s a step).
LAST_STAGE_MAX_STEPS = 100
DEFAULT_SCHEDULE = (
    Stage(n_cells=4096, keep=2, max_steps=60),
    Stage(n_cells=32768, keep=1, max_steps=60),
    Stage(n_cells=262144, keep=1, max_steps=LAST_STAGE_MAX_STEPS, round_steps=5),
)


#: Preview: the same without the last refinement (errors still reported on all valid cells),
#: and only the best start per material type on from the first stage: the second start nearly
#: always reached the same minimum (on 9 stand-ins, 2026-12-04, the same type and log RMSE to
#: 5 digits with one as with two; in process, warm, up to 2.3 s less per fit, median 0.9 s).
PREVIEW_SCHEDULE = (dataclasses.replace(DEFAULT_SCHEDULE[0], keep=1), DEFAULT_SCHEDULE[1])


#: Full: the last refinement on every fitted cell.
FULL_SCHEDULE = DEFAULT_SCHEDULE[:2] + (dataclasses.replace(DEFAULT_SCHEDULE[2], n_cells=None),)


SCHEDULES = {"default": DEFAULT_SCHEDULE, "preview": PREVIEW_SCHEDULE, "full": FULL_SCHEDULE}


def resolve_schedule(schedule) -> tuple[Stage, ...]:
    if isinstance(schedule, str):
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {tuple(SCHEDULES)} or a list of Stage")
        return SCHEDULES[schedule]
    stages = tuple(schedule)
    if not stages or not all(isinstance(s, Stage) for s in stages):
        raise ValueError("schedule must be a non-empty sequence of Stage")
    return stages
