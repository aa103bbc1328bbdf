"""Every update rule of conf/optim/ through one contract, as optax's alias tests do for its
optimisers: built from its YAML and trained by the real runner on a small linear least-squares
problem, it lowers the held-out loss (the extras it takes, such as the Jacobian, value_fn or the
network's layers, are accepted), and its step is traced the same number of times however long it
trains (no retrace per iteration)."""

from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

from physgrad.experiment import run_experiment
from physgrad.nets import apply_mlp, init_mlp
from physgrad.optim.capabilities import capabilities
from physgrad.results import read_run
from physgrad.tasks import Scene
from tests.helpers import load

RULES = sorted(
    path.stem for path in (Path(__file__).resolve().parent.parent / "conf" / "optim").glob("*.yaml")
)
INPUTS, OUTPUTS = 4, 3
TRACES = {"sample_output": 0}  # Python runs a function's body once per trace


def least_squares(key, **unused) -> Scene:
    """y = W x through the identity "physics", target A x with x ~ N(0, I): the loss 1/2 |W x - A
    x|^2 has the unique minimum W = A, reached in one Gauss-Newton step."""
    truth = 0.3 * jax.random.normal(jax.random.PRNGKey(7), (INPUTS, OUTPUTS))

    def make(k, count):
        x = jax.random.normal(k, (count, INPUTS))
        return {"x": x, "target": x @ truth}

    def sample_output(params, sample):
        TRACES["sample_output"] += 1
        return apply_mlp(params, sample["x"], hidden="tanh")

    return Scene(
        init_params=lambda k: init_mlp(k, [INPUTS, OUTPUTS], jnp.zeros(()).dtype),
        sample_loss=lambda y, sample: 0.5 * jnp.sum((y - sample["target"]) ** 2),
        test_set=make(key, 64),
        sample_output=sample_output,
        draw_batch=lambda k, count, train_set: make(k, count),
    )


def train(tmp_path, rule: str, iterations: int):
    """(the run, the traces of sample_output while it was built and trained)."""
    # a rule with a backprop mode (bptt, stable_bptt) is Adam on a gradient pass through time: its
    # update rule is held to the contract on this scene without time, the route dropped
    optim = load("task=toy", f"optim={rule}").optim
    route = ["optim.backprop=null"] if optim.get("backprop") else []
    # Adam's preset step (1e-3) needs about a thousand steps from the network's initial weights to
    # the optimum; a rate ten times larger, inside its tuning range, needs two hundred
    rate = ["optim.learning_rate=1e-2"] if optim.get("learning_rate") == 1e-3 else []
    cfg = load(
        "task=toy",
        f"optim={rule}",
        "task._target_=tests.test_rule_contract.least_squares",
        f"trainer.iterations={iterations}",
        "trainer.eval_every=10",
        "trainer.batch_size=32",
        *route,
        *rate,
    )
    before = TRACES["sample_output"]
    outcome, path = run_experiment(cfg, tmp_path / f"{rule}_{iterations}")
    assert outcome.status == "completed", (rule, outcome.reason)
    return read_run(path), TRACES["sample_output"] - before


@pytest.mark.parametrize("rule", RULES)
def test_every_rule_trains_a_least_squares_problem_without_retracing(tmp_path, rule):
    short, traces_short = train(tmp_path, rule, 20)
    long, traces_long = train(tmp_path, rule, 200)
    first, last = float(long.eval["loss"][0]), float(long.eval["loss"][-1])
    assert last < 0.5 * first, (rule, first, last)
    assert traces_long == traces_short, (rule, traces_short, traces_long)
    uses_jacobian = str(long.attrs.get("jacobian", "")) not in ("", "none")
    assert uses_jacobian == capabilities(load("task=toy", f"optim={rule}").optim).needs_jacobian, (
        rule,
        long.attrs.get("jacobian"),
    )
