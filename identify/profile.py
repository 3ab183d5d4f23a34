r"""Profiles of the loss: how far a measured value can move before the recording objects.

The standard errors (`result.summarize`) read the loss as the quadratic bowl its curvature at
the optimum describes. Where the unknowns are nearly collinear the bowl is a curved valley, and
the valley can hold a second minimum: on ``triskele_push_release_r1`` a set of lengths 300 µm
from the fit's fits as well (the loss 0.3 lower at 20 nodes, dt 0.25 ms), while the reported
standard error of a length is 25-80 µm.

The profile of one unknown ``theta_k`` is the loss minimised over all the others with
``theta_k`` held, on a walk outward from the optimum on both sides: each point starts where the
linearised problem puts the other unknowns (the conditional Gauss-Newton step) and is polished
by Levenberg-Marquardt. By Wilks' theorem the profile rises by ``LEVEL`` = 1/2 (in units of the
reduced chi-square) at one standard deviation, so the values where it crosses that level bound a
68 % interval that follows the valley wherever it bends; for a quadratic loss they are the
optimum ± its standard error. A walk ends where the loss has risen by ``STOP`` above the lowest
point met (two standard deviations), after ``MAX_POINTS`` points, or where a simulation fails;
its steps double while the loss barely changes (a flat valley), up to ``MAX_STRIDE`` standard
errors, and a step is halved (down to ``MIN_STRIDE``) where its held fit fails or the loss
rises by ``STOP`` over it: a held fit over the whole recording started too far along a curved
valley can stop in a minimum of its own (an oscillation's phase wrapped), and its cost is only
an upper bound of the profile. A held minimisation that does not converge at the smallest step
ends its walk, and the interval is open on that side. A profile that falls below the
fit's loss says the fit stopped short of a lower minimum; its lowest point is reported. Every
point is a set of values whose loss the held fit reached, so a point below the fit's loss is a
better fit whatever else holds; a point above can sit above the profile where the held fit
stopped in a minimum of its own (on ``triskele_push_release_r1`` neighbouring points differ by
up to 0.7 reduced chi-square along the lengths), which narrows the interval.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .least_squares import FitError, decrement, levenberg_marquardt
from .problem import NUISANCE

LEVEL = 0.5  # rise of the loss, in reduced chi-square, at one standard deviation
STOP = 2.0  # a walk ends where the loss rose this much above the lowest point met
MAX_POINTS = 6  # points per side
FLAT = 0.1  # a step that raises the loss by less than this (reduced chi-square) doubles the next
MAX_STRIDE = 4.0  # steps at most this many standard errors ...
MIN_STRIDE = 0.25  # ... and at least this many: a step whose held fit fails or rises by STOP is halved down to it


@dataclasses.dataclass
class Profile:
    """The profile of one unknown: the held values ``theta`` (sorted) and the minimised costs
    ``cost`` (``0.5 |r|^2``); the interval ``lower``..``upper`` where it lies within ``LEVEL``
    reduced chi-square of its lowest point (NaN where a walk ended before crossing it), and
    its minimum (``lowest``, the parabola through the lowest point walked and its neighbours,
    and its ``drop`` below the fit's cost: > 0 when the fit stopped short of it)."""

    index: int
    theta: np.ndarray
    cost: np.ndarray
    lower: float
    upper: float
    lowest: float
    drop: float
    complete: bool  # both walks crossed the level
    best: np.ndarray  # theta of the lowest point walked (all unknowns)


def _crossing(x, rise, m, direction) -> tuple[float, int]:
    """(where the signed root ``sqrt(2 rise)`` of the profile, linear in the held value for a
    quadratic loss, first reaches 1 walking from index ``m`` in ``direction`` (-1, +1), the
    index of the point past it); (NaN, -1) if it does not."""
    q = np.sqrt(2.0 * np.maximum(rise, 0.0))
    i = m
    while 0 <= i + direction < len(x):
        j = i + direction
        if rise[j] > LEVEL:
            return float(x[i] + (1.0 - q[i]) * (x[j] - x[i]) / (q[j] - q[i])), j
        i = j
    return math.nan, -1


def profile(
    rf, rj, theta, J, r, index: int, se: float, chi2: float, max_step, max_iter: int = 30, progress=None, huber=math.inf
) -> Profile:
    """The `Profile` of ``theta[index]`` about the optimum ``theta`` (residuals ``r``, Jacobian
    ``J``) of ``0.5 |rf(theta)|^2``, ``rj(theta) = (residual, Jacobian)``; ``se`` its standard
    error, ``chi2`` the reduced chi-square that scales the levels, ``max_step`` the fit's step
    bounds (one per unknown). Each crossing of the level is evaluated once more where the walk's
    points put it, and placed again with that point. ``progress(held value, cost)`` after each
    point. ``huber``: the threshold of the Huber loss the residuals are transformed by
    (`least_squares.levenberg_marquardt`)."""
    theta = np.asarray(theta, float)
    others = np.arange(theta.size) != index
    max_step = np.broadcast_to(np.asarray(max_step, float), theta.shape)
    cost0 = 0.5 * float(r @ r)
    tol = 0.01 * chi2 / max(cost0, 1e-300)  # held fits within 0.01 reduced chi-square of their minimum
    points = {float(theta[index]): (cost0, theta, np.asarray(J))}  # held value -> (cost, theta, J)

    def held_minimum(x, Jx, held):
        """(cost, theta, J) of the minimum over the others with theta[index] = held, from the
        point (x, Jx) moved as its linearisation says; None where a simulation fails or the
        minimisation does not converge in ``max_iter`` iterations (its cost would only bound the
        profile from above)."""
        shift = np.linalg.lstsq(Jx[:, others], -Jx[:, index] * (held - x[index]), rcond=None)[0]
        full = {}

        def join(y):
            out = np.empty_like(theta)
            out[others], out[index] = y, held
            return out

        def rj_held(y):
            res, jac = (np.asarray(a) for a in rj(join(np.asarray(y, float))))
            full["J"] = jac
            return res, jac[:, others]

        try:
            y, jac_y, r_y, _, converged, _ = levenberg_marquardt(
                lambda y: rf(join(np.asarray(y, float))),
                rj_held,
                x[others] + shift,
                max_iter,
                ftol=tol,
                max_step=max_step[others],
                huber=huber,
            )
        except FitError:
            return None
        # out of iterations, or stopped where no damped step lowered the cost (which the fitter
        # also calls converged) with the linearised problem still gaining more than tol
        if not converged or decrement(jac_y, r_y, huber) > tol * cost0:
            return None
        cost = 0.5 * float(r_y @ r_y)
        if progress is not None:
            progress(held, cost)
        return cost, join(y), full["J"]

    for direction in (-1.0, 1.0):
        x, Jx, lowest, last, stride, taken = theta, np.asarray(J), cost0, cost0, 1.0, 0
        for _ in range(3 * MAX_POINTS):
            held = float(x[index] + direction * stride * se)
            got = held_minimum(x, Jx, held)
            if (got is None or got[0] - last > STOP * chi2) and stride > MIN_STRIDE:
                stride /= 2.0  # a held fit that failed or rose steeply: again from nearer
                continue
            if got is None:
                break  # a simulation failed here, or the held fit did not converge: the walk ends
            points[held] = got
            cost, x, Jx = got
            lowest, taken = min(lowest, cost), taken + 1
            if cost - lowest > STOP * chi2 or taken == MAX_POINTS:
                break
            if abs(cost - last) < FLAT * chi2:
                stride = min(2.0 * stride, MAX_STRIDE)
            last = cost

    def table():
        """(held values, costs, the lowest point's index, rises above the profile's minimum,
        where it is and its cost: the parabola through the lowest point and its neighbours)."""
        xs = np.array(sorted(points))
        ys = np.array([points[v][0] for v in xs])
        m = int(np.argmin(ys))
        x_min, y_min = float(xs[m]), float(ys[m])
        if 0 < m < len(xs) - 1:
            (x0, x1, x2), (y0, y1, y2) = xs[m - 1 : m + 2], ys[m - 1 : m + 2]
            d1, d2 = (y1 - y0) / (x1 - x0), (y2 - y1) / (x2 - x1)
            curv = (d2 - d1) / (x2 - x0)  # half the second derivative
            vertex = float(0.5 * (x0 + x1) - d1 / (2.0 * curv)) if curv > 0 else x_min
            y_vertex = float(y1 + d1 * (vertex - x1) + curv * (vertex - x0) * (vertex - x1))
            if y_min - LEVEL * chi2 <= y_vertex <= y_min:  # a parabola that fits: else the points are no bowl
                x_min, y_min = vertex, y_vertex
        return xs, ys, m, (ys - y_min) / chi2, x_min, y_min

    xs, ys, m, rise, *_ = table()
    for direction in (-1, 1):  # one more point at each crossing the walk brackets
        guess, j = _crossing(xs, rise, m, direction)
        if math.isfinite(guess) and guess not in points and min(xs[j], xs[j - direction]) < guess < max(xs[j], xs[j - direction]):
            near = points[xs[j - direction]]
            got = held_minimum(near[1], near[2], guess)
            if got is not None:
                points[guess] = got
    xs, ys, m, rise, x_min, y_min = table()
    lower, upper = _crossing(xs, rise, m, -1)[0], _crossing(xs, rise, m, 1)[0]
    return Profile(
        index=index,
        theta=xs,
        cost=ys,
        lower=lower,
        upper=upper,
        lowest=x_min,
        drop=float(cost0 - y_min),
        complete=bool(np.isfinite(lower) and np.isfinite(upper)),
        best=points[float(xs[m])][1],
    )


def widening(entry: dict) -> float:
    """How many times its standard error the profile ``entry`` (`report`) puts the 68 % interval's
    farther end from the fit's value (at least 1): the factor by which a curved or flat valley
    widens the standard error. An open end counts as the farthest point walked on its side (a
    lower bound of the interval there)."""
    v, se = entry["value"], entry["standard_error"]
    ends = []
    for bound, side in ((entry["lower"], -1.0), (entry["upper"], 1.0)):
        if bound is None:
            walked = [x for x, _ in entry["points"] if side * (x - v) > 0]
            bound = max(walked, key=lambda x: side * (x - v)) if walked else v
        ends.append(abs(bound - v))
    return max(1.0, max(ends) / se) if se > 0 else 1.0


def report(pb, theta, J, r, chi2: float, se_theta, progress=None) -> tuple[dict, np.ndarray | None]:
    """(name -> (a dict, or a list of them for a vector) the profiles of the measured unknowns
    (`Problem.measured`) of the fit's problem ``pb`` (the final pass's noise and loss) at its optimum, in
    the values' units: ``lower``, ``upper`` (None: beyond the walk), ``lowest`` and its ``drop``
    below the fit's loss, the fit's ``value`` and the ``points`` walked ([value, rise of the loss above the fit's]);
    losses in units of the reduced chi-square ``chi2`` (``0.5 |r|^2 / chi2``); theta of the
    lowest point any walk met where that lies more than ``LEVEL`` below the fit's loss, else None)."""
    theta = np.asarray(theta, float)
    cost0 = 0.5 * float(r @ r)
    out, deepest = {}, (cost0 - LEVEL * chi2, None)
    for u in pb.unknowns:
        if u.name in NUISANCE:
            continue
        entries = []
        for k in range(u.size):
            index = pb.slices[u.name].start + k

            def value(x, index=index, k=k, u=u):
                th = theta.copy()
                th[index] = x
                return float(np.atleast_1d(np.asarray(pb.to_values(th)[u.name], float))[k])

            label = u.name if u.size == 1 else f"{u.name}[{k}]"
            say = (
                None
                if progress is None
                else (lambda x, c, label=label, value=value: progress(label, value(x), (c - cost0) / chi2))
            )
            pr = profile(
                lambda th: np.asarray(pb.residual(th)),
                pb.residual_and_jacobian,
                theta,
                J,
                r,
                index,
                se_theta[index],
                chi2,
                pb.max_step,
                progress=say,
                huber=pb.huber,
            )
            entries.append(
                dict(
                    value=value(theta[index]),
                    lower=None if math.isnan(pr.lower) else value(pr.lower),
                    upper=None if math.isnan(pr.upper) else value(pr.upper),
                    lowest=value(pr.lowest),
                    drop=pr.drop / chi2,
                    # the fit's grid's Gauss-Newton standard error that scaled the walk (with that
                    # grid's noise levels, not the finest model's that the result reports)
                    standard_error=se_theta[index] * (value(theta[index]) if u.log else u.unit),
                    points=[[value(x), (float(c) - cost0) / chi2] for x, c in zip(pr.theta, pr.cost, strict=True)],
                )
            )
            walked = float(np.min(pr.cost))
            if walked < deepest[0]:
                deepest = (walked, pr.best)
        out[u.name] = entries if u.size > 1 else entries[0]
    return out, deepest[1]
