"""The guard of the training loop: after every step, each seed's logged scalars are checked for NaN
or infinity in a guarded quantity, and its loss for a blow-up past trainer.divergence_factor times
the first step's; a seed that fails a check ends diverged, with the reason in one line."""

from __future__ import annotations

import math

from physgrad.writers import SeedRun

# checked for NaN/Inf after every step, in causal order: the physical output (the simulated state or
# what is read out of it: a blow-up of the physics shows here first), the loss, the gradient, the
# update; the first non-finite one is the reason
GUARDED = ("output_max_abs", "loss", "grad_norm", "update_norm")
QUANTITY = {
    "output_max_abs": "output",
    "loss": "loss",
    "grad_norm": "gradient",
    "update_norm": "update",
}


def divergence_reason(quantity: str, logs: dict, iteration: int, svd_failures_before: float) -> str:
    """One line: which quantity went non-finite first, its value, the iteration, and a failed
    factorisation if that is what happened at this step."""
    reason = f"{QUANTITY[quantity]} became {logs[quantity]} at iteration {iteration} ({quantity})"
    if logs.get("svd_failures", 0.0) > svd_failures_before:
        reason += (
            "; the SVD/eigh of the Jacobian did not converge (optim.retry_float64=true retries it "
            "in float64, precision=64 runs everything in float64)"
        )
    return reason


def blew_up(loss: float, first_loss: float | None, factor: float | None) -> bool:
    """A finite training loss past factor times the first step's (a blow-up that has not reached NaN
    yet); never when the first loss is 0 or the bound is off (factor None)."""
    return (
        factor is not None
        and first_loss is not None
        and first_loss > 0
        and loss > factor * first_loss
    )


class RowGuard:
    """The check of one seed's logged scalars after a step: NaN/Inf in a GUARDED quantity, or a
    finite loss past trainer.divergence_factor times the first step's (a blow-up without NaN)."""

    def __init__(self, log_names: list[str], divergence_factor: float | None) -> None:
        self.names, self.factor = log_names, divergence_factor
        self.guarded = [log_names.index(name) for name in GUARDED]
        self.loss_at = log_names.index("loss")
        self.svd_at = log_names.index("svd_failures") if "svd_failures" in log_names else None

    def check(self, run: SeedRun, row: list, iteration: int) -> str | None:
        """Why the seed diverged at this step, or None; keeps the seed's first loss (the blow-up
        bound's scale) and its count of failed factorisations (to name a new one in a later
        reason)."""
        bad = next((self.names[i] for i in self.guarded if not math.isfinite(row[i])), None)
        if run.first_loss is None:
            run.first_loss = row[self.loss_at]
        if bad is not None:
            return divergence_reason(bad, dict(zip(self.names, row)), iteration, run.svd_failures)
        if blew_up(row[self.loss_at], run.first_loss, self.factor):
            return (
                f"loss grew to {row[self.loss_at]:.4g} at iteration {iteration}, more than "
                f"trainer.divergence_factor={self.factor:g} times its first value "
                f"{run.first_loss:.4g} (a blow-up without NaN)"
            )
        if self.svd_at is not None:
            run.svd_failures = row[self.svd_at]
        return None
