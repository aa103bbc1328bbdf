"""The layer-factorised Jacobian (physgrad.jacobians) against the explicit per-sample Jacobian in
float64, the spectral direction it gives against the float64 SVD, and the automatic choice of the
form."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.gradients import JacobianPass
from physgrad.jacobians import LayerPlan, dense_jacobian, layer_jacobian, plan_layers
from physgrad.nets import apply_mlp, init_mlp
from physgrad.optim.spectral import truncated_spectral_direction

NETWORKS = {
    "one hidden tanh": ([3, 5, 2], "tanh"),
    "two hidden relu": ([4, 8, 8, 3], "relu"),
    "wide tanh": ([6, 16, 12, 1], "tanh"),
    "linear": ([5, 4], "tanh"),
}

PHYSICS = ("none", "nonlinear")


def problem(sizes, hidden, physics, batch=5, seed=0):
    """A random dense network (non-zero biases; with relu, a third of the first layer's units dead
    for every sample) and a batch with a duplicated sample; physics "nonlinear" maps the network's
    output u to y = (sin(M u), x_0 u^2) with a fixed random M, so y has more components than u."""
    k1, k2, k3, k4 = jax.random.split(jax.random.PRNGKey(seed), 4)
    params = init_mlp(k1, sizes, jnp.float64)
    params = [
        {"w": layer["w"], "b": 0.3 * jax.random.normal(k, layer["b"].shape, jnp.float64)}
        for layer, k in zip(params, jax.random.split(k2, len(params)))
    ]
    if hidden == "relu":
        dead = sizes[1] // 3
        params[0]["b"] = params[0]["b"].at[:dead].set(-1e3)  # never active for inputs of order 1
    x = jax.random.normal(k3, (batch, sizes[0]), jnp.float64)
    x = x.at[-1].set(x[0])  # duplicated sample: J has repeated rows, so J J^T is singular
    mixing = jax.random.normal(k4, (3, sizes[-1]), jnp.float64)

    def sample_output(p, sample):
        u = apply_mlp(p, sample["x"], hidden=hidden)
        if physics == "none":
            return u
        return jnp.concatenate([jnp.sin(mixing @ u), sample["x"][0] * u**2])

    return params, {"x": x}, sample_output


# make test-long: the networks without the physics and the wide network (further instances of the
# same factors); make test keeps every other network through the nonlinear physics, whose y has more
# components than u ([one hidden tanh-nonlinear], [two hidden relu-nonlinear], [linear-nonlinear])
FACTOR_CASES = [
    pytest.param(
        network,
        physics,
        marks=() if physics == "nonlinear" and network != "wide tanh" else pytest.mark.long,
    )
    for network in NETWORKS
    for physics in PHYSICS
]


@pytest.mark.parametrize("network, physics", FACTOR_CASES)
def test_factors_give_the_explicit_jacobian_its_gram_matrix_and_products(x64, network, physics):
    params, batch, sample_output = problem(*NETWORKS[network], physics)
    plan = plan_layers(sample_output, params, {"x": batch["x"][0]})
    assert isinstance(plan, LayerPlan), plan

    @jax.jit
    def both_forms(params, batch, w):
        y_dense, dense = dense_jacobian(sample_output, params, batch)
        y, factored = layer_jacobian(sample_output, params, batch, plan)
        assert factored.shape == dense.shape
        return (
            y_dense,
            dense.matrix,
            y,
            factored.dense(),
            factored.gram64(),
            factored.transpose_apply(w),
        )

    m = jax.eval_shape(lambda: dense_jacobian(sample_output, params, batch)[1].matrix).shape[0]
    w = np.random.default_rng(1).standard_normal(m)
    y_dense, jac, y, factored_dense, gram, product = map(
        np.asarray, both_forms(params, batch, jnp.asarray(w))
    )
    assert np.abs(jac).max() > 0
    np.testing.assert_array_equal(y, y_dense)
    np.testing.assert_allclose(factored_dense, jac, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(
        gram, jac @ jac.T, rtol=1e-12, atol=1e-12 * np.abs(jac @ jac.T).max()
    )
    np.testing.assert_allclose(product, jac.T @ w, rtol=1e-12, atol=1e-12 * np.abs(jac.T @ w).max())
    sizes, hidden = NETWORKS[network]
    if hidden == "relu":  # the dead units' bias and incoming weights are zero columns of J
        assert np.count_nonzero(np.abs(jac).sum(axis=0) == 0) >= (sizes[1] // 3) * (1 + sizes[0])


# make test-long: the other kappa of each network; make test keeps both networks and both kappas,
# one pair each ([two hidden relu-0.5], [wide tanh-1.0])
@pytest.mark.parametrize(
    "network, kappa",
    [
        pytest.param("two hidden relu", 1.0, marks=pytest.mark.long),
        ("two hidden relu", 0.5),
        ("wide tanh", 1.0),
        pytest.param("wide tanh", 0.5, marks=pytest.mark.long),
    ],
)
def test_direction_from_factors_equals_the_float64_svd_direction_on_rank_deficient_jacobians(
    x64, network, kappa
):
    """Duplicated samples (and dead units) make J rank deficient: the factorised Gram route must
    keep exactly the singular values the SVD keeps (s > tau max s) and give the same direction to
    1e-10 relative (a float64 J; docs/decisions.md, "Factorisation route", states 5e-8 for a
    float32 J)."""
    params, batch, sample_output = problem(*NETWORKS[network], "nonlinear", batch=6, seed=3)
    batch = {"x": batch["x"].at[2].set(batch["x"][1])}  # a second duplicate
    plan = plan_layers(sample_output, params, {"x": batch["x"][0]})
    jac = np.asarray(
        jax.jit(lambda p, b: dense_jacobian(sample_output, p, b)[1].matrix)(params, batch)
    )
    g = np.random.default_rng(2).standard_normal(jac.shape[0])
    u, s, vt = np.linalg.svd(jac, full_matrices=False)
    keep = s > 1e-6 * s.max()
    assert 0 < keep.sum() < len(s)  # rank deficient for real
    expected = vt[keep].T @ (s[keep] ** -kappa * (u[:, keep].T @ g))
    got = np.asarray(
        jax.jit(
            lambda p, b, g: truncated_spectral_direction(
                layer_jacobian(sample_output, p, b, plan)[1], g, kappa, 1e-6, route="gram"
            )
        )(params, batch, jnp.asarray(g))
    )
    assert np.linalg.norm(got - expected) <= 1e-10 * np.linalg.norm(expected)


def mlp_output(params, sample):
    return apply_mlp(params, sample["x"], hidden="tanh")


def twice(params, sample):
    return apply_mlp(params, apply_mlp(params, sample["x"], hidden="tanh"), hidden="tanh")


def in_scan(params, sample):
    def body(x, _):
        return apply_mlp(params, x, hidden="tanh"), None

    return jax.lax.scan(body, sample["x"], None, length=3)[0]


def over_points(params, sample):
    return jax.vmap(lambda x: apply_mlp(params, x, hidden="tanh"))(
        jnp.stack([sample["x"], -sample["x"]])
    ).ravel()


def on_a_matrix(params, sample):
    return apply_mlp(params, jnp.stack([sample["x"], -sample["x"]]), hidden="tanh").ravel()


def scaled_weights(params, sample):
    return apply_mlp(
        jax.tree_util.tree_map(lambda leaf: 2.0 * leaf, params), sample["x"], hidden="tanh"
    )


def extra_gain(params, sample):
    return params["gain"] * apply_mlp(params["net"], sample["x"], hidden="tanh")


def also_outside(params, sample):
    return apply_mlp(params, sample["x"], hidden="tanh") + jnp.sum(params[0]["b"])


def hand_written(params, sample):
    return jnp.tanh(sample["x"] @ params[0]["w"] + params[0]["b"]) @ params[1]["w"] + params[1]["b"]


@pytest.mark.parametrize(
    "output, reason",
    [
        (mlp_output, None),
        (twice, "more than once"),
        (in_scan, "inside a loop"),
        (over_points, "inside a loop"),
        (on_a_matrix, "several inputs"),
        (scaled_weights, "transformed or shared"),
        (extra_gain, "not weights"),
        (also_outside, "other than through"),
        (hand_written, "not built with"),
    ],
)
def test_the_factorised_form_is_chosen_only_where_it_is_exact(output, reason):
    params = init_mlp(jax.random.PRNGKey(0), [3, 4, 3], jnp.float32)
    if output is extra_gain:
        params = {"net": params, "gain": jnp.ones(())}
    sample = {"x": jnp.ones(3)}
    route = JacobianPass.for_network(output, params, sample)
    if reason is None:
        assert isinstance(route.plan, LayerPlan) and route.name == "layer-factorised"
    else:
        assert route.plan is None and reason in route.name and route.name.startswith("per-sample: ")


# make test-long: three built-in scenes' forms (6.7 s of building); make test keeps the choice on
# every kind of network (test_the_factorised_form_is_chosen_only_where_it_is_exact) and on built-in
# scenes (test_configs.py's pairs quantum-kfac, factorised, and multicart-kfac, refused per sample)
@pytest.mark.long
def test_built_in_scenes_get_the_form_their_network_allows():
    """Open-loop scenes (the network applied once per sample) are factorised; closed-loop ones,
    whose network acts at every step of the rollout, and the CNN controller keep the per-sample pass
    (the results file names the form: tests/test_cli.py)."""
    from physgrad.configs import compose
    from physgrad.experiment import prepare
    from physgrad.job_spec import checked

    # one scene of each kind (poisson's form is checked in its results file: tests/test_cli.py)
    expected = {"oscillator": True, "multicart": False, "quantum_control": False}
    for task, factorised in expected.items():
        cfg = compose(
            [
                f"task={task}",
                "optim=hig",
                "trainer.batch_size=2",
                "task.test_size=2",
                "task.train_size=2",
            ]
        )
        _, rule, _ = prepare(checked(cfg), [0])
        assert (rule.gradient.plan is not None) == factorised, (task, rule.gradient.name)


@pytest.mark.long
def test_training_steps_are_the_same_on_both_forms(x64):
    """HIG on a small Poisson problem in float64: a few compiled training steps through the runner
    with the factorised and with the per-sample Jacobian give the same parameters and logs."""
    import dataclasses

    import numpy as onp

    from physgrad.configs import compose
    from physgrad.experiment import prepare
    from physgrad.job_spec import checked
    from physgrad.runner import compile_training

    cfg = compose(
        ["task=poisson", "task.grid=4", "optim=hig", "precision=64", "trainer.batch_size=8"]
    )
    spec = checked(cfg)
    settings = spec.trainer
    scene, rule, seeds = prepare(spec, [0])
    assert rule.gradient.plan is not None
    results = []
    for gradient in (rule.gradient, dataclasses.replace(rule.gradient, plan=None)):
        compiled = compile_training(
            scene, rule._replace(gradient=gradient), seeds, settings.batch_size
        )
        params, state = compiled.params, compiled.opt_state
        for iteration in range(4):
            params, state, logs = compiled.step(
                params, state, onp.int32(iteration), seeds.train_keys, seeds.train_sets
            )
        results.append((onp.asarray(params), onp.asarray(logs)))
    np.testing.assert_allclose(results[0][0], results[1][0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(results[0][1], results[1][1], rtol=1e-9, atol=1e-12)
