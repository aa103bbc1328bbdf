"""Rules that are not element-wise see the network's layers (physgrad.optim.on_tree); element-wise
rules keep the fused flat update, which computes the same numbers."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

import physgrad
from physgrad.configs import compose
from physgrad.errors import UserError
from physgrad.experiment import prepare
from physgrad.job_spec import checked
from physgrad.optim import build_rule, on_tree
from physgrad.runner import compile_training
from physgrad.trainer_settings import TrainerSettings


def toy(optim: str, *extra):
    # two 20 x 20 hidden kernels: matrices a layer-wise rule factors or orthogonalises
    cfg = compose(["task=toy", "task.hidden=[20,20]", f"optim={optim}", *extra])
    settings = TrainerSettings.from_config(cfg.trainer)
    scene, rule, seeds = prepare(checked(cfg), [0])
    return scene, rule, seeds, settings


def first_step(scene, rule, seeds, settings):
    compiled = compile_training(scene, rule, seeds, settings.batch_size)
    params, _, _ = compiled.step(
        compiled.params, compiled.opt_state, np.int32(0), seeds.train_keys, seeds.train_sets
    )
    return np.asarray(params[0])


def reference_step(scene, transform, seeds, settings, on_layers: bool):
    """One step of the transform by hand on the same batch: on the parameter tree, or on the flat
    vector."""
    tree = seeds.network()
    flat, unravel = ravel_pytree(tree)
    batch = scene.sample_train(jax.random.fold_in(seeds.train_keys[0], 0), settings.batch_size)
    loss = lambda p: scene.batch_loss(scene.batch_output(p, batch), batch)  # noqa: E731
    if on_layers:
        grads = jax.grad(loss)(tree)
        updates, _ = transform.update(grads, transform.init(tree), tree)
        return np.asarray(ravel_pytree(optax.apply_updates(tree, updates))[0])
    grads = jax.grad(lambda f: loss(unravel(f)))(flat)
    updates, _ = transform.update(grads, transform.init(flat), flat)
    return np.asarray(flat + updates)


@pytest.mark.long
def test_muon_orthogonalises_each_layer_not_one_flat_vector(x64):
    # float64: the comparison is of rules, not of round-off
    scene, rule, seeds, settings = toy("muon", "precision=64")
    assert rule.on_layers
    muon = optax.contrib.muon(0.02, adam_learning_rate=1e-3, beta=0.95)
    stepped = first_step(scene, rule, seeds, settings)
    np.testing.assert_allclose(
        stepped, reference_step(scene, muon, seeds, settings, True), rtol=1e-5, atol=1e-7
    )
    assert not np.allclose(stepped, reference_step(scene, muon, seeds, settings, False), rtol=1e-3)
    # each kernel's update is Newton-Schulz of its own momentum, which pulls its singular values
    # together: the spread of the leading two is smaller than the raw gradient's (the first step's
    # gradient of a kernel fed by a 1-D input has rank about 2, so the rest stay near 0)
    tree = seeds.network()
    unravel = ravel_pytree(tree)[1]
    update = [
        a - b
        for a, b in zip(
            jax.tree_util.tree_leaves(unravel(jnp.asarray(stepped))),
            jax.tree_util.tree_leaves(tree),
        )
        if a.shape == (20, 20)
    ]
    batch = scene.sample_train(jax.random.fold_in(seeds.train_keys[0], 0), settings.batch_size)
    grads = jax.grad(lambda p: scene.batch_loss(scene.batch_output(p, batch), batch))(tree)
    raw = [g for g in jax.tree_util.tree_leaves(grads) if g.shape == (20, 20)]
    for u, g in zip(update, raw):
        su, sg = (
            np.linalg.svd(np.asarray(u), compute_uv=False),
            np.linalg.svd(np.asarray(g), compute_uv=False),
        )
        assert su[0] / su[1] < sg[0] / sg[1]


# Adam in make test, plain gradient descent (the simpler element-wise rule) in make test-long
@pytest.mark.parametrize("optim", ["adam", pytest.param("gd", marks=pytest.mark.long)])
def test_element_wise_rules_compute_the_same_on_the_flat_vector(optim):
    scene, rule, seeds, settings = toy(optim)
    assert not rule.on_layers
    tree_rule = rule._replace(on_layers=True)
    np.testing.assert_allclose(
        first_step(scene, rule, seeds, settings),
        first_step(scene, tree_rule, seeds, settings),
        rtol=1e-6,
        atol=1e-8,
    )


def test_adafactor_factors_a_kernel():
    rule = build_rule(
        {
            "name": "adafactor",
            "_target_": "optax.adafactor",
            "learning_rate": 1e-3,
            "min_dim_size_to_factor": 8,
        }
    )
    assert rule.on_layers
    _, _, seeds, _ = toy("adam")
    flat, unravel = ravel_pytree(seeds.network())
    shapes = {
        leaf.shape
        for leaf in jax.tree_util.tree_leaves(on_tree(rule.transform, unravel).init(flat))
    }
    assert (
        20,
    ) in shapes and flat.shape not in shapes  # row factors of the 20 x 20 kernels; no full v
    flat_shapes = {leaf.shape for leaf in jax.tree_util.tree_leaves(rule.transform.init(flat))}
    assert flat.shape in flat_shapes  # one flat vector: nothing to factor


def test_muon_on_a_network_without_matrices_is_refused_in_one_line(monkeypatch):
    from physgrad.tasks import Scene

    def vector_scene(*args, **kwargs):
        return Scene(
            init_params=lambda k: {"controls": jnp.zeros(4)},
            sample_loss=lambda y, s: jnp.sum(y**2),
            test_set={"x": jnp.ones((8, 4))},
            train_set={"x": jnp.ones((8, 4))},
            sample_output=lambda p, s: p["controls"] * s["x"],
        )

    monkeypatch.setattr("physgrad.experiment.build_scene", vector_scene)
    with pytest.raises(UserError, match="Muon partition would be empty"):
        toy("muon", "task.batch_size=4")


# a 60-iteration run: make test-long; make test keeps Muon training a least-squares problem in its
# compiled step (test_rule_contract.py[muon]) and through the runner (test_configs.py's pair
# oscillator task.closed_loop=true-muon)
@pytest.mark.long
def test_muon_trains_the_toy(tmp_path):
    run = physgrad.run(
        "task=toy", "optim=muon", "trainer.iterations=60", "trainer.eval_every=30", out_dir=tmp_path
    )
    assert run.attrs["status"] == "completed" and run.eval["loss"][-1] < run.eval["loss"][0]
