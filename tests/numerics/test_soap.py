"""Numerics layer (closed forms, plain-loop references, float64) of the tests of: SOAP
(physgrad.optim.soap), Adam in the eigenbasis of Shampoo's preconditioner."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from physgrad.optim.soap import soap

LR, B1, B2, EPS = 0.01, 0.9, 0.99, 1e-8


def updates_of(transform, gradients, params):
    """The updates a transformation gives for a sequence of gradients (each a pytree)."""
    state, out = transform.init(params), []
    step = jax.jit(transform.update)
    for g in gradients:
        u, state = step(g, state, params)
        out.append(u)
    return out


def test_where_shampoos_basis_is_the_identity_soap_is_adam_one_step_later(x64):
    """Diagonal gradients with ascending entries: G G^T and G^T G are diagonal and ascending, so
    their eigenvectors are the identity at every recomputation (every 3 steps here); the first step
    moves nothing and every later step is Adam's step on the gradients from the second on. A bias
    (no basis) likewise."""
    rng = np.random.default_rng(0)
    params = {"w": jnp.zeros((4, 4)), "b": jnp.zeros(3)}
    gradients = [
        {
            "w": jnp.diag(jnp.asarray(np.sort(rng.uniform(0.1, 2.0, 4)))),
            "b": jnp.asarray(rng.normal(size=3)),
        }
        for _ in range(10)
    ]
    got = updates_of(soap(LR, B1, B2, eps=EPS, precondition_frequency=3), gradients, params)
    adam = updates_of(optax.adam(LR, B1, B2, eps=EPS), gradients[1:], params)
    assert all(float(jnp.abs(leaf).max()) == 0.0 for leaf in jax.tree_util.tree_leaves(got[0]))
    for soap_update, adam_update in zip(got[1:], adam):
        for key in ("w", "b"):
            np.testing.assert_allclose(soap_update[key], adam_update[key], rtol=1e-12, atol=1e-15)


def test_a_constant_rank_one_gradient_gets_a_unit_rank_one_step(x64):
    """G = s u v^T: in Shampoo's eigenbasis G is one entry, which Adam's normalisation sends to
    sign(s); rotated back the step is -lr sign(s) u v^T, of Frobenius norm lr (Adam's own step,
    -lr sign(G) elementwise, has norm lr sqrt(m n))."""
    rng = np.random.default_rng(1)
    u = rng.normal(size=5)
    v = rng.normal(size=3)
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    for s in (2.5, -0.7):
        gradient = {"w": jnp.asarray(s * np.outer(u, v))}
        got = updates_of(soap(LR, B1, B2, eps=EPS), [gradient] * 6, {"w": jnp.zeros((5, 3))})
        for update in got[1:]:
            np.testing.assert_allclose(update["w"], -LR * np.sign(s) * np.outer(u, v), atol=1e-9)
        adam = updates_of(optax.adam(LR, B1, B2, eps=EPS), [gradient], {"w": jnp.zeros((5, 3))})
        assert float(jnp.linalg.norm(adam[0]["w"])) == pytest.approx(LR * np.sqrt(15), rel=1e-6)


def plain_soap(gradients, frequency, max_dim=10_000):
    """SOAP on one matrix as the module docstring states it, step by step in NumPy."""
    m, n = gradients[0].shape
    left, right = np.zeros((m, m)), np.zeros((n, n))
    q_left, q_right = np.eye(m), np.eye(n)
    mu, nu, out = np.zeros((m, n)), np.zeros((m, n)), []
    for t, g in enumerate(gradients):
        if t == 0:
            out.append(np.zeros((m, n)))
        else:
            mu = B1 * mu + (1 - B1) * g
            nu = B2 * nu + (1 - B2) * (q_left.T @ g @ q_right) ** 2
            m_hat = q_left.T @ mu @ q_right / (1 - B1**t)
            v_hat = nu / (1 - B2**t)
            out.append(-LR * q_left @ (m_hat / (np.sqrt(v_hat) + EPS)) @ q_right.T)
        left = B2 * left + (1 - B2) * g @ g.T
        right = B2 * right + (1 - B2) * g.T @ g
        if t % frequency == 0:
            if m <= max_dim:
                q_left = np.linalg.eigh(left + (1e-30 + 1e-12 * np.trace(left) / m) * np.eye(m))[1]
            if n <= max_dim:
                q_right = np.linalg.eigh(right + (1e-30 + 1e-12 * np.trace(right) / n) * np.eye(n))[
                    1
                ]
    return out


@pytest.mark.parametrize("shape, max_dim", [((4, 4), 10_000), ((5, 3), 4)])
def test_the_updates_are_those_of_a_plain_loop_of_the_stated_equations(x64, shape, max_dim):
    """Random gradients over 12 steps (the basis recomputed after steps 1, 5 and 9) against the
    equations stepped in NumPy: a square matrix (its first factors full rank, so that the basis is
    unique: in a degenerate eigenspace any basis is an eigenbasis), and a 5 x 3 one with
    max_precondition_dim=4, whose 5-long side keeps the identity basis."""
    rng = np.random.default_rng(2)
    gradients = [rng.normal(size=shape) for _ in range(12)]
    got = updates_of(
        soap(LR, B1, B2, eps=EPS, precondition_frequency=4, max_precondition_dim=max_dim),
        [{"w": jnp.asarray(g)} for g in gradients],
        {"w": jnp.zeros(shape)},
    )
    for ours, plain in zip(got, plain_soap(gradients, 4, max_dim)):
        np.testing.assert_allclose(ours["w"], plain, rtol=1e-9, atol=1e-12)


def test_a_frequency_below_one_is_refused():
    with pytest.raises(ValueError, match="precondition_frequency"):
        soap(LR, precondition_frequency=0)
