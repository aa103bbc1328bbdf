"""An inverse problem through exponax's Burgers stepper: which start gives this field later?

    u_t + u u_x = nu u_xx  on the periodic domain [0, 1), `points` grid points,

stepped by exponax's ETDRK Burgers stepper (exponax.stepper.Burgers, time step dt). A sample is a
field u_T observed after `horizon` steps from a start that is a sum of `modes` random sine and
cosine modes. The network maps u_T to a start u0; the physical output y is u0 stepped `horizon`
times (`points` components), and the per-sample loss is the mean of (y - u_T)^2: zero when the
network's start reproduces the observation.
"""

import exponax
import jax
import jax.numpy as jnp

from physgrad.nets import apply_mlp, init_mlp
from physgrad.tasks import Scene
from physgrad.validate import number


def build(key, *, points, dt, viscosity, horizon, modes, amplitude, hidden, train_size, test_size):
    """physgrad calls this with the keys of conf/task/burgers_inverse.yaml and a PRNG key."""
    dt = number("task.dt", dt, 0, open_low=True)
    dtype = jnp.zeros(()).dtype
    stepper = exponax.stepper.Burgers(1, 1.0, points, dt, diffusivity=viscosity)
    grid = jnp.arange(points, dtype=dtype) / points

    def evolve(start):
        def step(field, _):
            return stepper(field), None

        return jax.lax.scan(step, start[None, :], None, length=horizon)[0][0]

    def observations(k, count):
        weights = jax.random.normal(k, (count, 2, modes), dtype) * amplitude
        waves = 2 * jnp.pi * jnp.arange(1, modes + 1, dtype=dtype)[:, None] * grid
        starts = weights[:, 0] @ jnp.sin(waves) + weights[:, 1] @ jnp.cos(waves)
        return {"target": jax.vmap(evolve)(starts)}

    train_key, test_key = jax.random.split(key)
    return Scene(
        init_params=lambda k: init_mlp(k, [points, *hidden, points], dtype),
        train_set=observations(train_key, train_size),
        test_set=observations(test_key, test_size),
        sample_output=lambda params, sample: evolve(
            apply_mlp(params, sample["target"], hidden="tanh")
        ),
        sample_loss=lambda y, sample: jnp.mean((y - sample["target"]) ** 2),
    )
