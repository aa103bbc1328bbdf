"""The `trainer` section of a run's config, checked once into typed settings: when a run stops
(iterations, a time budget on the measured or the calibrated clock), evaluates, writes and logs, and
what the calibrated clock charges a step."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from physgrad.errors import UserError
from physgrad.readout import DIVERGENCE_FACTOR
from physgrad.validate import choice, number

if TYPE_CHECKING:
    from physgrad.optim.capabilities import ScheduledUpdate

DEFAULT_ITERATIONS = 2000  # trainer.iterations=null without a time budget
CLOCKS = ("measured", "calibrated")
# trainer.eval_seconds=null with a time budget: an evaluation every budget / 20
EVALUATIONS_PER_BUDGET = 20
MIN_STEP_COST = 1e-6  # seconds: the calibrated clock's floor (trainer.step_cost, calibration.json)


@dataclass(frozen=True)
class TrainerSettings:
    """The `trainer` config section: when to stop, evaluate, write and log. iterations is None for
    no limit (a time budget alone ends the run); eval_seconds None for evaluations by iteration
    only."""

    iterations: int | None
    time_budget: float | None
    eval_every: int
    eval_seconds: float | None
    batch_size: int
    flush_seconds: float
    log_seconds: float
    divergence_factor: float | None = DIVERGENCE_FACTOR
    # seconds per step from a calibration (physgrad.calibration), or None
    step_cost: float | None = None
    # which clock the time budget and eval_seconds read: measured | calibrated
    clock: str = "measured"
    # the part of step_cost a scheduled update costs (physgrad.optim.capabilities.ScheduledUpdate),
    # and that schedule (set by physgrad.refusals.check_config from the optim config), or None
    update_cost: float | None = None
    scheduled_update: ScheduledUpdate | None = field(default=None, compare=False)
    # a line-search rule's cost of one evaluation (a value and gradient of the batch loss) and the
    # evaluations per step step_cost holds (their mean in the calibration's steps), or None
    evaluation_cost: float | None = None
    step_evaluations: float | None = None

    @classmethod
    def from_config(cls, trainer_cfg: Mapping) -> TrainerSettings:
        """trainer.iterations=null means 2000 without a time budget and no limit with one;
        trainer.eval_seconds= null means time_budget / 20 with a budget (so that a slow variant
        still gets a curve) and none without."""
        # a budget below the calibrated clock's floor is no step of any rule: a mistake, not a run
        budget = number(
            "trainer.time_budget", trainer_cfg.get("time_budget"), MIN_STEP_COST, optional=True
        )
        iterations = number(
            "trainer.iterations", trainer_cfg.get("iterations"), 1, integer=True, optional=True
        )
        eval_seconds = number(
            "trainer.eval_seconds", trainer_cfg.get("eval_seconds"), 0, optional=True, open_low=True
        )
        # a training step faster than a microsecond is no step: such a cost would never end a
        # time budget
        step_cost = number(
            "trainer.step_cost", trainer_cfg.get("step_cost"), MIN_STEP_COST, 3600.0, optional=True
        )
        clock = choice("trainer.clock", trainer_cfg.get("clock", "measured"), CLOCKS)
        if clock == "calibrated" and step_cost is None:
            raise UserError(
                "trainer.clock=calibrated needs trainer.step_cost (seconds per step from a "
                "calibration: physgrad compare measures it) or trainer.clock=measured"
            )
        update_cost = number(
            "trainer.update_cost", trainer_cfg.get("update_cost"), 0, 3600.0, optional=True
        )
        if update_cost is not None and (step_cost is None or update_cost > step_cost):
            raise UserError(
                f"trainer.update_cost={update_cost:g} is the part of trainer.step_cost a scheduled "
                "update costs: give it with a step_cost at least as large, or leave it out (null)"
            )
        evaluation_cost, step_evaluations = line_search_costs(trainer_cfg, step_cost)
        if iterations is None and budget is None:
            iterations = DEFAULT_ITERATIONS
        if eval_seconds is None and budget is not None:
            eval_seconds = budget / EVALUATIONS_PER_BUDGET
        return cls(
            iterations=iterations,
            time_budget=budget,
            eval_every=number("trainer.eval_every", trainer_cfg.get("eval_every"), 1, integer=True),
            eval_seconds=eval_seconds,
            batch_size=number("trainer.batch_size", trainer_cfg.get("batch_size"), 1, integer=True),
            flush_seconds=number(
                "trainer.flush_seconds", trainer_cfg.get("flush_seconds"), 0, open_low=True
            ),
            log_seconds=number(
                "trainer.log_seconds", trainer_cfg.get("log_seconds", 30.0), 0, open_low=True
            ),
            divergence_factor=number(
                "trainer.divergence_factor",
                trainer_cfg.get("divergence_factor", DIVERGENCE_FACTOR),
                1,
                optional=True,
                open_low=True,
            ),
            step_cost=step_cost,
            clock=clock,
            update_cost=update_cost,
            evaluation_cost=evaluation_cost,
            step_evaluations=step_evaluations,
        )

    def charged_seconds(self, iterations: int, evaluations: float = 0.0) -> float:
        """The calibrated clock's time after `iterations` steps: iterations x step_cost s; with a
        line search whose evaluations cost v each, s holding e of them per step on average, the
        steps' own part and the E = `evaluations` they made,

            charged = iterations (s - v e) + v E;

        with a scheduled update of cost u, what the steps cost on average
        (ScheduledUpdate.charged_seconds: the steps that skip the update are charged s - u)."""
        if self.evaluation_cost is not None:
            own = self.step_cost - self.evaluation_cost * self.step_evaluations
            return iterations * own + self.evaluation_cost * evaluations
        if self.update_cost is None:
            return iterations * self.step_cost
        if self.scheduled_update is None:  # check_config attaches it, or refuses the run
            raise ValueError("trainer.update_cost without the rule's schedule")
        return self.scheduled_update.charged_seconds(iterations, self.step_cost, self.update_cost)


def line_search_costs(trainer_cfg: Mapping, step_cost: float | None) -> tuple:
    """trainer.evaluation_cost v (seconds of one line-search evaluation) and
    trainer.step_evaluations e (the evaluations per step within trainer.step_cost), both given or
    neither, with v e <= step_cost; (None, None) where neither is given."""
    cost = number(
        "trainer.evaluation_cost", trainer_cfg.get("evaluation_cost"), 0, 3600.0, optional=True
    )
    mean = number(
        "trainer.step_evaluations", trainer_cfg.get("step_evaluations"), 0, 1e6, optional=True
    )
    if cost is None and mean is None:
        return None, None
    if cost is None or mean is None or step_cost is None:
        raise UserError(
            "trainer.evaluation_cost and trainer.step_evaluations charge a line search's "
            "evaluations: give both with trainer.step_cost (a calibration does), or neither"
        )
    if cost * mean > step_cost * (1 + 1e-9):
        raise UserError(
            f"trainer.evaluation_cost={cost:g} x trainer.step_evaluations={mean:g} is more than "
            f"trainer.step_cost={step_cost:g}, which holds them: give a calibration's values"
        )
    return cost, mean
