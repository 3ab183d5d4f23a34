"""Profiles of the loss (`identify.profile`) against closed forms.

An exponential decay ``y = a exp(-b t)`` with Gaussian noise: for a held rate ``b`` the best
amplitude is linear least squares, so the profile of ``b`` is closed-form,
``cost(b) = (sum y^2 - (sum y e)^2 / sum e^2) / (2 sigma^2)``, ``e = exp(-b t)``; its 68 % interval
is where that rises by 1/2 above its minimum (found here by `scipy.optimize.brentq`). The
profile of the amplitude is checked against SciPy's bounded scalar minimiser over the rate.
"""

import math

import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar

from identify.least_squares import levenberg_marquardt, standard_errors_theta
from identify.profile import profile, widening

SIGMA = 0.05
T = np.linspace(0.0, 2.0, 40)


def _data(seed):
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0.5, 2.0), rng.uniform(0.5, 3.0)
    return a * np.exp(-b * T) + SIGMA * rng.standard_normal(T.size)


def _problem(y):
    def rf(th):
        th = np.asarray(th, float)
        return (th[0] * np.exp(-th[1] * T) - y) / SIGMA

    def rj(th):
        th = np.asarray(th, float)
        e = np.exp(-th[1] * T)
        return rf(th), np.stack([e, -th[0] * T * e], axis=1) / SIGMA

    return rf, rj


def _rate_profile(y, b):
    e = np.exp(-b * T)
    return 0.5 * (y @ y - (y @ e) ** 2 / (e @ e)) / SIGMA**2


def _amplitude_profile(y, a):
    return minimize_scalar(
        lambda b: 0.5 * np.sum(((a * np.exp(-b * T) - y) / SIGMA) ** 2),
        bounds=(0.01, 20.0),
        method="bounded",
        options=dict(xatol=1e-12),
    ).fun


def _fit(rf, rj, start=(1.0, 1.0)):
    th, J, r, *_ = levenberg_marquardt(rf, rj, np.asarray(start, float), 100, ftol=1e-14, max_step=np.inf)
    return th, J, r


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_profile_intervals_match_the_closed_form_profile(seed):
    """A 12-frame-per-second decay with truths drawn at random: both profiles' 68 % bounds lie
    within 1e-3 standard errors of the closed form's (the known noise: chi2 = 1), and they are
    asymmetric about the optimum as the exact profile is (not optimum ± SE)."""
    y = _data(seed)
    rf, rj = _problem(y)
    th, J, r = _fit(rf, rj)
    se = standard_errors_theta(J, 1.0)
    for index, exact in ((1, lambda b: _rate_profile(y, b)), (0, lambda a: _amplitude_profile(y, a))):
        pr = profile(rf, rj, th, J, r, index, se[index], 1.0, np.inf)
        low = exact(th[index])
        lo = brentq(lambda v: exact(v) - low - 0.5, th[index] - 10 * se[index], th[index])
        hi = brentq(lambda v: exact(v) - low - 0.5, th[index], th[index] + 10 * se[index])
        print(index, "profile", pr.lower, pr.upper, "exact", lo, hi, "se", se[index])
        assert pr.complete and abs(pr.drop) < 0.01  # the held fits' tolerance
        assert abs(pr.lower - lo) < 1e-3 * se[index] and abs(pr.upper - hi) < 1e-3 * se[index]
        # every point of the walk is the held minimum, to the held fits' tolerance (0.01)
        for v, c in zip(pr.theta, pr.cost, strict=True):
            assert -1e-9 < c - exact(v) < 0.01, (v, c, exact(v))
        # the statistical error a profile reports: the interval's farther end, in standard errors
        entry = dict(value=th[index], lower=pr.lower, upper=pr.upper, standard_error=se[index], points=[])
        assert abs(widening(entry) - max(1.0, max(hi - th[index], th[index] - lo) / se[index])) < 1e-3
    assert abs((hi - th[0]) - (th[0] - lo)) > 1e-3 * se[0] or abs((hi - th[1]) - (th[1] - lo)) > 1e-3 * se[1]


def test_a_profile_widens_the_standard_error_to_its_farther_end_or_the_farthest_point_walked():
    """`widening` on hand-made profiles: a symmetric interval of one standard error gives 1, an
    interval reaching 3 SE on one side gives 3, one narrower than the SE gives 1 (never less),
    and an open end counts as the farthest point walked on its side."""
    base = dict(value=2.0, standard_error=0.5, points=[[1.0, 2.0], [2.0, 0.0], [2.4, 0.1], [3.5, 0.4]])
    assert widening(dict(base, lower=1.5, upper=2.5)) == pytest.approx(1.0)
    assert widening(dict(base, lower=1.8, upper=3.5)) == pytest.approx(3.0)
    assert widening(dict(base, lower=1.9, upper=2.1)) == 1.0
    assert widening(dict(base, lower=1.5, upper=None)) == pytest.approx(3.0)  # walked to 3.5, still inside
    assert widening(dict(base, lower=None, upper=None, points=[[2.0, 0.0]])) == 1.0


def test_a_profile_from_short_of_the_minimum_finds_it():
    """Started from a point 1.5 standard errors along the rate from the optimum (the amplitude
    at its best there): the profile finds the true minimum (closed form) and the drop to it,
    and its interval is the one about the optimum."""
    y = _data(5)
    rf, rj = _problem(y)
    th, J, r = _fit(rf, rj)
    se = standard_errors_theta(J, 1.0)
    b0 = th[1] + 1.5 * se[1]
    e = np.exp(-b0 * T)
    start = np.array([(y @ e) / (e @ e), b0])
    r0, J0 = rj(start)
    pr = profile(rf, rj, start, J0, r0, 1, se[1], 1.0, np.inf)
    drop = _rate_profile(y, b0) - _rate_profile(y, th[1])
    assert drop > 1.0 and abs(pr.drop - drop) < 0.02
    assert abs(pr.lowest - th[1]) < 0.05 * se[1]
    exact = _rate_profile(y, th[1])
    lo = brentq(lambda v: _rate_profile(y, v) - exact - 0.5, th[1] - 10 * se[1], th[1])
    hi = brentq(lambda v: _rate_profile(y, v) - exact - 0.5, th[1], th[1] + 10 * se[1])
    assert abs(pr.lower - lo) < 0.01 * se[1] and abs(pr.upper - hi) < 0.01 * se[1], (pr.lower, pr.upper, lo, hi)


def test_a_fit_whose_profile_walks_into_a_lower_minimum_moves_there(monkeypatch):
    """`fit._profiled` on a tilted double well: the unknown ``a`` has minima at -0.76 and +1
    (the latter lower by 0.65 of the reduced chi-square, 2.9 standard errors away, over a
    barrier 0.07 above the first), ``b`` follows it. From the optimum at -0.76 the profile of
    ``a`` walks into the lower well, the fit moves there, and the profiles about +1 find nothing
    lower; started at +1 it stays."""
    from types import SimpleNamespace

    from identify import fit as fit_module
    from identify.result import Result

    tilt, m0 = 0.6, 100

    def rf(th):
        a, b = np.asarray(th, float)
        return np.concatenate([[a * a - 1.0, tilt * (a - 1.0), 10.0 * (b - a)], np.ones(m0)])

    def rj(th):
        a, _ = np.asarray(th, float)
        J = np.zeros((m0 + 3, 2))
        J[0, 0], J[1, 0], J[2] = 2.0 * a, tilt, [-10.0, 10.0]
        return rf(th), J

    unknowns = [SimpleNamespace(name=n, size=1, log=False, unit=1.0) for n in ("a", "b")]
    pb = SimpleNamespace(
        unknowns=unknowns,
        slices={"a": slice(0, 1), "b": slice(1, 2)},
        to_values=lambda th: {"a": th[0], "b": th[1]},
        residual=rf,
        residual_and_jacobian=rj,
        max_step=np.full(2, np.inf),
        measured=np.array([True, True]),
        counted=lambda t_end: m0 + 3,
        huber=math.inf,  # least squares
    )

    def summary(pb, theta, J, r, iterations, converged, history, stages, notes=()):
        return Result(["a", "b"], {"a": float(theta[0])}, {}, [], [], float(r @ r) / (r.size - 2), [], iterations,
                      history=list(history), stages=list(stages), message=" ".join(notes))  # fmt: skip

    monkeypatch.setattr(fit_module, "_summary", summary)
    for start, moved in ((-1.0, True), (1.0, False)):
        th, J, r = _fit(rf, rj, np.array([start, start]))
        assert np.sign(th[0]) == start  # the well it started in
        result, theta, _, _ = fit_module._profiled(pb, th, J, r, summary(pb, th, J, r, 0, True, [], []), 30, None)
        assert abs(theta[0] - 1.0) < 0.2 and abs(result.values["a"] - theta[0]) < 1e-12
        assert ("moved there" in result.message) == moved, result.message
        assert result.profiles["a"]["drop"] < 0.5
