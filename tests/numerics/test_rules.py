"""Update rules as built from the configs: Adam's epsilon, clipping before the rule, the presets,
the gradient route a rule gets, and any optax factory named by _target_."""

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from physgrad.errors import UserError
from physgrad.gradients import Combined, JacobianPass, Regular
from physgrad.optim import CLIPPING, build_rule
from physgrad.unroll import PHYSICS_ONLY, REGULAR
from tests.helpers import load


def test_value_clipping_is_element_wise_and_norm_clipping_global():
    grads = {"a": jnp.array([3.0, -0.5]), "b": jnp.array([-2.0])}
    clipped, _ = CLIPPING["value"]().update(grads, None)
    np.testing.assert_array_equal(clipped["a"], [1.0, -0.5])
    np.testing.assert_array_equal(clipped["b"], [-1.0])
    clipped, _ = CLIPPING["norm"]().update(grads, CLIPPING["norm"]().init(grads))
    np.testing.assert_allclose(optax.tree.norm(clipped), 1.0, rtol=1e-6)
    np.testing.assert_allclose(clipped["a"][0] / clipped["b"][0], -1.5, rtol=1e-6)  # direction kept


@pytest.mark.parametrize(
    "overrides, route",
    [
        (["optim=adam"], Regular(REGULAR)),
        (["optim=gd"], Regular(REGULAR)),
        (["optim=bptt"], Regular(REGULAR)),
        (["optim=bptt", "optim.backprop=M"], Regular(PHYSICS_ONLY)),
        (["optim=stable_bptt"], Combined()),
        (["optim=adam", "optim.backprop=C"], Combined()),
        (["optim=hig"], JacobianPass()),
        (["optim=gauss_newton"], JacobianPass()),
    ],
)
def test_each_rule_gets_its_gradient_route(overrides, route):
    rule = build_rule(load("task=multicart", *overrides).optim)
    assert rule.gradient == route and rule.uses_jacobian == isinstance(route, JacobianPass)


def not_a_rule(**settings: object) -> dict:
    """A function of the user's (a test module) that builds no update rule."""
    return {}


@pytest.mark.parametrize(
    "overrides, fragment",
    [
        (["optim=hig", "optim.backprop=C"], "optim.backprop=C applies to gradient-based rules"),
        (["optim=hig", "optim.clip=norm"], "optim.clip=norm applies to gradient-based rules"),
        (
            ["optim=bptt", "optim.backprop=X"],
            "optim.backprop='X' is not allowed: choose one of R, M, S, C",
        ),
        (["optim=adam", "optim.clip=huge"], "optim.clip='huge' is not allowed"),
        (
            ["optim=adam", "+optim.epsilon=1e-8"],
            "optim.epsilon is not a setting of optax.adam: did you mean optim.eps?",
        ),
        (
            ["optim=adam", "optim._target_=optax.adamm"],
            "optim._target_=optax.adamm cannot be imported",
        ),
        (
            ["optim=adam", "optim._target_=tests.numerics.test_rules.not_a_rule"],
            "returned dict, not an optax GradientTransformation",
        ),
        (
            ["optim=adam", "optim._target_=collections.OrderedDict"],
            "optim._target_=collections.OrderedDict is not allowed",
        ),
        (
            ["optim=adam", "optim._target_=builtins.dict"],
            "optim._target_=builtins.dict is not allowed",
        ),
    ],
)
def test_a_rule_that_cannot_be_built_is_one_line(overrides, fragment):
    with pytest.raises(UserError) as error:
        build_rule(load(*overrides).optim)
    assert fragment in str(error.value) and "\n" not in str(error.value), str(error.value)


def test_any_optax_factory_composes_with_clipping_and_the_combined_gradient():
    """optim=<a YAML naming optax.lion> with optim.backprop=C and optim.clip=value: clip, then lion,
    on C."""
    node = {
        "name": "lion",
        "_target_": "optax.lion",
        "learning_rate": 1e-3,
        "backprop": "C",
        "clip": "value",
    }
    rule = build_rule(node)
    assert rule.gradient == Combined() and not rule.uses_jacobian
    params = {"w": jnp.zeros(2)}
    updates, _ = rule.transform.update(
        {"w": jnp.array([50.0, -0.2])}, rule.transform.init(params), params
    )
    # lion: -lr sign(clipped gradient)
    np.testing.assert_allclose(updates["w"], [-1e-3, 1e-3], rtol=1e-6)


def test_nested_targets_build_a_schedule():
    node = {
        "name": "adamw",
        "_target_": "optax.adamw",
        "weight_decay": 0.0,
        "learning_rate": {
            "_target_": "optax.linear_schedule",
            "init_value": 1.0,
            "end_value": 0.0,
            "transition_steps": 2,
        },
    }
    rule = build_rule(node)
    params = {"w": jnp.zeros(1)}
    state = rule.transform.init(params)
    sizes = []
    for _ in range(3):
        updates, state = rule.transform.update({"w": jnp.array([1.0])}, state, params)
        sizes.append(float(abs(updates["w"][0])))
    # Adam: first steps of size lr (eps aside)
    np.testing.assert_allclose(sizes, [1.0, 0.5, 0.0], rtol=1e-4)


@pytest.mark.parametrize("optim", ["adam", "bptt", "stable_bptt"])
def test_adam_uses_keras_epsilon(optim):
    cfg = load("task=multicart", f"optim={optim}")
    assert cfg.optim.eps == 1e-7
    rule = build_rule(cfg.optim)
    params = {"w": jnp.zeros(2)}
    # the first Adam step is -lr * g / (|g| + eps) per element: eps shows for tiny gradients
    updates, _ = rule.transform.update(
        {"w": jnp.array([1e-7, 1.0])}, rule.transform.init(params), params
    )
    np.testing.assert_allclose(updates["w"], [-1e-3 * 0.5, -1e-3 / (1 + 1e-7)], rtol=1e-4)
    assert rule.uses_jacobian is False


def test_stable_bptt_clips_before_adam():
    rule = build_rule(load("task=multicart", "optim=stable_bptt", "optim.clip=value").optim)
    assert rule.gradient == Combined()
    params = {"w": jnp.zeros(1)}
    # after an element clip at 1, Adam's first step has magnitude lr whatever the gradient's size
    updates, _ = rule.transform.update(
        {"w": jnp.array([50.0])}, rule.transform.init(params), params
    )
    np.testing.assert_allclose(updates["w"], [-1e-3], rtol=1e-4)
