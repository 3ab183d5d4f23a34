"""Profiles of the loss (`identify.profile`) against closed forms.

An exponential decay ``y = a exp(-b t)`` with Gaussian noise: for a held rate ``b`` the best
amplitude is linear least squares, so the profile of ``b`` is closed-form,
``cost(b) = (sum y^2 - (sum y e)^2 / sum e^2) / (2 sigma^2)``, ``e = exp(-b t)``; its 68 % interval
is where that rises by 1/2 above its minimum (found here by `scipy.optimize.brentq`). The
profile of the amplitude is checked against SciPy's bounded scalar minimiser over the rate.
"""

import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar

from identify.least_squares import levenberg_marquardt, standard_errors_theta
from identify.profile import profile

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


def _fit(rf, rj):
    th, J, r, *_ = levenberg_marquardt(rf, rj, np.array([1.0, 1.0]), 100, ftol=1e-14, max_step=np.inf)
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
    assert abs((hi - th[0]) - (th[0] - lo)) > 1e-3 * se[0] or abs((hi - th[1]) - (th[1] - lo)) > 1e-3 * se[1]


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
