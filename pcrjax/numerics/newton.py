"""Newton's method with Jacobian reuse and a backtracking line search, differentiated implicitly.

`solve` is the only root finder of pcrjax. The forward solve may use a stale Jacobian (chord
iterations), refreshes it when the contraction is poor or the line search fails, and reports its
iterations and final residual instead of raising, so failures travel as data through `lax.scan`
and are reported once at the end (as diffrax does). Gradients never unroll the iterations:
`_implicit` applies the implicit function theorem with the exact Jacobian at the root.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from . import results


class NewtonSettings(eqx.Module):
    tol: float = eqx.field(static=True, default=1e-10)
    max_iter: int = eqx.field(static=True, default=50)
    max_backtracks: int = eqx.field(static=True, default=12)
    refresh_ratio: float = eqx.field(static=True, default=0.5)
    broyden: bool = eqx.field(static=True, default=True)


def _power_of_two(x):
    """Nearest power of two of positive ``x`` (1 where x is 0): scaling by it is exact."""
    return jnp.where(x > 0, jnp.exp2(jnp.round(jnp.log2(jnp.where(x > 0, x, 1.0)))), 1.0)


class Jacobian(eqx.Module):
    """A dense Jacobian with the LU factors of its equilibrated form, carried between Newton calls.

    Rows, then columns, are scaled by powers of two to unit max-norm before factoring
    (``D_r J D_c = LU``). Scaling the unknowns and residuals by physical units (`shooting.Scales`)
    leaves entries of 1e6-1e7 where stiff axial rods meet a light platform under large $c_0^2$;
    equilibration cut the condition number of the Triskele-bot's step Jacobian from 7e12 to 7e5,
    and with it the round-off of each Newton direction.
    """

    matrix: jnp.ndarray
    lu: jnp.ndarray
    piv: jnp.ndarray
    row: jnp.ndarray
    col: jnp.ndarray

    @classmethod
    def factor(cls, J):
        row = 1.0 / _power_of_two(jnp.max(jnp.abs(J), axis=1))
        Jr = J * row[:, None]
        col = 1.0 / _power_of_two(jnp.max(jnp.abs(Jr), axis=0))
        lu, piv = jsl.lu_factor(Jr * col[None, :])
        return cls(J, lu, piv, row, col)

    @classmethod
    def empty(cls, size, dtype=jnp.float64):
        return cls.factor(jnp.eye(size, dtype=dtype))

    def solve(self, b):
        """$J^{-1} b$."""
        return self.col * jsl.lu_solve((self.lu, self.piv), self.row * b)


class Stats(eqx.Module):
    """Newton iterations (directions taken), final max-norm scaled residual, Jacobians evaluated,
    residual evaluations, and the `results` code saying why the solve stopped."""

    iterations: jnp.ndarray
    residual: jnp.ndarray
    jacobians: jnp.ndarray
    evaluations: jnp.ndarray
    result: jnp.ndarray

    @classmethod
    def zero(cls):
        z = jnp.asarray(0)
        return cls(z, jnp.asarray(0.0), z, z, jnp.asarray(results.SUCCESSFUL))


def dense_jacobian(fn: Callable, x, colors: np.ndarray | None = None, mask: np.ndarray | None = None):
    """Jacobian of ``fn`` at ``x`` by forward mode, optionally compressed by a column colouring.

    With ``colors`` (column -> colour) and ``mask`` (the sparsity pattern), one JVP per colour
    is enough; columns sharing a colour must not share a nonzero row.
    """
    if colors is None:
        return jax.jacfwd(fn)(x)
    _, colors = np.unique(colors, return_inverse=True)
    n_colors = int(colors.max()) + 1
    seeds = jnp.asarray(np.eye(n_colors)[colors].T, dtype=x.dtype)  # (colours, n)
    _, cols = jax.vmap(lambda t: jax.jvp(fn, (x,), (t,)))(seeds)  # (colours, m)
    return cols.T[:, colors] * jnp.asarray(mask, dtype=x.dtype)


def _norm(r):
    return jnp.max(jnp.abs(r))


class _State(eqx.Module):
    """One pass of `newton`'s loop: iterate, its residual and norm, the Jacobian in use, and the
    current direction with its line-search step."""

    x: jnp.ndarray
    r: jnp.ndarray
    nrm: jnp.ndarray
    jac: Jacobian
    need: jnp.ndarray  # refresh the Jacobian before the next direction
    fresh: jnp.ndarray  # the Jacobian was evaluated at the current iterate
    dx: jnp.ndarray
    lam: jnp.ndarray
    it: jnp.ndarray
    nj: jnp.ndarray
    evals: jnp.ndarray
    started: jnp.ndarray  # fn(x0) has been evaluated
    gave_up: jnp.ndarray  # the last direction's line search failed
    trial_finite: jnp.ndarray  # the last trial residual was finite


def newton(fn, x0, jac0: Jacobian, jac_fn, settings: NewtonSettings, need_jacobian=True):
    """Solve ``fn(x) = 0`` from ``x0``; returns ``(x, Jacobian, Stats)``. Never raises.

    One `while_loop` whose every pass evaluates ``fn`` once (so the residual is traced once):
    a pass either takes a new Newton direction (full step first) or halves the step of the
    current one (Armijo backtracking). ``jac0`` is reused (chord iterations) unless
    ``need_jacobian``; the Jacobian is refreshed when the contraction is worse than
    ``refresh_ratio`` or a stale direction fails its line search. A fresh direction that fails
    is taken with the smallest step (damped Newton), so the iteration always moves.
    """
    n = x0.shape[0]
    false, zero = jnp.asarray(False), jnp.asarray(0)
    init = _State(
        x=x0,
        r=jnp.zeros(n, x0.dtype),
        nrm=jnp.asarray(jnp.inf, x0.dtype),
        jac=jac0,
        need=jnp.asarray(need_jacobian),
        fresh=false,
        dx=jnp.zeros(n, x0.dtype),
        lam=jnp.asarray(0.0, x0.dtype),
        it=zero,
        nj=zero,
        evals=zero,
        started=false,
        gave_up=false,
        trial_finite=jnp.asarray(True),
    )
    lam_min = 0.5**settings.max_backtracks

    def cond(st: _State):
        return (~st.started) | ((st.nrm > settings.tol) & (st.it < settings.max_iter) & jnp.isfinite(st.nrm))

    def body(st: _State):
        x, r, nrm, jac, need, fresh, dx, lam, started = st.x, st.r, st.nrm, st.jac, st.need, st.fresh, st.dx, st.lam, st.started
        new_dir = started & (lam == 1.0)
        refresh = new_dir & need
        jac, fresh, nj = jax.lax.cond(
            refresh,
            lambda: (Jacobian.factor(jac_fn(fn, x)), jnp.asarray(True), st.nj + 1),
            lambda: (jac, fresh, st.nj),
        )
        dx = jnp.where(new_dir, -jac.solve(r), dx)
        r_t = fn(x + lam * dx)
        nrm_t = _norm(r_t)
        finite = jnp.isfinite(nrm_t)
        ok = (nrm_t <= (1.0 - 1e-4 * lam) * nrm) & finite
        ok = ok | ~started  # the first pass only evaluates fn(x0)
        give_up = ~ok & (lam <= lam_min)
        forced = give_up & fresh & finite
        move = ok | forced
        # Broyden's ("good") rank-one update keeps reused Jacobians accurate: superlinear
        # convergence without re-evaluating the Jacobian. Refactoring is cheap next to a residual.
        step_x = lam * dx
        upd = move & started & (jnp.dot(step_x, step_x) > 0)
        J_b = jac.matrix + jnp.outer(r_t - r - jac.matrix @ step_x, step_x) / jnp.where(upd, jnp.dot(step_x, step_x), 1.0)
        jac = jax.lax.cond(upd & settings.broyden, lambda: Jacobian.factor(J_b), lambda: jac)
        # Next pass: after a move or a failed search, a new direction (lam = 1); else backtrack.
        need_new = jnp.where(move & started, (nrm_t > settings.refresh_ratio * nrm) | forced, need) | give_up
        searched = (move | give_up) & started
        return _State(
            x=jnp.where(move, x + lam * dx, x),
            r=jnp.where(move, r_t, r),
            nrm=jnp.where(move, nrm_t, nrm),
            jac=jac,
            need=need_new,
            fresh=fresh & ~(move & started),
            dx=dx,
            lam=jnp.where(move | give_up, 1.0, 0.5 * lam),
            it=st.it + jnp.where(searched, 1, 0),
            nj=nj,
            evals=st.evals + 1,
            started=jnp.asarray(True),
            gave_up=jnp.where(searched, give_up, st.gave_up),
            trial_finite=finite,
        )

    st = jax.lax.while_loop(cond, body, init)
    result = jnp.where(
        st.nrm <= settings.tol,
        results.SUCCESSFUL,
        jnp.where(
            ~jnp.isfinite(st.nrm) | (st.gave_up & ~st.trial_finite),
            results.NONFINITE,
            jnp.where(st.gave_up, results.LINE_SEARCH_FAILED, results.MAX_ITERATIONS),
        ),
    )
    return st.x, st.jac, Stats(iterations=st.it, residual=st.nrm, jacobians=st.nj, evaluations=st.evals, result=result)


def solve(fn, x0, jac0: Jacobian, jac_fn, settings: NewtonSettings, need_jacobian=True, fallback=None):
    """Root of ``fn`` with implicit differentiation; returns ``(x, Jacobian, Stats)``.

    ``jac_fn(f, x)`` gives the exact Jacobian of ``f`` at ``x``; it serves the forward Newton and,
    at the root, the tangent solve of the implicit function theorem: ``dx = -J^{-1} (df/dp) dp``
    for every value ``p`` that ``fn`` closes over (`_implicit`). A ``jac_fn`` may exploit the
    structure of ``fn`` (the robots' leg-by-leg Jacobian). `jax.lax.custom_root` would pass the
    tangent solve only the linearised function, whose dense Jacobian costs one forward pass per
    unknown, and trace that solve even where nothing is differentiated.

    ``fn`` and ``jac_fn(fn, .)`` are traced once each (`jax.closure_convert`); the Newton loop
    and the tangent rule evaluate those traces. The forward solve sees its inputs through
    ``stop_gradient``: no tangent flows through its iterations.

    ``fallback``, if given, is ``(homotopy, homotopy_jac, s, starts, chain)``: stages tried in order
    only while the solve has not converged (traced once, run only if needed). Stage k solves
    ``homotopy(x, s[k]) = 0`` (with ``homotopy(x, 1) == fn(x)``; None: ``fn`` itself, with
    ``jac_fn``) from ``starts[k]``, or, where ``chain[k]``, from stage k-1's result, with a fresh
    Jacobian ``homotopy_jac(x, s[k])``. Load continuation and a restart from the previous time
    step are both written this way.
    """
    f_conv, f_consts = jax.closure_convert(fn, x0)
    j_conv, j_consts = jax.closure_convert(lambda x: jac_fn(fn, x), x0)
    fixed = lambda consts: [jax.lax.stop_gradient(c) for c in consts]  # noqa: E731
    f_fc, j_fc = fixed(f_consts), fixed(j_consts)
    f = lambda x: f_conv(x, *f_fc)  # noqa: E731
    jac_f = lambda _f, x: j_conv(x, *j_fc)  # noqa: E731
    x0, jac0 = jax.lax.stop_gradient((x0, jac0))

    x, jac, stats = newton(f, x0, jac0, jac_f, settings, need_jacobian)
    if fallback is not None:
        homotopy, homotopy_jac, svals, starts, chain = fallback
        if homotopy is None:
            stage_fn, stage_jac = lambda _s: f, lambda _s: jac_f
        else:
            h_conv, h_consts = jax.closure_convert(homotopy, x0, svals[0])
            hj_conv, hj_consts = jax.closure_convert(homotopy_jac, x0, svals[0])
            h_fc, hj_fc = fixed(h_consts), fixed(hj_consts)
            stage_fn = lambda s: lambda z: h_conv(z, s, *h_fc)  # noqa: E731
            stage_jac = lambda s: lambda _f, z: hj_conv(z, s, *hj_fc)  # noqa: E731

        def stage(carry, inp):
            x, jac, done, total = carry
            s, start, from_prev = inp

            def run():
                x2, jac2, st = newton(stage_fn(s), jnp.where(from_prev, x, start), jac, stage_jac(s), settings, True)
                return x2, jac2, (s == 1.0) & (st.residual <= settings.tol), accumulate(total, st)

            return jax.lax.cond(done, lambda: (x, jac, done, total), run), None

        done = stats.residual <= settings.tol
        (x, jac, _, stats), _ = jax.lax.scan(stage, (x, jac, done, stats), jax.lax.stop_gradient((svals, starts, chain)))
    return _implicit(f_conv, j_conv, x, f_consts, j_consts), jac, stats


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
    J = Jacobian.factor(j_conv(x, *j_consts))
    _, rhs = jax.jvp(lambda c: f_conv(x, *c), (list(f_consts),), (list(df_consts),))
    return x, -J.solve(rhs)


def accumulate(total: Stats, st: Stats) -> Stats:
    """Stats of two solves in sequence: counts add up, the residual and result are the later one's."""
    return Stats(
        total.iterations + st.iterations,
        st.residual,
        total.jacobians + st.jacobians,
        total.evaluations + st.evaluations,
        st.result,
    )


def continuation(homotopy, homotopy_jac, n: int, size: int, dtype=jnp.float64):
    """Fallback stages for load continuation: s = 1/n .. 1, starting from the root x = 0 at s = 0."""
    svals = jnp.linspace(1.0 / n, 1.0, n, dtype=dtype)
    chain = jnp.arange(n) > 0
    return homotopy, homotopy_jac, svals, jnp.zeros((n, size), dtype), chain


def restart(x):
    """Fallback stage for a time step: Newton again from ``x`` (the previous step's solution)
    with a fresh Jacobian."""
    return None, None, jnp.ones(1, x.dtype), jax.lax.stop_gradient(x)[None], jnp.zeros(1, bool)
