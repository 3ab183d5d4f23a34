"""Least-squares minimisers of ``0.5 |r(theta)|^2``: Levenberg-Marquardt (the fit's) and optax
Adam (for comparison), and the Gauss-Newton covariance at an optimum."""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np


class FitError(RuntimeError):
    """The fit cannot go on (a simulation that does not converge at the values it must start from)."""


def covariance(J):
    """(J^T J)^{-1}, the Gauss-Newton covariance of unit-variance residuals, inverted with the
    columns scaled to unit norm (unknowns of very different sizes)."""
    return _inverse(J.T @ J)


def _inverse(A):
    """The pseudo-inverse of a Gauss-Newton Hessian ``A``, its columns scaled to unit norm."""
    d = 1.0 / np.sqrt(np.maximum(np.diag(A), 1e-300))
    return d[:, None] * np.linalg.pinv(d[:, None] * A * d[None, :], rcond=1e-14) * d[None, :]


def levenberg_marquardt(
    rf: Callable,
    rj: Callable,
    theta0,
    max_iter=30,
    xtol=1e-8,
    ftol=1e-10,
    max_step=0.5,
    start: dict | None = None,
    save=None,
    progress=None,
    initial=None,
    lam0: float = 1e-3,
    huber: float = math.inf,
    secant_jacobian: bool = False,
    exact_test: bool = True,
    initial_exact: bool = True,
    geodesic: bool = False,
    secant_test: bool = False,
    speculate: bool = False,
):
    """Minimise ``0.5 |rf(theta)|^2``, with ``rj(theta) = (residual, Jacobian)``.

    The model of the cost's Hessian is the Gauss-Newton ``J^T J`` plus a structured secant
    estimate ``S`` of the residuals' own curvature ``sum_i r_i Hess(r_i)`` (`_secant_update`,
    NL2SOL's). Gauss-Newton alone drops that term, which is right when the residuals vanish at
    the optimum; a fit's residuals are the noise, and where the unknowns are nearly collinear
    (the smallest eigenvalues of the scaled ``J^T J`` 1e-4) the term is as large as the Gauss-Newton
    curvature along them: Gauss-Newton steps along that valley then overshoot, the damping stays
    high, and the iterations crawl with gains that look like convergence. On a Triskele
    push-release, from where a Gauss-Newton fit had stopped, 25 more Gauss-Newton iterations
    gained 0.02 and moved the unknowns 0.15 standard errors; with this model the fit reaches that
    point in half the iterations, and the loss gains no more than 1e-3 by its linearisation.

    Residuals transformed by a Huber loss of threshold ``huber`` (`robust.huber`: ``0.5 r^2`` is
    the loss, ``|r| > huber`` beyond the threshold) keep the loss's own curvature: a row beyond
    the threshold, where the loss grows linearly, adds to the gradient but not to the model's
    Hessian (its Gauss-Newton term ``(h' J_z)^T (h' J_z)`` is cancelled by the transform's own
    curvature ``r h''``), and the secant estimates the curvature of the whitened residuals
    alone. With the Gauss-Newton term kept, each such row makes the steps too short: on a
    Triskele actuator step simulated on a finer grid (8 of 684 rows beyond), the fit crawled
    7 iterations to its optimum; with the loss's curvature, 2.

    Converged: when the Gauss-Newton decrement ``0.5 g^T (J^T J)^+ g`` (the cost the linearised
    problem could still gain; ``0.5 (delta / SE)^2`` for a parameter ``delta`` off a quadratic
    optimum) falls below ``ftol`` times the cost, when a step moves theta by less than
    ``xtol``, or when no damped step lowers the cost (the optimum to the precision of the model's
    solves; or none is left that moves theta by ``xtol``, which is not tried). Each damped step
    tried differs from the last rejected one by a tenth of its size at least (`_same_step`); the
    damping falls tenfold after a step whose first trial passed, and stays after one that passed
    only with more. A small gain of one step alone is no sign of convergence (a crawl has those).

    Steps are bounded to ``max_step`` (a number, or one per unknown: they are O(1), logs and
    typical units), a trust region that keeps the first steps from a poor guess out of far minima. ``start`` (a
    state that ``save`` was given) resumes an interrupted run; ``save(state)`` is called after
    every accepted step; ``initial``, ``rj(theta0)`` if already known. Returns (theta, J, r,
    iterations, converged, history). ``lam0``: the first damping (small: the first step Gauss-Newton's).

    ``secant_jacobian``: for a Jacobian that costs many residuals (a rollout's tangents), an
    accepted step updates ``J`` by Broyden's rank-one secant from the trial's residuals instead
    of calling ``rj``. The exact Jacobian is taken where the secant one is not to be trusted:
    when a trial step fails (then the same damping is tried again), before convergence is
    declared (the test is made again with it) and at the end, so the returned ``J`` is always
    ``rj``'s. The secant estimate ``S`` is updated between exact Jacobians only. Without
    ``exact_test``, a secant Jacobian's convergence test stands and the ``J`` returned may be the
    secant one (a pass whose answer only starts another); ``initial_exact`` False: ``initial``'s
    Jacobian is such a one.

    ``geodesic``: each trial step on an exact Jacobian is corrected by geodesic acceleration
    (`_accelerated`, Transtrum and Sethna's), for one more residual per trial. Where the valley
    of the loss is curved, Gauss-Newton steps leave its floor and the iterations crawl along it,
    and a secant Jacobian's steps fail there again and again: with ``secant_jacobian`` too, the
    secant is used until a step on it fails, and every accepted step takes the exact Jacobian
    after that. The noise-weighted passes of the Triskele push-releases, replayed from their
    starts (exact Jacobians + residuals): on `triskele_push_release_r1`, 5 + 10 with both, 4 + 7
    with geodesic steps on exact Jacobians throughout, 6 + 6 with plain steps on exact
    Jacobians, 7 + 15 with the secant alone; on `triskele_push_release_r2`, 2 + 6 with both,
    4 + 7 with geodesic steps on exact Jacobians throughout, 3 + 7 with the secant alone. Both
    together cost the fewest Jacobians over the two.

    ``secant_test`` (for a pass whose answer only starts another, without ``exact_test``): after
    a step accepted on an exact Jacobian, the convergence test is made first on that Jacobian's
    Broyden update, and the exact one is taken only where that test fails. A window of a
    Triskele push-release mostly stops after one step, and its exact Jacobian there (the next
    window takes its own at the same point) cost as much as the step.

    ``speculate``: ``rj`` at each trial point starts in another thread beside ``rf`` there, where
    an accepted step would take the exact Jacobian; accepted, the step has its Jacobian a residual
    sooner. ``rj`` and ``rf`` then run side by side (programs free of batched LAPACK calls,
    `identify.threads`), and no trial starts another while a rejected one's still runs."""
    theta = np.asarray(theta0, float)
    lam, history, it0, S = lam0, [], 0, np.zeros((theta.size, theta.size))
    if start is not None:
        theta, lam, history, it0 = np.asarray(start["theta"], float), start["lam"], list(start["history"]), start["iteration"]
        S = np.asarray(start.get("secant", S), float)
    r, J = (np.asarray(a) for a in (rj(jnp.asarray(theta)) if initial is None or start is not None else initial))
    cost = 0.5 * float(r @ r)
    if not (np.isfinite(cost) and np.all(np.isfinite(J))):
        raise FitError(
            "the residual or its Jacobian at the start is not finite (a simulation whose Newton solves did not converge)"
        )
    if not history:
        history.append(cost)
    exact = initial_exact or initial is None or start is not None
    anchor = (theta, r, J) if exact else None  # the last point where J was rj's

    def take_exact(known=None):
        """rj at theta (``known``: already taken there), and the secant estimate updated over the
        steps since the last exact Jacobian."""
        nonlocal r, J, S, exact, anchor, cost
        r_new, J_new = known if known is not None else _evaluated(rj, theta)
        if not (np.all(np.isfinite(r_new)) and np.all(np.isfinite(J_new))):
            raise FitError("the Jacobian at an accepted step is not finite (its tangent solves did not converge)")
        if anchor is not None and np.any(theta != anchor[0]):
            th0, r0, J0 = anchor
            S = _secant_update(S, theta - th0, J_new.T @ r_new - J0.T @ r0, (J_new - _rescaled(J0, r0, r_new, huber)).T @ r_new)
        r, J, exact, anchor = r_new, J_new, True, (theta, r_new, J_new)
        cost = 0.5 * float(r @ r)

    def hessian_model():
        A = _gauss_newton(J, r, huber)
        return J.T @ r, A + S, np.diag(np.diag(A) + 1e-12 * np.max(np.diag(A)))

    small = False  # the last step moved theta by less than xtol
    # an accepted step updates J by the secant (a resumed pass as where it stopped)
    secant = secant_jacobian and (start is None or start.get("secant_steps", True))

    def passes():
        """The convergence test at theta: the decrement within ftol of the cost, or a step below xtol."""
        return decrement(J, r, huber) < ftol * cost or small

    converged = passes()
    pool = ThreadPoolExecutor(max_workers=1) if speculate else None
    ahead = None  # (trial point, the future of rj there) started beside a trial's residual
    it = it0
    for it in range(it0 + 1, max_iter + 1):
        if converged and not exact and exact_test:  # a secant Jacobian's test is made again with the exact one
            take_exact()
            converged = passes()
        if converged:
            it -= 1
            break
        g, model, scale = hessian_model()
        accepted, rejected = False, None
        for _ in range(12):
            step = _damped_step(model, scale, g, lam)
            # raise the damping until the step fits the region (and the model is definite)
            while (step is None or np.any(np.abs(step) > max_step)) and lam < 1e30:
                lam *= 4.0
                step = _damped_step(model, scale, g, lam)
            # and until it differs from the step last rejected, which it would repeat
            while step is not None and _same_step(step, rejected) and lam < 1e30:
                lam *= 2.0
                step = _damped_step(model, scale, g, lam)
            if step is not None and exact and _negligible(step, theta, xtol):
                break  # damped below xtol: no step left to try (the `small` test)
            damped = step
            if step is not None and geodesic and exact:
                step = _accelerated(rf, theta, r, J, step, model + lam * scale, scale, max_step)
            if step is not None:
                if pool is not None and not secant and (ahead is None or ahead[1].done()):
                    ahead = (theta + step, pool.submit(_evaluated, rj, theta + step))
                r_t = np.asarray(rf(jnp.asarray(theta + step)))
                cost_t = 0.5 * float(r_t @ r_t) if np.all(np.isfinite(r_t)) else math.inf
                if cost_t < cost:
                    accepted = True
                    break
            if not exact:  # the secant Jacobian may be what failed: the exact one, same damping
                take_exact()
                rejected = None
                if geodesic:  # exact Jacobians from here
                    secant = False
                g, model, scale = hessian_model()
                continue
            if step is None:  # no damping makes the model definite (a non-finite Jacobian): no step to try
                break
            rejected = damped
            lam *= 10.0
        if not accepted:
            converged = True  # no decrease along any damped step: a minimum to the precision of the model
            it -= 1
            break
        theta = theta + step
        if rejected is None:  # the first damping passed: less of it next time
            lam = max(lam / 10.0, 1e-12)
        # else the damping that passed is kept: lowered again, it fails again and costs a rollout
        # each iteration (a held Jacobian's crawl through a window alternated the two)
        if secant:
            J = _broyden(J, step, r_t - r)
            r, cost, exact = r_t, cost_t, False
        else:
            updated = _broyden(J, step, r_t - r) if secant_test else None
            if updated is not None and decrement(updated, r_t, huber) < ftol * cost_t:
                J, r, cost, exact = updated, r_t, cost_t, False
            else:
                take_exact(ahead[1].result() if ahead is not None and np.array_equal(ahead[0], theta) else None)
        history.append(cost)
        if save is not None:
            save(dict(theta=theta.tolist(), lam=lam, history=history, iteration=it, secant=S.tolist(), secant_steps=secant))
        if progress is not None:
            progress(it, cost, float(np.max(np.abs(step))))
        small = _negligible(step, theta, xtol)
        converged = passes()
    if not exact and exact_test:  # out of iterations on a secant Jacobian: the exact one, and its test
        take_exact()
        converged = passes()
    if pool is not None:
        pool.shutdown(wait=False)
    return theta, J, r, it, converged, history


def _evaluated(rj, theta):
    """``rj(theta)`` as numpy arrays (the program run to its end)."""
    return tuple(np.asarray(a) for a in rj(jnp.asarray(theta)))


# Geodesic acceleration (Transtrum and Sethna 2012): the residuals' second derivative along the
# step by a finite difference of this fraction of it, and the largest ratio of the acceleration
# to the velocity (in the damping's metric) at which the corrected step is taken.
GEODESIC_H = 0.1
GEODESIC_RATIO = 0.75


def _accelerated(rf, theta, r, J, v, damped, scale, max_step):
    """The step ``v + a / 2`` that follows the curvature of the residuals along the damped step
    ``v`` (geodesic acceleration): ``a = -damped^{-1} J^T r_vv``, with ``r_vv``, the residuals'
    second directional derivative along ``v``, from one more residual at ``theta + h v``. A
    Gauss-Newton step is the tangent of the model's path through parameter space; along a
    curved valley of the loss (nearly collinear unknowns bent by the model's nonlinearity)
    it leaves the valley floor, the damping then cuts it short, and the steps crawl. ``v``
    alone where the acceleration is not small beside it (the expansion does not hold), leaves
    the trust region ``max_step``, or the extra residual is not finite."""
    r_h = np.asarray(rf(jnp.asarray(theta + GEODESIC_H * v)))
    if not np.all(np.isfinite(r_h)):
        return v
    r_vv = (2.0 / GEODESIC_H) * ((r_h - r) / GEODESIC_H - J @ v)
    try:
        a = -np.linalg.solve(damped, J.T @ r_vv)
    except np.linalg.LinAlgError:
        return v
    step = v + 0.5 * a
    small = 2.0 * np.sqrt(max(float(a @ scale @ a), 0.0)) <= GEODESIC_RATIO * np.sqrt(float(v @ scale @ v))
    return step if small and np.all(np.abs(step) <= max_step) and np.all(np.isfinite(step)) else v


def _broyden(J, step, change):
    """Broyden's rank-one update of the Jacobian ``J`` after a ``step`` that changed the residuals
    by ``change``: ``J + (change - J step) step^T / step^T step``."""
    return J + np.outer(change - J @ step, step) / float(step @ step)


def decrement(J, r, huber: float = math.inf) -> float:
    """``0.5 g^T A^+ g``, g = J^T r: what the Gauss-Newton step would gain on the linearised
    problem (the columns scaled to unit norm for the pseudo-inverse); ``A`` the Gauss-Newton
    Hessian of the rows within the Huber threshold ``huber`` (`_gauss_newton`)."""
    g = J.T @ r
    return 0.5 * float(g @ _inverse(_gauss_newton(J, r, huber)) @ g)


def _gauss_newton(J, r, huber: float):
    """``J^T J`` over the rows whose Huber-transformed residual ``r`` lies within the threshold
    ``huber``: the loss is linear in the whitened residual beyond it, which adds no curvature."""
    inner = np.abs(r) <= huber
    return J.T @ J if inner.all() else J[inner].T @ J[inner]


def _rescaled(J_old, r_old, r_new, huber: float):
    """``J_old`` with each row's Huber slope ``h'`` (1 within the threshold, ``huber / |r|``
    beyond) that of ``r_new``: ``J_new - _rescaled(...)`` is then the change of the whitened
    residuals' Jacobian, weighted as now (what the secant of their curvature needs)."""
    if np.all(np.abs(r_old) <= huber) and np.all(np.abs(r_new) <= huber):
        return J_old
    slope = lambda r: np.minimum(1.0, huber / np.maximum(np.abs(r), 1e-300))  # noqa: E731
    return J_old * (slope(r_new) / slope(r_old))[:, None]


def _negligible(step, theta, xtol: float) -> bool:
    """Whether ``step`` moves ``theta`` by less than ``xtol`` (relative, largest component)."""
    return bool(np.max(np.abs(step)) < xtol * (1.0 + np.max(np.abs(theta))))


def _same_step(step, rejected, within: float = 0.1) -> bool:
    """Whether ``step`` lies within ``within`` (a fraction of its size, largest component) of
    the step ``rejected`` (None: none yet). Where the unknowns are nearly collinear, damping
    below the model's smallest scaled curvature (1e-4 on a Triskele) changes a step by little, and
    such a trial costs a rollout to fail as the last one did: from a Gauss-Newton start
    (damping 1e-9) a refit tried 7 steps in a row before one passed."""
    return rejected is not None and bool(np.max(np.abs(step - rejected)) < within * np.max(np.abs(rejected)))


def _damped_step(model, scale, g, lam):
    """The step minimising the quadratic model ``g^T s + 0.5 s^T model s`` damped by ``lam *
    scale``; None where the damped model is not positive definite (the secant part can make it
    indefinite: more damping)."""
    try:
        c = np.linalg.cholesky(model + lam * scale)
    except np.linalg.LinAlgError:
        return None
    return -np.linalg.solve(c.T, np.linalg.solve(c, g))


def _secant_update(S, s, y, y_structured):
    """The Dennis-Gay-Welsch update of ``S``, the estimate of ``sum_i r_i Hess(r_i)``, after a step
    ``s`` that changed the gradient by ``y``; ``y_structured`` = (J_new - J_old)^T r_new is what
    that term did along the step. First sized down where it overestimated the curvature along
    ``s`` (NL2SOL); unchanged where the step met no positive curvature (``y^T s <= 0``)."""
    sSs = float(s @ S @ s)
    if sSs != 0.0:
        S = S * min(1.0, abs(float(s @ y_structured)) / abs(sSs))
    ys = float(y @ s)
    if not ys > 0.0:
        return S
    w = y_structured - S @ s
    return S + (np.outer(w, y) + np.outer(y, w)) / ys - float(w @ s) * np.outer(y, y) / ys**2


def adam(fun: Callable, theta0, steps=300, learning_rate=3e-2, progress=None):
    """Minimise ``0.5 |fun(theta)|^2`` with optax Adam (reverse-mode gradients); for comparison.
    Stops at a non-finite loss (a step into parameters where the simulation fails: Adam has no
    way to reject a step), the NaN last in the history."""
    import optax

    loss = jax.jit(jax.value_and_grad(lambda th: 0.5 * jnp.sum(fun(th) ** 2)))
    opt = optax.adam(learning_rate)
    theta = jnp.asarray(theta0)
    state = opt.init(theta)
    history = []
    for k in range(steps):
        val, g = loss(theta)
        history.append(float(val))
        if not np.isfinite(history[-1]):
            break
        upd, state = opt.update(g, state)
        theta = optax.apply_updates(theta, upd)
        if progress is not None:
            progress(k + 1, float(val), float(jnp.max(jnp.abs(upd))))
    return np.asarray(theta), history


def standard_errors_theta(J, chi2: float):
    """Standard errors of theta from the Gauss-Newton covariance rescaled by ``chi2``."""
    return np.sqrt(np.maximum(np.diag(covariance(J) * chi2), 0.0))
