"""`identify.discretisation`'s refits on a model whose finer grids are linear least-squares
problems with closed-form optima: the refit with the coarse Jacobian held must reach each grid's
own optimum (through the windows), and a grid that fits far worse than the fit must be reported
as a failed refit, its values unused."""

from __future__ import annotations

import types

import numpy as np

from identify import discretisation

RNG = np.random.default_rng(4)
FRAMES, UNKNOWNS = 40, 3
A0 = RNG.standard_normal((3 * FRAMES, UNKNOWNS))
SIGMA = 1e-2  # the noise: residuals are whitened by it, as `Problem`'s are
B = A0 @ np.array([1.0, -2.0, 0.5]) + SIGMA * RNG.standard_normal(3 * FRAMES)
T = np.linspace(0.0, 1.0, FRAMES)


class Linear:
    """Whitened residuals ``((A0 + h E) theta - b - offset(h)) / SIGMA`` over the frames up to
    ``t_end``: a grid of spacing ``h`` moves the model by ``h E`` (|E| ~ 0.1 |A0|); ``offset``
    is a misfit no parameter can absorb."""

    def __init__(self, h: float, offset=lambda h: 0.0):
        self.h, self.offset = h, offset
        self.A = A0 + 0.1 * h * np.sin(np.arange(A0.size).reshape(A0.shape))
        self.scene = types.SimpleNamespace(
            solver=types.SimpleNamespace(nodes=round(1 / h), dt=h, newton=types.SimpleNamespace(tol=1e-10))
        )
        self.max_step = np.inf

    def window(self, t_end=None):
        return (T <= (np.inf if t_end is None else t_end)).astype(float), None

    def counted(self, t_end=None):
        return 3 * int(np.sum(self.window(t_end)[0]))

    def residual(self, theta, t_end=None):
        rows = np.repeat(self.window(t_end)[0] > 0, 3)
        return np.where(rows, self.A @ np.asarray(theta) - B - self.offset(self.h), 0.0) / SIGMA

    def refined(self, nodes, dt, tol):
        return Linear(dt, self.offset)

    def optimum(self):
        return np.linalg.lstsq(self.A, B + self.offset(self.h), rcond=None)[0]


def test_refits_reach_each_finer_grids_own_optimum():
    coarse = Linear(0.1)
    theta = coarse.optimum()
    r = coarse.residual(theta)
    chi2 = float(r @ r) / (r.size - UNKNOWNS)
    se = np.sqrt(np.diag(np.linalg.inv(A0.T @ A0)) * chi2) * SIGMA
    levels, failed = discretisation.refine(
        coarse, theta, coarse.A / SIGMA, se, max_levels=2, chi2=chi2, window_ends=(0.3, 0.6, None)
    )
    assert not failed
    assert [lv.what for lv in levels] == ["tolerance", "grid", "grid"]
    for lv in levels[1:]:
        # the refit stops when a step gains less than a parameter 0.05 SE off would add;
        # measured: within 0.012 SE, the moves 0.67 and 0.36 SE (both refinements needed)
        assert np.all(np.abs(lv.theta - Linear(lv.dt).optimum()) < 0.05 * se)


def test_a_refit_that_fits_far_worse_is_reported_and_not_used():
    """The finest grid's model is off by a constant no parameter absorbs (a refit stuck in a
    wrong minimum looks the same to the caller): it is reported, and the levels stop before it."""
    offset = lambda h: 0.0 if h > 0.03 else 0.5  # noqa: E731  (the second grid refinement, dt 0.025)
    coarse = Linear(0.1, offset)
    theta = coarse.optimum()
    r = coarse.residual(theta)
    chi2 = float(r @ r) / (r.size - UNKNOWNS)
    se = np.sqrt(np.diag(np.linalg.inv(A0.T @ A0)) * chi2) * SIGMA
    levels, failed = discretisation.refine(coarse, theta, coarse.A / SIGMA, se, max_levels=2, chi2=chi2)
    assert [lv.what for lv in levels] == ["tolerance", "grid"]
    assert len(failed) == 1 and "did not find that grid's optimum" in failed[0]
