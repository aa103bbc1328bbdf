"""Every update rule of conf/optim/ through one contract, as optax's alias tests hold optimisers:
built from its YAML as `physgrad run` builds it (physgrad.experiment.prepare, then the step that
physgrad.training.compile_training compiles ahead of time), a few hundred updates on a small linear
least-squares problem lower the held-out loss (the extras a rule takes, such as the Jacobian,
value_fn or the network's layers, are accepted). No retrace per update: an ahead-of-time compiled
step takes only the shapes and dtypes it was compiled for, so a rule whose state changes either
from one update to the next (what makes jit trace again) fails here. No files, no runner."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.experiment import prepare
from physgrad.job_spec import checked
from physgrad.nets import apply_mlp, init_mlp
from physgrad.optim.capabilities import capabilities
from physgrad.tasks import Scene
from physgrad.training import compile_training
from tests.helpers import REPO, load

RULES = sorted(path.stem for path in (REPO / "conf" / "optim").glob("*.yaml"))
INPUTS, OUTPUTS = 4, 3


def least_squares(key, **unused) -> Scene:
    """y = W x through the identity "physics", target A x with x ~ N(0, I): the loss 1/2 |W x - A
    x|^2 has the unique minimum W = A, reached in one Gauss-Newton step."""
    truth = 0.3 * jax.random.normal(jax.random.PRNGKey(7), (INPUTS, OUTPUTS))

    def make(k, count):
        x = jax.random.normal(k, (count, INPUTS))
        return {"x": x, "target": x @ truth}

    def sample_output(params, sample):
        return apply_mlp(params, sample["x"], hidden="tanh")

    return Scene(
        init_params=lambda k: init_mlp(k, [INPUTS, OUTPUTS], jnp.zeros(()).dtype),
        sample_loss=lambda y, sample: 0.5 * jnp.sum((y - sample["target"]) ** 2),
        test_set=make(key, 64),
        sample_output=sample_output,
        draw_batch=lambda k, count, train_set: make(k, count),
    )


def config(rule: str):
    # a rule with a backprop mode (bptt, stable_bptt) is Adam on a gradient pass through time: its
    # update rule is held to the contract on this scene without time, the route dropped
    optim = load("task=toy", f"optim={rule}").optim
    route = ["optim.backprop=null"] if optim.get("backprop") else []
    # Adam's preset step (1e-3) needs about a thousand steps from the network's initial weights to
    # the optimum; a rate ten times larger, inside its tuning range, needs two hundred
    rate = ["optim.learning_rate=1e-2"] if optim.get("learning_rate") == 1e-3 else []
    return load(
        "task=toy",
        f"optim={rule}",
        "task._target_=tests.numerics.test_rule_contract.least_squares",
        "trainer.batch_size=32",
        *route,
        *rate,
    )


@pytest.mark.parametrize("rule", RULES)
def test_every_rule_trains_a_least_squares_problem_in_its_compiled_step(rule):
    cfg = config(rule)
    spec = checked(cfg)
    settings = spec.trainer
    scene, update_rule, seeds = prepare(spec, [0])
    compiled = compile_training(scene, update_rule, seeds, settings.batch_size)
    params, state = compiled.params, compiled.opt_state
    first = float(compiled.evaluate(params, seeds.test_sets)["loss"][0])
    for iteration in range(200):
        params, state, logs = compiled.step(
            params, state, np.int32(iteration), seeds.train_keys, seeds.train_sets
        )
    last = float(compiled.evaluate(params, seeds.test_sets)["loss"][0])
    assert np.isfinite(np.asarray(logs)).all(), (rule, logs)
    assert last < 0.5 * first, (rule, first, last)
    assert update_rule.uses_jacobian == capabilities(cfg.optim).needs_jacobian, rule
