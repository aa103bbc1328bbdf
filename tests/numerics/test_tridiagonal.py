"""The tridiagonal solves of physgrad.tridiagonal against a dense numpy solve (float64), their
gradients against finite differences, and the quantum scene's loss, gradient and per-sample Jacobian
the same on every path."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad.tasks.quantum as quantum
from physgrad import tridiagonal
from physgrad.configs import compose
from physgrad.experiment import prepare
from physgrad.job_spec import checked
from physgrad.tasks.quantum import crank_nicolson_step, eigenstate, grid

PATHS = sorted(tridiagonal.SOLVES)


def crank_nicolson_system(rng: np.random.Generator, points: int) -> tuple:
    """A = I + i dt/2 H with H = -D2 + u diag(x) (a random field, strong and of either sign) and a
    random complex right-hand side: the systems the quantum scene solves."""
    x = np.arange(1, points + 1) * 2.0 / (points + 1)
    dx, dt, u = x[0], 0.05, rng.uniform(-200, 200)
    half = 0.5j * dt
    diagonal = 1.0 + half * (2.0 / dx**2 + u * x)
    off = np.full(points, -half / dx**2)
    lower, upper = off.copy(), off.copy()
    lower[0] = upper[-1] = 0.0
    rhs = rng.standard_normal(points) + 1j * rng.standard_normal(points)
    return lower, diagonal, upper, rhs


def dense_reference(lower, diagonal, upper, rhs):
    matrix = np.diag(diagonal) + np.diag(lower[1:], -1) + np.diag(upper[:-1], 1)
    return np.linalg.solve(matrix, rhs)


# make test-long: the larger systems (32 and 200 points); make test keeps every path at 3 points and
# at the quantum scenes' 14
@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize(
    "points",
    [3, 14, pytest.param(32, marks=pytest.mark.long), pytest.param(200, marks=pytest.mark.long)],
)
def test_every_path_solves_the_crank_nicolson_system(x64, path, points):
    rng = np.random.default_rng(points)
    for _ in range(5):
        system = crank_nicolson_system(rng, points)
        x = tridiagonal.SOLVES[path](*map(jnp.asarray, system))
        np.testing.assert_allclose(x, dense_reference(*system), rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("path", PATHS)
def test_every_path_solves_a_real_diagonally_dominant_system(x64, path):
    rng = np.random.default_rng(7)
    lower, upper = rng.uniform(-1, 1, 20), rng.uniform(-1, 1, 20)
    lower[0] = upper[-1] = 0.0
    diagonal = 2.5 + rng.uniform(0, 1, 20)
    rhs = rng.standard_normal(20)
    x = tridiagonal.SOLVES[path](*map(jnp.asarray, (lower, diagonal, upper, rhs)))
    np.testing.assert_allclose(x, dense_reference(lower, diagonal, upper, rhs), rtol=1e-12)


@pytest.mark.parametrize("path", PATHS)
def test_gradients_of_every_path_match_finite_differences(x64, path):
    """d/du of |<phi_2| psi(T)>|^2 after 40 Crank-Nicolson steps under a field u_k, against central
    differences, with the solve of `path`."""
    x, psi0 = grid(14, jnp.float64), eigenstate(1, 14, jnp.float64).astype(jnp.complex128)
    target = eigenstate(2, 14, jnp.float64)
    solve = tridiagonal.SOLVES[path]

    def loss(field):
        def body(psi, u):
            return crank_nicolson_step(psi, u, x, 0.05, solve), None

        return jnp.abs(jnp.vdot(target, jax.lax.scan(body, psi0, field)[0])) ** 2

    field = jax.random.normal(jax.random.PRNGKey(3), (40,), jnp.float64) * 3.0
    grad = jax.grad(loss)(field)
    eps = 1e-6
    for k in (0, 17, 39):
        bump = jnp.zeros(40).at[k].set(eps)
        numeric = (loss(field + bump) - loss(field - bump)) / (2 * eps)
        assert abs(float(grad[k]) - float(numeric)) < 1e-8 * max(1.0, abs(float(numeric)))


def scene_quantities(monkeypatch, path: str, overrides: list[str]) -> tuple:
    """The quantum scene built with `path`: batch loss, its gradient and the per-sample Jacobian
    of the outputs (jacrev under vmap, the Jacobian route's form) on one minibatch."""
    monkeypatch.setattr(quantum, "solve_for", lambda backend: tridiagonal.SOLVES[path])
    cfg = compose(overrides)
    scene, _, seeds = prepare(checked(cfg), [cfg.seed])
    params = seeds.network()
    batch = scene.sample_train(jax.random.PRNGKey(1), 4)

    def loss(p):
        return scene.batch_loss(scene.batch_output(p, batch), batch)

    # compiled whole: op by op, each of the rollout's operations would be a compile of its own
    value, grad = jax.jit(jax.value_and_grad(loss))(params)
    jacobian = jax.jit(jax.vmap(jax.jacrev(scene.sample_output), in_axes=(None, 0)))(params, batch)
    return value, grad, jacobian


# the data sets' sizes do not change what one minibatch computes
SMALL_DATA = ["task.train_size=8", "task.test_size=8", "task.batch_size=4"]


# whole float64 rollouts of both quantum scenes through every path, against the library's solve
# (6 to 7 s each on 2 cores): make test-long; make test checks each path's solve and gradients above
@pytest.mark.long
@pytest.mark.parametrize("path", [p for p in PATHS if p != "library"])
@pytest.mark.parametrize(
    "overrides",
    [
        ["task=quantum", "task.unroll=24", "precision=64", *SMALL_DATA],
        ["task=quantum_control", "task.unroll=4", "precision=64", *SMALL_DATA],
    ],
)
def test_the_scene_gives_the_same_loss_gradient_and_jacobian_on_every_path(
    x64, monkeypatch, path, overrides
):
    reference = scene_quantities(monkeypatch, "library", overrides)
    other = scene_quantities(monkeypatch, path, overrides)
    for a, b in zip(jax.tree_util.tree_leaves(reference), jax.tree_util.tree_leaves(other)):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)


def test_each_backend_and_route_gets_a_path_and_an_unknown_backend_the_cpus():
    for backend in ("cpu", "gpu", "tpu"):
        for route in tridiagonal.ROUTES:
            name = tridiagonal.fastest(backend, route)
            assert name in tridiagonal.SOLVES
            known = (backend, route) in tridiagonal.FASTEST
            assert name == tridiagonal.FASTEST[(backend, route) if known else ("cpu", route)]


def test_the_jacobian_pass_traces_the_scene_on_the_jacobian_route(monkeypatch):
    """The solve a scene built for a backend calls is the route's: the Jacobian pass (both forms
    of J) traces inside jacobian_route, a plain gradient outside it."""
    called = []
    for name, solve in tridiagonal.SOLVES.items():
        monkeypatch.setitem(
            tridiagonal.SOLVES,
            name,
            lambda *args, name=name, solve=solve: called.append(name) or solve(*args),
        )
    monkeypatch.setitem(tridiagonal.FASTEST, ("cpu", "gradient"), "library")
    monkeypatch.setitem(tridiagonal.FASTEST, ("cpu", "jacobian"), "dense")
    for optim, expected in (("adam", "library"), ("hig", "dense"), ("gauss_newton", "dense")):
        cfg = compose(["task=quantum", f"optim={optim}", "task.unroll=4", "task.batch_size=2"])
        scene, rule, seeds = prepare(checked(cfg), [cfg.seed])
        batch = scene.sample_train(jax.random.PRNGKey(0), 2)
        called.clear()  # building the rule traces the scene once (a layer plan): not a step
        jax.eval_shape(lambda p: rule.gradient(scene, p, batch)[0], seeds.network())
        assert called and set(called) == {expected}, (optim, set(called))
