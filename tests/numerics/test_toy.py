"""The book's badly scaled toy against a plain numpy reading of the PBDL book's formula."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from physgrad.nets import count_params
from physgrad.tasks.toy import GRID, PROBE, SATURATED, build
from tests.helpers import REPO


def numpy_net(params, x):
    """1 -> hidden (tanh) -> 2 by hand: (hidden activations, outputs) for inputs x of shape (n,)."""
    h = np.tanh(x[:, None] * np.asarray(params[0]["w"])[0] + np.asarray(params[0]["b"]))
    return h, h @ np.asarray(params[1]["w"]) + np.asarray(params[1]["b"])


def toy(scale=0.01, test_size=16):
    return build(jax.random.PRNGKey(3), scale=scale, hidden=[7], test_size=test_size)


def test_the_default_is_the_book_s_network_and_lambda():
    config = yaml.safe_load((REPO / "conf" / "task" / "toy.yaml").read_text())
    assert config["hidden"] == [7] and config["scale"] == 0.01
    assert count_params(toy().init_params(jax.random.PRNGKey(0))) == 30  # 1 -> 7 -> 2


@pytest.mark.parametrize("scale", [1.0, 0.01])
def test_loss_is_the_book_s_with_lambda_on_the_network_s_second_output_only(x64, scale):
    scene = toy(scale)
    params = scene.init_params(jax.random.PRNGKey(1))
    x = np.asarray(scene.test_set["x"][:, 0])
    _, y = numpy_net(params, x)
    # L = 1/2 (y1 - sin 6x)^2 + 1/2 (lambda y2 - cos 9x)^2: the target is not scaled
    expected = 0.5 * (y[:, 0] - np.sin(6 * x)) ** 2 + 0.5 * (scale * y[:, 1] - np.cos(9 * x)) ** 2
    per_sample = jax.vmap(lambda s: scene.sample_loss(scene.sample_output(params, s), s))(
        scene.test_set
    )
    np.testing.assert_allclose(per_sample, expected, rtol=1e-12)
    # at lambda = 0.01 the network must output y2 = 100 cos 9x to reach zero loss
    perfect = {"x": scene.test_set["x"][:1], "target": scene.test_set["target"][0]}
    y_needed = jnp.array([np.sin(6 * x[0]), np.cos(9 * x[0]) / scale])
    assert float(scene.sample_loss(jnp.array([1.0, scale]) * y_needed, perfect)) < 1e-24


def test_training_batches_are_uniform_on_the_interval_with_unscaled_targets(x64):
    scene = toy()
    batch = scene.sample_train(jax.random.PRNGKey(5), 4096)
    x = np.asarray(batch["x"][:, 0])
    assert -1 <= x.min() < -0.99 and 0.99 < x.max() <= 1
    assert abs(x.mean()) < 0.05 and abs(x.var() - 1 / 3) < 0.02  # U(-1, 1)
    np.testing.assert_allclose(batch["target"], np.stack([np.sin(6 * x), np.cos(9 * x)], 1))


def test_activation_metrics_and_probe_match_a_plain_loop(x64):
    scene = toy()
    params = scene.init_params(jax.random.PRNGKey(2))
    sample = jax.tree_util.tree_map(lambda leaf: leaf[0], scene.test_set)
    metrics = scene.sample_metrics(params, sample, scene.sample_output(params, sample))
    h, _ = numpy_net(params, np.linspace(-1, 1, GRID))
    assert float(metrics["hidden_magnitude"]) == pytest.approx(np.abs(h).mean(), rel=1e-12)
    assert float(metrics["hidden_spread"]) == pytest.approx(h.std(axis=0).mean(), rel=1e-12)
    assert float(metrics["hidden_saturated"]) == pytest.approx((np.abs(h) > SATURATED).mean())
    _, probe = numpy_net(params, np.array([PROBE]))
    np.testing.assert_allclose(
        [metrics["probe_y1"], metrics["probe_y2"]], [probe[0, 0], 0.01 * probe[0, 1]], rtol=1e-12
    )
    error = np.abs(np.asarray(scene.sample_output(params, sample)) - np.asarray(sample["target"]))
    np.testing.assert_allclose([metrics["error_first"], metrics["error_second"]], error)


def test_saturated_neurons_have_no_spread(x64):
    """The book's sign of a destroyed network: every hidden neuron at +-1 whatever the input."""
    scene = toy()
    params = scene.init_params(jax.random.PRNGKey(2))
    params[0]["b"] = jnp.where(jnp.arange(7) % 2 == 0, 40.0, -40.0)
    sample = jax.tree_util.tree_map(lambda leaf: leaf[0], scene.test_set)
    metrics = scene.sample_metrics(params, sample, scene.sample_output(params, sample))
    assert float(metrics["hidden_spread"]) < 1e-12
    assert float(metrics["hidden_saturated"]) == 1.0
    assert float(metrics["hidden_magnitude"]) == pytest.approx(1.0)
