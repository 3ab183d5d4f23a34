r"""The discretisation error of a fitted answer: refit on a finer model and see how far it moves.

The standard errors say how well the noise pins the parameters of *this* model, which is itself
an approximation (N nodes, a time step dt, a Newton tolerance); reality has no grid. After the
fit the recording is refitted from the optimum:

1. with the Newton tolerance a tenth of the fit's (same grid): the solver-tolerance error;
2. on a grid of twice the nodes and half the time step (and the tenth of the tolerance): the
   move of each parameter is the discretisation error of the coarser grid's answer. While a
   move exceeds a third of its standard error, the finer grid's answer is taken and that grid
   is refined once more, up to ``max_levels`` refinements.

The reported values are those of the finest grid evaluated, and the discretisation error beside
each is its last move (for a convergent scheme, a bound on the finest grid's own error); if the
last move still exceeds a third of the standard error, the result says so. The noise levels
were estimated from the fit's residuals, which hold the coarse grid's model error too; they and
the standard errors are rescaled by the finest grid's reduced chi-square (one factor for all
columns), so the standard errors are the noise's alone.

Each refit holds the fit's Jacobian (a chord method: Levenberg-Marquardt with the Jacobian of
the coarse model, each step taken only where it lowers the cost): a finer grid moves the
residuals by far more than their derivatives, so an iteration costs one forward rollout on the
finer grid and no tangents. A grid refit runs over the fit's windows of growing length, since
the coarse answer can be cycles of phase off the finer grid's over a whole recording. A refit
that ends at a reduced chi-square more than ``WORSE`` times the fit's found no optimum: it is
reported as failed and its values are not used.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from .least_squares import FitError, levenberg_marquardt, standard_errors_theta

THIRD = 1.0 / 3.0  # a move below this fraction of the standard error is negligible beside it
TOL_FACTOR = 0.1
CHORD_ITER = 20  # Levenberg-Marquardt iterations per window
STILL = 0.05  # a refit ends when a step gains less than a parameter this many standard errors off
WORSE = 2.0  # a refit whose reduced chi-square is this many times the fit's did not find the optimum


@dataclasses.dataclass(frozen=True)
class Level:
    """One refit: its model (nodes, dt, tol), the values there, their move from the previous
    model in standard errors (per label), the reduced chi-square and the chord iterations."""

    what: str
    nodes: int
    dt: float
    tol: float
    theta: np.ndarray
    move_se: np.ndarray
    chi2: float
    iterations: int
    wall_s: float
    problem: object = dataclasses.field(repr=False, compare=False, default=None)

    def to_json(self) -> dict:
        return dict(
            refit=self.what,
            nodes=self.nodes,
            dt=self.dt,
            tol=self.tol,
            largest_move_se=float(np.max(np.abs(self.move_se))),
            reduced_chi2=self.chi2,
            chord_iterations=self.iterations,
            wall_s=round(self.wall_s, 1),
            values={} if self.problem is None else _plain(self.problem.reported(self.theta)),
        )


def _plain(values: dict) -> dict:
    """Reported values as JSON numbers (scalars as floats, vectors as lists)."""
    return {k: (v.tolist() if v.size > 1 else float(v[0])) for k, v in values.items()}


def chord_refit(problem, theta, J, window_ends=(None,), max_iter: int = CHORD_ITER):
    """(theta, cost, iterations) minimising ``problem``'s residuals over the whole recording
    from ``theta`` with the Jacobian ``J`` held (of another discretisation of the same problem):
    Levenberg-Marquardt steps with that Jacobian, each taken only where it lowers the cost, over
    windows ending at ``window_ends`` (the fit's continuation: a coarse grid's answer can be
    cycles of phase off over a long recording, as the Triskele's 150 Hz modes are at dt 0.5 ms),
    each from the previous one's answer. The whole recording's refit stops when a step lowers
    the cost by less than a parameter ``STILL`` standard errors off the optimum would add.
    Raises `FitError` where the refined model's rollout fails."""
    theta = np.asarray(theta, float)
    total = 0
    for t_end in window_ends:
        rows = np.repeat(np.asarray(problem.window(t_end)[0]) > 0, 3)
        held = J * rows[:, None]
        last = {}

        def residual(x, t_end=t_end, last=last):
            x = np.asarray(x, float)
            if last.get("x") is None or not np.array_equal(last["x"], x):  # the accepted trial's rollout is reused
                last["x"], last["r"] = x, np.asarray(problem.residual(x, t_end))
            return last["r"]

        r0 = residual(theta)
        if not np.all(np.isfinite(r0)):
            raise FitError(
                f"the model with {problem.scene.solver.nodes} nodes, dt {float(problem.scene.solver.dt):.3g} s does not converge"
            )
        ftol = 1e-6 if t_end is not None else 0.5 * STILL**2 / max(0.5 * float(r0 @ r0), 1e-300)
        theta, _, r, it, _, _ = levenberg_marquardt(
            residual, lambda x, residual=residual: (residual(x), held), theta, max_iter, ftol=ftol, max_step=problem.max_step
        )
        total += it
    return theta, 0.5 * float(r @ r), total


def refine(problem, theta, J, se_theta, max_levels: int = 2, progress=None, chi2: float = 1.0, window_ends=(None,)):
    """(the `Level` list: the tolerance refit first, then the grids; the failures: a refit whose
    rollout failed ends the list) for the fit ``problem`` at its optimum ``theta`` (Jacobian
    ``J``, standard errors ``se_theta`` of theta at its reduced chi-square ``chi2``, its noise
    levels); each move is in the standard errors of its own grid (rescaled by its reduced
    chi-square). ``progress(message)``."""
    m = problem.counted(None) - theta.size
    solver = problem.scene.solver
    nodes, dt, tol = solver.nodes, float(solver.dt), float(solver.newton.tol)
    levels, base_theta, failed = [], np.asarray(theta, float), []
    plan = [("tolerance", nodes, dt, tol * TOL_FACTOR)]
    plan += [("grid", nodes * 2**k, dt / 2**k, tol * TOL_FACTOR) for k in range(1, max_levels + 1)]
    for what, n, h, tl in plan:
        t0 = time.perf_counter()
        if progress is not None:
            progress(f"refit with {n} nodes, dt {h:.3g} s, Newton tolerance {tl:.0e} (discretisation error) ...")
        fine = problem.refined(nodes=n, dt=h, tol=tl)
        try:
            th, cost, it = chord_refit(fine, base_theta, J, window_ends if what == "grid" else (None,))
        except FitError as e:  # the fit's answer stands; the refit's failure is reported with it
            failed.append(f"the refit with {n} nodes, dt {h:.3g} s, tolerance {tl:.0e} failed ({e})")
            break
        chi2_here = 2 * cost / max(m, 1)
        if chi2_here > WORSE * chi2:  # a finer model fits worse than the coarse one: a wrong minimum
            failed.append(
                f"the refit with {n} nodes, dt {h:.3g} s reached a reduced chi-square of {chi2_here:.3g} against the fit's "
                f"{chi2:.3g}: it did not find that grid's optimum, so its discretisation error is not measured"
            )
            break
        move = (th - base_theta) / np.maximum(se_theta * np.sqrt(chi2_here / chi2), 1e-300)
        levels.append(Level(what, n, h, tl, th, move, chi2_here, it, time.perf_counter() - t0, fine))
        if progress is not None:
            progress(f"  largest move {np.max(np.abs(move)):.3g} SE, reduced chi-square {levels[-1].chi2:.4g}")
        if what == "tolerance":
            continue  # the grid refinements start from the fit's own optimum and tolerance
        base_theta = th
        if np.max(np.abs(move)) <= THIRD:
            break
    return levels, failed


def _difference(a: dict, b: dict) -> dict:
    return {k: (np.abs(a[k] - b[k]).tolist() if a[k].size > 1 else float(abs(a[k] - b[k])[0])) for k in a}


def report(problem, theta, J, result, max_levels: int = 2, progress=None, window_ends=(None,)):
    """``result`` (the `fit.Result` of ``problem`` at ``theta``, Jacobian ``J``) with the values
    of the finest model evaluated by `refine`, their discretisation and tolerance errors, the
    model they come from and the refits made; its message says when the last refinement still
    moved a value by more than a third of its standard error."""
    levels, failed = refine(
        problem, theta, J, standard_errors_theta(J, result.loss), max_levels, progress, result.loss, window_ends
    )
    message = " ".join([result.message, *failed]).strip()
    if len(levels) < 2:  # no grid refinement came through: the fit's own values, no error measured
        return dataclasses.replace(result, refinements=[lv.to_json() for lv in levels], message=message)
    at_fit = problem.reported(theta)
    tol, grids = levels[0], levels[1:]
    coarse = grids[-2] if len(grids) > 1 else None
    before = at_fit if coarse is None else coarse.problem.reported(coarse.theta)
    finest = grids[-1].problem.reported(grids[-1].theta)
    values = _plain(finest)
    noise = np.sqrt(grids[-1].chi2 / result.loss)  # the residuals' scale on the finest grid vs the fit's
    worst = float(np.max(np.abs(grids[-1].move_se)))
    if worst > THIRD:
        label = problem.labels()[int(np.argmax(np.abs(grids[-1].move_se)))]
        message = (f"{message} " if message else "") + (
            f"the last grid refinement (to {grids[-1].nodes} nodes, dt {grids[-1].dt:.3g} s) still moved {label} by "
            f"{worst:.2g} standard errors (more than {THIRD:.2f}): the discretisation error is not negligible; "
            "a finer [solver] grid in the sidecar would settle it"
        )
    return dataclasses.replace(
        result,
        values=values,
        standard_errors={
            k: (np.asarray(e) * noise).tolist() if np.size(e) > 1 else float(e) * noise for k, e in result.standard_errors.items()
        },
        sigma=[s * float(noise) for s in result.sigma],
        discretisation_errors=_difference(finest, before),
        tolerance_errors=_difference(tol.problem.reported(tol.theta), at_fit),
        model=dict(nodes=grids[-1].nodes, dt=grids[-1].dt, tol=grids[-1].tol),
        refinements=[lv.to_json() for lv in levels],
        message=message,
    )
