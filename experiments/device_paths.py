"""Which computational path is fastest on this device? Three measurements behind the choices that
physgrad makes per jax backend (docs/benchmarks.md, "Paths per device"), each timed in turn with
its alternatives in one process (physgrad.timing.interleaved_times), so the ratios are fair on a
noisy machine:

- tridiagonal: the quantum scene's training step with each tridiagonal solve of
  physgrad.tridiagonal (library, thomas, dense), for a plain gradient (adam) and the Jacobian route
  (hig, gauss_newton), on both presets (quantum: N = 14, quantum_control: N = 32); the step the
  scene picks is marked.
- eigh: the decomposition of the Gram route for several seeds trained together (8 random 512 x 512
  float64 Gram matrices, HIG's size on the oscillator): vmapped eigh with each of jax's
  implementations, one seed after another (lax.map), float32 eigh, and the SVD of the 512 x 2,956
  Jacobians in float32, against one matrix's eigh.
- overhead: the Adam step of a scene (oscillator by default) as physgrad compiles it, against the
  same step with parts taken away: the flat parameter vector and packed logs, and a hand-written
  step (a jitted value_and_grad and optax update on the same minibatch draw; on one fixed batch).

    python experiments/device_paths.py tridiagonal --out outputs/paths
    python experiments/device_paths.py eigh --out outputs/paths
    python experiments/device_paths.py overhead --out outputs/paths [--task oscillator]

Each writes <out>/<name>.md (and .json) with the jax backend and device in its first line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from physgrad.files import open_append, write_text
from physgrad.readout import fmt

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


MAX_SECONDS = [60.0]  # per measurement (--max-seconds): slow steps are timed fewer times


def _medians(fns: dict, repeats: int, min_seconds: float) -> dict:
    from physgrad.timing import interleaved_times

    times = interleaved_times(list(fns.values()), repeats, min_seconds, True, MAX_SECONDS[0])
    return {name: statistics.median(t) for name, t in zip(fns, times)}


def _device() -> str:
    import jax

    device = jax.devices()[0]
    return f"jax {jax.__version__}, {jax.default_backend()}: {device.device_kind}"


def agreement() -> list[str]:
    """The largest difference of each solve from the library's over 64 Crank-Nicolson steps of
    the quantum scene (N = 14, a random field) and of their gradient with respect to the field, in
    the default float precision."""
    import jax
    import jax.numpy as jnp

    from physgrad import tridiagonal as paths
    from physgrad.tasks.quantum import crank_nicolson_step, eigenstate, fidelity, grid

    x, psi0 = grid(14), eigenstate(1, 14).astype(jnp.complex64)
    target = eigenstate(2, 14).astype(jnp.complex64)
    field = jax.random.normal(jax.random.PRNGKey(0), (64,))

    def final(u, solve):
        def body(psi, u_k):
            return crank_nicolson_step(psi, u_k, x, 0.05, solve), None

        return jax.lax.scan(body, psi0, u)[0]

    def loss(u, solve):
        return fidelity(target, final(u, solve))

    rows = []
    ref_psi = final(field, paths.library_solve)
    ref_grad = jax.grad(loss)(field, paths.library_solve)
    for name, solve in paths.SOLVES.items():
        dpsi = float(jnp.max(jnp.abs(final(field, solve) - ref_psi)))
        dgrad = float(jnp.max(jnp.abs(jax.grad(loss)(field, solve) - ref_grad)))
        scale = float(jnp.max(jnp.abs(ref_grad)))
        rows.append(f"| {name} | {dpsi:.2e} | {dgrad / scale:.2e} |")
    return [
        "| solve | max abs diff of psi(T) | of the gradient (relative) |",
        "|---|---|---|",
        *rows,
    ]


def tridiagonal(
    repeats: int, min_seconds: float, tasks: list[str], optims: list[str], emit=print
) -> tuple[list[str], dict]:
    import jax

    import physgrad.tasks.quantum as quantum
    from physgrad import tridiagonal as paths
    from physgrad.configs import compose
    from physgrad.timing import compiled_step

    backend = jax.default_backend()
    rows, data = [], {}
    head = [
        "| task | optim | " + " | ".join(paths.SOLVES) + " |",
        "|---|---|" + "---|" * len(paths.SOLVES),
    ]
    emit([*agreement(), "", *head])
    for task in tasks:
        for optim in optims if task == tasks[0] else optims[:2]:
            steps = {}
            for name in paths.SOLVES:
                quantum.solve_for = lambda backend, name=name: paths.SOLVES[name]
                cfg = compose([f"task={task}", f"optim={optim}"])
                *_, compile_s, one_step = compiled_step(cfg, [cfg.seed])
                steps[name] = one_step
                data[f"{task}/{optim}/{name}/compile_s"] = compile_s
            medians = _medians(steps, repeats, min_seconds)
            base = medians["library"]
            route = "gradient" if optim == "adam" else "jacobian"
            chosen = paths.fastest(backend, route)
            cells = [
                f"{fmt(medians[n] * 1e3)} ms ({medians[n] / base:.2f}x)"
                + (" *" if n == chosen else "")
                for n in paths.SOLVES
            ]
            rows.append(f"| {task} | {optim} | " + " | ".join(cells) + " |")
            emit(rows[-1:])
            data.update({f"{task}/{optim}/{n}/step_s": medians[n] for n in paths.SOLVES})
    note = "\nseconds per step (ratio to library); * the path the scene takes here on that route"
    emit([note])
    return [], data


def eigh(repeats: int, min_seconds: float, seeds: int = 8, m: int = 512, n: int = 2956) -> tuple:
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(0)
    jacobians = jnp.asarray(rng.standard_normal((seeds, m, n)) / np.sqrt(n))
    grams = jnp.einsum("smn,skn->smk", jacobians, jacobians)
    ready = jax.block_until_ready
    fns = {}

    def compiled(fn, *args):
        exe = jax.jit(fn).lower(*args).compile()
        return lambda: ready(exe(*args))

    fns["one matrix eigh f64"] = compiled(jnp.linalg.eigh, grams[0])
    from jax.lax.linalg import EighImplementation

    for impl in (None, *EighImplementation):
        label = "default" if impl is None else impl.value

        def batched(g, impl=impl):
            return jax.vmap(lambda x: jax.lax.linalg.eigh(x, implementation=impl))(g)

        try:
            fns[f"vmap eigh f64 {label}"] = compiled(batched, grams)
            fns[f"vmap eigh f64 {label}"]()
        except Exception as error:  # an implementation this backend lacks
            fns.pop(f"vmap eigh f64 {label}", None)
            print(f"eigh {label}: {type(error).__name__}: {str(error)[:120]}", file=sys.stderr)
    fns["lax.map eigh f64"] = compiled(lambda g: jax.lax.map(jnp.linalg.eigh, g), grams)
    fns["vmap eigh f32"] = compiled(jax.vmap(jnp.linalg.eigh), grams.astype(jnp.float32))
    fns["vmap svd f32 of J"] = compiled(
        jax.vmap(lambda j: jnp.linalg.svd(j, full_matrices=False)), jacobians.astype(jnp.float32)
    )
    fns["vmap svd f64 of J"] = compiled(
        jax.vmap(lambda j: jnp.linalg.svd(j, full_matrices=False)), jacobians
    )
    medians = _medians(fns, repeats, min_seconds)
    one = medians["one matrix eigh f64"]
    rows = ["| path | seconds | throughput vs one seed's eigh |", "|---|---|---|"]
    for name, seconds in medians.items():
        count = 1 if name.startswith("one") else seeds
        rows.append(f"| {name} | {fmt(seconds * 1e3)} ms | {count * one / seconds:.2f}x |")
    rows.append(f"\n{seeds} Gram matrices {m} x {m} (J {m} x {n}); throughput = seeds x t1 / tN")
    return rows, medians


def overhead(repeats: int, min_seconds: float, task: str = "oscillator") -> tuple:
    import jax
    import numpy as np
    import optax

    from physgrad.configs import compose
    from physgrad.timing import compiled_step
    from physgrad.training import make_step

    cfg = compose([f"task={task}", "optim=adam"])
    settings, scene, rule, seeds, compiled, _, one_step = compiled_step(cfg, [cfg.seed])
    params, key, train_set = seeds.network(), seeds.train_keys[0], None
    if seeds.train_sets is not None:
        train_set = jax.tree_util.tree_map(lambda x: x[0], seeds.train_sets)
    batch_size = settings.batch_size
    ready = jax.block_until_ready
    fns = {"physgrad step (flat vector, vmap axis, logs)": one_step}

    tree_step = make_step(scene, rule, batch_size)
    exe = jax.jit(tree_step).lower(params, rule.transform.init(params), np.int32(0), key, train_set)
    exe = exe.compile()
    state = [params, rule.transform.init(params)]

    def pytree_step() -> None:
        state[0], state[1], logs = exe(state[0], state[1], np.int32(0), key, train_set)
        ready(state[0])

    fns["same step on the pytree, logs as dict"] = pytree_step

    adam = optax.adam(float(cfg.optim.learning_rate))

    def hand(p, opt, k):
        batch = scene.draw_batch(k, batch_size, train_set)
        loss, grads = jax.value_and_grad(
            lambda q: scene.batch_loss(scene.batch_output(q, batch), batch)
        )(p)
        updates, opt = adam.update(grads, opt, p)
        return optax.apply_updates(p, updates), opt, loss

    hand_exe = jax.jit(hand).lower(params, adam.init(params), key).compile()
    hand_state = [params, adam.init(params)]

    def hand_step() -> None:
        hand_state[0], hand_state[1], _ = hand_exe(hand_state[0], hand_state[1], key)
        ready(hand_state[0])

    fns["hand-written: draw, value_and_grad, optax adam"] = hand_step

    fixed = scene.draw_batch(key, batch_size, train_set)

    def hand_fixed(p, opt, batch):
        loss, grads = jax.value_and_grad(
            lambda q: scene.batch_loss(scene.batch_output(q, batch), batch)
        )(p)
        updates, opt = adam.update(grads, opt, p)
        return optax.apply_updates(p, updates), opt, loss

    fixed_exe = jax.jit(hand_fixed).lower(params, adam.init(params), fixed).compile()
    fixed_state = [params, adam.init(params)]

    def fixed_step() -> None:
        fixed_state[0], fixed_state[1], _ = fixed_exe(fixed_state[0], fixed_state[1], fixed)
        ready(fixed_state[0])

    fns["hand-written on one fixed batch"] = fixed_step
    medians = _medians(fns, repeats, min_seconds)
    base = medians["hand-written: draw, value_and_grad, optax adam"]
    rows = [f"| {task} adam step | seconds | vs hand-written |", "|---|---|---|"]
    rows += [f"| {n} | {fmt(s * 1e3)} ms | {s / base:.3f}x |" for n, s in medians.items()]
    return rows, medians


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=("tridiagonal", "eigh", "overhead"))
    parser.add_argument("--out", default="outputs/paths")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--min-seconds", type=float, default=2.0)
    parser.add_argument("--max-seconds", type=float, default=60.0, help="per measurement")
    parser.add_argument("--task", default="oscillator", help="overhead: the scene")
    parser.add_argument("--tasks", default="quantum,quantum_control", help="tridiagonal")
    parser.add_argument(
        "--optims",
        default="adam,hig,gauss_newton",
        help="tridiagonal: all of them on the first task, the first two on the others",
    )
    options = parser.parse_args()
    measure = {"tridiagonal": tridiagonal, "eigh": eigh, "overhead": overhead}[options.what]
    MAX_SECONDS[0] = options.max_seconds
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    table = out / f"{options.what}.md"
    write_text(table, f"{options.what} on {_device()}\n\n")

    def emit(rows: list[str]) -> None:  # rows as they are measured: a timeout keeps the first
        with open_append(table) as f:
            f.write("\n".join(rows) + "\n")
        print("\n".join(rows), flush=True)

    kwargs = {
        "overhead": {"task": options.task},
        "tridiagonal": {
            "tasks": options.tasks.split(","),
            "optims": options.optims.split(","),
            "emit": emit,
        },
        "eigh": {},
    }[options.what]
    rows, data = measure(options.repeats, options.min_seconds, **kwargs)
    if rows:
        emit(rows)
    write_text(out / f"{options.what}.json", json.dumps(data, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
