"""A pendulum brought to rest by an open-loop control, the ODE solved with diffrax.

    theta'' = -(g / l) sin(theta) - damping * theta' + u(t),   t in [0, t1],
    u(t) = sum_j a_j sin(j pi t / t1),  j = 1..modes,

from a start (theta, theta') drawn uniformly in [-1, 1]^2. The network maps the start to the
coefficients a; the physical output y is the final state (theta, theta')(t1), and the per-sample
loss |y|^2 is zero when the pendulum ends at rest, hanging down.

diffrax integrates with Tsit5: a fixed step t1 / steps (adaptive=false), or steps chosen by a PID
controller at tolerances rtol and atol (adaptive=true), at most max_steps of them (beyond: the run
ends `solver failed`). Gradients go through diffrax's default adjoint (RecursiveCheckpointAdjoint:
reverse mode only; physgrad's Jacobian check builds its reference in reverse mode then).

network=physgrad builds the network with physgrad.nets (the Gauss-Newton and HIG steps get the
layer-factorised Jacobian); network=equinox uses eqx.nn.MLP, whose layers physgrad does not see:
the per-sample Jacobian, with the reason in the job's log.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.validate import number


def build(
    key,
    *,
    gravity,
    length,
    damping,
    t1,
    modes,
    steps,
    adaptive,
    rtol,
    atol,
    max_steps,
    network,
    hidden,
    train_size,
    test_size,
):
    """physgrad calls this with the keys of conf/task/ode_control.yaml and a PRNG key."""
    t1 = number("task.t1", t1, 0, open_low=True)
    dtype = jnp.zeros(()).dtype
    frequencies = jnp.arange(1, modes + 1, dtype=dtype) * jnp.pi / t1

    def vector_field(t, state, coefficients):
        theta, omega = state
        torque = jnp.sum(coefficients * jnp.sin(frequencies * t))
        return jnp.stack([omega, -gravity / length * jnp.sin(theta) - damping * omega + torque])

    if adaptive:
        controller = diffrax.PIDController(rtol=rtol, atol=atol)
    else:
        controller = diffrax.ConstantStepSize()

    def final_state(coefficients, start):
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field),
            diffrax.Tsit5(),
            t0=0.0,
            t1=t1,
            dt0=t1 / steps,
            y0=start,
            args=coefficients,
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=controller,
            max_steps=max_steps,
        )
        return solution.ys[-1]

    sizes = [2, *hidden, modes]
    if network == "equinox":
        width, depth = hidden[0], len(hidden)

        def mlp(k):
            return eqx.nn.MLP(2, modes, width, depth, activation=jnp.tanh, dtype=dtype, key=k)

        static = eqx.partition(mlp(jax.random.PRNGKey(0)), eqx.is_array)[1]

        def init_params(k):
            return eqx.partition(mlp(k), eqx.is_array)[0]

        def controls(params, start):
            return eqx.combine(params, static)(start)
    elif network == "physgrad":

        def init_params(k):
            return init_mlp(k, sizes, dtype)

        def controls(params, start):
            return apply_mlp(params, start, hidden="tanh")
    else:
        raise ValueError(f"task.network={network}: physgrad or equinox")

    def starts(k, count):
        return {"start": jax.random.uniform(k, (count, 2), dtype, -1.0, 1.0)}

    train_key, test_key = jax.random.split(key)
    return Scene(
        init_params=init_params,
        train_set=starts(train_key, train_size),
        test_set=starts(test_key, test_size),
        sample_output=lambda params, sample: final_state(
            controls(params, sample["start"]), sample["start"]
        ),
        sample_loss=lambda y, sample: jnp.sum(y**2),
    )
