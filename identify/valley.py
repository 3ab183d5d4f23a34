"""Whether the loss is the quadratic bowl its standard errors assume, along its weakest direction.

The standard errors come from the Gauss-Newton curvature ``J^T J`` at the optimum: the loss is
read as rising by 1/2 (in reduced chi-square) one standard error away in any direction. Along
the least determined combination of the unknowns (the smallest eigenvalue of the scaled
``J^T J``) the residuals' own curvature, which Gauss-Newton drops, can dominate. Where the
first-order effect of that combination on the motion nearly vanishes at the optimum (a pinch
of the valley: on noise draws of ``triskele_push_release_r1`` the lengths' combination
+1, -1, -0.8), the loss rises tens to thousands of times faster than that, and the reported
errors of the values in it are several times their spread over noise draws; where the valley
flattens, the loss rises slower and the errors understate. Two residuals, one standard error
either side along that direction, measure the rise; the profiles (`profile`) then give the
intervals.
"""

from __future__ import annotations

import math

import numpy as np

from . import threads

# A rise this many times the quadratic one (or this many times smaller) one standard error from
# the optimum: the width the loss gives that direction is at most half (or at least twice) its
# standard error.
FACTOR = 4.0
# A smallest eigenvalue of the scaled J^T J below this fraction of the largest: no curvature at all
# (the standard errors are unbounded), no direction to step along.
SINGULAR = 1e-14
# Unknowns named in a report: those at least this fraction of the direction's largest component
# (in standard errors).
SHARE = 0.5


def weakest_direction(J, chi2: float) -> tuple[np.ndarray, bool]:
    """(the step one standard error along the least determined combination of the unknowns:
    ``v`` with ``v^T J^T J v = chi2`` along the eigenvector of the smallest eigenvalue of
    ``J^T J`` with its columns scaled to unit norm, its largest component positive; whether the
    recording determines it: where that eigenvalue is numerically zero ``v`` is the eigenvector
    itself, as there is no standard error to step)."""
    A = J.T @ J
    d = 1.0 / np.sqrt(np.maximum(np.diag(A), 1e-300))
    lam, vecs = np.linalg.eigh(d[:, None] * A * d[None, :])
    u = d * vecs[:, 0]
    u = u if u[np.argmax(np.abs(u))] > 0 else -u
    if not lam[0] > SINGULAR * lam[-1]:
        return u, False
    return u * math.sqrt(chi2 / float(u @ A @ u)), True


def rise_ratio(rf, theta, r, v, chi2: float) -> float:
    """The loss's rise one step ``v`` either side of the optimum ``theta`` (residuals ``r``),
    the mean of both sides (which cancels the slope), over the quadratic rise ``chi2 / 2`` the
    Gauss-Newton curvature gives it; NaN where a residual is not finite."""
    cost0 = 0.5 * float(r @ r)
    costs = []
    # the two sides side by side, one per core
    for rs in threads.map_in_threads(lambda x: np.asarray(rf(x)), [theta + v, theta - v], first_alone=False):
        if not np.all(np.isfinite(rs)):
            return math.nan
        costs.append(0.5 * float(rs @ rs))
    return (0.5 * (costs[0] + costs[1]) - cost0) / (0.5 * chi2)


def check(rf, theta, J, r, chi2: float, labels, se) -> dict:
    """The weakest direction's ``direction`` (label -> component in standard errors ``se``, for
    the unknowns at least `SHARE` of its largest; relative to the largest where the recording
    does not determine it), its ``rise`` (`rise_ratio`; None where not measured) and a ``note``
    ('' where the rise is within a factor `FACTOR` of the quadratic one)."""
    theta = np.asarray(theta, float)
    v, determined = weakest_direction(np.asarray(J), chi2)
    rise = rise_ratio(rf, theta, np.asarray(r), v, chi2) if determined else math.nan
    comp = v / np.where(np.asarray(se) > 0, se, np.inf)
    if not determined:  # no standard error to measure it in: its shape only
        comp = comp / np.max(np.abs(comp))
    big = np.abs(comp) >= SHARE * np.max(np.abs(comp))
    direction = {lab: round(float(c), 3) for lab, c, b in zip(labels, comp, big, strict=True) if b}
    named = ", ".join(f"{c:+.2g} {lab}" for lab, c in direction.items())
    note = ""
    if not determined:
        note = f"the recording does not determine the combination ({named}) of the unknowns: its standard errors are unbounded"
    elif not math.isfinite(rise):
        note = f"the loss one standard error along the least determined combination ({named}) could not be simulated"
    elif not 1.0 / FACTOR <= rise <= FACTOR:
        steep = rise > FACTOR
        note = (
            f"one standard error along the least determined combination ({named}), the loss rises {'' if steep else 'only '}"
            f"{rise:.3g} times as much as the standard errors assume: those values' standard errors "
            f"{'overstate' if steep else 'understate'} their uncertainty (--profile measures it)"
        )
    return dict(direction=direction, rise=None if not math.isfinite(rise) else float(rise), note=note)
