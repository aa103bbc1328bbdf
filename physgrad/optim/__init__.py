"""Update rules, each an optax GradientTransformation, built from the `optim` config group.

An optim config names a factory with ``_target_`` (any optax factory, e.g. optax.adam or optax.lion,
or physgrad's spectral rule for Gauss-Newton and HIG) and gives its keyword arguments; ``name``,
``backprop`` and ``clip`` are physgrad's own keys and are not passed to the factory.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree
from omegaconf import OmegaConf

from physgrad.errors import UserError
from physgrad.gradients import gradient_pass
from physgrad.optim.capabilities import capabilities, check_settings
from physgrad.optim.spectral import JacobianRule, MarquardtRule
from physgrad.validate import call_target, choice, number

RESERVED_KEYS = ("name", "backprop", "clip")
CLIPPING = {
    "none": None,
    "value": lambda: optax.clip(1.0),
    "norm": lambda: optax.clip_by_global_norm(1.0),
}


class UpdateRule(NamedTuple):
    """transform: the optax transformation; gradient: the gradient pass, how the step gets the
    gradient and the rule's extra arguments (physgrad.gradients); on_layers: the rule is given the
    network's parameter tree (its layers), not one flat vector (rules that are not element-wise:
    Muon, Adafactor, LAMB, LARS, ...)."""

    transform: optax.GradientTransformation
    gradient: Callable
    on_layers: bool = False
    # trials trained together: per optim key, one value per member (the transform holds these keys
    # as inputs in its state, optax.inject_hyperparams; set_member_values puts them there)
    member_values: Mapping[str, tuple[float, ...]] | None = None

    @property
    def uses_jacobian(self) -> bool:
        return isinstance(self.transform, JacobianRule)


def build_rule(
    optim_cfg: Mapping[str, Any], member_values: Mapping[str, Any] | None = None
) -> UpdateRule:
    """The factory's transformation, behind the clipping of ``optim.clip`` (element-wise to [-1, 1],
    global norm 1, or none), with the gradient pass its kind and ``optim.backprop`` ask for.
    member_values (optim key -> one value per member, the job's trial_values): those keys become
    inputs of the transformation (optax.inject_hyperparams: the same rule, its values held in its
    state), so members with other values train in one vectorised step; UserError for a rule whose
    factory cannot take them so."""
    node = (
        OmegaConf.to_container(optim_cfg, resolve=True)
        if OmegaConf.is_config(optim_cfg)
        else dict(optim_cfg)
    )
    if isinstance(node.get("learning_rate"), (int, float)):
        number("optim.learning_rate", node["learning_rate"], 0, open_low=True)
    clip = choice("optim.clip", node.get("clip", "none"), tuple(CLIPPING))
    check_settings(node)
    through = None
    if member_values:
        static = tuple(
            k for k in node if k not in member_values and k not in (*RESERVED_KEYS, "_target_")
        )
        through = lambda factory: optax.inject_hyperparams(factory, static_args=static)  # noqa: E731
    transform = call_target("optim", node, reserved=RESERVED_KEYS, through=through)
    if not hasattr(transform, "init") or not hasattr(transform, "update"):
        raise UserError(
            f"optim._target_={node['_target_']} returned {type(transform).__name__}, not an optax "
            "GradientTransformation"
        )
    if member_values:
        transform = _as_built(node, transform)
    jacobian = isinstance(transform, JacobianRule)
    if member_values and not _holds_inputs(transform, member_values):
        raise UserError(
            f"optim={node.get('name')} cannot train trials together (its "
            f"{', '.join(member_values)} cannot be an input of its optax transformation): "
            "train one trial per job"
        )
    # Levenberg-Marquardt takes value and value_fn; an optax rule that needs optax's extra arguments
    # (optax.lbfgs) is found by tracing once the parameters are known (needs_value_arguments)
    gradient = gradient_pass(node.get("backprop"), jacobian, isinstance(transform, MarquardtRule))
    on_layers = not jacobian and not capabilities(node).elementwise
    if clip != "none":
        if isinstance(transform, JacobianRule):
            raise UserError(
                f"optim.clip={clip} applies to gradient-based rules, and {node.get('name')} takes "
                "the Jacobian: remove optim.clip"
            )
        transform = optax.chain(CLIPPING[clip](), transform)
    values = (
        {k: tuple(float(v) for v in vs) for k, vs in member_values.items()}
        if member_values
        else None
    )
    return UpdateRule(transform, gradient, on_layers, values)


def _as_built(node: dict, injected: optax.GradientTransformation) -> optax.GradientTransformation:
    """The transformation built through inject_hyperparams, as the kind of rule the factory builds
    (inject_hyperparams returns a plain optax transformation): a Jacobian rule stays one, so its
    step still builds J for it; a rule with a kind of its own that the injected form would lose
    (Levenberg-Marquardt's extra arguments) is refused."""
    plain = call_target("optim", node, reserved=RESERVED_KEYS)
    if isinstance(plain, MarquardtRule):
        raise UserError(
            f"optim={node.get('name')} cannot train trials together (its gain ratio takes the "
            "loss function as an argument): train one trial per job"
        )
    return JacobianRule(*injected) if isinstance(plain, JacobianRule) else injected


def _holds_inputs(transform: optax.GradientTransformation, keys: Mapping[str, Any]) -> bool:
    """Whether the transformation built through inject_hyperparams holds every key as an input in
    its state (its initial state traced, nothing computed)."""
    try:
        state = jax.eval_shape(transform.init, jnp.zeros(2))
    except Exception:  # noqa: BLE001 - a factory that cannot be traced so cannot batch its values
        return False
    found = set()
    for node in jax.tree_util.tree_leaves(state, is_leaf=_is_injected):
        if _is_injected(node):
            found |= set(node.hyperparams)
    return set(keys) <= found


def _is_injected(node: Any) -> bool:
    return isinstance(node, (optax.InjectHyperparamsState, optax.InjectStatefulHyperparamsState))


def set_member_values(opt_state: Any, values: Mapping[str, tuple[float, ...]]) -> Any:
    """The optimiser state of members stacked on a leading axis, with each member's values of the
    injected keys (values: key -> one per member) in place of the configured ones."""

    def put(node: Any) -> Any:
        if not _is_injected(node):
            return node
        hyperparams = dict(node.hyperparams)
        for key, per_member in values.items():
            hyperparams[key] = jnp.asarray(per_member, hyperparams[key].dtype).reshape(
                hyperparams[key].shape
            )
        return node._replace(hyperparams=hyperparams)

    return jax.tree_util.tree_map(put, opt_state, is_leaf=_is_injected)


def on_tree(
    transform: optax.GradientTransformation, unravel: Callable[[jax.Array], optax.Params]
) -> optax.GradientTransformationExtraArgs:
    """The rule applied to the network's parameter tree while physgrad keeps one flat vector:
    gradient,
    parameters and the extra arguments grad and value_fn are unravelled into the tree (unravel, from
    ravel_pytree) before the rule and its update is ravelled after it; slices and a concatenation,
    which XLA fuses into the step."""

    def init(flat_params: jax.Array) -> optax.OptState:
        return transform.init(unravel(flat_params))

    def update(
        updates: jax.Array, state: optax.OptState, params: jax.Array | None = None, **extra: Any
    ) -> tuple[jax.Array, optax.OptState]:
        if "grad" in extra:
            extra["grad"] = unravel(extra["grad"])
        if "value_fn" in extra:
            value_fn = extra["value_fn"]
            extra["value_fn"] = lambda tree: value_fn(ravel_pytree(tree)[0])
        tree_updates, state = transform.update(
            unravel(updates), state, None if params is None else unravel(params), **extra
        )
        return ravel_pytree(tree_updates)[0], state

    return optax.GradientTransformationExtraArgs(init, update)


def matrix_leaves(params: optax.Params) -> int:
    """The number of 2-D parameter arrays (what Muon orthogonalises)."""
    return sum(jnp.ndim(leaf) == 2 for leaf in jax.tree_util.tree_leaves(params))


def needs_value_arguments(transform: optax.GradientTransformation, params: optax.Params) -> bool:
    """Whether an optax rule's update needs optax's extra arguments value, grad and value_fn
    (optax.lbfgs's line search does): its update is traced once without them (jax.eval_shape,
    nothing computed) and a TypeError about missing keyword arguments says so. A chain passes the
    arguments on to the members that take them."""
    if not isinstance(transform, optax.GradientTransformationExtraArgs):
        return False
    state = jax.eval_shape(transform.init, params)
    try:
        jax.eval_shape(lambda g, s, p: transform.update(g, s, p), params, state, params)
    except TypeError as error:
        return "keyword" in str(error) and any(name in str(error) for name in ("value", "grad"))
    return False


# the logged count of a step's line-search evaluations (optax's zoom line search: one value and
# gradient of the batch loss each), which the calibrated clock charges (TrainerSettings)
LINE_SEARCH_LOG = "linesearch_evaluations"


def _reports(node: Any) -> bool:
    return hasattr(node, "logs") or isinstance(node, optax.ScaleByZoomLinesearchState)


def state_logs(opt_state: Any) -> dict:
    """Scalars an update rule reports about itself: every node of its state with a logs() method
    (e.g. the spectral rules' svd_failures), merged, and the evaluations its zoom line searches
    made in this step (LINE_SEARCH_LOG, summed over line searches)."""
    logs = {}
    for node in jax.tree_util.tree_leaves(opt_state, is_leaf=_reports):
        if isinstance(node, optax.ScaleByZoomLinesearchState):
            found = jnp.asarray(node.info.num_linesearch_steps, jnp.float32)
            logs[LINE_SEARCH_LOG] = logs.get(LINE_SEARCH_LOG, 0.0) + found
        elif hasattr(node, "logs"):
            logs.update(node.logs())
    return logs
