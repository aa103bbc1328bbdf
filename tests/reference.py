"""Plain Python loops as references for the scan-based rollouts (no lax.scan, no stop_gradient); the
loops themselves ship in physgrad.loop_reference for scene authors."""

import jax

from physgrad import loop_reference


def forward_states(step, policy, x0, steps):
    """x_0..x_steps of the forward pass, as constants: the values every mode shares
    (physgrad.loop_reference)."""
    return loop_reference.forward_states(step, policy, x0, steps)


def loop_states(step, policy, x0, steps, backprop, frozen):
    """x_1..x_steps, where a mode's stopped inputs are the constant forward states `frozen`
    (physgrad.loop_reference)."""
    return loop_reference.loop_states(step, policy, x0, steps, backprop, frozen)[0]


def check_gradient(loss, scan_loss, params, rtol=1e-9, fd_rtol=1e-5, directions=3):
    """scan_loss and loss agree in value and gradient; the gradient matches central finite
    differences of loss along random unit directions (float64)."""
    import jax.numpy as jnp
    import numpy as np
    from jax.flatten_util import ravel_pytree

    np.testing.assert_allclose(scan_loss(params), loss(params), rtol=1e-12)
    g_scan, g_loop = jax.grad(scan_loss)(params), jax.grad(loss)(params)
    for a, b in zip(jax.tree_util.tree_leaves(g_scan), jax.tree_util.tree_leaves(g_loop)):
        np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-12)
    flat, unravel = ravel_pytree(params)
    flat_grad = ravel_pytree(g_scan)[0]
    for i in range(directions):
        direction = jax.random.normal(jax.random.PRNGKey(100 + i), flat.shape)
        direction = direction / jnp.linalg.norm(direction)
        eps = 1e-6
        central = (
            loss(unravel(flat + eps * direction)) - loss(unravel(flat - eps * direction))
        ) / (2 * eps)
        np.testing.assert_allclose(central, flat_grad @ direction, rtol=fd_rtol, atol=1e-9)
    return g_scan
