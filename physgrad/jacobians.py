"""The network-through-physics Jacobian J = dy/dtheta (m x n, m = batch * k outputs) as the Jacobian
rules use it: its Gram matrix J J^T in float64, products J^T w, and, for the SVD, J itself.

Two forms, chosen once per run (`plan_layers`):

- DenseJacobian: J from one per-sample reverse pass, vmapped over the batch (any network);
- LayerJacobian: the layer-factorised form of a network built with physgrad.nets.apply_mlp and
  applied once per sample. For a dense layer z = a W + b, row r of J holds a_s(r) (outer) delta_r
  for W and delta_r for b, where a_s(r) is the layer's input for the sample of row r and delta_r =
  dy_r/dz its cotangent at the pre-activation. So the layer's block of J J^T is (delta_r . delta_r')
  (a_s(r) . a_s(r') + 1), and
      J J^T = sum_l (Delta_l Delta_l^T) o ((A_l A_l^T + 1) (x) 1_{k x k})
  costs m^2 * sum_l width_l instead of m^2 * n (Novak et al., ICML 2022, "structured derivatives"),
  and J^T w = [A_l^T S_l, sum_s S_l] with S_l[s] = sum_{r of s} w_r delta_r, so J itself is never
  formed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from jax.extend.core import Var
from jax.flatten_util import ravel_pytree

from physgrad.nets import layer_tap

if TYPE_CHECKING:
    import numpy as np
    from jax.extend.core import ClosedJaxpr
    from jax.typing import DTypeLike

    from physgrad.nets import Params, Pytree


@dataclass(frozen=True)
class DenseJacobian:
    """J as one m x n matrix."""

    matrix: jax.Array

    @property
    def shape(self) -> tuple[int, int]:
        return self.matrix.shape

    @property
    def dtype(self) -> np.dtype:
        return self.matrix.dtype

    def dense(self) -> jax.Array:
        return self.matrix

    def gram64(self) -> jax.Array:
        """J J^T, formed in float64 (call under jax.enable_x64)."""
        jac64 = self.matrix.astype(jnp.float64)
        return jac64 @ jac64.T

    def transpose_apply(self, weights: jax.Array) -> jax.Array:
        """J^T w, in the precision of w."""
        return self.matrix.astype(weights.dtype).T @ weights

    def finite(self) -> jax.Array:
        return jnp.isfinite(self.matrix).all()

    def astype(self, dtype: DTypeLike) -> "DenseJacobian":
        return DenseJacobian(self.matrix.astype(dtype))


@dataclass(frozen=True)
class LayerPlan:
    """Where each parameter leaf sits in the network, in ravel_pytree order: (layer index, "w" or
    "b")."""

    leaves: tuple[tuple[int, str], ...]
    widths: tuple[int, ...]  # each layer's number of outputs


@dataclass(frozen=True)
class LayerJacobian:
    """J in factors: per layer l, its inputs A_l (batch, in_l) and the cotangents Delta_l (batch, k,
    out_l)."""

    plan: LayerPlan
    inputs: tuple
    cotangents: tuple

    @property
    def shape(self) -> tuple[int, int]:
        batch, k, _ = self.cotangents[0].shape
        n = sum(
            self.inputs[i].shape[1] * self.cotangents[i].shape[2]
            if kind == "w"
            else self.cotangents[i].shape[2]
            for i, kind in self.plan.leaves
        )
        return batch * k, n

    @property
    def dtype(self) -> np.dtype:
        return self.cotangents[0].dtype

    def dense(self) -> jax.Array:
        """J itself (for the SVD route): per leaf, a_s(r) (outer) delta_r for a kernel and delta_r
        for a bias."""
        batch, k, _ = self.cotangents[0].shape
        blocks = []
        for layer, kind in self.plan.leaves:
            a, delta = self.inputs[layer], self.cotangents[layer]
            block = delta if kind == "b" else jnp.einsum("bi,bko->bkio", a, delta)
            blocks.append(block.reshape(batch * k, -1))
        return jnp.concatenate(blocks, axis=1)

    def gram64(self) -> jax.Array:
        """sum_l (Delta_l Delta_l^T) o (A_l A_l^T + 1) per sample pair, in float64 (call under
        enable_x64)."""
        batch, k, _ = self.cotangents[0].shape
        gram = jnp.zeros((batch, k, batch, k), jnp.float64)
        for a, delta in zip(self.inputs, self.cotangents):
            a64, delta64 = a.astype(jnp.float64), delta.astype(jnp.float64)
            inputs_gram = a64 @ a64.T + 1.0  # (batch, batch): the kernel's and the bias's share
            flat = delta64.reshape(batch * k, -1)
            gram = (
                gram + (flat @ flat.T).reshape(batch, k, batch, k) * inputs_gram[:, None, :, None]
            )
        return gram.reshape(batch * k, batch * k)

    def transpose_apply(self, weights: jax.Array) -> jax.Array:
        """J^T w in the precision of w, in ravel_pytree order of the parameters: A_l^T S_l for a
        kernel and sum_s S_l[s] for a bias, S_l[s] = sum_{r of s} w_r delta_r."""
        batch, k, _ = self.cotangents[0].shape
        w = weights.reshape(batch, k)
        parts = []
        for layer, kind in self.plan.leaves:
            summed = jnp.einsum("bk,bko->bo", w, self.cotangents[layer].astype(w.dtype))
            part = (
                summed.sum(axis=0) if kind == "b" else self.inputs[layer].astype(w.dtype).T @ summed
            )
            parts.append(part.reshape(-1))
        return jnp.concatenate(parts)

    def finite(self) -> jax.Array:
        return jnp.all(jnp.stack([jnp.isfinite(x).all() for x in (*self.inputs, *self.cotangents)]))

    def astype(self, dtype: DTypeLike) -> "LayerJacobian":
        cast = lambda arrays: tuple(x.astype(dtype) for x in arrays)  # noqa: E731
        return LayerJacobian(self.plan, cast(self.inputs), cast(self.cotangents))


def as_jacobian(jac: DenseJacobian | LayerJacobian | jax.Array) -> "DenseJacobian | LayerJacobian":
    """A form of J as it is, a plain m x n matrix as a DenseJacobian."""
    return jac if isinstance(jac, (DenseJacobian, LayerJacobian)) else DenseJacobian(jac)


def dense_jacobian(
    sample_output: Callable[[Params, Pytree], jax.Array], params: Params, batch: Pytree
) -> tuple[jax.Array, DenseJacobian]:
    """y (batch, k) and J (m x n, m = batch * k) from one per-sample reverse-mode pass, vmapped over
    the batch: J's rows are sample major, its columns follow ravel_pytree(params). The forward pass
    that builds each sample's pullback also gives y, so a step needs no separate forward or gradient
    pass (dL/dtheta = J^T g)."""
    flat, unravel = ravel_pytree(params)

    def output_twice(flat_params: jax.Array, sample: Pytree) -> tuple[jax.Array, jax.Array]:
        y = sample_output(unravel(flat_params), sample)
        return y, y

    jac, y = jax.vmap(jax.jacrev(output_twice, has_aux=True), in_axes=(None, 0))(flat, batch)
    return y, DenseJacobian(jac.reshape(-1, flat.size))


class _Recorder:
    """Layer tap for planning: which parameter leaves each apply_mlp layer uses (by identity), and
    the rank of its input."""

    def __init__(self, leaf_index: dict) -> None:
        self.leaf_index = leaf_index
        self.layers: list[tuple] = []

    def __call__(self, layer: dict[str, jax.Array], x: jax.Array) -> jax.Array:
        w, b = layer["w"], layer["b"]
        self.layers.append(
            (self.leaf_index.get(id(w)), self.leaf_index.get(id(b)), x.ndim, w.shape[1])
        )
        return x @ w + b


class _Perturbed:
    """Layer tap for the factors: z = x W + b + p_l with p_l = 0 (so that dy/dp_l is the cotangent
    at the pre-activation) and the layer's input x recorded. For planning, kernels replace the
    network's own and every pre-activation must belong to the trace of the planned function (one
    inside a scan or a vmap has its own trace: the layer would run several times per sample)."""

    def __init__(
        self,
        perturbations: Sequence[jax.Array],
        kernels: Sequence[tuple[jax.Array, jax.Array]] | None = None,
    ) -> None:
        self.perturbations = perturbations
        self.kernels = kernels
        self.inputs: list = []

    def __call__(self, layer: dict[str, jax.Array], x: jax.Array) -> jax.Array:
        index = len(self.inputs)
        self.inputs.append(x)
        if index >= len(self.perturbations):
            raise _NotPlannable("a layer is applied more than once per sample")
        w, b = (layer["w"], layer["b"]) if self.kernels is None else self.kernels[index]
        pre_activation = x @ w + b + self.perturbations[index]
        if self.kernels is not None and pre_activation._trace is not w._trace:
            raise _NotPlannable(
                "the network is applied inside a loop or a transformation of the rollout"
            )
        return pre_activation


class _NotPlannable(Exception):
    pass


def _depends_on(closed_jaxpr: ClosedJaxpr, inputs: int, outputs: int) -> bool:
    """Whether any of the first ``outputs`` outputs may depend on any of the first ``inputs`` inputs
    (an equation with a dependent operand makes all its results dependent: conservative)."""
    jaxpr = closed_jaxpr.jaxpr
    tainted = set(jaxpr.invars[:inputs])
    for eqn in jaxpr.eqns:
        if any(isinstance(v, Var) and v in tainted for v in eqn.invars):
            tainted.update(eqn.outvars)
    return any(isinstance(v, Var) and v in tainted for v in jaxpr.outvars[:outputs])


def _network_library(params: Params) -> str | None:
    """The library a network's parameters are a module of (equinox, flax), where they are one."""
    found = []

    def module(node: object) -> bool:
        library = type(node).__module__.partition(".")[0]
        if library in ("equinox", "flax"):
            found.append(library)
            return True
        return False

    jax.tree_util.tree_flatten(params, is_leaf=module)
    return found[0] if found else None


def plan_layers(
    sample_output: Callable[[Params, Pytree], jax.Array], params: Params, sample: Pytree
) -> LayerPlan | str:
    """The layer plan of a scene's network, or why the per-sample pass is kept (a phrase).

    The factorised form is exact when every parameter leaf is the kernel or bias of one apply_mlp
    layer, each layer is applied exactly once per sample to one input vector (not inside a loop, a
    scan or a vmap), and the output depends on the parameters only through those layers. Checked by
    tracing (no computation)."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    recorders = []

    def record(*leaf_values: jax.Array) -> jax.Array:
        tree = jax.tree_util.tree_unflatten(treedef, leaf_values)
        recorder = _Recorder({id(leaf): i for i, leaf in enumerate(leaf_values)})
        recorders.append(recorder)
        with layer_tap(recorder):
            return sample_output(tree, sample)

    try:
        jax.eval_shape(record, *leaves)
    except Exception as error:  # a scene that cannot be traced this way keeps the per-sample pass
        return f"the output could not be traced layer by layer ({type(error).__name__})"
    layers = recorders[0].layers
    if not layers:
        library = _network_library(params)
        if library is not None:
            return (
                f"the network is {'an' if library == 'equinox' else 'a'} {library} module, whose "
                "layers physgrad cannot see (its "
                "weights through physgrad.nets.apply_mlp would give the layer-factorised form)"
            )
        return "the network is not built with physgrad.nets.apply_mlp"
    where: dict[int, tuple[int, str]] = {}
    for index, (w_leaf, b_leaf, ndim, _) in enumerate(layers):
        if w_leaf is None or b_leaf is None:
            return "a layer's weights are not parameter leaves as given (transformed or shared)"
        if ndim != 1:
            return "the network is applied to several inputs per sample"
        for leaf, kind in ((w_leaf, "w"), (b_leaf, "b")):
            if leaf in where:
                return "a layer is applied more than once per sample"
            where[leaf] = (index, kind)
    if len(where) != len(leaves):
        return "some parameters are not weights of the network's layers"

    widths = [width for *_, width in layers]
    kernels = [
        tuple(
            jax.ShapeDtypeStruct(leaves[leaf].shape, leaves[leaf].dtype)
            for leaf in (w_leaf, b_leaf)
        )
        for w_leaf, b_leaf, *_ in layers
    ]

    def detached(
        leaf_values: list[jax.Array], kernel_values: list[tuple[jax.Array, jax.Array]]
    ) -> tuple[jax.Array, list[jax.Array]]:
        tap = _Perturbed([jnp.zeros((width,), leaves[0].dtype) for width in widths], kernel_values)
        with layer_tap(tap):
            y = sample_output(jax.tree_util.tree_unflatten(treedef, leaf_values), sample)
        return y, tap.inputs

    try:
        jaxpr = jax.make_jaxpr(detached)(list(leaves), kernels)
    except _NotPlannable as reason:
        return str(reason)
    except Exception as error:
        return f"the output could not be traced layer by layer ({type(error).__name__})"
    if _depends_on(jaxpr, len(leaves), outputs=1):
        return "the output depends on the parameters other than through the network's layers"
    return LayerPlan(tuple(where[i] for i in range(len(leaves))), tuple(widths))


def layer_jacobian(
    sample_output: Callable[[Params, Pytree], jax.Array],
    params: Params,
    batch: Pytree,
    plan: LayerPlan,
) -> tuple[jax.Array, LayerJacobian]:
    """y (batch, k) and J in factors: per sample, one forward pass with zero perturbations p_l added
    to every pre-activation, then dy/dp_l by reverse mode (k passes that stop at the layers'
    pre-activations)."""
    dtype = jax.tree_util.tree_leaves(params)[0].dtype

    def per_sample(
        sample: Pytree,
    ) -> tuple[jax.Array, tuple[jax.Array, ...], tuple[jax.Array, ...]]:
        def output(
            perturbations: list[jax.Array],
        ) -> tuple[jax.Array, tuple[jax.Array, list[jax.Array]]]:
            tap = _Perturbed(perturbations)
            with layer_tap(tap):
                y = sample_output(params, sample)
            return y, (y, tap.inputs)

        zeros = [jnp.zeros((width,), dtype) for width in plan.widths]
        cotangents, (y, inputs) = jax.jacrev(output, has_aux=True)(zeros)
        return y, tuple(inputs), tuple(cotangents)

    y, inputs, cotangents = jax.vmap(per_sample)(batch)
    return y, LayerJacobian(plan, inputs, cotangents)
