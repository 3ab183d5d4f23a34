"""Newton's method with Jacobian reuse and a backtracking line search, differentiated implicitly.

`solve` is the only root finder of pcrjax. The forward solve may use a stale Jacobian (chord
iterations), refreshes it when the contraction is poor or the line search fails, and reports its
iterations and final residual instead of raising, so failures travel as data through `lax.scan`
and are reported once at the end (as diffrax does). Gradients never unroll the iterations:
`_implicit` applies the implicit function theorem with the exact Jacobian at the root.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from . import results
from .few_inputs import linearizing


def _number(dtype):
    """A field converter: a number as a 0-d array (numpy, so that no JAX array exists before x64
    is enabled); arrays, traced ones included, pass as they are."""
    return lambda x: x if isinstance(x, jax.Array | np.ndarray) else np.asarray(x, dtype)


class NewtonSettings(eqx.Module):
    """``tol`` (scaled max-norm residual) and ``max_iter`` (directions per stage) are arrays, not
    compiled structure: scenes that differ only there share their programs.

    ``stop_when_lost``: a stage that ends unconverged ends the solve where the next stage would
    start from its result (a continuation that lost its path). Off by default: a platform's static
    continuation can fail a middle stage and still converge at the last. A screen of many
    candidates that only asks which converge turns it on (failures then cost 2-4x less)."""

    tol: jnp.ndarray = eqx.field(default=1e-10, converter=_number(np.float64))
    max_iter: jnp.ndarray = eqx.field(default=50, converter=_number(np.int64))
    max_backtracks: int = eqx.field(static=True, default=12)
    refresh_ratio: float = eqx.field(static=True, default=0.5)
    broyden: bool = eqx.field(static=True, default=True)
    stop_when_lost: bool = eqx.field(static=True, default=False)


def _power_of_two(x):
    """Nearest power of two of positive ``x`` (1 where x is 0): scaling by it is exact."""
    return jnp.where(x > 0, jnp.exp2(jnp.round(jnp.log2(jnp.where(x > 0, x, 1.0)))), 1.0)


class Jacobian(eqx.Module):
    """A dense Jacobian and its inverse, carried between Newton calls.

    The inverse comes from the LU factors of the equilibrated matrix: rows, then columns, are
    scaled by powers of two to unit max-norm first (``D_r J D_c = LU``, so
    ``J^{-1} = D_c (LU)^{-1} D_r``). Scaling the unknowns and residuals by physical units
    (`shooting.Scales`) leaves entries of 1e6-1e7 where stiff axial rods meet a light platform
    under large $c_0^2$; equilibration cut the condition number of the Triskele-bot's step
    Jacobian from 7e12 to 7e5, and with it the round-off of each Newton direction. Holding the
    inverse makes a direction one matrix-vector product and a Broyden update O(n^2)
    (Sherman-Morrison) instead of a new factorisation, O(n^3), at every iteration.
    """

    matrix: jnp.ndarray
    inverse: jnp.ndarray

    @classmethod
    def factor(cls, J):
        lu, row, col = _equilibrated_lu(J)
        return cls(J, col[:, None] * jsl.lu_solve(lu, jnp.diag(row)))

    @classmethod
    def empty(cls, size, dtype=jnp.float64):
        return cls.factor(jnp.eye(size, dtype=dtype))

    def solve(self, b):
        """$J^{-1} b$."""
        return self.inverse @ b

    def broyden(self, step, change):
        """Broyden's ("good") rank-one update after a ``step`` that changed the residual by
        ``change``: ``J + (change - J step) step^T / step^T step``, and its inverse by
        Sherman-Morrison. An update that would make the matrix (nearly) singular is not made."""
        u = (change - self.matrix @ step) / jnp.dot(step, step)
        Hu = self.inverse @ u
        denom = 1.0 + jnp.dot(step, Hu)
        ok = jnp.abs(denom) > 1e-8
        inverse = self.inverse - jnp.outer(Hu, step @ self.inverse) / jnp.where(ok, denom, 1.0)
        return Jacobian(jnp.where(ok, self.matrix + jnp.outer(u, step), self.matrix), jnp.where(ok, inverse, self.inverse))


class Stats(eqx.Module):
    """Newton iterations (directions taken), final max-norm scaled residual, Jacobians evaluated,
    residual evaluations, and the `results` code saying why the solve stopped."""

    iterations: jnp.ndarray
    residual: jnp.ndarray
    jacobians: jnp.ndarray
    evaluations: jnp.ndarray
    result: jnp.ndarray


def _equilibrated_lu(J):
    """(LU factors of ``D_r J D_c``, the row scales ``D_r``, the column scales ``D_c``): `Jacobian`'s
    equilibration by powers of two."""
    row = 1.0 / _power_of_two(jnp.max(jnp.abs(J), axis=1))
    Jr = J * row[:, None]
    col = 1.0 / _power_of_two(jnp.max(jnp.abs(Jr), axis=0))
    return jsl.lu_factor(Jr * col[None, :]), row, col


def solve_once(J, b):
    """``J^{-1} b`` (``b``: (n,) or (n, k)) by the equilibrated LU factors, with `Jacobian`'s
    round-off but not its inverse, whose n right-hand sides cost more than the factors: for a
    tangent rule, which solves with each step's Jacobian once."""
    lu, row, col = _equilibrated_lu(J)
    along = lambda d: d.reshape(d.shape + (1,) * (b.ndim - 1))  # noqa: E731
    return along(col) * jsl.lu_solve(lu, along(row) * b)


def _norm(r):
    return jnp.max(jnp.abs(r))


class Stages(eqx.Module):
    """Newton solves run in sequence inside one loop: stage k solves ``homotopy(x, s[k]) = 0`` from
    ``starts[k]``, or, where ``chain[k]``, from the previous stage's result; with a fresh Jacobian
    where ``fresh[k]`` (else the previous stage's, Broyden-updated); stages marked ``fallback``
    run only while the solve is not done (converged at s = 1). The last stage has s = 1.

    One loop, whatever the stages: the residual and the Jacobian are compiled once, not once per
    stage. Build them with `plain`, `with_restart`, `with_continuation` or `continuation_first`.
    """

    s: jnp.ndarray  # (K,)
    starts: jnp.ndarray  # (K, n)
    chain: jnp.ndarray  # (K,) bool
    fresh: jnp.ndarray  # (K,) bool
    fallback: jnp.ndarray  # (K,) bool


def _stages(rows, x0):
    s, starts, chain, fresh, fallback = zip(*rows, strict=True)
    stack = lambda v, dt: jnp.stack([jnp.asarray(a, dt) for a in v])  # noqa: E731
    return Stages(
        stack(s, x0.dtype),
        jnp.stack([jnp.asarray(a, x0.dtype) for a in starts]),
        stack(chain, bool),
        stack(fresh, bool),
        stack(fallback, bool),
    )


def plain(x0, need_jacobian=True) -> Stages:
    """One Newton solve from ``x0``."""
    return _stages([(1.0, x0, False, need_jacobian, False)], x0)


def with_restart(x0, x_restart, need_jacobian=True) -> Stages:
    """A solve from ``x0``, and if it fails, again from ``x_restart`` with a fresh Jacobian (a time
    step: from the extrapolated guess, then from the previous step's solution)."""
    return _stages([(1.0, x0, False, need_jacobian, False), (1.0, x_restart, False, True, True)], x0)


def with_continuation(x0, n: int, need_jacobian=True) -> Stages:
    """A solve from ``x0``, and if it fails, load continuation s = 1/n .. 1 from the root x = 0 at
    s = 0, each stage from the last with a fresh Jacobian."""
    zero = jnp.zeros_like(x0)
    rows = [(1.0, x0, False, need_jacobian, False)] + [((k + 1) / n, zero, k > 0, True, True) for k in range(n)]
    return _stages(rows, x0)


def continuation_first(x0, n: int, retry: int = 0) -> Stages:
    """Continuation s = 1/n .. 1 from ``x0`` (the root at s = 0), each stage from the last, with a
    fresh Jacobian at the first stage only (Broyden-updated after). With ``retry``, if that
    does not converge, a continuation of ``retry`` stages from ``x0`` again, each with a fresh
    Jacobian: a path that n stages lose (a stage's Newton wanders off and the rest follow) is
    followed in shorter steps."""
    rows = [((k + 1) / n, x0, k > 0, k == 0, False) for k in range(n)]
    rows += [((k + 1) / retry, x0, k > 0, True, True) for k in range(retry)]
    return _stages(rows, x0)


class _State(eqx.Module):
    """One pass of `_staged_newton`'s loop: the stage, the iterate, its residual and norm, the
    Jacobian in use, and the current direction with its line-search step."""

    k: jnp.ndarray  # stage
    x: jnp.ndarray
    r: jnp.ndarray
    nrm: jnp.ndarray
    jac: Jacobian
    need: jnp.ndarray  # refresh the Jacobian before the next direction
    fresh: jnp.ndarray  # the Jacobian was evaluated at the current iterate
    dx: jnp.ndarray
    lam: jnp.ndarray
    it: jnp.ndarray  # directions of this stage
    total_it: jnp.ndarray
    nj: jnp.ndarray
    evals: jnp.ndarray
    started: jnp.ndarray  # fn(x) has been evaluated at this stage's start
    gave_up: jnp.ndarray  # the last direction's line search failed
    trial_finite: jnp.ndarray  # the last trial residual was finite
    finished: jnp.ndarray
    aux: tuple  # what fn returned beside the residual at x (`solve`'s ``has_aux``), else ()


def _initial_state(jac0: Jacobian, stages: Stages, aux) -> _State:
    x0 = stages.starts[0]
    n = x0.shape[0]
    false, zero = jnp.asarray(False), jnp.asarray(0)
    return _State(
        k=zero, x=x0, r=jnp.zeros(n, x0.dtype), nrm=jnp.asarray(jnp.inf, x0.dtype), jac=jac0, need=stages.fresh[0], fresh=false,
        dx=jnp.zeros(n, x0.dtype), lam=jnp.asarray(0.0, x0.dtype), it=zero, total_it=zero, nj=zero, evals=zero, started=false,
        gave_up=false, trial_finite=jnp.asarray(True), finished=false, aux=aux,
    )  # fmt: skip


def _direction(st: _State, stages: Stages):
    """The stage's homotopy parameter, and whether this pass refreshes the Jacobian (a new
    direction is due and the last one asked for it)."""
    return stages.s[st.k], st.started & (st.lam == 1.0) & st.need


def _trial(st: _State):
    """The direction (a new one after a move or a failed search, else the current one) and the
    point this pass evaluates."""
    new_dir = st.started & (st.lam == 1.0)
    dx = jnp.where(new_dir, -st.jac.solve(st.r), st.dx)
    return dx, st.x + st.lam * dx


def _accept(st: _State, stages: Stages, settings: NewtonSettings, dx, r_t, aux_t):
    """Armijo's test of the trial residual ``r_t`` (and what came with it, ``aux_t``), the next
    state (its Jacobian not yet Broyden-updated), the updated matrix and whether to factor it."""
    x, r, nrm, lam, started = st.x, st.r, st.nrm, st.lam, st.started
    K = stages.s.shape[0]
    lam_min = 0.5**settings.max_backtracks
    nrm_t = _norm(r_t)
    finite = jnp.isfinite(nrm_t)
    ok = (nrm_t <= (1.0 - 1e-4 * lam) * nrm) & finite
    ok = ok | ~started  # the first pass of a stage only evaluates fn at its start
    give_up = ~ok & (lam <= lam_min)
    forced = give_up & st.fresh & finite
    move = ok | forced
    # Broyden's ("good") rank-one update keeps reused Jacobians accurate: superlinear
    # convergence without re-evaluating the Jacobian.
    step_x = lam * dx
    upd = move & started & (jnp.dot(step_x, step_x) > 0) & settings.broyden
    # Next pass: after a move or a failed search, a new direction (lam = 1); else backtrack.
    need_new = jnp.where(move & started, (nrm_t > settings.refresh_ratio * nrm) | forced, st.need) | give_up
    searched = (move | give_up) & started
    x_new = jnp.where(move, x + step_x, x)
    nrm_new = jnp.where(move, nrm_t, nrm)
    it_new = st.it + jnp.where(searched, 1, 0)
    # The stage ends when it converges, runs out of directions or overflows; the solve ends
    # after the last stage, or when done and only fallback stages remain.
    s = stages.s[st.k]
    ended = ~((nrm_new > settings.tol) & (it_new < settings.max_iter) & jnp.isfinite(nrm_new))
    done = (nrm_new <= settings.tol) & (s == 1.0)
    k_next = jnp.minimum(st.k + 1, K - 1)
    finished = ended & ((st.k == K - 1) | (done & stages.fallback[k_next]))
    if settings.stop_when_lost:
        finished = finished | (ended & (nrm_new > settings.tol) & stages.chain[k_next] & (st.k < K - 1))
    advance = ended & ~finished
    nxt = _State(
        k=jnp.where(advance, k_next, st.k),
        x=jnp.where(advance & ~stages.chain[k_next], stages.starts[k_next], x_new),
        r=jnp.where(move, r_t, r),
        nrm=jnp.where(advance, jnp.inf, nrm_new),
        jac=st.jac,
        need=jnp.where(advance, stages.fresh[k_next] | need_new, need_new),
        fresh=jnp.where(advance, False, st.fresh & ~(move & started)),  # a new stage's start is a new point
        dx=dx,
        lam=jnp.where(advance, 0.0, jnp.where(move | give_up, 1.0, 0.5 * lam)),
        it=jnp.where(advance, 0, it_new),
        total_it=st.total_it + jnp.where(searched, 1, 0),
        nj=st.nj,
        evals=st.evals + 1,
        started=~advance,
        gave_up=jnp.where(advance, False, jnp.where(searched, give_up, st.gave_up)),
        trial_finite=finite,
        finished=finished,
        aux=jax.tree.map(lambda a, b: jnp.where(move, a, b), aux_t, st.aux),
    )
    return nxt, (step_x, r_t - r), upd


# Members whose Jacobians a batched solve evaluates together, by backend: on a CPU a batched
# Jacobian costs in proportion to its members, so small chunks; on a GPU a chunk's members run in
# parallel and each chunk is a sequential pass of many small kernels, so larger ones.
JAC_CHUNK = {"cpu": 4}
JAC_CHUNK_ACCELERATOR = 128


def jac_chunk() -> int:
    """`JAC_CHUNK` for the backend that programs are compiled for now."""
    return JAC_CHUNK.get(jax.default_backend(), JAC_CHUNK_ACCELERATOR)


def _where(p, new, old):
    """``new`` where the members' flags ``p`` (B,) hold, else ``old`` (pytrees, leading axis B)."""
    return jax.tree.map(lambda a, b: jnp.where(p.reshape(p.shape + (1,) * (a.ndim - 1)), a, b), new, old)


def _staged_newton(fn, jac_fn, jac0: Jacobian, settings: NewtonSettings, stages: Stages, batched: bool = False, has_aux=False):
    """Solve ``fn(x, s) = 0`` stage after stage (`Stages`); returns ``(x, Jacobian, Stats, aux)``
    (with ``has_aux``, ``fn`` returns ``(residual, aux)`` and aux is that of the returned x;
    else aux is ()). Never raises.

    One `while_loop` whose every pass evaluates ``fn`` once (so the residual is traced once):
    a pass either takes a new Newton direction (full step first) or halves the step of the
    current one (Armijo backtracking). The Jacobian is reused (chord iterations) unless a stage
    asks for a fresh one; it is refreshed when the contraction is worse than ``refresh_ratio``
    or a stale direction fails its line search. A fresh direction that fails is taken with the
    smallest step (damped Newton), so the iteration always moves. A stage ends when it meets the
    tolerance, reaches ``max_iter`` directions or its residual is not finite.

    ``batched``: every array carries a leading axis of B independent members; ``fn(x, s)``
    takes and returns the whole batch and ``jac_fn(x, s, members)`` the Jacobians of the listed
    members (indices into the batch, one row of ``x`` and ``s`` each). The members' decisions
    stay their own: Jacobians are evaluated only for the members that ask for one, `jac_chunk()`
    at a time (a batched Jacobian costs in proportion to its members, and in a large batch a
    few members refresh in most passes); Broyden updates are made when some member takes
    one. The loop runs until every member has finished; a finished member's state is held.
    """
    per = jax.vmap if batched else (lambda f: f)
    evaluate = fn if has_aux else (lambda x, s: (fn(x, s), ()))

    def maybe(p, make, old):
        if not batched:
            return jax.lax.cond(p, make, lambda: old)
        return jax.lax.cond(jnp.any(p), lambda: _where(p, make(), old), lambda: old)

    def fresh_jacobians(p, x, s, old):
        if not batched:
            return maybe(p, lambda: Jacobian.factor(jac_fn(x, s)), old)
        size = p.shape[0]
        m = jac_chunk()
        if size <= m:
            return maybe(p, lambda: jax.vmap(Jacobian.factor)(jac_fn(x, s, jnp.arange(size))), old)
        chunks = -(-size // m)
        order = jnp.nonzero(p, size=chunks * m, fill_value=size)[0]  # flagged members first, then past the end

        def chunk(c, jac):
            idx = jax.lax.dynamic_slice(order, (c * m,), (m,))
            member = jnp.minimum(idx, size - 1)
            new = jax.vmap(Jacobian.factor)(jac_fn(x[member], s[member], member))
            return jax.tree.map(lambda a, v: a.at[idx].set(v, mode="drop"), jac, new)

        return jax.lax.fori_loop(0, (jnp.sum(p) + m - 1) // m, chunk, old)

    def body(st: _State):
        s, refresh = per(_direction)(st, stages)
        if batched:
            refresh = refresh & ~st.finished
        jac = fresh_jacobians(refresh, st.x, s, st.jac)
        st = eqx.tree_at(lambda t: (t.jac, t.fresh, t.nj), st, (jac, st.fresh | refresh, st.nj + jnp.where(refresh, 1, 0)))
        dx, x_t = per(_trial)(st)
        r_t, aux_t = evaluate(x_t, s)
        nxt, (step_x, change), upd = per(_accept)(st, stages, settings, dx, r_t, aux_t)
        if batched:
            upd = upd & ~st.finished
        updated = lambda: per(lambda j, a, b: j.broyden(a, b))(st.jac, step_x, change)  # noqa: E731
        nxt = eqx.tree_at(lambda t: t.jac, nxt, maybe(upd, updated, nxt.jac))
        return _where(st.finished, st, nxt) if batched else nxt

    aux0 = ()
    if has_aux:  # zeros of aux's shape until the first pass evaluates fn
        x0, s0 = (stages.starts[:, 0], stages.s[:, 0]) if batched else (stages.starts[0], stages.s[0])
        aux0 = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(fn, x0, s0)[1])
    init = per(_initial_state)(jac0, stages, aux0)
    more = (lambda st: ~jnp.all(st.finished)) if batched else (lambda st: ~st.finished)
    st = jax.lax.while_loop(more, body, init)
    result = jnp.where(
        st.nrm <= settings.tol,
        results.SUCCESSFUL,
        jnp.where(
            ~jnp.isfinite(st.nrm) | (st.gave_up & ~st.trial_finite),
            results.NONFINITE,
            jnp.where(st.gave_up, results.LINE_SEARCH_FAILED, results.MAX_ITERATIONS),
        ),
    )
    return (
        st.x,
        st.jac,
        Stats(iterations=st.total_it, residual=st.nrm, jacobians=st.nj, evaluations=st.evals, result=result),
        st.aux,
    )


def solve(
    fn,
    jac_fn,
    jac0: Jacobian,
    settings: NewtonSettings,
    stages: Stages,
    homotopy=None,
    has_aux=False,
    aux_tangents=None,
    held=None,
):
    """Root of ``fn`` with implicit differentiation; returns ``(x, Jacobian, Stats)``.

    ``jac_fn(x)`` gives the exact Jacobian of ``fn`` at ``x``; it serves the forward Newton and,
    at the root, the tangent solve of the implicit function theorem: ``dx = -J^{-1} (df/dp) dp``
    for every value ``p`` that ``fn`` closes over (`_implicit`). A ``jac_fn`` may exploit the
    structure of ``fn`` (the robots' leg-by-leg Jacobian). `jax.lax.custom_root` would pass the
    tangent solve only the linearised function, whose dense Jacobian costs one forward pass per
    unknown, and trace that solve even where nothing is differentiated.

    ``stages`` (`Stages`) say where Newton starts and what it tries next; ``homotopy``, if given,
    is ``(h, h_jac)`` with ``h(x, 1) == fn(x)``, solved at each stage's ``s`` (without it every
    stage solves ``fn``); the tangent rule then evaluates ``h`` and ``h_jac`` at s = 1, and
    ``fn`` and ``jac_fn`` are not traced. The functions are traced once each
    (`jax.closure_convert`); the Newton loop and the tangent rule evaluate those traces. The
    forward solve sees its inputs through ``stop_gradient``: no tangent flows through its
    iterations.

    ``has_aux``: ``fn`` (and the homotopy's ``h``) return ``(residual, aux)``, and the solve
    returns ``(x, Jacobian, Stats, aux)`` with the aux of the returned x: what a caller would
    otherwise compute again at the root (the legs' nodes) comes from the last evaluation. It
    carries no derivatives (`recorded` gives it those of the function that made it) unless
    ``aux_tangents`` is given: ``(jac_aux_fn, aux_tangent)``, where ``jac_aux_fn(x)`` returns
    the exact Jacobian and whatever ``aux_tangent(that, dx)`` needs to give the aux's derivative
    along a change ``dx`` of the unknowns (``aux_tangent`` is closed over no arrays). The aux's
    derivative is then the tangent of ``fn``'s aux along the inputs (from the pass that gives
    the implicit function theorem its right-hand side) plus ``aux_tangent`` along the root's
    tangent, so no second pass through ``fn`` is made: along the legs, the Jacobian's own
    integration gives every node's tangent (`_implicit_with_aux`).

    ``held`` (with ``aux_tangents``; forward mode): ``(Jacobians, unknowns)``, what
    ``jac_aux_fn`` gave at those unknowns on an earlier solve of a like problem. The tangent
    solve takes them instead of evaluating ``jac_aux_fn`` at the root while the root lies within
    ``HOLD_MOVE`` (max-norm) of those unknowns (NaN unknowns: never), and the solve returns
    ``(x, Jacobian, Stats, aux, held)`` with what the next solve may hold: a rollout at rest
    needs the exact Jacobian once, not at every step (`_implicit_with_aux_held`).

    Under `jax.vmap` the solve runs as one batched loop (`_batched`) that evaluates Jacobians
    only when some member needs one; each member's iterates are those of its own solve.
    """
    x0 = stages.starts[0]
    if homotopy is None:
        f_conv, f_consts = jax.closure_convert(fn, x0)
        j_conv, j_consts = jax.closure_convert(jac_fn, x0)
        g, g_consts = (lambda x, s, c: f_conv(x, *c)), f_consts
        g_jac, gj_consts = (lambda x, s, c: j_conv(x, *c)), j_consts
    else:  # fn is the homotopy at s = 1: its trace serves the tangent rule too (one trace less)
        h_conv, g_consts = jax.closure_convert(homotopy[0], x0, stages.s[0])
        hj_conv, gj_consts = jax.closure_convert(homotopy[1], x0, stages.s[0])
        g, g_jac = (lambda x, s, c: h_conv(x, s, *c)), (lambda x, s, c: hj_conv(x, s, *c))
        f_conv, f_consts = _at_one(h_conv), g_consts
        j_conv, j_consts = _at_one(hj_conv), gj_consts
    fixed = jax.lax.stop_gradient
    x, jac, stats, aux = _batched(g, g_jac, settings, has_aux)(fixed(g_consts), fixed(gj_consts), fixed(jac0), fixed(stages))
    if aux_tangents is not None:
        if homotopy is not None or not has_aux:
            raise ValueError("aux_tangents needs has_aux and no homotopy")
        ja_conv, ja_consts = jax.closure_convert(aux_tangents[0], x0)
        if held is not None:
            x, aux, held = _implicit_with_aux_held(f_conv, ja_conv, aux_tangents[1], x, aux, fixed(held), f_consts, ja_consts)
            return x, jac, stats, aux, held
        x, aux = _implicit_with_aux(f_conv, j_conv, ja_conv, aux_tangents[1], x, aux, f_consts, j_consts, ja_consts)
        return x, jac, stats, aux
    x = _implicit(_residual_of(f_conv) if has_aux else f_conv, j_conv, x, f_consts, j_consts)
    return (x, jac, stats, aux) if has_aux else (x, jac, stats)


def _residual_of(f):
    return lambda x, *c: f(x, *c)[0]


def recorded(fn, x, value):
    """``value``, which is ``fn(x)`` computed elsewhere (`solve`'s aux at its root), with the
    derivatives of ``fn`` at ``x``: a run without derivatives takes ``value`` and does not
    evaluate ``fn``; a derivative evaluates ``fn``'s JVP at ``x``."""
    conv, consts = jax.closure_convert(fn, x)
    return _recorded(conv, x, value, consts)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _recorded(conv, x, value, consts):
    return value


@_recorded.defjvp
def _recorded_jvp(conv, primals, tangents):
    x, _, consts = primals
    dx, _, dconsts = tangents
    return jax.jvp(lambda z, c: conv(z, *c), (x, list(consts)), (dx, list(dconsts)))


def _at_one(h):
    """``h(x, 1, *consts)`` as a function of ``(x, *consts)``."""
    return lambda x, *c: h(x, jnp.ones((), x.dtype), *c)


def _batched(g, g_jac, settings: NewtonSettings, has_aux=False):
    """`_staged_newton` of ``g(x, s, consts)`` as a function of its arrays, with a `vmap` rule.

    Batched by plain `vmap`, every `lax.cond` of the loop whose predicate differs between members
    becomes a `select` that runs both branches: every member would evaluate a Jacobian and
    refactor at every pass. The rule runs `_staged_newton` on the batch instead.
    """

    numbers, fixed = eqx.partition(settings, eqx.is_array)

    @jax.custom_batching.custom_vmap
    def run(consts, jac_consts, jac0, stages, numbers):
        return _staged_newton(
            lambda x, s: g(x, s, consts),
            lambda x, s: g_jac(x, s, jac_consts),
            jac0,
            eqx.combine(numbers, fixed),
            stages,
            has_aux=has_aux,
        )

    @run.def_vmap
    def rule(size, in_batched, consts, jac_consts, jac0, stages, numbers):
        axes = lambda flags: [0 if b else None for b in flags]  # noqa: E731
        spread = lambda tree, flags: jax.tree.map(  # noqa: E731
            lambda a, b: a if b else jnp.broadcast_to(a, (size,) + jnp.shape(a)), tree, flags
        )
        fn = jax.vmap(g, in_axes=(0, 0, axes(in_batched[0])))
        jac_fn = jax.vmap(g_jac, in_axes=(0, 0, axes(in_batched[1])))
        pick = lambda members: [c[members] if b else c for c, b in zip(jac_consts, in_batched[1], strict=True)]  # noqa: E731
        out = _staged_newton(
            lambda x, s: fn(x, s, consts),
            lambda x, s, members: jac_fn(x, s, pick(members)),
            spread(jac0, in_batched[2]),
            eqx.combine(spread(numbers, in_batched[4]), fixed),  # each member's tolerance and cap
            spread(stages, in_batched[3]),
            batched=True,
            has_aux=has_aux,
        )
        return out, jax.tree.map(lambda _: True, out)

    return lambda consts, jac_consts, jac0, stages: run(consts, jac_consts, jac0, stages, numbers)


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _implicit(f_conv, j_conv, x, f_consts, j_consts):
    """``x``, a root of ``f_conv(., *f_consts)``, with the tangent of the implicit function theorem
    (``x``'s own tangent is ignored: the root does not depend on where Newton started)."""
    return x


@_implicit.defjvp
def _implicit_jvp(f_conv, j_conv, primals, tangents):
    x, f_consts, j_consts = primals
    _, df_consts, _ = tangents
    x = _implicit(f_conv, j_conv, x, f_consts, j_consts)  # differentiable again (second order)
    _, rhs = jax.jvp(lambda c: f_conv(x, *c), (list(f_consts),), (list(df_consts),))
    return x, -solve_once(j_conv(x, *j_consts), rhs)


@partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3))
def _implicit_with_aux(f_conv, j_conv, ja_conv, aux_tangent, x, aux, f_consts, j_consts, ja_consts):
    """``(x, aux)``: a root of ``f_conv(., *f_consts)``'s residual and that function's aux there,
    with `_implicit`'s tangent for ``x`` and the aux's own (`solve`'s ``aux_tangents``)."""
    return x, aux


@_implicit_with_aux.defjvp
def _implicit_with_aux_jvp(f_conv, j_conv, ja_conv, aux_tangent, primals, tangents):
    x, aux, f_consts, j_consts, ja_consts = primals
    df_consts = tangents[2]
    x, aux = _implicit_with_aux(f_conv, j_conv, ja_conv, aux_tangent, *primals)  # second order
    if linearizing(jax.tree.leaves(df_consts)):
        # Reverse mode would keep every step's aux Jacobian for the transpose: the aux's tangent
        # comes instead from a second pass through fn along the root's tangent, as `recorded`.
        _, rhs = jax.jvp(lambda c: f_conv(x, *c)[0], (list(f_consts),), (list(df_consts),))
        dx = -solve_once(j_conv(x, *j_consts), rhs)
        _, (_, daux) = jax.jvp(lambda z, c: f_conv(z, *c), (x, list(f_consts)), (dx, list(df_consts)))
        return (x, aux), (dx, daux)
    dx, daux = _root_and_aux_tangents(f_conv, aux_tangent, x, f_consts, df_consts, *ja_conv(x, *ja_consts))
    return (x, aux), (dx, daux)


def _root_and_aux_tangents(f_conv, aux_tangent, x, f_consts, df_consts, Jm, aux_jac):
    """(the root's tangent, the aux's) from the exact Jacobian ``Jm`` at the root and what
    ``aux_tangent`` needs (``aux_jac``): the inputs' pass gives the right-hand side and the aux's
    own part, the root's tangent the rest (`solve`'s ``aux_tangents``)."""
    _, (rhs, daux_inputs) = jax.jvp(lambda c: f_conv(x, *c), (list(f_consts),), (list(df_consts),))
    dx = -solve_once(Jm, rhs)
    return dx, jax.tree.map(jnp.add, daux_inputs, aux_tangent(aux_jac, dx))


# A held tangent Jacobian serves while the unknowns (scaled) moved less than this since it was
# taken: there the step Jacobian changes far less than the 1e-3 a fit's Jacobian needs.
HOLD_MOVE = 1e-6


def _refreshed(ja_conv, x, held, ja_consts):
    """``held`` = (exact Jacobian and legs' Jacobians, the unknowns where they were taken), taken
    again at ``x`` where the unknowns moved more than ``HOLD_MOVE`` since (or never were)."""
    tj, x_held = held
    need = ~(jnp.max(jnp.abs(x - x_held)) <= HOLD_MOVE)
    tj = jax.lax.cond(need, lambda: ja_conv(x, *ja_consts), lambda: tj)
    return tj, jnp.where(need, x, x_held)


@partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _implicit_with_aux_held(f_conv, ja_conv, aux_tangent, x, aux, held, f_consts, ja_consts):
    """`_implicit_with_aux` whose tangent solve takes the Jacobians ``held`` from an earlier step
    while the unknowns stayed within ``HOLD_MOVE`` of where they were taken; returns ``(x, aux,
    held)`` for the next step."""
    return x, aux, _refreshed(ja_conv, x, held, ja_consts)


@_implicit_with_aux_held.defjvp
def _implicit_with_aux_held_jvp(f_conv, ja_conv, aux_tangent, primals, tangents):
    x, aux, held, f_consts, ja_consts = primals
    df_consts = tangents[3]
    x, aux, held = _implicit_with_aux_held(f_conv, ja_conv, aux_tangent, *primals)
    dx, daux = _root_and_aux_tangents(f_conv, aux_tangent, x, f_consts, df_consts, *held[0])
    return (x, aux, held), (dx, daux, jax.tree.map(jnp.zeros_like, held))
