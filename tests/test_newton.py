"""`newton.solve`'s implicit derivatives against closed forms.

The root of x^3 + p x - q = 0 (one real root for p > 0) has dx/dq = 1 / (3x^2 + p),
dx/dp = -x / (3x^2 + p), and d2x/dq2 = -6x (dx/dq)^3; forward, reverse and second-order
derivatives through the solve must give these, whether or not the fallback stages ran.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pcrjax.numerics import newton

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
