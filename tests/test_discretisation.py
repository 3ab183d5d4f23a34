"""`identify.discretisation`'s refits on models whose finer grids have known optima (linear
least-squares problems in closed form; a nonlinear oscillation, by SciPy): a refit (the coarse
Jacobian held through the windows, then the finer model's own) must reach each grid's own
optimum, and a grid that fits far worse than the fit must be reported as a failed refit, its
values unused."""

from __future__ import annotations

import types

import numpy as np
import pytest

from identify import discretisation, robust
from identify.problem import Unknown

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
            solver=types.SimpleNamespace(nodes=nodes, grid_nodes=nodes, dt=dt, newton=types.SimpleNamespace(tol=1e-10))
        )
        self.max_step = np.inf
        self.measured = np.ones(UNKNOWNS, bool)
        self.sigma = np.full(3, SIGMA)  # the whitening of the three columns
        self.huber = robust.NONE
        self.keep = np.ones(FRAMES, bool)
        self.unknowns = [Unknown("a", 2, False, 1.0), Unknown("b", 1, False, 1.0)]
        self.slices = {"a": slice(0, 2), "b": slice(2, 3)}

    def to_values(self, theta):
        return {"a": np.asarray(theta)[:2], "b": np.asarray(theta)[2]}

    def frame(self, theta):  # no camera frame: zero, and independent of theta
        return np.zeros(3), np.zeros((3, UNKNOWNS))

    def window(self, t_end=None):
        return (T <= (np.inf if t_end is None else t_end)).astype(float), None

    def counted(self, t_end=None):
        return 3 * int(np.sum(self.window(t_end)[0]))

    def residual(self, theta, t_end=None):
        rows = np.repeat(self.window(t_end)[0] > 0, 3)
        return np.where(rows, self.A @ np.asarray(theta) - B - self.offset(self.dt), 0.0) / np.tile(self.sigma, FRAMES)

    def residual_and_jacobian(self, theta, t_end=None):
        rows = np.repeat(self.window(t_end)[0] > 0, 3)
        return self.residual(theta, t_end), np.where(rows[:, None], self.A, 0.0) / np.tile(self.sigma, FRAMES)[:, None]

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
    levels, failed = discretisation.refine(coarse, theta, coarse.A / SIGMA, max_levels=2, chi2=chi2, window_ends=(0.3, 0.6, None))
    assert not failed
    grids = [(lv.what, lv.nodes, lv.dt) for lv in levels]
    # nodes doubled at the fit's dt, then dt halved at the nodes space settled on
    # (no space move settled below a third of an SE, so time refines at the finest nodes)
    assert grids == [("tolerance", 10, 0.1), ("space", 20, 0.1), ("space", 40, 0.1), ("time", 40, 0.05), ("time", 40, 0.025)], (
        grids
    )
    assert [lv.parent for lv in levels] == [None, None, 1, 2, 3]
    for lv in levels[1:]:
        # the refit stops when its linearisation puts the parameters within 0.05 SE of the
        # optimum; measured: within 0.027 SE of the closed form, every move above a third of an SE
        assert np.all(np.abs(lv.theta - Linear(lv.nodes, lv.dt).optimum()) < 0.05 * se), lv


def test_a_refit_that_fits_far_worse_is_reported_and_not_used():
    """The second time refinement's model is off by a constant no parameter absorbs (a refit
    stuck in a wrong minimum looks the same to the caller): it is reported, and the levels stop
    before it."""
    offset = lambda dt: 0.0 if dt > 0.03 else 0.5  # noqa: E731
    coarse = Linear(10, 0.1, offset)
    theta, chi2, se = _start(coarse)
    levels, failed = discretisation.refine(coarse, theta, coarse.A / SIGMA, max_levels=2, chi2=chi2)
    assert [lv.what for lv in levels] == ["tolerance", "space", "space", "time"]
    # the refit converged to that model's own minimum, so the note says that it fits worse there
    assert len(failed) == 1 and "at a minimum of that model" in failed[0], failed


def test_a_time_refit_on_a_finer_internal_grid_is_reported():
    """pcrjax refines a rod's internal grid as dt shrinks (the dynamic step's boundary layer);
    a time refit whose internal grid is finer than its parent's measured a space move too, and
    the notes say so (they do not where the grid is held)."""

    class Boundary(Linear):
        def __init__(self, nodes, dt, offset=lambda dt: 0.0):
            super().__init__(nodes, dt, offset)
            self.scene.solver.grid_nodes = nodes * (2 if dt < 0.03 else 1)

        def refined(self, nodes, dt, tol):
            return Boundary(nodes, dt)

    coarse = Boundary(10, 0.1)
    theta, chi2, _ = _start(coarse)
    levels, notes = discretisation.refine(coarse, theta, coarse.A / SIGMA, max_levels=2, chi2=chi2)
    assert [(lv.what, lv.dt) for lv in levels][-2:] == [("time", 0.05), ("time", 0.025)]
    assert len(notes) == 1 and "dt 0.025 s also refined the internal grid from 40 to 80 nodes" in notes[0], notes
    levels, notes = discretisation.refine(Linear(10, 0.1), theta, coarse.A / SIGMA, max_levels=2, chi2=chi2)
    assert not notes


class Nuisance(Linear):
    """`Linear` whose grids move only the last unknown, a nuisance parameter."""

    def __init__(self, nodes, dt, offset=lambda dt: 0.0):
        super().__init__(nodes, dt, offset)
        self.A = A0 @ (np.eye(UNKNOWNS) + np.diag([0.0, 0.0, 5.0 / nodes + 5.0 * dt]))
        self.measured = np.array([True, True, False])

    def refined(self, nodes, dt, tol):
        return Nuisance(nodes, dt)


def test_only_the_measured_parameters_decide_the_refinement():
    """A grid that moves only a nuisance parameter (the push, the camera) by many standard
    errors: each chain stops after one refinement, the move still recorded."""
    coarse = Nuisance(10, 0.1)
    theta, chi2, se = _start(coarse)
    levels, failed = discretisation.refine(coarse, theta, coarse.A / SIGMA, max_levels=2, chi2=chi2)
    assert not failed and [lv.what for lv in levels] == ["tolerance", "space", "time"]
    assert abs(levels[1].move_se[2]) > 10 and np.all(np.abs(levels[1].move_se[:2]) < 1 / 3)
    # space settled at the fit's 10 nodes (the move to 20 is their error): time refines there,
    # from the fit's own optimum
    assert (levels[2].nodes, levels[2].dt, levels[2].parent) == (10, 0.05, None)
    assert np.all(np.abs(levels[2].theta - Nuisance(10, 0.05).optimum()) < 0.05 * se)


class Skewed(Linear):
    """`Linear` whose operator changes with the grid far more than its optimum does: ``A0 + 0.5 D
    (1 - 10 / nodes)``, so a finer grid's Jacobian is half again off the fit's (10 nodes) and a
    refit that held the fit's Jacobian to the end would stop at that Jacobian's fixed point,
    hundreds of standard errors from the finer grid's optimum."""

    D = np.random.default_rng(5).standard_normal(A0.shape)

    def __init__(self, nodes, dt, offset=lambda dt: 0.0):
        super().__init__(nodes, dt, offset)
        self.A = A0 + 0.5 * self.D * (1.0 - 10.0 / nodes)

    def refined(self, nodes, dt, tol):
        return Skewed(nodes, dt)


def test_a_refit_takes_the_finer_models_own_jacobian_over_the_whole_recording():
    coarse, fine = Skewed(10, 0.1), Skewed(40, 0.1)
    theta, chi2, se = _start(coarse)
    th, _, _, jacobians, distance = discretisation.chord_refit(fine, theta, coarse.A / SIGMA, (0.3, 0.6, None))
    assert np.max(np.abs(fine.optimum() - theta) / se) > 100  # the move to measure
    assert np.all(np.abs(th - fine.optimum()) < 0.05 * se), (th - fine.optimum()) / se
    # taken where the held Jacobian stopped (a Gauss-Newton step to the linear model's optimum) and there
    assert jacobians == 2
    assert distance < discretisation.STILL


class Curved(Linear):
    """`Linear` plus ``kappa |theta|^2 u`` along a unit residual direction ``u`` that no column of
    ``A0`` reaches, against data that miss the model by ``mu u``: the residuals' curvature term
    sum r_i Hess r_i = -2 kappa mu / SIGMA^2 I is a fraction of the Gauss-Newton curvature (as a
    recording's noise makes it along nearly collinear unknowns), so a Jacobian held from where
    it was taken has a fixed point off the optimum by that fraction of the distance."""

    U = RNG.standard_normal(3 * FRAMES)
    U -= A0 @ np.linalg.lstsq(A0, U, rcond=None)[0]
    U /= np.linalg.norm(U)

    def __init__(self, nodes, dt, kappa=1.0, mu=10.0):
        super().__init__(nodes, dt)
        self.kappa, self.mu = kappa, mu

    def residual_and_jacobian(self, theta, t_end=None):
        th = np.asarray(theta, float)
        rows = np.repeat(self.window(t_end)[0] > 0, 3)
        r = self.A @ th + self.kappa * (th @ th) * self.U - B - self.mu * self.U
        J = self.A + 2.0 * self.kappa * np.outer(self.U, th)
        return np.where(rows, r, 0.0) / SIGMA, np.where(rows[:, None], J, 0.0) / SIGMA

    def residual(self, theta, t_end=None):
        return self.residual_and_jacobian(theta, t_end)[0]

    def refined(self, nodes, dt, tol):
        return Curved(nodes, dt, self.kappa, self.mu)

    def optimum(self):
        """(theta, standard errors) by SciPy's trust-region least squares, to a tight tolerance."""
        from scipy.optimize import least_squares

        sol = least_squares(
            self.residual, np.array([1.0, -2.0, 0.5]), jac=lambda x: self.residual_and_jacobian(x)[1], xtol=1e-15, ftol=1e-15,
            gtol=1e-15,
        )  # fmt: skip
        return sol.x, np.sqrt(np.diag(np.linalg.inv(sol.jac.T @ sol.jac)))


def test_a_refit_reaches_its_optimum_where_the_residuals_curvature_moves_a_held_jacobians_fixed_point():
    """The curvature term a tenth of the Gauss-Newton one (kappa 1, mu 10): a refit that took the
    finer model's Jacobian once and held it stopped 0.6-1.4 standard errors from the optimum
    (SciPy's); with that model's Jacobian at every step every refit comes within 0.05, and says
    so. Where the term is half the Gauss-Newton one (kappa 3, mu 3) ``REFRESH`` Jacobians do not
    always reach 0.05: the distance the refit reports bounds how far each unknown lies off."""
    for kappa, mu, converges in ((1.0, 10.0, True), (3.0, 3.0, False)):
        coarse = Curved(10, 0.1, kappa, mu)
        theta, _ = coarse.optimum()
        J = coarse.residual_and_jacobian(theta)[1]
        for nodes, dt in ((20, 0.1), (10, 0.05), (40, 0.1)):
            fine = coarse.refined(nodes, dt, None)
            best, se = fine.optimum()
            th, _, _, jacobians, distance = discretisation.chord_refit(fine, theta, J, (None,))
            off = np.max(np.abs(th - best) / se)
            assert np.max(np.abs(best - theta) / se) > 5  # the move to measure
            assert jacobians <= discretisation.REFRESH
            assert off <= 1.05 * distance, (kappa, nodes, dt, off, distance)
            if converges:
                assert distance < discretisation.STILL and off < 0.05, (nodes, dt, off, distance)


def test_a_refit_from_known_residuals_takes_them_as_its_first():
    """`chord_refit` given the residuals at its start over the whole recording (``r0``, as
    `refine` has them from its reach test) ends where it ends without them, one rollout fewer;
    with windows first they are not used."""
    coarse, fine = Curved(10, 0.1), Curved(20, 0.1)
    theta, _ = coarse.optimum()
    J = coarse.residual_and_jacobian(theta)[1]
    calls = []
    fine.residual = lambda th, t_end=None: calls.append(t_end) or Curved.residual(fine, th, t_end)
    plain = discretisation.chord_refit(fine, theta, J, (None,))
    n_plain = len(calls)
    known = discretisation.chord_refit(fine, theta, J, (None,), r0=Curved.residual(fine, theta))
    assert len(calls) - n_plain == n_plain - 1
    np.testing.assert_array_equal(known[0], plain[0])
    windows = discretisation.chord_refit(fine, theta, J, (0.3, 0.6, None), r0=np.zeros(3 * FRAMES))  # a wrong r0: unused
    np.testing.assert_array_equal(discretisation.chord_refit(fine, theta, J, (0.3, 0.6, None))[0], windows[0])


class Oscillation(Linear):
    """Whitened residuals of a decaying oscillation ``a exp(-d t) sin(w t)`` (unknowns: a, log w,
    log(d / 0.1)) whose frequency the grid moves by ``SHIFT (0.2 dt + 0.5 / nodes^2)`` (2.5 % on
    the fit's grid at ``SHIFT`` 1: almost a cycle of phase by the record's end), against
    ``Oscillation.data``."""

    TRUTH = np.array([1.0, 2.0, -0.3])
    TIMES = np.linspace(0.0, 30.0, 3 * FRAMES)  # one residual row each
    SHIFT = 1.0
    data = None

    def _model(self, theta):
        shift = self.SHIFT * (0.2 * self.dt + 0.5 / self.nodes**2)
        a, w, d = theta[0], np.exp(theta[1]) * (1.0 + shift), 0.1 * np.exp(theta[2])
        t = self.TIMES
        f = a * np.exp(-d * t) * np.sin(w * t)
        return f, np.stack([f / a, a * np.exp(-d * t) * np.cos(w * t) * w * t, -f * d * t], axis=1)

    def residual(self, theta, t_end=None):
        return self.residual_and_jacobian(theta, t_end)[0]

    def residual_and_jacobian(self, theta, t_end=None):
        rows = np.repeat(self.window(t_end)[0] > 0, 3)
        f, J = self._model(np.asarray(theta, float))
        return np.where(rows, f - self.data, 0.0) / SIGMA, np.where(rows[:, None], J, 0.0) / SIGMA

    def refined(self, nodes, dt, tol):
        return Oscillation(nodes, dt)

    def optimum(self):
        """(theta, standard errors) by SciPy's trust-region least squares from the truth, to a
        tight tolerance: an optimiser independent of the refits'."""
        from scipy.optimize import least_squares

        sol = least_squares(
            self.residual, self.TRUTH, jac=lambda x: self.residual_and_jacobian(x)[1], xtol=1e-15, ftol=1e-15, gtol=1e-15
        )
        chi2 = float(sol.fun @ sol.fun) / (sol.fun.size - UNKNOWNS)
        return sol.x, np.sqrt(np.diag(np.linalg.inv(sol.jac.T @ sol.jac)) * chi2)


@pytest.mark.parametrize("shift", [1.0, 0.01])
def test_refits_of_a_nonlinear_model_reach_each_grids_own_optimum(shift, monkeypatch):
    """Data from a converged grid plus noise; the fit on 10 nodes, dt 0.1. With the frequency
    2.5 % off there (the finer grids' optima tens to hundreds of standard errors away) the first
    refit of each chain goes through the windows; with a hundredth of that (moves of 1-3
    standard errors), where the fit's Jacobian's step from the coarser optimum is within
    ``NEAR_SE`` standard errors, every refit goes over the whole recording at once. Either way
    every refit lies within 0.05 of its grid's standard errors of that grid's optimum as SciPy
    finds it."""
    monkeypatch.setattr(Oscillation, "SHIFT", shift)
    Oscillation.data = Oscillation(10**4, 0.0)._model(Oscillation.TRUTH)[0] + SIGMA * np.random.default_rng(7).standard_normal(
        3 * FRAMES
    )
    coarse = Oscillation(10, 0.1)
    theta, se_fit = coarse.optimum()
    r, J = coarse.residual_and_jacobian(theta)
    chi2 = float(r @ r) / (r.size - UNKNOWNS)
    windowed = []
    residual = Oscillation.residual
    monkeypatch.setattr(Oscillation, "residual", lambda self, th, t_end=None: windowed.append(t_end) or residual(self, th, t_end))
    levels, failed = discretisation.refine(coarse, theta, J, max_levels=2, chi2=chi2, window_ends=(0.3, 0.6, None))
    assert not failed and [lv.what for lv in levels].count("time") >= 1
    assert any(t is not None for t in windowed) == (shift == 1.0), windowed
    assert np.max(np.abs(levels[1].move_se)) > 0.9  # a move to measure (1 and 98 standard errors)
    for lv in levels[1:]:
        best, se = Oscillation(lv.nodes, lv.dt).optimum()
        assert np.all(np.abs(lv.theta - best) < 0.05 * se), (lv.what, lv.nodes, lv.dt, (lv.theta - best) / se)


P_T2, P_T3 = 3.0 * RNG.standard_normal((2, UNKNOWNS, UNKNOWNS))  # second- and third-order dt terms


class SecondOrder(Linear):
    """`Linear` with a second-order scheme in time: the grid's operator is
    ``A0 (I + P_T2 dt^2 + P_T3 dt^3)``, so the optimum moves by O(dt^2) and the extrapolation
    to dt 0 has a closed form (``SecondOrder(nodes, 0.0).optimum()``)."""

    def __init__(self, nodes, dt, offset=lambda dt: 0.0):
        super().__init__(nodes, dt, offset)
        self.A = A0 @ (np.eye(UNKNOWNS) + P_T2 * dt**2 + P_T3 * dt**3)

    def refined(self, nodes, dt, tol):  # the same whitening, as `Problem.refined` keeps it
        out = SecondOrder(nodes, dt)
        out.sigma = self.sigma
        return out

    def reported(self, theta):
        return {"a": np.asarray(theta)[:2], "b": float(np.asarray(theta)[2])}

    def labels(self):
        return ["a[0]", "a[1]", "b"]


def test_second_order_time_moves_are_extrapolated_to_dt_zero():
    """Time moves that shrink 4x per halving: the chain stops once the Richardson extrapolation's
    uncertainty is below a third of an SE (before it would by halving alone), and the reported
    values are the extrapolation, which lies within its reported error of the dt -> 0 optimum,
    far closer than the finest grid's own."""
    from identify.result import Result

    coarse = SecondOrder(10, 0.1)
    theta, chi2, se = _start(coarse)
    J = coarse.A / SIGMA
    levels, failed = discretisation.refine(coarse, theta, J, max_levels=6, chi2=chi2)
    times = [lv for lv in levels if lv.what == "time"]
    assert not failed and len(times) >= 2
    moves = [np.max(np.abs(lv.move_se)) for lv in times]
    assert moves[-1] > 1 / 3  # halving alone has not settled it
    order = np.log2(np.linalg.norm(times[-2].move_se) / np.linalg.norm(times[-1].move_se))
    assert abs(order - 2) < 0.5, order
    result = Result(
        labels=coarse.labels(), values=coarse.reported(theta), standard_errors={"a": se[:2].tolist(), "b": float(se[2])},
        correlation=[], sigma=[SIGMA, SIGMA], loss=chi2, rms=[],
    )  # fmt: skip
    rep = discretisation.report(coarse, theta, J, result, max_levels=6)
    assert rep.model["extrapolated_from_dt"] == [times[-2].dt, times[-1].dt]
    limit = SecondOrder(coarse.nodes, 0.0).optimum()
    got = np.append(rep.values["a"], rep.values["b"])
    err = np.append(rep.discretisation_errors["a"], rep.discretisation_errors["b"])
    finest = times[-1].theta
    assert np.all(np.abs(got - limit) <= err + 0.05 * se), ((got - limit) / se, err / se)
    assert np.all(err <= se / 3 + 1e-12)
    assert np.max(np.abs(got - limit) / se) < 0.2 * np.max(np.abs(finest - limit) / se)
    assert "not negligible" not in rep.message


Q4, Q6 = 0.03 * np.random.default_rng(8).standard_normal((2, UNKNOWNS, UNKNOWNS))  # fourth- and sixth-order node terms


class FourthOrderSpace(SecondOrder):
    """`SecondOrder` with RK4's order in space: the grid's operator is ``A0 (I + Q4 x^4 + Q6 x^6 +
    P_T2 dt^2 + P_T3 dt^3)``, x = 10 / the internal grid's nodes (`internal_grid`: the nodes); the
    optimum at infinitely many nodes and dt 0 is A0's least-squares solution."""

    SPACE = 1.0  # the size of the space terms

    def __init__(self, nodes, dt, offset=lambda dt: 0.0):
        super().__init__(nodes, dt, offset)
        self.scene.solver.grid_nodes = self.internal_grid(nodes, dt)
        x = 10.0 / self.scene.solver.grid_nodes
        self.A = A0 @ (np.eye(UNKNOWNS) + self.SPACE * (Q4 * x**4 + Q6 * x**6) + P_T2 * dt**2 + P_T3 * dt**3)

    @staticmethod
    def internal_grid(nodes, dt):
        """The nodes the space error follows (pcrjax's ``solver.grid_nodes``)."""
        return nodes

    def refined(self, nodes, dt, tol):
        return type(self)(nodes, dt)


def _report(coarse):
    """(`discretisation.report` of the fit on ``coarse`` with up to 6 refinements per chain, the
    fit's standard errors)."""
    from identify.result import Result

    theta, chi2, se = _start(coarse)
    result = Result(
        labels=coarse.labels(), values=coarse.reported(theta), standard_errors={"a": se[:2].tolist(), "b": float(se[2])},
        correlation=[], sigma=[SIGMA, SIGMA], loss=chi2, rms=[],
    )  # fmt: skip
    return discretisation.report(coarse, theta, coarse.A / SIGMA, result, max_levels=6), se


def test_space_moves_at_rk4s_order_are_extrapolated_and_time_refines_at_the_coarser_nodes():
    """Space moves of 45, 6.2 and 0.45 SE (the last still above a third, as on the random-truth
    Triskele push-release): they shrink at order 4, so the space error is extrapolated from the
    last two (Richardson, 16 m2 / 15 added to the coarser grid's values), the time chain runs at
    the coarser 40 nodes instead of 80, and the values lie within their reported error of the
    optimum at infinitely many nodes and dt 0, which the 40-node values alone miss by more than
    a third of an SE."""
    rep, se = _report(FourthOrderSpace(10, 0.1))
    space = [r for r in rep.refinements if r["refit"] == "space"]
    times = [r for r in rep.refinements if r["refit"] == "time"]
    assert [r["nodes"] for r in space] == [20, 40, 80] and space[-1]["largest_move_se"] > 1 / 3
    assert {r["nodes"] for r in times} == {40}
    assert rep.model["extrapolated_from_nodes"] == [40, 80] and "extrapolated_from_dt" in rep.model
    limit = np.linalg.lstsq(A0, B, rcond=None)[0]
    got = np.append(rep.values["a"], rep.values["b"])
    err = np.append(rep.discretisation_errors["a"], rep.discretisation_errors["b"])
    assert np.all(np.abs(got - limit) <= err + 0.05 * se), ((got - limit) / se, err / se)
    assert np.all(err <= se / 3)
    at_40 = FourthOrderSpace(40, 0.0).optimum()  # what the time chain converges to without the space correction
    assert np.max(np.abs(at_40 - limit) / se) > 1 / 3
    assert "not negligible" not in rep.message


class RefiningGrid(FourthOrderSpace):
    """`FourthOrderSpace` whose internal grid doubles below dt 0.03, as pcrjax's does when the
    dynamic step's boundary layer narrows: the space error follows the internal grid."""

    @staticmethod
    def internal_grid(nodes, dt):
        return nodes * (2 if dt < 0.03 else 1)


def test_a_time_refit_on_a_finer_internal_grid_has_the_space_move_it_holds_taken_out():
    """The space chain of `test_space_moves_at_rk4s_order_are_extrapolated...` settles by
    extrapolation at 40 nodes; the time chain's internal grid doubles at dt 0.025, so that
    refit's move holds most of the 40-node space error, which the extrapolated correction would
    add again. Scaled to each level's internal grid (RK4's order), the correction is counted
    once and the values lie within their reported error of the limit (counted twice, b missed
    it by 0.38 SE against an error of 0.14)."""
    rep, se = _report(RefiningGrid(10, 0.1))
    times = [r for r in rep.refinements if r["refit"] == "time"]
    assert {r["nodes"] for r in times} == {40} and min(r["dt"] for r in times) < 0.03
    assert "taken out by the space chain's estimate" in rep.message, rep.message
    limit = np.linalg.lstsq(A0, B, rcond=None)[0]
    got = np.append(rep.values["a"], rep.values["b"])
    err = np.append(rep.discretisation_errors["a"], rep.discretisation_errors["b"])
    assert np.all(np.abs(got - limit) <= err + 0.05 * se), ((got - limit) / se, err / se)


class TwoBasins(Linear):
    """One unknown x whose loss has two basins on every grid, near ``a = C dt^2`` and
    ``b = 1 + C dt^2``: rows ``W (x - a)(x - b)``, ``H (x - b)``, ``Q(dt) (x - a)`` and unit noise.
    The basin at a costs about ``H^2 / 2``, the one at b ``Q^2 / 2``: with ``Q = 8 dt / 0.1``
    (``flips``) the fit's grid (dt 0.1) prefers a by 24 and dt 0.025 prefers b by 6; at dt 0 the
    optimum is x = 1 exactly. Without ``flips`` (Q = 8) b is worse on every grid."""

    W, H, C = 100.0, 4.0, 10.0
    NOISE = np.random.default_rng(11).standard_normal(3 * FRAMES - 3)

    def __init__(self, nodes, dt, flips=True):
        super().__init__(nodes, dt)
        self.flips = flips
        self.measured = np.ones(1, bool)
        self.sigma = np.ones(3)  # unit noise
        self.unknowns, self.slices = [Unknown("x", 1, False, 1.0)], {"x": slice(0, 1)}

    def to_values(self, theta):
        return {"x": np.asarray(theta)[0]}

    def frame(self, theta):
        return np.zeros(3), np.zeros((3, 1))

    def _rows(self, x):
        a, b = self.C * self.dt**2, 1.0 + self.C * self.dt**2
        q = 8.0 * self.dt / 0.1 if self.flips else 8.0
        r = np.concatenate([[self.W * (x - a) * (x - b), self.H * (x - b), q * (x - a)], self.NOISE])
        J = np.zeros((r.size, 1))
        J[:3, 0] = [self.W * (2 * x - a - b), self.H, q]
        return r, J

    def residual(self, theta, t_end=None):
        return self.residual_and_jacobian(theta, t_end)[0]

    def residual_and_jacobian(self, theta, t_end=None):
        rows = np.repeat(self.window(t_end)[0] > 0, 3)
        r, J = self._rows(float(np.asarray(theta)[0]))
        return np.where(rows, r, 0.0), np.where(rows[:, None], J, 0.0)

    def fit_linear(self, theta, t_end=None):
        r = self.residual(theta, t_end)
        return np.asarray(theta, float), 0.5 * float(r @ r)

    def refined(self, nodes, dt, tol):
        return type(self)(nodes, dt, self.flips)

    def reported(self, theta):
        return {"x": float(np.asarray(theta)[0])}

    def labels(self):
        return ["x"]

    def optimum(self, start):
        from scipy.optimize import least_squares

        sol = least_squares(self.residual, [start], jac=lambda x: self.residual_and_jacobian(x)[1], xtol=1e-15, ftol=1e-15)
        chi2 = float(sol.fun @ sol.fun) / (sol.fun.size - 1)
        return sol.x, chi2, np.sqrt(np.diag(np.linalg.inv(sol.jac.T @ sol.jac)) * chi2)


def _two_basins_report(flips: bool, start=None, model=TwoBasins):
    """(the fit's grid's problem, its standard error, the report) of a fit on ``model`` that ended
    in the basin near 0, having begun at ``start`` (default: x = 1, in the other basin)."""
    from identify.result import Result

    coarse = model(10, 0.1, flips)
    theta, chi2, se = coarse.optimum(0.0)  # the fit's grid leads to the basin near 0
    J = coarse.residual_and_jacobian(theta)[1]
    result = Result(
        labels=["x"], values=coarse.reported(theta), standard_errors={"x": float(se[0])}, correlation=[], sigma=[1.0, 1.0],
        loss=chi2, rms=[],
    )  # fmt: skip
    start = np.array([1.0]) if start is None else start(theta, se)
    return coarse, se, discretisation.report(coarse, theta, J, result, max_levels=2, rivals=[start])


def test_a_start_in_a_basin_that_a_finer_grid_prefers_takes_the_answer_over():
    """The fit's grid prefers the wrong basin; on the finest grid the start's basin fits better:
    the answer is that basin's, its time error measured on coarser grids and extrapolated, and
    it lies within that error of the dt -> 0 optimum (x = 1), 100 standard errors from the
    basin the fit's grid chose."""
    coarse, se, rep = _two_basins_report(flips=True)
    whats = [r["refit"] for r in rep.refinements]
    assert whats[-4:] == ["rival", "rival", "time", "time"], whats
    assert [r["dt"] for r in rep.refinements[-3:]] == [0.1, 0.05, 0.025]
    assert "fits better" in rep.message and rep.model["extrapolated_from_dt"] == [0.05, 0.025]
    got, err = rep.values["x"], rep.discretisation_errors["x"]
    assert abs(got - 1.0) <= err + 0.05 * se[0], ((got - 1.0) / se[0], err / se[0])
    assert abs(rep.refinements[-5]["values"]["x"] - 1.0) > 0.9  # the chain's own answer: the other basin


class FarBasins(TwoBasins):
    """`TwoBasins` with the basins moving three times as far with dt (C 30: the rival's optimum
    at x = 1.3 on the fit's grid, 1.02 at the finest)."""

    C = 30.0


def test_refits_that_stop_short_of_their_optima_widen_the_error_they_measure(monkeypatch):
    """Every refit given one Jacobian of its own model, so that the rival basin's refits stop
    0.35 to 0.94 standard errors short of their optima: their distances are reported, each in a
    note, and the time error of the answer (extrapolated from two of them) covers the distance
    to the dt -> 0 optimum x = 1 (0.33 SE; without the distances the error claimed 0.087 SE)."""
    attempt = discretisation._attempt

    def one_jacobian(fine, tries, J, m, chi2, refresh=discretisation.REFRESH, progress=None):
        return attempt(fine, tries, J, m, chi2, min(refresh, 1), progress)

    monkeypatch.setattr(discretisation, "_attempt", one_jacobian)
    _, se, rep = _two_basins_report(flips=True, model=FarBasins)
    rivals = [r for r in rep.refinements if r["refit"] == "rival"]
    assert len(rivals) == 2 and all(r["distance_to_optimum_se"] is not None for r in rivals), rivals
    far = [r for r in rep.refinements if (r["distance_to_optimum_se"] or 0.0) > discretisation.STILL]
    assert len(far) >= 2 and all(f"dt {r['dt']:.3g} s stopped" in rep.message for r in far), rep.message
    got, err = rep.values["x"], rep.discretisation_errors["x"]
    assert abs(got - 1.0) > 0.1 * se[0]  # the distances matter here
    assert abs(got - 1.0) <= err, ((got - 1.0) / se[0], err / se[0])


def test_a_start_whose_basin_fits_worse_on_the_finest_grid_leaves_the_answer():
    """The start's basin is worse on every grid: its optimum on the finest grid is listed as a
    rival, and the values are the chain's (the basin near 0)."""
    _, se, rep = _two_basins_report(flips=False)
    whats = [r["refit"] for r in rep.refinements]
    assert whats[-1] == "rival" and whats.count("rival") == 1, whats
    assert abs(rep.values["x"]) < 0.01 and "fits better" not in rep.message and "as well" not in rep.message


def test_a_start_in_the_basin_the_fit_ended_in_does_not_contest():
    """The fit ended half a standard error from its start, in the basin near 0; the time chain
    then moves the answer about 9 standard errors along that basin (its optimum a = C dt^2), so
    the start lies far from the finest grid's answer, yet in the basin the chain followed: no
    refit of the start (a contest would cost a whole refit on the finest grid and find the same
    optimum), no second optimum reported, and the values are the chain's."""
    _, se, rep = _two_basins_report(flips=True, start=lambda theta, se: theta + 0.5 * se)
    whats = [r["refit"] for r in rep.refinements]
    assert "rival" not in whats, whats
    finest = rep.refinements[-1]
    assert finest["refit"] == "time" and abs(finest["values"]["x"] - rep.refinements[0]["values"]["x"]) > 3 * se[0]
    assert abs(rep.values["x"]) < 0.01 and "optimum" not in rep.message and "fits better" not in rep.message


def test_the_sandwich_covariance_is_the_spread_of_a_fit_weighted_with_other_noise_levels():
    """A linear fit that weights the three columns with levels (3, 3, 0.5) times the true ones,
    as a fit whose coarse grid's residuals inflate the positions' noise does: `noise_covariance`
    with the true levels equals the covariance of its answers over 4000 noise draws (Monte Carlo
    to its sampling error), and the plain rescaled covariance does not."""
    from identify.result import noise_covariance

    true = np.array([2e-9, 2e-9, 2e-6])
    weights = true * np.array([3.0, 3.0, 0.5])
    pb = types.SimpleNamespace(sigma=weights)
    A = RNG.standard_normal((3 * FRAMES, UNKNOWNS)) * np.tile(true * 1e6, FRAMES)[:, None]
    J = A / np.tile(weights, FRAMES)[:, None]
    draws = np.random.default_rng(3).standard_normal((4000, 3 * FRAMES)) * np.tile(true, FRAMES)
    answers = np.linalg.lstsq(J, (draws / np.tile(weights, FRAMES)).T, rcond=None)[0].T
    spread = np.cov(answers.T)
    got = noise_covariance(pb, J, true)
    np.testing.assert_allclose(np.sqrt(np.diag(got)), np.sqrt(np.diag(spread)), rtol=0.05)
    r = np.linalg.lstsq(J, (draws[0] / np.tile(weights, FRAMES)), rcond=None)
    rescaled = (
        np.linalg.inv(J.T @ J) * float(np.sum((J @ r[0] - draws[0] / np.tile(weights, FRAMES)) ** 2)) / (J.shape[0] - UNKNOWNS)
    )
    assert np.max(np.abs(np.sqrt(np.diag(rescaled) / np.diag(spread)) - 1)) > 0.2


def _misfit_fit():
    """(coarse, theta, J, chi2, se, result) of a fit on a grid whose position columns carry a
    model error (a misfit of 5 noise levels that the refined grids do not have), the fit's noise
    levels estimated per column on its own residuals: the positions' 3.6x too high, the
    angle's right."""
    from identify.result import Result

    misfit = np.tile([5 * SIGMA, 5 * SIGMA, 0.0], FRAMES) * np.sin(np.arange(3 * FRAMES))
    coarse = SecondOrder(10, 0.1, offset=lambda dt: misfit)  # its refinements have no misfit
    raw = (coarse.A @ coarse.optimum() - B - misfit).reshape(-1, 3)
    coarse.sigma = robust.noise_levels(raw)  # the fit's own estimate, per column
    assert coarse.sigma[0] > 3 * SIGMA and abs(coarse.sigma[2] / SIGMA - 1) < 0.3
    theta = coarse.optimum()
    r, J = coarse.residual_and_jacobian(theta)
    chi2 = float(r @ r) / (r.size - UNKNOWNS)
    se = np.sqrt(np.diag(np.linalg.inv(J.T @ J)) * chi2)
    result = Result(
        labels=coarse.labels(), values=coarse.reported(theta), standard_errors={"a": se[:2].tolist(), "b": float(se[2])},
        correlation=[], sigma=[float(coarse.sigma[0]), float(coarse.sigma[2])], loss=chi2, rms=[],
    )  # fmt: skip
    return coarse, theta, J, chi2, se, result


def test_noise_levels_and_standard_errors_come_from_the_finest_model():
    """The misfit fit grid (`_misfit_fit`): the reported noise levels are the finest model's,
    within 15 % of the true one in every column (one factor for all columns, the finest reduced
    chi-square, left the positions 2.6x too high and the angle 0.6x too low), and the standard
    errors follow."""
    from identify.result import noise_covariance

    coarse, theta, J, chi2, se, result = _misfit_fit()
    rep = discretisation.report(coarse, theta, J, result, max_levels=2)
    np.testing.assert_allclose(rep.sigma, SIGMA, rtol=0.15)
    # the fit's estimator under the true noise (its covariance checked by Monte Carlo above)
    se_true = np.sqrt(np.diag(noise_covariance(coarse, J, np.full(3, SIGMA))))
    got = np.append(rep.standard_errors["a"], rep.standard_errors["b"])
    np.testing.assert_allclose(got, se_true, rtol=0.15)
    assert np.max(np.abs(se * np.sqrt(rep.refinements[-1]["reduced_chi2"] / chi2) / se_true - 1)) > 0.3  # one factor for all


def test_every_refit_measures_its_move_in_the_standard_errors_of_the_true_noise():
    """The misfit fit grid (`_misfit_fit`): each refit's move is in the fit's estimator's
    standard errors under the true noise (within 15 %), so a chain goes on until its moves are
    below a third of those. One factor for all columns (the refit's reduced chi-square over the
    fit's) measured them in errors up to 2.6x off, and settled too early."""
    from identify.result import noise_covariance

    coarse, theta, J, chi2, _, _ = _misfit_fit()
    se_true = np.sqrt(np.diag(noise_covariance(coarse, J, np.full(3, SIGMA))))
    levels, failed = discretisation.refine(coarse, theta, J, max_levels=4, chi2=chi2)
    assert not failed and len(levels) >= 3
    for lv in levels:
        parent = theta if lv.parent is None else levels[lv.parent].theta
        np.testing.assert_allclose(np.abs(lv.move_se), np.abs(lv.theta - parent) / se_true, rtol=0.15, atol=1e-3)
        np.testing.assert_allclose(lv.noise, SIGMA, rtol=0.15)


class SmallSpaceError(RefiningGrid):
    """`RefiningGrid` with space terms 0.6 times as large: from a fit at 40 nodes, the first
    space refit moves less than a third of an SE."""

    SPACE = 0.6


class SmallSpaceErrorFixed(FourthOrderSpace):
    """`SmallSpaceError` on a fixed internal grid."""

    SPACE = SmallSpaceError.SPACE


def test_a_space_chain_settled_by_its_last_move_takes_the_space_part_out_of_the_time_moves():
    """The space chain settles at its first refit (40 to 80 nodes, less than a third of an SE),
    so the time chain runs at 40 nodes, whose internal grid doubles below dt 0.03: that refit's
    move would hold 15/16 of the 40-node space error besides the time move. The last space move,
    scaled at RK4's order, takes it out: that move equals the time move on a fixed grid of 80
    nodes within twice the refits' own tolerance (``STILL``: 0.03 SE; 0.28 SE with the space
    part left in), and the values lie within their reported error of the limit."""
    coarse = SmallSpaceError(40, 0.1)
    theta, chi2, se = _start(coarse)
    levels, notes = discretisation.refine(coarse, theta, coarse.A / SIGMA, max_levels=6, chi2=chi2)
    space = [lv for lv in levels if lv.what == "space"]
    assert [lv.nodes for lv in space] == [80] and np.max(np.abs(space[0].move_se)) <= 1 / 3
    times = [lv for lv in levels if lv.what == "time"]
    assert {lv.nodes for lv in times} == {40}
    assert any("taken out by the space chain's estimate" in n for n in notes), notes
    model = lambda i: coarse if i is None else levels[i].problem  # noqa: E731
    (lv,) = [lv for lv in times if lv.problem.scene.solver.grid_nodes != model(lv.parent).scene.solver.grid_nodes]
    g = lv.problem.scene.solver.grid_nodes
    pure = (SmallSpaceErrorFixed(g, lv.dt).optimum() - SmallSpaceErrorFixed(g, model(lv.parent).dt).optimum()) / lv.se
    assert np.max(np.abs(lv.move_se - pure)) < 2 * discretisation.STILL, (lv.dt, lv.move_se - pure)
    rep, se = _report(coarse)
    assert "taken out by the space chain's estimate" in rep.message
    limit = np.linalg.lstsq(A0, B, rcond=None)[0]
    got = np.append(rep.values["a"], rep.values["b"])
    err = np.append(rep.discretisation_errors["a"], rep.discretisation_errors["b"])
    assert np.all(np.abs(got - limit) <= err + 0.05 * se), ((got - limit) / se, err / se)


@pytest.mark.parametrize("case", ["space settles at once", "space chain goes on", "a rival takes over"])
def test_refits_run_side_by_side_give_the_levels_of_one_core(case, monkeypatch):
    """On two cores the first time refit runs beside the tolerance and space refits, and the
    start's refit on the finest grid beside the last time refit; each is used only where the
    chains then ask for it. The levels and notes equal one core's, where nothing runs ahead: a
    refit run ahead and used (the space chain settling at once; the rival), one dropped (the
    space chain going on, the time chain then starting on a finer grid)."""

    def run():
        if case == "a rival takes over":
            rep = _two_basins_report(flips=True)[2]
            return [(r["refit"], r["nodes"], r["dt"], r["values"]["x"]) for r in rep.refinements], rep.message
        if case == "space settles at once":
            coarse = Nuisance(10, 0.1)
        else:
            coarse = Linear(10, 0.1)
        theta, chi2, _ = _start(coarse)
        levels, notes = discretisation.refine(coarse, theta, coarse.A / SIGMA, max_levels=2, chi2=chi2)
        return [(lv.what, lv.nodes, lv.dt, lv.parent, lv.theta.tolist()) for lv in levels], notes

    two = run()
    monkeypatch.setattr(discretisation.threads, "WORKERS", 1)
    one = run()
    assert two == one
    whats = [lv[0] for lv in one[0]]
    assert whats[:2] == ["tolerance", "space"] and "time" in whats, whats
