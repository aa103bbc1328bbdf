"""An inverted pendulum on a motor: a closed-loop controller must catch it and hold it upright.

theta = 0 is upright; theta'' = (g / l) sin(theta) - damping * theta' + torque. Semi-implicit Euler
with step dt. Start: theta and theta' uniform in [-0.6, 0.6]. The physical output y is the final
state (theta, theta'), and the per-sample loss |y|^2: zero when the pendulum ends upright and at
rest.
"""

import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.unroll import Dynamics
from physgrad.validate import number


def build(key, *, gravity, length, damping, dt, unroll, hidden, train_size, test_size):
    """physgrad calls this with the keys of conf/task/pendulum.yaml and a PRNG key for the data."""
    dt = number("task.dt", dt, 0, open_low=True)  # a bad setting is a one-line error naming the key
    dtype = jnp.zeros(()).dtype  # float32, or float64 under precision=64

    def step(state, torque):
        theta, omega = state
        omega = omega + dt * (gravity / length * jnp.sin(theta) - damping * omega + torque)
        return jnp.stack([theta + dt * omega, omega])

    def policy(params, sample):  # closed loop: the network sees the state at every step
        return lambda state, k: apply_mlp(params, state, hidden="tanh")[0]

    def starts(k, count):
        return {"state": jax.random.uniform(k, (count, 2), dtype, -0.6, 0.6)}

    train_key, test_key = jax.random.split(key)
    return Scene(
        init_params=lambda k: init_mlp(k, [2, *hidden, 1], dtype),
        train_set=starts(train_key, train_size),
        test_set=starts(test_key, test_size),
        dynamics=Dynamics(
            step=step,
            policy=policy,
            initial=lambda sample: sample["state"],
            unroll=unroll,
            closed_loop=True,
        ),
        sample_loss=lambda y, sample: jnp.sum(y**2),
        sample_metrics=lambda params, sample, y: {"upright": (jnp.abs(y[0]) < 0.1).astype(dtype)},
    )
