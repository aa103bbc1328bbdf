"""Kuramoto-Sivashinsky: the ETD solvers against closed forms (linear part, nonlinear term) and
their order of convergence, the data cache, the training modalities' gradients against plain loops
and finite differences (float64), NOG's and ONE's structure, and the held-out metric against a numpy
evaluation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.nets import apply_resnet, init_resnet
from physgrad.tasks import build_scene
from physgrad.tasks.ks_solver import (
    cache_dir,
    dataset,
    etd_step,
    nonlinear,
    phi1,
    phi2,
    solver_step,
    wavenumbers,
)
from physgrad.unroll import MODES
from tests.helpers import REPO, load
from tests.reference import check_gradient, forward_states, loop_states

# a small network and short trajectories: every check below is about structure, not about the data's
# size
SMALL = [
    "task.channels=3",
    "task.blocks=1",
    "task.train_steps=30",
    "task.warmup=20",
    "task.test_count=2",
    "task.test_steps=24",
    "task.horizon=4",
    "task.long_horizon=12",
    "task.train_sizes=[0.9,1.1]",
    "task.test_sizes=[0.85,1.4]",
]


def scene_of(*overrides):
    return build_scene(load("task=ks", *SMALL, *overrides).task, jax.random.PRNGKey(0))


def grid(points, length):
    return length * np.arange(points) / points


@pytest.mark.parametrize("order", [1, 2])
def test_linear_part_is_exact_for_any_step(order, x64):
    """A single small Fourier mode evolves as eps e^{(k^2 - k^4) t} cos(k x) + O(eps^2): both
    schemes integrate the linear part exactly, so the error is the nonlinear term's, relative
    O(eps), at any step size."""
    points, length, eps = 48, 2 * math.pi * 8 * 1.1, 1e-9
    x = grid(points, length)
    for n in (1, 5, 9, 17, 23):
        kappa = 2 * math.pi * n / length
        u = eps * np.cos(kappa * x)
        for h in (0.05, 0.5, 2.0):
            exact = eps * math.exp((kappa**2 - kappa**4) * h) * np.cos(kappa * x)
            stepped = np.asarray(etd_step(jnp.asarray(u), length, h, order))
            np.testing.assert_allclose(stepped, exact, atol=1e-6 * eps, rtol=0)


def test_nonlinear_term_is_minus_u_u_x(x64):
    """N(u) of u = sin(k x) + cos(2 k x)/2 against -u u_x written out by hand."""
    points, length = 48, 2 * math.pi * 8
    kappa = 2 * math.pi * 3 / length
    x = grid(points, length)
    u = np.sin(kappa * x) + 0.5 * np.cos(2 * kappa * x)
    u_x = kappa * np.cos(kappa * x) - kappa * np.sin(2 * kappa * x)
    got = np.fft.irfft(np.asarray(nonlinear(jnp.asarray(u), wavenumbers(points, length))), points)
    np.testing.assert_allclose(got, -u * u_x, atol=1e-13)


def test_phi_functions_at_round_off_near_zero(x64):
    """phi1 and phi2 from math.expm1 where it is exact enough, from their series where the direct
    form cancels; at x ~ 1e-16 (kappa = 1 exactly: base_domain * size whole) they are their limits,
    not noise."""
    for x in (-50.0, -3.0, -0.5, -0.1000001, -0.0999999, -1e-3, 1e-3, 0.0999999, 0.1000001, 0.7):
        np.testing.assert_allclose(float(phi1(jnp.float64(x))), math.expm1(x) / x, rtol=1e-14)
    for x in (-50.0, -3.0, -0.5, -0.1000001, 0.1000001, 0.7):
        np.testing.assert_allclose(
            float(phi2(jnp.float64(x))), (math.expm1(x) - x) / x**2, rtol=1e-13
        )
    for x in (0.0, 1e-16, -2e-16, 1e-9):  # the series' leading terms
        np.testing.assert_allclose(float(phi1(jnp.float64(x))), 1 + x / 2, rtol=1e-15)
        np.testing.assert_allclose(float(phi2(jnp.float64(x))), 0.5 + x / 6, rtol=1e-15)
    # the step itself is continuous across a size where one mode's linear rate is exactly 0
    rng = np.random.default_rng(0)
    u = jnp.asarray(rng.normal(size=48))
    at = etd_step(u, 2 * math.pi * 8 * 1.0, 0.5, 2)
    near = etd_step(u, 2 * math.pi * 8 * (1.0 + 1e-12), 0.5, 2)
    np.testing.assert_allclose(at, near, atol=1e-9)


# the scene's ETD2RK in make test, ETD1 in make test-long
@pytest.mark.parametrize("order", [pytest.param(1, marks=pytest.mark.long), 2])
def test_order_of_convergence(order, x64):
    """Error at t = 2 of a smooth state against ETD2RK with 1024 steps: it falls by 2^order per
    halving of h."""
    points, length = 48, 2 * math.pi * 8 * 0.95
    x = grid(points, length)
    u0 = jnp.asarray(np.cos(2 * math.pi * x / length) + 0.5 * np.sin(4 * math.pi * x / length))
    reference = solver_step(u0, length, 2.0 / 1024, 1024, 2)
    errors = [
        float(jnp.max(jnp.abs(solver_step(u0, length, 2.0 / steps, steps, order) - reference)))
        for steps in (8, 16, 32, 64)
    ]
    rates = [math.log2(a / b) for a, b in zip(errors, errors[1:])]
    assert all(abs(rate - order) < 0.15 for rate in rates), (errors, rates)


def test_data_generated_once_and_again_when_settings_change(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path))
    assert cache_dir() == tmp_path
    settings = {
        "points": 16,
        "base_domain": 2.0,
        "train_sizes": [1.0],
        "test_sizes": [1.2],
        "dt": 0.5,
        "substeps": 2,
        "warmup": 5,
        "train_steps": 7,
        "test_count": 2,
        "test_steps": 4,
    }
    first = dataset(settings)
    assert first["train"].shape == (1, 6, 8, 16) and first["test"].shape == (1, 2, 5, 16)
    assert first["train"].dtype == np.float64
    files = sorted(tmp_path.glob("ks-*.npz"))
    assert len(files) == 1
    stamp = files[0].stat().st_mtime_ns
    again = dataset(settings)
    np.testing.assert_array_equal(again["train"], first["train"])
    assert files[0].stat().st_mtime_ns == stamp  # read, not written again
    changed = dataset({**settings, "dt": 0.25})
    assert len(sorted(tmp_path.glob("ks-*.npz"))) == 2
    assert not np.allclose(changed["train"][:, :, -1], first["train"][:, :, -1])
    files[0].write_bytes(b"damaged")  # a damaged cache file is generated again
    np.testing.assert_array_equal(dataset(settings)["train"], first["train"])
    assert not list(tmp_path.glob(".*tmp"))


def test_data_are_the_ground_truth_solver(x64):
    """Consecutive stored frames are one ETD2RK model step apart (float64 data)."""
    scene = scene_of()
    frames, size = np.asarray(scene.train_set["frames"]), np.asarray(scene.train_set["size"])
    length = 2 * math.pi * 8 * size[3]
    # compiled, as the data's generator compiles it: eagerly, each ETD step's small operations were
    # compiled one by one; the same operations, at the same tolerance
    step = jax.jit(solver_step, static_argnums=(2, 3, 4))
    np.testing.assert_allclose(
        step(jnp.asarray(frames[3]), length, 0.5, 2, 2), frames[4], atol=1e-12
    )
    assert set(np.unique(size)) == {0.9, 1.1}
    test = scene.test_set
    assert test["state"].shape == (4, 48) and test["target"].shape == (4, 24, 48)


def resnet_in_plain_numpy(params, u, size):
    """The ResNet written out point by point (periodic indices) in numpy."""

    def conv(x, w, b):
        w, b = np.asarray(w), np.asarray(b)
        n = x.shape[0]
        return np.stack([sum(x[(i + k - 1) % n] @ w[k] for k in range(3)) + b for i in range(n)])

    def leaky(z):
        return np.where(z > 0, z, 0.01 * z)

    x = conv(
        np.stack([u, np.full_like(u, size)], axis=1), params["input"]["w"], params["input"]["b"]
    )
    first, second = params["blocks"]["first"], params["blocks"]["second"]
    for index in range(first["w"].shape[0]):
        inner = leaky(conv(x, first["w"][index], first["b"][index]))
        x = leaky(conv(inner, second["w"][index], second["b"][index]) + x)
    return conv(x, params["output"]["w"], params["output"]["b"])[:, 0]


def test_network_against_numpy_and_its_size(x64):
    layers = init_resnet(jax.random.PRNGKey(1), 4, 2, jnp.float64)
    u = np.random.default_rng(1).normal(size=12)
    np.testing.assert_allclose(
        apply_resnet(layers, jnp.asarray(u), 1.1), resnet_in_plain_numpy(layers, u, 1.1), rtol=1e-12
    )
    reference = init_resnet(jax.random.PRNGKey(0), 16, 10, jnp.float32)
    assert sum(leaf.size for leaf in jax.tree_util.tree_leaves(reference)) == 15841
    # PyTorch's default: U(-1/sqrt(fan_in), 1/sqrt(fan_in)), fan_in = 3 C_in
    bound = 1 / math.sqrt(3 * 16)
    blocks = reference["blocks"]["first"]["w"]
    assert 0.9 * bound < float(jnp.max(jnp.abs(blocks))) <= bound
    zero = init_resnet(jax.random.PRNGKey(0), 16, 10, jnp.float32, zero_output=True)
    assert float(jnp.max(jnp.abs(apply_resnet(zero, jnp.ones(48), 1.0)))) == 0.0


@pytest.mark.long
def test_unrolled_gradients_against_loops_and_finite_differences(x64):
    """WIG (R), M and S against plain loops with the same stops, and against finite differences of
    them, for both steppers; NOG is S: the same gradient, whatever optim.backprop adds."""
    for stepper in ("correct", "predict"):
        scene = scene_of(f"task.stepper={stepper}", "task.unroll=3")
        nog = scene_of(f"task.stepper={stepper}", "task.unroll=3", "task.training=NOG")
        params = scene.init_params(jax.random.PRNGKey(3))
        batch = scene.sample_train(jax.random.PRNGKey(4), 2)
        dyn = scene.dynamics
        # one compiled solver step, called by the plain loops step after step (no lax.scan)
        step = jax.jit(dyn.step)
        samples = [jax.tree_util.tree_map(lambda leaf: leaf[i], batch) for i in range(2)]
        # the forward states at these parameters: the constants a mode's stopped inputs see
        frozen = [forward_states(step, dyn.policy(params, s), dyn.initial(s), 3) for s in samples]
        # (predict has no solver in the step: its M is S, checked below)
        for mode in ("R", "M", "S") if stepper == "correct" else ("R", "S"):

            def loop_loss(p, mode=mode):
                losses = []
                for i, sample in enumerate(samples):
                    states = loop_states(
                        step,
                        dyn.policy(p, sample),
                        dyn.initial(sample),
                        3,
                        MODES[mode],
                        frozen[i],
                    )
                    y = jnp.concatenate([s[0] for s in states])
                    losses.append(scene.sample_loss(y, sample))
                return jnp.mean(jnp.stack(losses))

            def scan_loss(p, mode=mode):
                output = scene.backprop_output(MODES[mode])
                return scene.batch_loss(jax.vmap(output, in_axes=(None, 0))(p, batch), batch)

            gradient = check_gradient(loop_loss, scan_loss, params, directions=2)
            if mode == "S":
                for nog_mode in ("R", "S"):
                    g_nog = jax.grad(
                        lambda p: nog.batch_loss(
                            jax.vmap(nog.backprop_output(MODES[nog_mode]), in_axes=(None, 0))(
                                p, batch
                            ),
                            batch,
                        )
                    )(params)
                    for a, b in zip(
                        jax.tree_util.tree_leaves(g_nog), jax.tree_util.tree_leaves(gradient)
                    ):
                        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
        if stepper == "predict":  # no solver path: M stops what S stops
            g_m = jax.grad(
                lambda p: scene.batch_loss(
                    jax.vmap(scene.backprop_output(MODES["M"]), in_axes=(None, 0))(p, batch), batch
                )
            )(params)
            g_s = jax.grad(
                lambda p: scene.batch_loss(
                    jax.vmap(scene.backprop_output(MODES["S"]), in_axes=(None, 0))(p, batch), batch
                )
            )(params)
            for a, b in zip(jax.tree_util.tree_leaves(g_m), jax.tree_util.tree_leaves(g_s)):
                np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


@pytest.mark.long  # float64 gradients through a 4-step rollout, twice: 6.6 s on 2 cores
def test_nog_has_no_path_through_earlier_steps(x64):
    """NOG's gradient is the sum of one-step gradients from the (detached) states the rollout
    visits: the loss term of step k does not depend on the network through steps before k."""
    scene = scene_of("task.training=NOG", "task.unroll=4")
    params = scene.init_params(jax.random.PRNGKey(5))
    sample = jax.tree_util.tree_map(
        lambda leaf: leaf[0], scene.sample_train(jax.random.PRNGKey(6), 1)
    )
    regular = scene_of("task.unroll=4")
    visited = forward_states(
        regular.dynamics.step,
        regular.dynamics.policy(params, sample),
        regular.dynamics.initial(sample),
        4,
    )
    h = 0.5

    def one_step_terms(p):
        total = 0.0
        for k in range(4):
            u, size = visited[k]
            next_u = solver_step(u, 2 * math.pi * 8 * size, h, 2, 1) + h * apply_resnet(p, u, size)
            total = total + jnp.sum((next_u - sample["target"][k]) ** 2)
        return total / sample["target"].size

    g_nog = jax.grad(lambda p: scene.sample_loss(scene.sample_output(p, sample), sample))(params)
    for a, b in zip(
        jax.tree_util.tree_leaves(g_nog),
        jax.tree_util.tree_leaves(jax.grad(one_step_terms)(params)),
    ):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-15)

    # and the last step's term has a gradient only through the last network call: perturbing the
    # states the rollout passed through (all but the last) does not change it
    def last_term(p):
        y = scene.sample_output(p, sample).reshape(4, -1)
        return jnp.sum((y[-1] - sample["target"][-1]) ** 2)

    def last_from_frozen(p):
        u, size = visited[3]
        return jnp.sum(
            (
                solver_step(u, 2 * math.pi * 8 * size, h, 2, 1)
                + h * apply_resnet(p, u, size)
                - sample["target"][-1]
            )
            ** 2
        )

    for a, b in zip(
        jax.tree_util.tree_leaves(jax.grad(last_term)(params)),
        jax.tree_util.tree_leaves(jax.grad(last_from_frozen)(params)),
    ):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-15)


@pytest.mark.long
def test_one_is_compute_matched_one_step_training(x64):
    """ONE: a batch of B holds B x m independent ground-truth pairs, each predicted from its
    ground-truth input: as many network and solver evaluations per update as B unrolled windows of m
    steps (the same update count); its gradient against a plain loop over the pairs and finite
    differences."""
    m, batch_size = 4, 3
    one = scene_of("task.training=ONE", f"task.unroll={m}")
    wig = scene_of(f"task.unroll={m}")
    params = one.init_params(jax.random.PRNGKey(7))
    pairs = one.sample_train(jax.random.PRNGKey(8), batch_size)
    windows = wig.sample_train(jax.random.PRNGKey(8), batch_size)
    assert (
        pairs["inputs"].shape
        == pairs["target"].shape
        == (batch_size, m, 48)
        == windows["target"].shape
    )
    assert pairs["sizes"].shape == (batch_size, m)
    y_one, y_wig = one.batch_output(params, pairs), wig.batch_output(params, windows)
    assert y_one.shape == y_wig.shape == (batch_size, m * 48)
    # the pairs are ground truth, one model step apart
    for b in range(batch_size):
        for k in range(m):
            length = 2 * math.pi * 8 * float(pairs["sizes"][b, k])
            np.testing.assert_allclose(
                solver_step(pairs["inputs"][b, k], length, 0.5, 2, 2),
                pairs["target"][b, k],
                atol=1e-12,
            )
    # drawn independently, not a window: no sample's pairs chain into each other
    chained = [
        bool(jnp.all(pairs["inputs"][b, 1:] == pairs["target"][b, :-1])) for b in range(batch_size)
    ]
    assert not any(chained)

    def count_network_calls(scene, batch):
        """Matrix products in the traced loss: 2 + 2 x blocks per network call."""
        jaxpr = jax.make_jaxpr(lambda p: scene.batch_loss(scene.batch_output(p, batch), batch))(
            params
        )
        text = str(jaxpr)
        return text.count("dot_general"), text.count("fft")

    one_calls, wig_calls = count_network_calls(one, pairs), count_network_calls(wig, windows)
    assert one_calls == wig_calls

    def loop_loss(p):
        total = 0.0
        for b in range(batch_size):
            for k in range(m):
                u, size = pairs["inputs"][b, k], pairs["sizes"][b, k]
                next_u = solver_step(u, 2 * math.pi * 8 * size, 0.5, 2, 1) + 0.5 * apply_resnet(
                    p, u, size
                )
                total = total + jnp.mean((next_u - pairs["target"][b, k]) ** 2)
        return total / (batch_size * m)

    check_gradient(
        loop_loss, lambda p: one.batch_loss(one.batch_output(p, pairs), pairs), params, directions=2
    )


def test_held_out_error_is_the_studys_relative_error(x64):
    """loss = mean over the horizon of min(mean_x (u - u*)^2 / max u*^2, 30) with the max over
    frames 0..horizon, against numpy from the rollout;
    a blown-up rollout counts 30 per step; the stability metrics from the long rollout."""
    scene = scene_of()
    params = scene.init_params(jax.random.PRNGKey(9))
    test = scene.test_set
    metrics = jax.jit(scene.evaluate)(params, test)
    horizon = 4
    errors = []

    # one model step of the correction stepper, compiled as the scene's rollout compiles it
    # (eagerly, each of its small operations was compiled one by one); the same operations
    @jax.jit
    def model_step(u, length, size):
        return solver_step(u, length, 0.5, 2, 1) + 0.5 * apply_resnet(params, u, size)

    for i in range(test["state"].shape[0]):
        u, states = test["state"][i], []
        for _ in range(horizon):
            length = 2 * math.pi * 8 * float(test["size"][i])
            u = model_step(u, length, test["size"][i])
            states.append(np.asarray(u))
        truth = np.asarray(test["target"][i, :horizon])
        # the study's normaliser: frames 0..horizon, the test state itself included
        scale = np.max(np.concatenate([np.asarray(test["state"][i])[None], truth]) ** 2)
        per_step = np.mean((np.array(states) - truth) ** 2, axis=1) / scale
        errors.append(np.mean(np.where(np.isfinite(per_step), np.minimum(per_step, 30.0), 30.0)))
    np.testing.assert_allclose(metrics["loss"], np.mean(errors), rtol=1e-10)
    assert 0 <= metrics["unstable_fraction"] <= 1 and 0 <= metrics["decorrelation_steps"] <= 12
    blown = {**jax.tree_util.tree_map(lambda leaf: leaf[:1], test)}
    bad = scene.sample_loss(
        jnp.full((horizon * 48,), jnp.nan), jax.tree_util.tree_map(lambda leaf: leaf[0], blown)
    )
    assert float(bad) == 30.0


def test_bad_settings_are_one_line(tmp_path):
    from physgrad.errors import UserError

    for override, fragment in (
        ("task.stepper=both", "task.stepper"),
        ("task.training=TBPTT", "task.training"),
        ("task.points=47", "even"),
        ("task.train_sizes=[]", "task.train_sizes"),
        ("task.horizon=100", "task.horizon"),
    ):
        with pytest.raises(UserError, match=fragment):
            scene_of(override)


def test_study_claims_compare_seed_by_seed():
    """experiments/ks_study.py: ratios and wins paired by seed, a diverged run as an infinite error,
    and the best unroll length by median."""
    import sys

    sys.path.insert(0, str(REPO / "experiments"))
    from ks_study import claims

    table = {
        ("correct", "WIG", 2): {0: (0.01, 0.0), 1: (0.02, 0.0)},
        ("predict", "WIG", 2): {0: (0.05, 0.0), 1: (0.04, 0.0)},
        ("correct", "NOG", 2): {0: (0.03, 0.0), 1: (0.01, 0.0)},
        ("correct", "ONE", 2): {0: (np.inf, 1.0), 1: (0.04, 0.0)},
        ("correct", "WIG", 4): {0: (0.005, 0.0), 1: (0.006, 0.0)},
    }
    text = claims(table)
    assert "predict/correct error ratio: 3.5 " in text and "correct lower in 2 / 2" in text
    assert "WIG < NOG 1/2 (NOG/WIG 1.75)" in text and "WIG < ONE 2/2" in text
    assert "ONE inf (diverged)" in text
    assert "(correct, WIG) | best m = 4" in text


def test_adam_on_ks_uses_pytorchs_epsilon_as_the_study_does():
    from physgrad.configs import compose

    # PyTorch's default (the study's framework)
    assert compose(["task=ks", "optim=adam"]).optim.eps == 1e-8
    # Keras's, as the HIG references
    assert compose(["task=oscillator", "optim=adam"]).optim.eps == 1e-7


def test_the_validation_states_are_the_test_family_from_other_seeds(tmp_path, monkeypatch):
    """Tuning sees held-out states of the test set's distribution, never the test states: both are
    the test family's members from fixed seeds (test 1000 + the size's index, validation 2000 + it),
    warmed up 2 x warmup model steps by the ground-truth solver."""
    from physgrad.experiment import validation_set
    from physgrad.job_spec import checked
    from physgrad.tasks.ks_solver import domain_length, test_initial_states, trajectories

    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path))
    settings = {
        "points": 16,
        "base_domain": 2.0,
        "train_sizes": [1.0],
        "test_sizes": [1.2, 1.4],
        "dt": 0.5,
        "substeps": 2,
        "warmup": 5,
        "train_steps": 7,
        "test_count": 3,
        "test_steps": 4,
    }
    data = dataset(settings)
    assert data["validation"].shape == data["test"].shape == (2, 3, 5, 16)
    for index, size in enumerate(settings["test_sizes"]):
        lengths = np.full(3, float(domain_length(2.0, size)))
        for part, seed in (("test", 1000), ("validation", 2000)):
            initial = test_initial_states(16, 2.0, size, 3, seed + index)
            warm = trajectories(initial, lengths, 10, 0.5, 2)[:, -1]
            np.testing.assert_allclose(data[part][index, :, 0], warm, rtol=1e-12, atol=1e-12)
    assert not np.allclose(data["validation"], data["test"])
    # read back from the cache
    np.testing.assert_array_equal(dataset(settings)["validation"], data["validation"])

    scene = scene_of()
    held_out = validation_set(checked(load("task=ks", *SMALL)), scene, jax.random.PRNGKey(0))
    assert held_out is scene.validation_set
    assert held_out["state"].shape == scene.test_set["state"].shape
    assert not np.allclose(held_out["state"], scene.test_set["state"])
