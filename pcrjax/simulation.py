"""Public solves: `solve_static`, `rollout` (pure, differentiable) and `simulate` (checked, with progress).

`rollout` is one `lax.scan` over time: `jax.grad`, `jax.jacfwd`, `jax.vmap` and `jax.jit` work
through it. `simulate` runs the same step in jitted chunks so that long runs show progress and
a failure stops at the chunk where it happened; it raises `ConvergenceError` naming the first
step whose Newton solve did not converge (never returns such a result silently).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import executables, traces
from .errors import ConvergenceError, SceneError
from .numerics import newton, results
from .numerics.few_inputs import forward_for_few
from .physics.rotations import rotation_vector
from .robots import dynamics, inverse, statics
from .robots.scene import Scene
from .robots.signals import PosePath


class StaticResult(eqx.Module):
    """Static equilibrium: tip or platform ``position`` (3,) m, ``rotation_vector`` (3,) rad,
    ``base_wrenches`` (legs, 2, 3) [n(0), m(0)] in N and N m, node ``positions`` (legs, N+1, 3),
    and the solve's stats: final scaled ``residual_norm``, ``newton_iterations`` and ``result``
    (a `pcrjax.numerics.results` code; `results.message` says it in words)."""

    position: jnp.ndarray
    rotation_vector: jnp.ndarray
    rotation: jnp.ndarray
    base_wrenches: jnp.ndarray
    positions: jnp.ndarray
    residual_norm: jnp.ndarray
    newton_iterations: jnp.ndarray
    result: jnp.ndarray
    tol: jnp.ndarray

    @property
    def converged(self):
        return self.result == results.SUCCESSFUL


class Trajectory(eqx.Module):
    """Time series: ``t`` (T,), tip or platform ``position`` (T, 3), ``rotation_vector`` (T, 3),
    node ``positions`` (T, legs, N+1, 3), ``actuators`` (T, actuators) (no columns for a fixed
    rod), ``base_wrenches`` (T, legs, 2, 3) [n(0), m(0)] in N and N m, total ``energy`` (T,) J of rods, platform, weights and the end's load; per step (T-1,):
    Newton ``iterations``, final scaled ``residual``, ``jacobians`` evaluated and ``result`` (a
    `pcrjax.numerics.results` code; a failed initial equilibrium or a stale structure marks every
    step). Row 0 is the initial static equilibrium."""

    t: jnp.ndarray
    position: jnp.ndarray
    rotation_vector: jnp.ndarray
    positions: jnp.ndarray
    actuators: jnp.ndarray
    base_wrenches: jnp.ndarray
    energy: jnp.ndarray
    iterations: jnp.ndarray
    residual: jnp.ndarray
    jacobians: jnp.ndarray
    result: jnp.ndarray
    tol: jnp.ndarray

    @property
    def converged(self):
        return self.result == results.SUCCESSFUL


def _is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _base_wrenches(nodes):
    """(legs, 2, 3) [n(0), m(0)] of each leg's ``nodes`` (legs, N+1, dim)."""
    return jnp.stack([nodes[:, 0, 12:15], nodes[:, 0, 15:18]], axis=1)


def static_result(scene, sol) -> StaticResult:
    nodes = sol.nodes
    return StaticResult(
        position=sol.position,
        rotation_vector=rotation_vector(sol.rotation),
        rotation=sol.rotation,
        base_wrenches=_base_wrenches(nodes),
        positions=nodes[:, :: scene.solver.refine, 0:3],
        residual_norm=sol.stats.residual,
        newton_iterations=sol.stats.iterations,
        result=sol.stats.result,
        tol=scene.solver.newton.tol,
    )


@eqx.filter_jit
def _static(scene):
    return static_result(scene, statics.solve_static(scene))


def solve_static(scene, *, throw: bool = True) -> StaticResult:
    """Static equilibrium under the initial loads and actuator values (t = 0). Raises
    `ConvergenceError` if the solve fails (when called outside a trace and ``throw``)."""
    if not any(_is_traced(leaf) for leaf in jax.tree.leaves(scene)):
        _before_new_static(scene)
    res = _static(scene)
    if throw and not _is_traced(res.residual_norm) and not bool(res.converged):
        raise static_failure(scene, res)
    return res


_STATIC_SEEN: set = set()  # structures whose static solve this process has compiled


def _before_new_static(scene):
    """`executables.make_room` before a structure's first static solve only: counting the
    process's memory mappings costs tens of ms in a large process, too much for every solve."""
    try:
        key = _signature(scene)
        if key in _STATIC_SEEN:
            return
    except TypeError:  # an unhashable static leaf: always check
        executables.make_room()
        return
    executables.make_room()
    _STATIC_SEEN.add(key)


def static_failure(scene, res) -> ConvergenceError:
    code = int(res.result)
    return ConvergenceError(
        f"static solve did not converge: {results.message(code)} (scaled residual {float(res.residual_norm):.3e}, tol {float(scene.solver.newton.tol):.1e})",
        0.0,
        float(res.residual_norm),
        code,
    )


def check_structure(scene):
    """Raise `SceneError` if a concrete scene's numbers outgrew its compiled structure."""
    if not any(_is_traced(leaf) for leaf in jax.tree.leaves(scene)) and int(scene.structure_result()) != results.SUCCESSFUL:
        raise SceneError(f"{scene.name}: {results.message(results.STALE_STRUCTURE)}")


def _initial(scene, path=None):
    """The static equilibrium at t = 0 (under the path's first pose, if given) and the rest state."""
    if path is None:
        static = statics.solve_static(scene)  # loads and actuators at t = 0
    else:
        static = inverse.solve_static_inverse(scene, *path.pose(jnp.zeros(()), scene.end.reference_position[2]))
    return static, dynamics.initial_step_state(scene, static, inverse_dynamics=path is not None)


def _scan_steps(scene, state, i0, count: int, active=None, path=None, checkpoint: int | None = None):
    """``count`` steps from ``state`` (the first at step i0 + 1) as one `lax.scan`. ``active``:
    steps past it hold the state and output zeros. ``checkpoint``: scan chunks of that many
    steps under `jax.checkpoint`, so that reverse mode stores one state per chunk and one
    chunk's intermediates at a time (memory ~ count/checkpoint + checkpoint steps, for about
    one more forward pass); a partial last chunk holds past ``count``."""

    def advance(st, i):
        t = (i0 + i + 1) * scene.solver.dt
        st, out = dynamics.step(scene, st, t, path)
        return st, (
            out.position,
            rotation_vector(out.rotation),
            out.positions,
            out.stats,
            out.actuators,
            out.energy,
            out.base_wrenches,
        )

    if checkpoint:
        size = max(1, min(int(checkpoint), count))
        chunks = -(-count // size)
        if chunks * size > count and active is None:
            active = count

    if active is None:
        step_fn = advance
    else:
        # The step is traced once, to a jaxpr whose outputs' shapes the held steps copy (eval_shape
        # of `advance` would trace the whole step a second time).
        i = jnp.zeros((), jnp.int32)
        advance_jaxpr, consts = jax.closure_convert(advance, state, i)
        out_shape = jax.eval_shape(advance_jaxpr, state, i, *consts)[1]

        def hold(st, i):  # past the active steps: state kept, zero outputs, no solve
            return st, jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), out_shape)

        def step_fn(st, i):
            return jax.lax.cond(i < active, lambda s, j: advance_jaxpr(s, j, *consts), hold, st, i)

    if not checkpoint:
        return jax.lax.scan(step_fn, state, jnp.arange(count, dtype=jnp.int32))

    @jax.checkpoint
    def chunk(st, c):
        return jax.lax.scan(step_fn, st, c * size + jnp.arange(size, dtype=jnp.int32))

    st, outs = jax.lax.scan(chunk, state, jnp.arange(chunks, dtype=jnp.int32))
    return st, jax.tree.map(lambda a: a.reshape((chunks * size,) + a.shape[2:])[:count], outs)


def _assemble(scene, static, state0, outs, steps):
    pos, rv, shapes, stats, act, energy, wrenches = outs
    t = jnp.arange(steps + 1) * scene.solver.dt
    e0 = dynamics.rest_energy(scene, state0, static)
    return Trajectory(
        t=t,
        position=jnp.concatenate([static.position[None], pos[:steps]]),
        rotation_vector=jnp.concatenate([rotation_vector(static.rotation)[None], rv[:steps]]),
        positions=jnp.concatenate([static.nodes[None, :, :: scene.solver.refine, 0:3], shapes[:steps]]),
        actuators=jnp.concatenate([static.actuators[None], act[:steps]]),
        base_wrenches=jnp.concatenate([_base_wrenches(static.nodes)[None], wrenches[:steps]]),
        energy=jnp.concatenate([e0[None], energy[:steps]]),
        iterations=stats.iterations[:steps],
        residual=stats.residual[:steps],
        jacobians=stats.jacobians[:steps],
        result=results.worst(scene.structure_result(), static.stats.result, stats.result[:steps]),
        tol=scene.solver.newton.tol,
    )


# Derivatives with respect to at most this many scalars are taken in forward mode, in every AD
# mode (`few_inputs`). Each forward column costs a node scan per step, so the break-even against
# reverse mode falls as Newton needs fewer iterations per step. Measured (`jax.grad` of a
# rollout): about 32 scalars on Till's cantilever (N 20, dt 5 ms), 23 on the Triskele at dt 1 ms,
# 14 on the Stewart-Gough platform, and 7 on the Triskele at dt 50 us (1-2 iterations a step).
FORWARD_COLUMNS = 6


def rollout(scene, active_steps=None, path=None, checkpoint: int | None = None, forward_columns: int | None = None) -> Trajectory:
    """Simulate ``scene.solver.steps`` steps from rest at the static equilibrium; pure function.

    ``path`` (`PosePath`): inverse dynamics; the platform follows it from rest at its first pose
    and the trajectory's ``actuators`` are the solved actuator values.

    ``active_steps`` (an integer, may be traced): simulate only the first ``active_steps`` steps;
    the later entries of the trajectory are zeros and cost no solve. One compiled program then
    serves every shorter horizon (a fit that lengthens its window step by step).

    **Derivatives.** With respect to at most ``forward_columns`` (default `FORWARD_COLUMNS`)
    perturbed scalars of ``scene`` and ``path``, every AD mode (`jax.grad` too) gets them by
    forward mode (`numerics.few_inputs`): one exact Jacobian per step serves all directions,
    and reverse mode keeps those columns of the outputs it uses (under `jit`), not every step's
    intermediates. `jax.grad` of a scalar with respect to a rod's length and Young's modulus
    then costs about 3 forward runs on Till's cantilever, against about 5 in reverse mode.
    With more perturbed scalars (an actuator table, say), reverse mode is JAX's;
    ``forward_columns=0`` asks for it always.

    ``checkpoint`` (steps per chunk): reverse-mode gradients through long rollouts store one
    state per chunk instead of every step's intermediates (`jax.checkpoint`); e.g. ~sqrt(steps).

    No convergence check is raised here (it cannot be, under `jit`/`grad`): inspect
    ``.converged`` or use `simulate`.
    """
    if not scene.effects.inertia:
        raise SceneError("effects.inertia is false: the scene is static; use solve_static")
    check_structure(scene)
    if path is not None:
        inverse.check_square(scene)

    def run(scene, active_steps, path):
        static, state = _initial(scene, path)
        _, outs = _scan_steps(scene, state, 0, scene.solver.steps, active_steps, path, checkpoint)
        return _assemble(scene, static, state, outs, scene.solver.steps)

    columns = FORWARD_COLUMNS if forward_columns is None else int(forward_columns)
    return forward_for_few(run, columns)(scene, active_steps, path)


@eqx.filter_jit
def _start(scene, path=None):
    return _initial(scene, path)


@eqx.filter_jit
def _advance(scene, state, i0, count: int, active, path=None):
    return _scan_steps(scene, state, i0, count, active, path=path)


_COMPILED: dict = {}


def release_compiled():
    """Forget the compiled chunks and the static structures seen (see `executables.make_room`)."""
    _COMPILED.clear()
    _STATIC_SEEN.clear()


def _signature(tree):
    """Hashable abstract signature of a pytree: structure, array shapes and dtypes, other leaves' values."""
    leaves, treedef = jax.tree.flatten(tree)
    sig = tuple((np.shape(x), str(jnp.result_type(x)), getattr(x, "weak_type", False)) if eqx.is_array(x) else x for x in leaves)
    return treedef, sig


def _advance_key(scene, state, chunk: int, path):
    """The key of `_COMPILED` for these arguments, or None if a static leaf is unhashable."""
    try:
        key = (_signature((scene, state, path)), chunk)
        hash(key)
    except TypeError:
        return None
    return key


def _compiled_advance(scene, state, chunk: int, path=None):
    """``_advance`` lowered and compiled once per process for each abstract signature (calls to
    ``simulate`` that differ only in numbers, e.g. alpha or dt, reuse it; ``lower().compile()``
    alone would compile again every time); without caching where a static leaf is unhashable."""
    key = _advance_key(scene, state, chunk, path)
    if key is None:
        return _kept_advance(scene, state, chunk, path)
    if key not in _COMPILED:
        _COMPILED[key] = _kept_advance(scene, state, chunk, path)
    return _COMPILED[key]


# A chunk's per-step outputs (`_scan_steps`'s tuple), for their structure.
_OUTPUTS = (0, 0, 0, newton.Stats(0, 0, 0, 0, 0), 0, 0, 0)


def _kept_advance(scene, state, chunk: int, path):
    """``_advance``'s chunk compiled, its trace kept on disk (`traces.compiled`), so that a later
    process skips tracing and lowering it. A kept program takes arrays: the arguments pass as
    their leaves, and the outputs come back as the state and the per-step tuple. The plain
    compile where a leaf is not an array."""
    leaves, structure = jax.tree.flatten((scene, state, path))
    if not all(isinstance(a, jax.Array | np.ndarray) for a in leaves):
        return _advance.lower(scene, state, jnp.asarray(0), chunk, jnp.asarray(0), path).compile()

    def chunk_of(leaves, i0, active):
        sc, st, pa = jax.tree.unflatten(structure, leaves)
        return jax.tree.leaves(_scan_steps(sc, st, i0, chunk, active, path=pa))

    program = traces.compiled(chunk_of, "simulate-chunk", (str(structure), chunk), (leaves, jnp.asarray(0), jnp.asarray(0)))
    out = jax.tree.structure((state, _OUTPUTS))

    def run(scene, state, i0, count, active, path):
        return jax.tree.unflatten(out, program(jax.tree.leaves((scene, state, path)), i0, active))

    return run


def _start_and_chunk(scene, path, chunk: int):
    """The initial state (`_start`) and the chunk of steps compiled (`_compiled_advance`, so that
    run time excludes compilation). A chunk not compiled yet in this process compiles in a second
    thread while the initial state's program compiles and runs: XLA compiles without holding
    Python's lock, so on two cores the two compiles overlap. Before a new chunk compiles,
    `executables.make_room` (here, on this thread: releasing compiled code while another thread
    compiles is not safe)."""
    like = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(_start, scene, path)[1])
    key = _advance_key(scene, like, chunk, path)
    if key is not None and key in _COMPILED:
        static, state = _start(scene, path)
        compiled = _COMPILED[key]
    else:
        if key is not None:
            executables.make_room()
        with ThreadPoolExecutor(max_workers=1) as pool:
            job = pool.submit(_compiled_advance, scene, like, chunk, path)
            static, state = _start(scene, path)
            jax.block_until_ready(state)
            compiled = job.result()
    if _signature(state) != _signature(like):  # a leaf's weak type differs: compile for the state itself
        key = _advance_key(scene, state, chunk, path)
        if key is not None and key not in _COMPILED:
            executables.make_room()
        compiled = _compiled_advance(scene, state, chunk, path)
    return static, state, compiled


@eqx.filter_jit
def _finish(scene, static, state0, outs, steps: int):
    return _assemble(scene, static, state0, outs, steps)


def _raise_first_failure(scene, traj):
    i = results.first_failure(traj.result)
    if i is not None:
        t = (i + 1) * float(scene.solver.dt)
        code = int(traj.result[i])
        res = float(traj.residual[i])
        raise ConvergenceError(
            f"Newton did not converge at t = {t:.6g} s (step {i + 1}): {results.message(code)} (scaled residual {res:.3e}, tol {float(scene.solver.newton.tol):.1e})",
            t,
            res,
            code,
        )


def simulate(
    scene: Scene,
    *,
    throw: bool = True,
    progress: bool | Callable = False,
    chunk: int = 100,
    timings: dict | None = None,
) -> Trajectory:
    """Forward dynamics from rest at the static equilibrium under the initial load.

    **Arguments:**
    - ``throw``: raise `ConvergenceError` at the first non-converged step (outside traces; under
      a trace this is `rollout`).
    - ``progress``: True for a progress bar, or a callable ``f(done_steps, total_steps)``.
    - ``chunk``: steps per jitted call. One compiled chunk serves every run of the scene's
      structure, whatever its length: steps past the run's end hold the state and cost no solve.
    - ``timings``: if a dict, receives ``compile_s`` and ``run_s`` (wall time after compilation).

    When a step fails, the steps up to it are kept in the exception's ``partial`` attribute.
    """
    return _run(scene, None, throw, progress, chunk, timings)


def inverse_dynamics(
    scene: Scene,
    path: PosePath,
    *,
    throw: bool = True,
    progress: bool | Callable = False,
    chunk: int = 100,
    timings: dict | None = None,
) -> Trajectory:
    """Direct inverse dynamics: the actuator values that make the platform follow ``path``
    (`PosePath`) over the scene's duration, from rest at the path's first pose. The trajectory's
    ``actuators`` are the solution; its ``position`` and ``rotation_vector`` are the path at the
    step times. Arguments and failures as in `simulate`."""
    if any(_is_traced(leaf) for leaf in jax.tree.leaves((scene, path))):
        return rollout(scene, path=path)
    inverse.check_square(scene)
    return _run(scene, path, throw, progress, chunk, timings)


def _stepper(scene: Scene) -> Scene:
    """``scene`` as the compiled start and chunk see it: a step does not depend on the run's
    length or the scene's name, so both are set aside and scenes that differ only there (a
    longer run, another file of the same robot) share one program."""
    return dataclasses.replace(scene, name="scene", solver=dataclasses.replace(scene.solver, steps=0))


def _run(scene, path, throw, progress, chunk, timings) -> Trajectory:
    if any(_is_traced(leaf) for leaf in jax.tree.leaves(scene)):
        return rollout(scene, path=path)
    if not scene.effects.inertia:
        raise SceneError("effects.inertia is false: the scene is static; use `pcrjax static`")
    check_structure(scene)
    steps = scene.solver.steps
    named, scene = scene, _stepper(scene)
    chunk = max(1, int(chunk))
    n_chunks = -(-steps // chunk)
    t_c0 = time.perf_counter()
    static, state, compiled = _start_and_chunk(scene, path, chunk)
    state0 = state
    if int(static.stats.result) != results.SUCCESSFUL:
        code, res = int(static.stats.result), float(static.stats.residual)
        raise ConvergenceError(
            f"initial static equilibrium did not converge: {results.message(code)} (scaled residual {res:.3e})", 0.0, res, code
        )
    compile_s = time.perf_counter() - t_c0
    bar = None
    if progress is True:
        try:
            from tqdm.auto import tqdm

            bar = tqdm(total=steps, unit="step", desc=named.name, leave=False)
        except ImportError:  # pragma: no cover
            bar = None
    outs_all = []
    t_r0 = time.perf_counter()
    failure = None
    for c in range(n_chunks):
        state, outs = compiled(scene, state, jnp.asarray(c * chunk), chunk, jnp.asarray(min(chunk, steps - c * chunk)), path)
        codes = np.asarray(outs[3].result)
        outs_all.append(outs)
        done = min((c + 1) * chunk, steps)
        if bar is not None:
            bar.update(done - c * chunk)
        elif callable(progress):
            progress(done, steps)
        if throw and np.any(codes[: done - c * chunk] != results.SUCCESSFUL):
            failure = c
            break
    run_s = time.perf_counter() - t_r0
    if bar is not None:
        bar.close()
    outs = jax.tree.map(lambda *a: jnp.concatenate(a), *outs_all)
    n_done = min(len(outs_all) * chunk, steps)
    traj = _finish(scene, static, state0, outs, n_done)
    if timings is not None:
        timings.update(compile_s=compile_s, run_s=run_s, steps=n_done)
    if failure is not None:
        try:
            _raise_first_failure(named, traj)
        except ConvergenceError as e:
            e.partial = traj
            raise
    return traj
