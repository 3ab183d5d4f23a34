"""The Huber loss as a transform of residuals, against its definition and finite differences."""

import jax.numpy as jnp
import numpy as np

from identify import robust
from identify.least_squares import decrement, levenberg_marquardt


def test_huber_transform_gives_the_huber_loss_and_its_slope():
    z = np.linspace(-10.0, 10.0, 2001)
    k = 3.0
    rho = np.where(np.abs(z) <= k, 0.5 * z**2, k * np.abs(z) - 0.5 * k**2)
    r = np.asarray(robust.huber(jnp.asarray(z), k))
    assert np.allclose(0.5 * r**2, rho, rtol=1e-14, atol=1e-14)
    h = 1e-6
    fd = (np.asarray(robust.huber(jnp.asarray(z + h), k)) - np.asarray(robust.huber(jnp.asarray(z - h), k))) / (2 * h)
    away = np.abs(np.abs(z) - k) > 2 * h  # the slope is continuous; its derivative is not, at |z| = k
    assert np.allclose(np.asarray(robust.huber_slope(jnp.asarray(z), k))[away], fd[away], rtol=1e-7)
    assert np.allclose(np.asarray(robust.unhuber(jnp.asarray(r), k)), z, rtol=1e-13)
    # no threshold: least squares
    assert np.array_equal(np.asarray(robust.huber(jnp.asarray(z), robust.NONE)), z)


def test_levenberg_marquardt_under_a_huber_loss_takes_newton_steps_of_that_loss():
    """A linear model with 10 % of its rows 20 noise levels off. Once it is known which rows lie
    beyond the threshold, the Huber loss is quadratic with those rows contributing a constant
    slope: its minimum solves ``A_in^T (A_in x - b_in) + k sum_out sign(z_i) a_i = 0``. From
    near it, one Levenberg-Marquardt step that knows the threshold lands there (the transform's
    Gauss-Newton curvature would make the step short: more iterations), and its decrement is the
    loss's own Newton decrement."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((200, 4))
    b = A @ np.array([1.0, -2.0, 0.5, 3.0]) + rng.standard_normal(200)
    b[:20] += 20.0 * rng.choice([-1.0, 1.0], 20)
    k = robust.HUBER

    def rj(x):
        z = A @ x - b
        return np.asarray(robust.huber(z, k)), np.asarray(robust.huber_slope(z, k))[:, None] * A

    x = np.linalg.lstsq(A, b, rcond=None)[0]
    for _ in range(20):  # the minimum for the rows beyond the threshold there, until they settle
        z = A @ x - b
        out = np.abs(z) > k
        x_new = np.linalg.solve(A[~out].T @ A[~out], A[~out].T @ b[~out] - k * A[out].T @ np.sign(z[out]))
        if np.array_equal(np.abs(A @ x_new - b) > k, out):
            break
        x = x_new
    else:
        raise AssertionError("the rows beyond the threshold did not settle: no closed-form minimum to compare with")
    best = x_new
    start = best + 0.01
    r, J = rj(start)
    g = J.T @ r
    newton = np.linalg.solve(A[~out].T @ A[~out], g)  # Newton's step of the loss, reversed
    assert np.isclose(decrement(J, r, k), 0.5 * g @ newton, rtol=1e-10)
    fitted, _, _, it, converged, _ = levenberg_marquardt(
        lambda x: rj(x)[0], rj, start, 10, ftol=1e-14, max_step=np.inf, huber=k, lam0=1e-12
    )
    assert converged and it == 1
    assert np.allclose(fitted, best, rtol=0, atol=1e-10)
    *_, it_gauss_newton, _, _ = levenberg_marquardt(lambda x: rj(x)[0], rj, start, 10, ftol=1e-14, max_step=np.inf, lam0=1e-12)
    assert it_gauss_newton > 1


def test_spikes_are_single_wild_frames_not_a_smooth_model_error():
    rng = np.random.default_rng(0)
    t = np.arange(2000) * 1e-3
    res = rng.standard_normal((2000, 3)) * 2e-6
    res[:, 0] += 3e-4 * np.exp(-t / 0.02) * np.sin(2 * np.pi * 9 * t)  # a model error 150 noise levels large
    wild = rng.random(2000) < 0.01
    res[wild, 1] += 2e-4  # 1 % of frames 100 noise levels off
    keep = np.ones(2000, bool)
    assert set(robust.spikes(res, keep)) == set(np.flatnonzero(wild))
    keep[np.flatnonzero(wild)[:3]] = False  # frames not counted are not reported
    assert set(robust.spikes(res, keep)) == set(np.flatnonzero(wild)[3:])
