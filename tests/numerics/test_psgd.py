"""Numerics layer (closed forms, plain-loop references, float64) of the tests of: PSGD Kron
(physgrad.optim.psgd, from psgdax), stochastic gradient descent preconditioned per weight matrix by
a Kronecker product fitted to whiten the gradient."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.optim.psgd import psgd_kron


def updates_of(transform, gradients, params, state=None):
    """The updates a transformation gives for a sequence of gradients, and its last state."""
    state = transform.init(params) if state is None else state
    step = jax.jit(transform.update)
    out = []
    for g in gradients:
        u, state = step(g, state, params)
        out.append(u)
    return out, state


def test_a_preconditioner_never_updated_is_momentum_gradient_descent(x64):
    """Q never updated (probability 0) from scale s: P = s^2 I, so the step is -lr s^2 m with
    m <- beta_t m + (1 - beta_t) g, beta_t = min(t / (t + 1), b1): the plain loop below, in
    float64 (which also checks that a float64 state steps at all); a leaf whose step has an RMS
    above grad_clip_max_amp is scaled down to it."""
    lr, b1, scale = 0.1, 0.9, 0.5
    rng = np.random.default_rng(0)
    params = {"w": jnp.zeros((4, 3)), "b": jnp.zeros(3)}
    gradients = [
        {
            "w": jnp.asarray(0.1 * rng.normal(size=(4, 3))),
            "b": jnp.asarray(0.1 * rng.normal(size=3)),
        }
        for _ in range(12)
    ]
    rule = psgd_kron(
        lr, b1=b1, preconditioner_update_probability=0.0, preconditioner_init_scale=scale
    )
    got, _ = updates_of(rule, gradients, params)
    momentum = {k: np.zeros(v.shape) for k, v in params.items()}
    for t, (g, u) in enumerate(zip(gradients, got)):
        beta = min(t / (t + 1), b1)
        for k in params:
            momentum[k] = beta * momentum[k] + (1 - beta) * np.asarray(g[k])
            assert u[k].dtype == jnp.float64
            # psgdax forms beta_t in float32 whatever the precision: agreement to its round-off
            expected = -lr * scale**2 * momentum[k]
            np.testing.assert_allclose(
                u[k], expected, rtol=1e-6, atol=1e-6 * np.max(np.abs(expected))
            )

    # a large gradient: each leaf's step scaled to an RMS of grad_clip_max_amp (1), times lr
    large = [{"w": jnp.full((4, 3), 50.0), "b": jnp.full(3, -80.0)}]
    clipped, _ = updates_of(
        psgd_kron(lr, b1=0.0, preconditioner_update_probability=0.0, preconditioner_init_scale=1.0),
        large,
        params,
    )
    for k in params:
        assert math.isclose(float(jnp.sqrt(jnp.mean(clipped[0][k] ** 2))), lr, rel_tol=1e-12)


def kronecker_gradients(seed, count, left, right, diagonal):
    """count gradients, stacked, of a 4 x 4 matrix with covariance right (x) left (G = L Z R^T, Z
    standard normal, L L^T = left, R R^T = right) and of a bias with variances `diagonal`."""
    rng = np.random.default_rng(seed)
    chol_left, chol_right = np.linalg.cholesky(left), np.linalg.cholesky(right)
    return {
        "w": jnp.asarray(chol_left @ rng.normal(size=(count, 4, 4)) @ chol_right.T),
        "b": jnp.asarray(np.sqrt(diagonal) * rng.normal(size=(count, 3))),
    }


def fitted(rule, gradients):
    """The rule's state after a step on each of the stacked gradients (one compiled scan)."""
    params = jax.tree.map(lambda g: jnp.zeros_like(g[0]), gradients)

    def step(state, g):
        return rule.update(g, state, params)[1], None

    return jax.jit(lambda gs: jax.lax.scan(step, rule.init(params), gs)[0])(gradients)


def whitened_spread(state, left, right, diagonal):
    """How far the preconditioner in `state`, frozen, leaves fresh gradients from white: the
    largest factor by which an eigenvalue of the preconditioned gradients' second moments, E[U U^T]
    / 4 (rows), E[U^T U] / 4 (columns) and the bias's E[u^2], differs from their mean (as a log)."""
    frozen = psgd_kron(
        -1.0, b1=0.0, preconditioner_update_probability=0.0, grad_clip_max_amp=math.inf
    )
    samples = kronecker_gradients(7, 4000, left, right, diagonal)
    params = jax.tree.map(lambda g: jnp.zeros_like(g[0]), samples)
    updates = jax.jit(jax.vmap(lambda g: frozen.update(g, state, params)[0]))(samples)
    u = np.asarray(updates["w"])
    rows = np.linalg.eigvalsh(np.einsum("sij,skj->ik", u, u) / len(u) / 4)
    cols = np.linalg.eigvalsh(np.einsum("sji,sjk->ik", u, u) / len(u) / 4)
    bias = np.mean(np.asarray(updates["b"]) ** 2, axis=0)
    return max(float(np.max(np.abs(np.log(v / v.mean())))) for v in (rows, cols, bias))


# long: 20,000 steps of the fit, 10 to 20 s on 2 cores
@pytest.mark.long
@pytest.mark.parametrize("preconditioner_lr, white", [(0.01, True), (0.0, False)])
def test_the_fitted_preconditioner_whitens_kronecker_structured_gradients(
    x64, preconditioner_lr, white
):
    """Q fitted on gradients with covariance B (x) A (condition numbers 100 and 30) and a bias with
    variances spanning 100x reaches the criterion's minimiser P = E[g g^T]^(-1/2): the
    preconditioned gradients are white, every eigenvalue of their second moments within 30% of
    their mean. The fit is stochastic (a fresh gradient each step): at preconditioner_lr 0.1 Q
    wanders by about 30% around the minimiser, at 0.01 (used here, 20,000 steps) by 9 to 19% (4
    seeds), and the sampling error of the 4,000 draws is about 5%. A preconditioner never fitted
    (preconditioner_lr 0) leaves them as colored as they came (the negative control)."""
    rng = np.random.default_rng(3)
    basis_left = np.linalg.qr(rng.normal(size=(4, 4)))[0]
    left = basis_left @ np.diag(np.geomspace(0.1, 10.0, 4)) @ basis_left.T
    basis_right = np.linalg.qr(rng.normal(size=(4, 4)))[0]
    right = basis_right @ np.diag(np.geomspace(0.2, 6.0, 4)) @ basis_right.T
    diagonal = np.array([0.01, 0.1, 1.0])
    rule = psgd_kron(
        1e-3, b1=0.0, preconditioner_lr=preconditioner_lr, preconditioner_update_probability=1.0
    )
    state = fitted(rule, kronecker_gradients(5, 20_000, left, right, diagonal))
    spread = whitened_spread(state, left, right, diagonal)
    if white:
        assert spread < math.log(1.3), spread
    else:
        assert spread > math.log(5.0), spread


@pytest.mark.parametrize(
    "settings, why",
    [
        ({"b1": 1.0}, "b1=1.0"),
        ({"preconditioner_update_probability": 1.5}, "in [0, 1]"),
        ({"whiten_grad": False, "b1": 0.0}, "give b1 > 0"),
    ],
)
def test_settings_out_of_range_are_refused_with_the_key(settings, why):
    with pytest.raises(ValueError, match=why.replace("[", r"\[").replace("]", r"\]")):
        psgd_kron(1e-3, **settings)


def test_the_schedule_is_psgdax_s_and_the_counter_set_by_at_step_sets_the_update_probability():
    """annealed_probability is psgdax's precond_update_prob_schedule (in float32 there) at steps 1
    to 20,000; at_step sets the step counter of a psgd_kron state and nothing else; from a state set
    to the start every one of 400 steps (one key each) updates the preconditioner, from one set to
    floor_step (p = 0.03) a binomial share: 12 expected, and fewer than 2 or more than 30 has
    probability below 1e-4."""
    from psgdax.psgd import KronState, precond_update_prob_schedule

    from physgrad.optim.psgd import annealed_probability, scheduled_update

    steps = np.arange(1, 20_001)
    np.testing.assert_allclose(
        annealed_probability(steps),
        np.asarray(precond_update_prob_schedule()(steps)),
        rtol=1e-6,
    )
    schedule = scheduled_update({"preconditioner_update_probability": None})
    assert scheduled_update({"preconditioner_update_probability": 0.5}) is None
    rule = psgd_kron(1e-3)
    params = {"w": jnp.ones((4, 3)), "b": jnp.ones(3)}
    gradient = jax.tree.map(lambda p: 0.1 * p, params)
    _, state = updates_of(rule, [gradient] * 3, params)
    pinned = schedule.at_step(state, schedule.floor_step)
    kron = [i for i, part in enumerate(state) if isinstance(part, KronState)]
    assert len(kron) == 1 and int(pinned[kron[0]].count) == schedule.floor_step
    unchanged = jax.tree.leaves(jax.tree.map(lambda a, b: bool(jnp.all(a == b)), state, pinned))
    assert unchanged.count(False) == 1  # the counter alone

    at = kron[0]

    def one(base, key):
        """One step from base with its own key: whether it changed the preconditioner, and the
        counter after it."""
        keyed = tuple(part._replace(key=key) if i == at else part for i, part in enumerate(base))
        _, after = rule.update(gradient, keyed, params)
        changed = jax.tree.map(
            lambda a, b: jnp.any(a != b),
            after[at].Qs_preconditioners,
            base[at].Qs_preconditioners,
        )
        return jnp.any(jnp.stack(jax.tree.leaves(changed))), after[at].count

    steps_from = jax.jit(jax.vmap(one, in_axes=(None, 0)))  # compiled once, for both counters

    def updated(start: int) -> int:
        """Of 400 steps from the state set to `start`, each with its own key: how many changed the
        preconditioner."""
        keys = jax.random.split(jax.random.PRNGKey(0), 400)
        changed, count = steps_from(schedule.at_step(state, start), keys)
        assert set(np.asarray(count).tolist()) == {start + 1}
        return int(np.sum(changed))

    assert updated(0) == 400
    assert 2 <= updated(schedule.floor_step) <= 30
