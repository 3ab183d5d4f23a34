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
P_S, P_T = 0.5 * RNG.standard_normal((2, UNKNOWNS, UNKNOWNS))  # how nodes and dt move the optimum


class Linear:
    """Whitened residuals ``((A0 (I + P_S / nodes + P_T dt) + E / nodes) theta - b - offset(dt))
    / SIGMA`` over the frames up to ``t_end``: the grid moves the optimum (``P_S``, ``P_T``, by
    tens of standard errors on the fit's grid of 10 nodes and dt 0.1) and a little of the fit
    (``E``); ``offset`` is a misfit no parameter can absorb."""

    def __init__(self, nodes: int, dt: float, offset=lambda dt: 0.0):
        self.nodes, self.dt, self.offset = nodes, dt, offset
        k = np.arange(A0.size).reshape(A0.shape)
        self.A = A0 @ (np.eye(UNKNOWNS) + P_S / nodes + P_T * dt) + 0.02 * np.sin(k) / nodes
        self.scene = types.SimpleNamespace(
            solver=types.SimpleNamespace(nodes=nodes, dt=dt, newton=types.SimpleNamespace(tol=1e-10))
        )
        self.max_step = np.inf
        self.measured = np.ones(UNKNOWNS, bool)

    def window(self, t_end=None):
        return (T <= (np.inf if t_end is None else t_end)).astype(float), None

    def counted(self, t_end=None):
        return 3 * int(np.sum(self.window(t_end)[0]))

    def residual(self, theta, t_end=None):
        rows = np.repeat(self.window(t_end)[0] > 0, 3)
        return np.where(rows, self.A @ np.asarray(theta) - B - self.offset(self.dt), 0.0) / SIGMA

    def refined(self, nodes, dt, tol):
        return Linear(nodes, dt, self.offset)

    def optimum(self):
        return np.linalg.lstsq(self.A, B + self.offset(self.dt), rcond=None)[0]


def _start(coarse):
    """(theta, reduced chi-square, standard errors) of the fit on ``coarse``."""
    theta = coarse.optimum()
    r = coarse.residual(theta)
    chi2 = float(r @ r) / (r.size - UNKNOWNS)
    return theta, chi2, np.sqrt(np.diag(np.linalg.inv(coarse.A.T @ coarse.A)) * chi2) * SIGMA


def test_refits_reach_each_finer_models_own_optimum_space_then_time():
    coarse = Linear(10, 0.1)
    theta, chi2, se = _start(coarse)
    levels, failed = discretisation.refine(
        coarse, theta, coarse.A / SIGMA, se, max_levels=2, chi2=chi2, window_ends=(0.3, 0.6, None)
    )
    assert not failed
    grids = [(lv.what, lv.nodes, lv.dt) for lv in levels]
    # nodes doubled at the fit's dt, then dt halved at the nodes space settled on
    # (no space move settled below a third of an SE, so time refines at the finest nodes)
    assert grids == [("tolerance", 10, 0.1), ("space", 20, 0.1), ("space", 40, 0.1), ("time", 40, 0.05), ("time", 40, 0.025)], (
        grids
    )
    assert [lv.parent for lv in levels] == [None, None, 1, 2, 3]
    for lv in levels[1:]:
        # the refit stops when a step gains less than a parameter 0.05 SE off would add;
        # measured: within 0.0011 SE of the closed form, every move above a third of an SE
        assert np.all(np.abs(lv.theta - Linear(lv.nodes, lv.dt).optimum()) < 0.05 * se), lv


def test_a_refit_that_fits_far_worse_is_reported_and_not_used():
    """The second time refinement's model is off by a constant no parameter absorbs (a refit
    stuck in a wrong minimum looks the same to the caller): it is reported, and the levels stop
    before it."""
    offset = lambda dt: 0.0 if dt > 0.03 else 0.5  # noqa: E731
    coarse = Linear(10, 0.1, offset)
    theta, chi2, se = _start(coarse)
    levels, failed = discretisation.refine(coarse, theta, coarse.A / SIGMA, se, max_levels=2, chi2=chi2)
    assert [lv.what for lv in levels] == ["tolerance", "space", "space", "time"]
    assert len(failed) == 1 and "did not find that model's optimum" in failed[0]


def test_only_the_measured_parameters_decide_the_refinement():
    """A grid that moves only a nuisance parameter (the push, the camera) by many standard
    errors: each chain stops after one refinement, the move still recorded."""

    class Nuisance(Linear):
        def __init__(self, nodes, dt, offset=lambda dt: 0.0):
            super().__init__(nodes, dt, offset)
            self.A = A0 @ (np.eye(UNKNOWNS) + np.diag([0.0, 0.0, 5.0 / nodes + 5.0 * dt]))
            self.measured = np.array([True, True, False])

        def refined(self, nodes, dt, tol):
            return Nuisance(nodes, dt)

    coarse = Nuisance(10, 0.1)
    theta, chi2, se = _start(coarse)
    levels, failed = discretisation.refine(coarse, theta, coarse.A / SIGMA, se, max_levels=2, chi2=chi2)
    assert not failed and [lv.what for lv in levels] == ["tolerance", "space", "time"]
    assert abs(levels[1].move_se[2]) > 10 and np.all(np.abs(levels[1].move_se[:2]) < 1 / 3)
    # space settled at the fit's 10 nodes (the move to 20 is their error): time refines there,
    # from the fit's own optimum
    assert (levels[2].nodes, levels[2].dt, levels[2].parent) == (10, 0.05, None)
    assert np.all(np.abs(levels[2].theta - Nuisance(10, 0.05).optimum()) < 0.05 * se)
