"""Dense quasi-Newton rules of the self-scaled Broyden family (SSBFGS, SSBroyden, and BFGS itself),
each an optax GradientTransformationExtraArgs with a zoom line search (strong Wolfe conditions).

Every step multiplies the gradient g_k by an approximation H_k of the inverse Hessian (n x n, over
every parameter of the network), and optax's zoom line search picks a step size along the
direction -H_k g_k (it evaluates the step's batch loss and gradient through the extra arguments
value, grad and value_fn, as optax.lbfgs does). With s = x_{k+1} - x_k and y = g_{k+1} - g_k the
approximation is updated in the self-scaled Broyden form (Al-Baali 1998; Al-Baali and Khalfan 2005;
as used for physics-informed networks by Kiyani et al. 2025, arXiv 2501.16371, and documented for
JAX by Bioli and Mendibe Abarrategi 2026, arXiv 2603.10599):

    H_{k+1} = (H_k - H y y^T H / (y^T H y) + phi_k (y^T H y) v v^T) / tau_k + s s^T / (y^T s),
    v = s / (y^T s) - H y / (y^T H y),    phi_k = (1 - theta_k) / (1 + a_k theta_k),

with h_k = y^T H y / (y^T s), b_k = s^T B s / (y^T s) = -alpha_k s^T g_k / (y^T s) (alpha_k the
step taken along -H_k g_k) and a_k = b_k h_k - 1 >= 0:

- **bfgs**: theta_k = 0 and tau_k = 1 (the textbook BFGS update of the inverse);
- **ssbfgs**: theta_k = 0, tau_0 = h_0 at the first update, then tau_k = min(1, 1 / b_k);
- **ssbroyden**: theta_k = max(theta^-, min(1 / rho^-, (1 - b_k) / b_k)) with
  rho^- = min(1, h_k (1 - c_k)), c_k = sqrt(a_k / (1 + a_k)), theta^- = (rho^- - 1) / a_k;
  tau_0 = h_0 / (1 + a_0 theta_0), then with sigma = 1 + theta_k a_k, rho = min(1, 1 / b_k) and
  sigma' = |sigma|^(1 / (1 - n)): tau_k = min(rho sigma', sigma) where theta_k <= 0, else
  rho min(sigma', 1 / theta_k).

The update is skipped where y^T s is not positive (a line search that stopped short of the
curvature condition) or where it is not finite. H_0 is the identity; the first direction is the
gradient scaled by min(1, 1 / |g_0|), as optax.lbfgs does, so that the first line search starts at
a step of at most unit length. The matrix costs n^2 numbers and O(n^2) work a step: the rule
refuses (UserError, one line) a network of more than `max_parameters` parameters, where L-BFGS
(`optim=lbfgs`) is its limited-memory relative.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from physgrad.errors import UserError

VARIANTS = ("bfgs", "ssbfgs", "ssbroyden")


class QuasiNewtonState(NamedTuple):
    count: jax.Array  # updates of H made so far (0: H is still the identity)
    steps: jax.Array  # directions given so far
    inverse_hessian: jax.Array  # H (n x n)
    params: jax.Array  # x_k of the last direction, flat
    grad: jax.Array  # g_k of the last direction, flat
    direction: jax.Array  # H_k g_k of the last direction (before the first step's scaling), flat


def broyden_parameters(
    variant: str, a: jax.Array, b: jax.Array, h: jax.Array, first: jax.Array, size: int
) -> tuple[jax.Array, jax.Array]:
    """(theta_k, tau_k) of the variant, from a_k, b_k, h_k (module docstring)."""
    if variant == "bfgs":
        return jnp.zeros_like(a), jnp.ones_like(a)
    rho = jnp.minimum(1.0, 1.0 / b)
    if variant == "ssbfgs":
        return jnp.zeros_like(a), jnp.where(first, h, rho)
    # a_k = 0 where y is parallel to B s: every member of the family gives the same H there (v = 0),
    # and a tiny a keeps theta^- finite
    a = jnp.maximum(a, jnp.finfo(a.dtype).tiny)
    c = jnp.sqrt(a / (1.0 + a))
    rho_minus = jnp.minimum(1.0, h * (1.0 - c))
    theta = jnp.maximum((rho_minus - 1.0) / a, jnp.minimum(1.0 / rho_minus, (1.0 - b) / b))
    sigma = 1.0 + theta * a
    sigma_root = jnp.abs(sigma) ** (1.0 / (1.0 - size)) if size > 1 else jnp.ones_like(sigma)
    later = jnp.where(
        theta <= 0,
        jnp.minimum(rho * sigma_root, sigma),
        rho * jnp.minimum(sigma_root, 1.0 / theta),
    )
    return theta, jnp.where(first, h / sigma, later)


def updated_inverse_hessian(
    variant: str,
    inverse_hessian: jax.Array,
    step: jax.Array,
    grad_change: jax.Array,
    previous_grad: jax.Array,
    step_size: jax.Array,
    first: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """H_{k+1} from H_k, s, y, g_k and alpha_k (module docstring), and whether it was updated (H_k
    is kept where y^T s <= 0 or the result is not finite)."""
    curvature = grad_change @ step  # y^T s
    hy = inverse_hessian @ grad_change
    yhy = grad_change @ hy
    h = yhy / curvature
    b = -step_size * (step @ previous_grad) / curvature
    a = b * h - 1.0
    theta, tau = broyden_parameters(variant, a, b, h, first, step.shape[0])
    phi = (1.0 - theta) / (1.0 + a * theta)
    v = step / curvature - hy / yhy
    # y^T s > 0 relative to |s| |y| (a curvature lost in round-off would blow H up), and every
    # scalar of the update finite: then so is the update of a finite H
    scale = jnp.sqrt((step @ step) * (grad_change @ grad_change))
    scalars = jnp.stack([curvature, yhy, tau, phi, phi * yhy])
    ok = (curvature > jnp.finfo(step.dtype).eps * scale) & (yhy > 0) & (tau != 0)
    ok = ok & jnp.all(jnp.isfinite(scalars)) & jnp.all(jnp.isfinite(v))
    # one pass over the n x n matrix: a rank-3 change of H / tau, zero where it is skipped
    columns = jnp.where(ok, jnp.stack([hy, v, step], axis=1), 0.0)  # no NaN times a zero weight
    weights = jnp.where(ok, jnp.stack([-1.0 / yhy, phi * yhy, tau / curvature]) / tau, 0.0)
    change = (columns * weights) @ columns.T
    return jnp.where(ok, inverse_hessian / tau, inverse_hessian) + change, ok


def scale_by_self_scaled_broyden(
    variant: str = "ssbfgs", max_parameters: int = 8192
) -> optax.GradientTransformation:
    """Multiplies the gradient by the variant's inverse-Hessian approximation H_k (module
    docstring), updated from the step and the change of gradient since the last call. The output
    is +H_k g_k (optax's convention: a learning-rate scaling flips its sign)."""
    if variant not in VARIANTS:
        raise UserError(f"optim.variant={variant} is not one of {', '.join(VARIANTS)}")

    def init(params: optax.Params) -> QuasiNewtonState:
        flat, _ = ravel_pytree(params)
        size = flat.shape[0]
        if size > max_parameters:
            raise UserError(
                f"the {variant} rule keeps a dense {size} x {size} inverse Hessian: the network "
                f"has {size} parameters, more than optim.max_parameters={max_parameters}; raise it "
                "if memory and O(n^2) work a step allow, or use optim=lbfgs (limited memory)"
            )
        zeros = jnp.zeros_like(flat)
        return QuasiNewtonState(
            count=jnp.zeros([], jnp.int32),
            steps=jnp.zeros([], jnp.int32),
            inverse_hessian=jnp.eye(size, dtype=flat.dtype),
            params=zeros,
            grad=zeros,
            direction=zeros,
        )

    def update(
        updates: optax.Updates, state: QuasiNewtonState, params: optax.Params | None = None
    ) -> tuple[optax.Updates, QuasiNewtonState]:
        if params is None:
            raise ValueError("the self-scaled Broyden rules need params")
        grad, unravel = ravel_pytree(updates)
        flat = ravel_pytree(params)[0]
        step = flat - state.params
        grad_change = grad - state.grad
        # the step taken along -H g: s = -alpha (H g)
        step_size = -(step @ state.direction) / jnp.maximum(
            state.direction @ state.direction, jnp.finfo(flat.dtype).tiny
        )
        # before the first step there is no step to learn from: s = x_0, y = g_0 are masked out by
        # a zero step
        first_call = state.steps == 0
        inverse_hessian, ok = updated_inverse_hessian(
            variant,
            state.inverse_hessian,
            jnp.where(first_call, 0.0, step),
            grad_change,
            state.grad,
            step_size,
            state.count == 0,
        )
        direction = inverse_hessian @ grad
        # the first direction is the gradient, at most of unit length (optax.lbfgs's choice)
        scale = jnp.where(state.steps == 0, jnp.minimum(1.0, 1.0 / jnp.linalg.norm(grad)), 1.0)
        new_state = QuasiNewtonState(
            count=state.count + ok.astype(jnp.int32),
            steps=state.steps + 1,
            inverse_hessian=inverse_hessian,
            params=flat,
            grad=grad,
            direction=direction,
        )
        return unravel(scale * direction), new_state

    return optax.GradientTransformation(init, update)


def self_scaled_broyden(
    learning_rate: float = 1.0,
    variant: str = "ssbfgs",
    max_parameters: int = 8192,
    max_linesearch_steps: int = 20,
) -> optax.GradientTransformationExtraArgs:
    """The variant's direction -H_k g_k, scaled by learning_rate, then optax's zoom line search
    (strong Wolfe conditions, first trial step 1), which takes the extra arguments value, grad and
    value_fn."""
    return optax.chain(
        scale_by_self_scaled_broyden(variant, max_parameters),
        optax.scale_by_learning_rate(learning_rate),
        optax.scale_by_zoom_linesearch(
            max_linesearch_steps=max_linesearch_steps, initial_guess_strategy="one"
        ),
    )
