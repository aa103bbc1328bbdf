"""Checks of a scene, for its author: `physgrad check [-cd DIR] task=NAME [key=value ...]` runs them
on any scene (built-in or a user's own), and a scene's own tests can call them (they ship in the
package).

Every check runs in float64 on the scene as configured (a few samples of its training data and its
initial network):

- builds: the scene builds and its loss and data pass the runner's checks;
- finite: the physical output, the loss and the held-out evaluation are finite at initialisation,
  and the losses are not negative (physgrad compare decides by ratios of losses);
- deterministic: the same seed gives the same data, network, batch and loss;
- rollout (temporal scenes): the lax.scan rollout equals a plain Python loop of the same step and
  policy;
- gradient <mode>: the gradient of each backprop mode that applies (R; M and S for a closed loop)
  equals the plain loop's (the mode's stopped inputs there are the forward states as constants)
  and central finite differences of that loop along random directions;
- jacobian (every scene, closed loops included: Gauss-Newton and HIG apply there through the
  regular gradient's Jacobian): J v and J^T u of the Jacobian pass against jax.jvp and jax.vjp of
  the batch output, and its gradient J^T g against jax.grad.
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from physgrad.configs import check_overrides, compose
from physgrad.errors import UserError, innermost_cause
from physgrad.experiment import build_seeds
from physgrad.job_spec import checked
from physgrad.loop_reference import loop_output, relative_error
from physgrad.members import set_precision
from physgrad.refusals import check_scene_values
from physgrad.scene_derivatives import (
    Check,
    batch_loss,
    batch_size,
    gradient_check,
    jacobian_check,
    sample_of,
    tighter_scene,
)

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from physgrad.job_spec import JobSpec
    from physgrad.nets import Params, Pytree
    from physgrad.tasks import Scene
    from physgrad.training import Seeds

BATCH = 3  # training samples the checks use
PRECISION_STEPS = 3  # plain gradient steps the precision check takes in the runs' precision
PRECISION_RATE = 1e-3  # their rate: small, so that the steps test the arithmetic, not the rate
EXACT_RTOL = 1e-9  # two exact computations of the same value (scan against loop, J v against jvp)


def check_scene(cfg: DictConfig) -> list[Check]:
    """Every check above on the scene of a composed config (precision is set to 64 here); an
    exception in the scene's code is a failed check with its one-line message."""
    try:
        return _check_scene(cfg)
    except Exception as error:  # noqa: BLE001
        return [
            Check(
                "runs",
                False,
                f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}",
            )
        ]


def _check_scene(cfg: DictConfig) -> list[Check]:
    set_precision(64)
    name = str(cfg.task.get("name", "?"))
    try:
        spec = checked(cfg)
        scene, seeds = build_seeds(spec, [spec.seed], 1)
        check_scene_values(scene, seeds, name)
    except UserError as error:
        return [Check("builds", False, str(error))]
    checks = [Check("builds", True, f"task={name} in float64")]
    params = seeds.network()
    batch = scene.sample_train(jax.random.PRNGKey(1), min(BATCH, scene.train_size or BATCH))
    y = scene.batch_output(params, batch)
    loss = batch_loss(scene, scene.sample_output, batch)(params)
    checks.append(_finite_check(scene, seeds, params, y, loss))
    checks.append(_deterministic_check(spec, scene, seeds, params, batch, loss))
    if scene.dynamics is not None:
        checks.append(_rollout_check(scene, params, batch, y))
    else:
        why = "the scene steps no dynamics (Scene.dynamics is None): nothing is unrolled"
        checks.append(Check("rollout", None, f"not checked: {why}"))
    tighter = functools.cache(lambda: tighter_scene(spec))
    for mode in ["R", "M", "S"] if scene.closed_loop else ["R"]:
        checks.append(gradient_check(scene, params, batch, mode, tighter))
    if not scene.closed_loop:
        why = "an open-loop scene: gradient stopping (M, S, C) applies to closed loops only"
        checks.append(Check("gradient M and S", None, f"not checked: {why}"))
    # every scene, closed loops included: Gauss-Newton and HIG apply there too (through the
    # regular gradient's Jacobian), so a check that said nothing of them would be a silent skip
    try:
        checks.append(jacobian_check(scene, params, batch))
    except Exception as error:  # noqa: BLE001 - a scene's code failing under jvp/vjp is a finding
        checks.append(
            Check("jacobian", False, f"{type(error).__name__}: {str(error).splitlines()[0]}")
        )
    return [*checks, _precision_check(spec)]


def _precision_check(spec: JobSpec) -> Check:
    """The scene in the precision its runs use (`precision`, float32 by default; the checks above
    run in float64): built, its data generated, PRECISION_STEPS plain gradient steps taken on a
    minibatch, and the held-out evaluation, each finite. A scene that works in float64 only (a
    solver's save times past its end in float32 round-off, a tolerance float32 cannot meet) fails
    here in one line that names precision=64, not in a study's first job."""
    bits = spec.precision
    if bits == 64:
        return Check("precision", True, "the runs use float64, as the checks above")
    set_precision(bits)
    try:
        scene, seeds = build_seeds(spec, [spec.seed], 1)
        params = seeds.network()
        batch = scene.sample_train(jax.random.PRNGKey(1), min(BATCH, scene.train_size or BATCH))
        value_and_grad = jax.jit(jax.value_and_grad(batch_loss(scene, scene.sample_output, batch)))
        losses = []
        for _ in range(PRECISION_STEPS):
            loss, gradient = value_and_grad(params)
            losses.append(float(loss))
            params = jax.tree_util.tree_map(lambda p, g: p - PRECISION_RATE * g, params, gradient)
        test_set = jax.tree_util.tree_map(lambda leaf: leaf[0], seeds.test_sets)
        held_out = float(scene.evaluate(params, test_set)["loss"])
    except Exception as error:  # noqa: BLE001 - the scene's code failing in this precision is the finding
        return Check(
            "precision",
            False,
            f"float{bits}: {innermost_cause(error)}; the checks above passed in float64: run "
            "with precision=64, or make the scene work in float32",
        )
    finally:
        set_precision(64)
    finite = all(math.isfinite(v) for v in [*losses, held_out])
    found = (
        f"float{bits}: built, {PRECISION_STEPS} gradient steps (loss {losses[0]:.6g} -> "
        f"{losses[-1]:.6g}) and the held-out loss {held_out:.6g}"
    )
    if not finite:
        found += " not all finite: run with precision=64, or make the scene work in float32"
    return Check("precision", finite, found)


def _finite_check(
    scene: Scene, seeds: Seeds, params: Params, y: jax.Array, loss: jax.Array
) -> Check:
    """The output, the loss and the held-out evaluation are finite at initialisation."""
    test_set = jax.tree_util.tree_map(lambda leaf: leaf[0], seeds.test_sets)
    evaluation = scene.evaluate(params, test_set)
    bad = [
        what
        for what, value in (("output", y), ("loss", loss), *evaluation.items())
        if not bool(jnp.all(jnp.isfinite(value)))
    ]
    negative = [
        f"{what} {float(value):.6g}"
        for what, value in (("loss", loss), ("held-out loss", evaluation["loss"]))
        if not bad and float(value) < 0
    ]
    if bad:
        found = f"not finite at initialisation: {', '.join(bad)}"
    elif negative:
        found = (
            f"negative at initialisation: {', '.join(negative)}; physgrad compare decides by "
            "ratios of losses, so give the scene a loss of at least 0 (subtract its lower bound)"
        )
    else:
        found = (
            f"output {tuple(y.shape)}, loss {float(loss):.6g}, held-out loss "
            f"{float(evaluation['loss']):.6g}"
        )
    return Check("finite", not bad and not negative, found)


def _deterministic_check(
    spec: JobSpec, scene: Scene, seeds: Seeds, params: Params, batch: Pytree, loss: jax.Array
) -> Check:
    """The scene built again from the same seed gives the same data, network, batch and loss."""

    again, seeds_again = build_seeds(spec, [spec.seed], 1)
    batch_again = again.sample_train(jax.random.PRNGKey(1), min(BATCH, again.train_size or BATCH))
    differences = {
        what: relative_error(a, b)
        for what, a, b in (
            ("test set", seeds_again.test_sets, seeds.test_sets),
            ("network", seeds_again.params, seeds.params),
            ("batch", batch_again, batch),
            ("loss", batch_loss(scene, again.sample_output, batch)(params), loss),
        )
    }
    differing = [what for what, error in differences.items() if error != 0.0]
    return Check(
        "deterministic",
        not differing,
        "the same seed gives another " + ", ".join(differing)
        if differing
        else "data, network, batch and loss identical from the same seed",
    )


def _rollout_check(scene: Scene, params: Params, batch: Pytree, y: jax.Array) -> Check:
    """A temporal scene's lax.scan rollout against a plain Python loop."""
    looped = jnp.stack(
        [loop_output(scene.dynamics, params, sample_of(batch, i)) for i in range(batch_size(batch))]
    )
    error = relative_error(y, looped)
    return Check(
        "rollout",
        error <= EXACT_RTOL,
        f"scan against a Python loop over {scene.unroll} steps: "
        f"relative difference {error:.1e} (at most {EXACT_RTOL:.0e})",
    )


def check_one_scene(overrides: list[str], config_dirs: list[str]) -> int:
    """`physgrad check [-cd DIR] task=NAME [key=value ...]`: check_scene's checks of that scene, one
    line each; 1 if one fails, 2 for a configuration mistake."""
    import os
    import sys

    if (
        os.getcwd() not in sys.path
    ):  # a scene named by _target_ may live in the folder the command runs from
        sys.path.append(os.getcwd())
    try:
        if not any(o.split("=", 1)[0].lstrip("+") == "task" for o in overrides):
            raise UserError(
                "name the scene to check: physgrad check [-cd DIR] task=NAME [key=value ...]"
            )
        check_overrides(overrides, multirun=False, config_dirs=config_dirs)
        cfg = compose(overrides, config_dirs)
    except UserError as error:
        print(f"physgrad: error: {error}", file=sys.stderr)
        return 2
    checks = check_scene(cfg)
    for check in checks:
        print(check.line())
    failed = [check.name for check in checks if check.passed is False]
    skipped = [check.name for check in checks if check.passed is None]
    ran = len(checks) - len(skipped)
    print(
        f"task={cfg.task.get('name')}: {ran - len(failed)} of {ran} checks passed"
        + (f"; failed: {', '.join(failed)}" if failed else "")
        + (f"; not checked (see above): {', '.join(skipped)}" if skipped else "")
    )
    return 1 if failed else 0
