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
        )

    def charged_seconds(self, iterations: int) -> float:
        """The calibrated clock's time after `iterations` steps: iterations x step_cost, or with a
        scheduled update of cost u, what the steps cost on average (ScheduledUpdate.charged_seconds:
        the steps that skip the update are charged step_cost - u)."""
        if self.update_cost is None:
            return iterations * self.step_cost
        if self.scheduled_update is None:  # check_config attaches it, or refuses the run
            raise ValueError("trainer.update_cost without the rule's schedule")
        return self.scheduled_update.charged_seconds(iterations, self.step_cost, self.update_cost)
