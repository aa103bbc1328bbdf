"""Update rules as built from the configs: Adam's epsilon, clipping before Adam, the presets."""

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from physgrad.optim import build_rule, clipping
from tests.test_configs import load


def test_value_clipping_is_element_wise_and_norm_clipping_global():
    grads = {"a": jnp.array([3.0, -0.5]), "b": jnp.array([-2.0])}
    clipped, _ = clipping("value").update(grads, None)
    np.testing.assert_array_equal(clipped["a"], [1.0, -0.5])
    np.testing.assert_array_equal(clipped["b"], [-1.0])
    clipped, _ = clipping("norm").update(grads, clipping("norm").init(grads))
    np.testing.assert_allclose(optax.tree.norm(clipped), 1.0, rtol=1e-6)
    np.testing.assert_allclose(clipped["a"][0] / clipped["b"][0], -1.5, rtol=1e-6)  # direction kept
    unclipped, _ = clipping("none").update(grads, None)
    assert unclipped is grads


@pytest.mark.parametrize("optim", ["adam", "bptt", "stable_bptt"])
def test_adam_uses_keras_epsilon(optim):
    cfg = load("task=multicart", f"optim={optim}")
    assert cfg.optim.eps == 1e-7
    rule = build_rule(cfg.optim)
    params = {"w": jnp.zeros(2)}
    # the first Adam step is -lr * g / (|g| + eps) per element: eps shows for tiny gradients
    updates, _ = rule.transform.update({"w": jnp.array([1e-7, 1.0])}, rule.transform.init(params), params)
    np.testing.assert_allclose(updates["w"], [-1e-3 * 0.5, -1e-3 / (1 + 1e-7)], rtol=1e-4)
    assert rule.uses_jacobian is False


def test_stable_bptt_clips_before_adam():
    rule = build_rule(load("task=multicart", "optim=stable_bptt", "optim.clip=value").optim)
    assert rule.backprop == "C"
    params = {"w": jnp.zeros(1)}
    # after an element clip at 1, Adam's first step has magnitude lr whatever the gradient's size
    updates, _ = rule.transform.update({"w": jnp.array([50.0])}, rule.transform.init(params), params)
    np.testing.assert_allclose(updates["w"], [-1e-3], rtol=1e-4)
