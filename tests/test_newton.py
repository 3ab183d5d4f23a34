"""`newton.solve`'s implicit derivatives against closed forms.

The root of x^3 + p x - q = 0 (one real root for p > 0) has dx/dq = 1 / (3x^2 + p),
dx/dp = -x / (3x^2 + p), and d2x/dq2 = -6x (dx/dq)^3; forward, reverse and second-order
derivatives through the solve must give these, whether or not the fallback stages ran.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pcrjax.numerics import newton, results

SETTINGS = newton.NewtonSettings(tol=1e-13, max_iter=40)


def _root(params, fallback=None):
    """The root from x0 = 4, or, with a fallback, from a NaN start (the first solve fails at once)
    so that the fallback's stages do the work: a restart from 0.5 (``fn`` itself) or a load
    continuation in q."""
    p, q = params[0], params[1]
    fn = lambda x: x**3 + p * x - q  # noqa: E731
    jac_fn = jax.jacfwd(fn)
    guess = jnp.full(1, 4.0 if fallback is None else jnp.nan)
    stages, homotopy = newton.plain(guess), None
    if fallback == "restart":
        stages = newton.with_restart(guess, jnp.full(1, 0.5))
    elif fallback == "continuation":
        h = lambda x, s: x**3 + p * x - s * q  # noqa: E731
        stages, homotopy = newton.with_continuation(guess, 4), (h, jax.jacfwd(h))
    x, _, stats = newton.solve(fn, jac_fn, newton.Jacobian.empty(1), SETTINGS, stages, homotopy)
    return x[0], stats


def _closed_form(p, q):
    x = np.roots([1.0, 0.0, p, -q])
    x = float(np.real(x[np.argmin(np.abs(np.imag(x)))]))
    dq = 1.0 / (3 * x**2 + p)
    return x, dq, -x * dq, -6 * x * dq**3


@pytest.mark.parametrize("fallback", [None, "restart", "continuation"])
def test_implicit_derivatives_of_a_cubic_root(fallback):
    params = jnp.array([2.0, 3.0])
    x_ref, dq, dp, dqq = _closed_form(2.0, 3.0)
    f = lambda prm: _root(prm, fallback)[0]  # noqa: E731
    x, stats = jax.jit(lambda prm: _root(prm, fallback))(params)
    assert float(stats.residual) <= 1e-13 and abs(float(x) - x_ref) < 1e-12
    np.testing.assert_allclose(jax.jacfwd(f)(params), [dp, dq], rtol=1e-10)
    np.testing.assert_allclose(jax.grad(f)(params), [dp, dq], rtol=1e-10)
    np.testing.assert_allclose(jax.hessian(f)(params)[1, 1], dqq, rtol=1e-8)


def _restart_root(params, start):
    """The cubic's root from ``start``, restarted from 0.5 if that solve fails (a NaN start)."""
    p, q = params[0], params[1]
    fn = lambda x: x**3 + p * x - q  # noqa: E731
    stages = newton.with_restart(jnp.full(1, start), jnp.full(1, 0.5))
    x, _, stats = newton.solve(fn, jax.jacfwd(fn), newton.Jacobian.empty(1), SETTINGS, stages)
    return x[0], stats


@pytest.mark.parametrize("chunk", [2, 4, 8])
def test_batched_solve_equals_single_solves_member_by_member(chunk, monkeypatch):
    """Under vmap the members keep their own iterates, stages and failures: a member that needs
    the restart, one whose residual is NaN (it fails; the others are unharmed), and plain ones;
    with the Jacobians evaluated a few members at a time or for the whole batch at once (a GPU's
    larger chunks)."""
    monkeypatch.setitem(newton.JAC_CHUNK, jax.default_backend(), chunk)
    params = jnp.array([[2.0, 3.0], [1.0, 1.0], [5.0, -2.0], [2.0, jnp.nan], [0.5, 7.0]])
    starts = jnp.array([4.0, jnp.nan, -3.0, 1.0, 10.0])
    xb, sb = jax.jit(jax.vmap(_restart_root))(params, starts)
    single = jax.jit(_restart_root)
    for i in range(len(starts)):
        x, s = single(params[i], starts[i])
        for name in ("iterations", "jacobians", "evaluations", "result"):
            assert int(getattr(sb, name)[i]) == int(getattr(s, name)), (i, name)
        if int(s.result) == 0:
            assert abs(float(xb[i]) - float(x)) <= 1e-12 * abs(float(x))
            assert abs(float(x) - _closed_form(*map(float, params[i]))[0]) < 1e-12
    assert int(sb.jacobians[1]) >= 1 and int(sb.iterations[1]) > 0  # the restarted member converged
    assert [int(r) for r in sb.result] == [0, 0, 0, 3, 0]
    # Implicit derivatives of every member under vmap.
    grads = jax.jit(jax.vmap(jax.grad(lambda prm, x0: _restart_root(prm, x0)[0])))(params, starts)
    for i in (0, 1, 2, 4):
        _, dq, dp, _ = _closed_form(*map(float, params[i]))
        np.testing.assert_allclose(grads[i], [dp, dq], rtol=1e-10)


def test_a_continuation_that_loses_its_path_ends_there_when_asked():
    """x^2 + 1 - 2s = 0 from x = 1 in four stages: s = 1/4 and 1/2 have no real root, s = 1 has
    x = 1. With ``stop_when_lost`` the first stage fails after max_iter directions and the solve
    ends there, reported as not converged; by default it goes on through the later stages."""
    h = lambda x, s: x**2 + 1.0 - 2.0 * s  # noqa: E731
    fn = lambda x: h(x, 1.0)  # noqa: E731
    stages = newton.continuation_first(jnp.ones(1), 4)

    def stats(settings):
        return newton.solve(fn, jax.jacfwd(fn), newton.Jacobian.empty(1), settings, stages, (h, jax.jacfwd(h)))[2]

    lost = stats(newton.NewtonSettings(tol=1e-13, max_iter=40, stop_when_lost=True))
    assert int(lost.result) != 0 and int(lost.iterations) == 40
    assert int(stats(SETTINGS).iterations) > 40


def test_a_continuation_that_loses_its_path_is_retried_in_shorter_steps():
    """sinh(x) = s sinh(3) from x = 0 with at most 5 directions per stage: two stages are too
    long a step (the second ends unconverged) and the solve is reported failed; with ``retry`` 8
    the retry's eight stages reach the root x = 3, and the implicit derivative through that solve
    is the closed form dx/dq = 1 / cosh(x) of sinh(x) = q."""
    settings = newton.NewtonSettings(tol=1e-13, max_iter=5)

    def root(q, retry):
        h = lambda x, s: jnp.sinh(x) - s * q  # noqa: E731
        fn = lambda x: h(x, 1.0)  # noqa: E731
        stages = newton.continuation_first(jnp.zeros(1), 2, retry)
        x, _, stats = newton.solve(fn, jax.jacfwd(fn), newton.Jacobian.empty(1), settings, stages, (h, jax.jacfwd(h)))
        return x[0], stats

    q = jnp.asarray(np.sinh(3.0))
    _, lost = root(q, 0)
    assert int(lost.result) != 0
    x, stats = jax.jit(lambda q: root(q, 8))(q)
    assert int(stats.result) == 0 and abs(float(x) - 3.0) < 1e-13
    assert int(stats.iterations) > int(lost.iterations)  # the first plan ran, then the retry
    np.testing.assert_allclose(jax.grad(lambda q: root(q, 8)[0])(q), 1.0 / np.cosh(3.0), rtol=1e-10)


def _root_with_aux(params, start, homotopy=False):
    """The cubic's root from ``start`` (restarted from 0.5 if that fails, or by a load continuation
    with ``homotopy``), with aux = exp(p x) from the residual's evaluations, given the derivatives
    of exp(p x) by `newton.recorded`."""
    p, q = params[0], params[1]
    with_aux = lambda x, s=1.0: (x**3 + p * x - s * q, jnp.exp(p * x))  # noqa: E731
    fn = lambda x: with_aux(x)[0]  # noqa: E731
    stages, h = newton.with_restart(jnp.full(1, start), jnp.full(1, 0.5)), None
    if homotopy:
        stages = newton.with_continuation(jnp.full(1, start), 4)
        h = (with_aux, jax.jacfwd(lambda x, s: with_aux(x, s)[0]))
    x, _, stats, aux = newton.solve(with_aux, jax.jacfwd(fn), newton.Jacobian.empty(1), SETTINGS, stages, h, has_aux=True)
    return x[0], newton.recorded(lambda z: jnp.exp(p * z), x, aux)[0], stats


@pytest.mark.parametrize("homotopy", [False, True])
def test_aux_of_the_root_is_its_functions_value_with_its_derivatives(homotopy):
    """``has_aux``: the aux returned is the one evaluated at the returned root, also after a
    restart or a continuation from a NaN start (whose aux is NaN), single and under vmap; with
    `newton.recorded` its derivatives are those of exp(p x(p, q)):
    (exp(p x) (x + p dx/dp), exp(p x) p dx/dq)."""
    params = jnp.array([[2.0, 3.0], [1.0, 1.0], [0.5, 7.0]])
    starts = jnp.array([4.0, jnp.nan, 10.0])
    run = lambda prm, x0: _root_with_aux(prm, x0, homotopy)[1]  # noqa: E731
    batched = jax.jit(jax.vmap(run))(params, starts)
    grads = jax.jit(jax.vmap(jax.grad(run)))(params, starts)
    for i in range(len(starts)):
        p = float(params[i, 0])
        x, dq, dp, _ = _closed_form(p, float(params[i, 1]))
        value = np.exp(p * x)
        np.testing.assert_allclose(jax.jit(run)(params[i], starts[i]), value, rtol=1e-13)
        np.testing.assert_allclose(batched[i], value, rtol=1e-13)
        np.testing.assert_allclose(jax.grad(run)(params[i], starts[i]), [value * (x + p * dp), value * p * dq], rtol=1e-10)
        np.testing.assert_allclose(grads[i], [value * (x + p * dp), value * p * dq], rtol=1e-10)


def test_solve_once_solves_a_badly_scaled_system_like_numpy():
    """The tangent rules' solve (equilibrated LU, no inverse) against numpy's, on a matrix whose
    rows span twelve decades (a stiff rod beside a light platform), for one and several
    right-hand sides, and under vmap."""
    rng = np.random.default_rng(3)
    n = 30
    J = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-6, 6, size=(n, 1))
    B = rng.normal(size=(n, 4))
    want = np.linalg.solve(J, B)
    got = np.asarray(newton.solve_once(jnp.asarray(J), jnp.asarray(B)))
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.max(np.abs(want)))
    one = np.asarray(newton.solve_once(jnp.asarray(J), jnp.asarray(B[:, 0])))
    np.testing.assert_allclose(one, want[:, 0], rtol=1e-9, atol=1e-12 * np.max(np.abs(want)))
    mapped = np.asarray(jax.vmap(lambda b: newton.solve_once(jnp.asarray(J), b), in_axes=1, out_axes=1)(jnp.asarray(B)))
    np.testing.assert_allclose(mapped, want, rtol=1e-9, atol=1e-12 * np.max(np.abs(want)))


def test_tolerance_and_cap_are_numbers_and_each_member_keeps_its_own():
    """Newton's ``tol`` and ``max_iter`` are arrays, not compiled structure: one trace serves every
    tolerance and cap, each solve stops at its own, and so does each member under vmap (the
    batched rule's members carry their own settings)."""
    traces = []

    def solve(settings, q):
        traces.append(None)
        fn = lambda x: x**3 + 2.0 * x - q  # noqa: E731
        _, _, stats = newton.solve(fn, jax.jacfwd(fn), newton.Jacobian.empty(1), settings, newton.plain(jnp.full(1, 4.0)))
        return stats.residual, stats.iterations, stats.result

    loose, tight, capped = (newton.NewtonSettings(tol=t, max_iter=m) for t, m in ((1e-3, 40), (1e-13, 40), (1e-13, 2)))
    f = jax.jit(solve)
    (rl, il, cl), (rt, it, ct), (rc, ic, cc) = (f(s, jnp.asarray(3.0)) for s in (loose, tight, capped))
    assert len(traces) == 1
    assert cl == ct == results.SUCCESSFUL and 1e-13 < rl <= 1e-3 and rt <= 1e-13 and il < it
    assert ic == 2 and cc == results.MAX_ITERATIONS and rc > 1e-13
    stacked = jax.tree.map(lambda *a: jnp.stack(a), loose, tight, capped)
    rb, ib, cb = jax.jit(jax.vmap(solve))(stacked, jnp.full(3, 3.0))
    assert np.array_equal(ib, [il, it, ic]) and np.array_equal(cb, [cl, ct, cc])
    assert np.allclose(rb, [rl, rt, rc], rtol=1e-12, atol=0)
