r"""The discretisation error of a fitted answer: refit on a finer model and see how far it moves.

The standard errors say how well the noise pins the parameters of *this* model, which is itself
an approximation (N nodes, a time step dt, a Newton tolerance); reality has no grid. After the
fit the recording is refitted from the optimum:

1. with the Newton tolerance a tenth of the fit's (same grid): the solver-tolerance error;
2. **space**: with twice the nodes at the fit's dt (and the tenth of the tolerance): the move
   of each parameter is the spatial discretisation error of the coarser answer. While the move
   of a parameter the fit is for (damping, lengths: `Problem.measured`; the push and the
   camera are nuisance parameters, their errors reported all the same) exceeds a third of its
   standard error, the finer answer is taken and the nodes doubled again, up to
   ``max_levels`` times;
3. **time**: then with half the dt, the same way, at the nodes step 2 settled on: the coarser
   grid of the last space refit when its move was below a third of an SE or its extrapolation
   settled (below: that move is the coarser grid's space error, so the finer grid need not be
   paid for again at every dt), else the finest.

The two are refined apart because one usually dominates, and each refit costs in proportion
to nodes / dt: on the Triskele push-release (modes at 70-155 Hz, N 10, dt 0.5 ms) halving dt
moved the lengths by up to 137 um and doubling N by up to 18 um.

The reported values are those of the last time refit (or the extrapolations below), and the
discretisation error beside each combines the last space move and the last time move in
quadrature (for a convergent scheme, each about the error of the coarser of its two grids, so
a bound on the finer's); if a last move of a measured parameter still exceeds a third of its
standard error, the result says which.

**Standard errors.** The fit's noise levels come from its own residuals, which hold the
coarse grid's model error too, and not in the same measure in each column (the position's can
be mostly model error, the angle's mostly noise). Each refit measures them again, per column,
on its own residuals, and its standard errors are those of the fit's estimator (which weighted
the columns with the coarse levels) under these levels: the sandwich covariance
(`noise_and_errors`). Each move is measured in the finer model's, and the finest model's are
the ones reported. A single rescaling by the reduced chi-square put the positions' noise at 7.1
nm and the angle's at 1.3 urad on `triskele_actuator_step_r1`, where it is 2 nm and 2 urad
(measured on the finest refit: 2.1 nm, 2.0 urad), so its standard errors were up to 3 times too
wide and the moves looked that much smaller.

**Extrapolation in dt.** BDF-alpha is second order, so once two successive time moves shrink at
that order (observed order log2(|m1| / |m2|) within ``ORDER_BAND`` of 2, over the measured
parameters in standard errors) the answer at dt -> 0 is Richardson's v2 + m2/3, with the error
estimate |4 m2 - m1|/3: the difference between the extrapolations from the last two pairs of
grids (zero only where the chain is exactly second order; it then bounds the error of the
coarser extrapolation, an order above the last move). It is used where it is below the last
move, and it is what the time chain must bring below a third of a standard error. On
`cantilever_independent` (another code's converged recording; fit at N 20, dt 1 ms) the length's
time moves were 288 and 73 standard errors down to dt 0.25 ms, at observed order 1.98: the
finest grid's length lies 24 standard errors from the truth, the extrapolation (space
extrapolated too) 0.22; reaching a third of one by halving alone would take dt near 10 us.

**Extrapolation in space.** RK4 is fourth order in the nodes, so where the last two space moves
shrink at that order (within ``ORDER_BAND`` of 4) the coarser grid's space error is 16 m2 / 15
(the last move and the rest of the series), uncertain by |16 m2 - m1| / 15; where that is below
a third of an SE the space chain has settled, the time chain refines at the coarser nodes of the
last move, and the correction is added to its values (the two errors add independently to
leading order, as their combination in quadrature assumes). On the random-truth Triskele
push-release r2 (truth tau 0.67 ms, fit N 10) the space moves were 45.7, 8.99 and 0.571 SE to
80 nodes, at order 3.98 for the last two: extrapolated, the time chain runs at 40 nodes, half
the cost of 80 at every dt.

The first refit of each chain goes over the whole recording at once where the fit's Jacobian
puts the finer grid's optimum within reach of the coarse answer (its Gauss-Newton step from
there, on the finer grid's residuals, is ``NEAR_SE`` standard errors at most, all unknowns
together); else, or where that refit fails or fits more than ``WORSE`` times worse than the fit,
through the fit's windows of growing length, as the coarse answer can be cycles of phase off the
finer grid's over a whole recording. On `triskele_push_release_r1` that step was 2.2 standard
errors to 20 nodes (the move 0.23): that refit took 10 residuals (that step's included) and 3
Jacobians of the whole recording, where through the windows it took 50 residuals of windows, 11
of the whole and 3 Jacobians (in 0.75 of the wall time, the tolerance refit included), to the
same values within 0.006 standard errors. The step was 462 standard errors to dt 0.25 ms (the
move 12.8): over the whole recording at once from there, that time refit ended after four of its
Jacobians at a reduced chi-square of 0.930, where through the windows it reaches 0.854. Through
the windows a refit holds the fit's Jacobian (a chord method: Levenberg-Marquardt with the
coarse model's Jacobian, each step taken only where it lowers the cost), so an iteration costs
one rollout of the window and no tangents.
Over the whole recording it holds that Jacobian for ``HELD_ITER`` iterations, then takes the
finer model's own where they stopped: the refit ends there if its Gauss-Newton decrement puts
the parameters within ``STILL`` standard errors of the optimum, else goes on by
Levenberg-Marquardt with the finer model's Jacobian at every step, up to ``REFRESH`` Jacobians
in all, and a refit that stops farther than ``STILL`` from its optimum is reported, its
distance (the decrement's, in standard errors) added to the error of every move and
extrapolation it enters (a value that far off its optimum moves that much less or more), and
in a contest the loss it would reach there, by its decrement, is compared. The coarse
Jacobian held to the end would stop at its own fixed point (J_held^T r = 0), which is the finer
grid's optimum only where the two grids' Jacobians agree, and where a finer dt moves the phase
of a long recording's modes they do not: on `triskele_push_release_r1` from dt 0.25 to 0.125 ms
(20 nodes) the held chord crawled through 40 iterations (81 rollouts, 254 s) to a point the
finer model's Jacobian put 0.47 standard errors from its optimum (decrement 0.73). Holding the
finer model's Jacobian once taken is no cure either: a recording's residuals are its noise,
whose curvature term (sum r_i Hess r_i, `least_squares.levenberg_marquardt`) is as large as the
Gauss-Newton curvature along the nearly collinear unknowns, so each held Jacobian's fixed point
lies only part of the way to the optimum. On `triskele_actuator_step_r2` at 40 nodes (dt 0.5 ms)
the refit that took one Jacobian and held it stopped 0.20 standard errors (in the decrement's
metric) from its optimum, where its move from 20 nodes was 0.64 and RK4's order put the next at
0.04; holding each of three Jacobians in turn came to 0.20, 0.13 and 0.09, a Jacobian at every
step with the curvature's secant estimate to 0.084 and 0.040 (four Jacobians in all). On the
fit's own grid (the tolerance refit) the fit's Jacobian is the model's and is held throughout. A
later refit of a chain starts where the chain's order predicts the optimum (the last move shrunk
by 2**order) and fits the whole recording at once, falling back to the windows from the coarser
optimum if that fails. A refit that ends at a reduced chi-square more than ``WORSE`` times the
fit's found no optimum: it is reported as failed and its values are not used.

**Two cores.** A refit runs one program at a time, on one core. Two refits whose starts are
known in advance run side by side (`identify.threads`): the first time refit (the fit's nodes,
half its dt, from its answer) beside the tolerance and space refits, used where the space chain
settles at its first refit (else dropped: the time chain starts on a finer grid); and the
start's refit on the grid the time chain will end on (below) beside the chain's last refit,
used where the start then contests the answer there. A refit run ahead keeps its progress lines
until it is used, so that they do not interleave with the others'.

**The internal grid.** pcrjax refines a rod's internal grid (``solver.grid_nodes``, nodes times
``solver.refine``) as dt shrinks, to resolve the dynamic step's boundary layer: the cantilever
at 20 nodes runs on 40 from dt 0.25 ms, the Triskele at 10 nodes on 20 from dt 62.5 us. A time
refit whose internal grid is finer than its parent's measured a space move too; the notes say
so. Where the space chain settled, its estimate of the space error left at the time chain's
nodes (the extrapolation's, or its last move's at RK4's order), scaled to each level's internal
grid at that order, is added to every time level's values before their moves are taken, so
that move is taken out. An extrapolated correction stays in the reported values and is counted
once (added unscaled, it would be counted twice); an estimate from a last move alone (one below a
third of an SE) only takes the space part out of the time moves, and the values keep the space
error of the finest internal grid, which the reported space move bounds. On
`triskele_push_release_r1` the space chain settled at its first refit (0.23 SE) and the time
chain's internal grid doubled at dt 62.5 us: that move held 15/16 of the 10-node space error.

**Rival basins.** The fit's grid can prefer another basin of the loss than finer grids do, and
the chains, each refit starting from the coarser answer, then converge cleanly to the wrong one.
On `triskele_push_release_r1` (truth simulated on a grid converged at the noise) the start put the lengths 12 um
from the truth; the fit's grid (10 nodes, dt 0.5 ms) walked 360 um away to a basin whose time
moves (11.9, 2.8, 0.58 SE down to dt 62.5 us) shrink at order 2.1-2.3, and answered 13 SE from
the truth; yet on the finest grid the truth, push and camera fitted, had a loss 4.5 below that
answer's (at dt 0.25 ms, 23 above), with a barrier between (the loss 120 higher a fifth of the
way across). So after the chains the start (where `fit.modal_start` put the measured values,
with the answer's push and camera) contests the answer on the finest grid when it lies more than
``RIVAL_SE`` standard errors from the fit's answer on the fit's grid (the fit left the start's
basin) and from the answer on the finest grid, and, push and camera refitted, within ``WORSE``
times the answer's loss: it is refitted there like a chain's later refit, over the whole
recording at once from the start (the screen matched its phase over every frame), holding the fit's model's
Jacobian at the start and then taking the finest model's own; only if that ends worse than
``WORSE`` through the fit's windows. An optimum whose loss is lower by more than
``CLOSE`` takes the answer over, its time error measured by refits of its own at 2 and 4 times
the finest dt (extrapolated like a chain's); one within ``CLOSE`` is reported as a second
optimum the recording cannot tell apart.
On r1 the start's optimum on the finest grid had a loss 6.1 below the answer's and lies 0.14
standard errors from the truth's lengths (tau 0.99 SE), its own time moves at most 0.49 SE; the
contest took 934 s (through the windows with the fit's Jacobian held: 2448 s, to a loss 0.6
higher). Where the fit ended near the start, the chains already followed the start's basin: on a
noise draw of r1's truth simulated on the fit's grid, whose fit ended 0.3 standard errors from the
start, a contest took 585 s of the 2340 s run (the time chain had moved the answer 11 standard
errors) and refitted the start to an optimum worse than the answer's.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np

from . import result as result_module
from . import robust, threads
from .least_squares import FitError, decrement, levenberg_marquardt

THIRD = 1.0 / 3.0  # a move below this fraction of the standard error is negligible beside it
TOL_FACTOR = 0.1
CHORD_ITER = 20  # Levenberg-Marquardt iterations per window
HELD_ITER = 5  # iterations over the whole recording with the fit's Jacobian, before the refined model's own
REFRESH = 4  # the refined model's Jacobians a refit takes over the whole recording, at most
STILL = 0.05  # a refit ends when its linearisation puts the parameters this many standard errors from its optimum
WORSE = 2.0  # a refit whose reduced chi-square is this many times the fit's did not find the optimum
ORDER = {"space": 4, "time": 2}  # RK4 in space, BDF-alpha in time: a move shrinks by 2**order per halving
ORDER_BAND = 0.5  # moves shrinking at an observed order within this of the scheme's are extrapolated
NEAR_SE = 3.0  # a first refit whose Gauss-Newton step (fit's Jacobian, sqrt(2 decrement)) is this small needs no windows
RIVAL_SE = 3.0  # a start this many standard errors from the answer (in a measured parameter) may lie in another basin
CLOSE = 2.0  # optima whose losses differ by less (chi-square 4: two standard deviations) fit a recording equally well


def extrapolation(prev, last, measured):
    """(usable, error) of Richardson's extrapolation from two successive refits `Level` ``prev``
    and ``last`` of one chain (their ``what``: dt -> 0 at BDF-alpha's order 2, or nodes -> inf
    at RK4's 4), the error in ``last``'s standard errors per parameter: usable where the
    measured parameters' moves shrink at an observed order within ``ORDER_BAND`` of the scheme's
    p and the error estimate of the extrapolated value is below the last move. The estimate is
    |2**p m2 - m1| / (2**p - 1) (the difference of the extrapolations from the last two pairs of
    grids; module doc) plus what the two refits' distances from their optima (`_off`) can move
    the extrapolated value, (2**p d_last + d_prev) / (2**p - 1)."""
    # each move is in the standard errors of its own model (its noise levels): m1 goes into
    # last's, or a 2 % difference in the scales leaves several SE in 4 m2 - m1
    m1 = np.asarray(prev.move_se, float) * prev.se / last.se
    m2 = np.asarray(last.move_se, float)
    k = 2.0 ** ORDER[last.what]
    error = np.abs(k * m2 - m1) / (k - 1.0) + _extrapolation_off(prev, last)
    a, b = np.linalg.norm(m1[measured]), np.linalg.norm(m2[measured])
    if not (a > 0 and b > 0):
        return False, error
    order = np.log2(a / b)
    shrinks = abs(order - ORDER[last.what]) <= ORDER_BAND
    return bool(shrinks and np.max(error[measured]) < np.max(np.abs(m2[measured]))), error


@dataclasses.dataclass(frozen=True)
class Level:
    """One refit: its model (nodes, dt, tol), the values there, their move in standard errors
    ``se`` (per label) from the model it refines (``parent``: an index into the levels; None:
    the fit's own), the reduced chi-square, the noise levels measured on its residuals
    (`noise_and_errors`: ``se`` are the fit's estimator's standard errors under them) and the
    chord iterations."""

    what: str
    nodes: int
    dt: float
    tol: float
    theta: np.ndarray
    move_se: np.ndarray
    chi2: float
    iterations: int
    wall_s: float
    noise: np.ndarray
    se: np.ndarray
    problem: object = dataclasses.field(repr=False, compare=False, default=None)
    parent: int | None = None
    jacobians: int = 0
    distance: float | None = None  # from this model's optimum, in standard errors (the decrement's; None: not measured)

    def to_json(self) -> dict:
        return dict(
            refit=self.what,
            nodes=self.nodes,
            internal_nodes=None if self.problem is None else self.problem.scene.solver.grid_nodes,
            dt=self.dt,
            tol=self.tol,
            largest_move_se=float(np.max(np.abs(self.move_se))),
            reduced_chi2=self.chi2,
            noise=[float(self.noise[0]), float(self.noise[2])],
            chord_iterations=self.iterations,
            jacobians=self.jacobians,
            distance_to_optimum_se=self.distance,
            wall_s=round(self.wall_s, 1),
            values={} if self.problem is None else _plain(self.problem.reported(self.theta)),
        )


def _off(level) -> float:
    """How far ``level``'s refit stopped from its model's optimum, in standard errors (0 for
    None, the fit's own optimum, and where it was not measured): its values, and a move from or
    to them, are uncertain by as much."""
    return 0.0 if level is None or level.distance is None else float(level.distance)


def _move_off(levels, level) -> float:
    """What the distances from their optima (`_off`) of ``level`` and of its parent in
    ``levels`` (None: the fit's own optimum) leave uncertain in ``level``'s move."""
    return _off(level) + _off(None if level.parent is None else levels[level.parent])


def _extrapolation_off(prev, last) -> float:
    """What the distances of ``prev`` and ``last`` (`_off`) can move Richardson's extrapolation
    from them, (2**p d_last + d_prev) / (2**p - 1)."""
    k = 2.0 ** ORDER[last.what]
    return (k * _off(last) + _off(prev)) / (k - 1.0)


def _grid(problem, levels, i) -> int:
    """The internal grid's nodes of level ``i`` of ``levels`` (None: the fit ``problem``'s)."""
    return (problem if i is None else levels[i].problem).scene.solver.grid_nodes


def _left_on(g0, g) -> float:
    """The fraction of the space error left on an internal grid of ``g0`` nodes that is left on
    one of ``g`` (RK4's order)."""
    return (g0 / g) ** ORDER["space"]


def _space_error(move):
    """The coarser grid's space error that a space refinement's ``move`` (finer less coarser)
    measures: the error shrinks 2**4-fold per halving (RK4's order), so it is the move times 16/15."""
    k = 2.0 ** ORDER["space"]
    return move * k / (k - 1.0)


def _time_move(lv, base, left, i, parent):
    """Time refit ``lv`` (level ``i``, its parent level ``parent`` at ``base``) with its move in
    standard errors taken without the space move of a refined internal grid: each side's values
    corrected by the space error ``left`` on its own internal grid."""
    return dataclasses.replace(lv, move_se=(lv.theta + left(i) - base - left(parent)) / lv.se)


def _plain(values: dict) -> dict:
    """Reported values as JSON numbers (scalars as floats, vectors as lists)."""
    out = {}
    for k, v in values.items():
        v = np.asarray(v, float).ravel()
        out[k] = v.tolist() if v.size > 1 else float(v[0])
    return out


def _iterations(progress, stage):
    """Levenberg-Marquardt's ``progress(i, loss, step)`` as the fit's ``progress(stage, i, loss,
    step)``, the stage indented under its refit's line (None: none)."""
    if progress is None:
        return None
    return lambda i, cost, step: progress(f"  {stage}", i, cost, step)


def _messages(progress):
    """The fit's ``progress(stage, i, loss, step)`` as ``say(message)``, a line without a loss."""
    if progress is None:
        return lambda msg: None
    return lambda msg: progress(msg, 0, None, 0.0)


def _held(problem, theta, J, t_end, max_iter, gain=None, r0=None, progress=None):
    """(theta, residuals, iterations) of Levenberg-Marquardt on ``problem``'s residuals over the
    frames up to ``t_end`` from ``theta`` (where they are ``r0``, if known), with the Jacobian
    ``J`` held (each step taken only where it lowers the cost), until the Gauss-Newton decrement
    is below ``gain`` (None: a millionth of the cost); each iteration told to ``progress``.
    Raises `FitError` where the rollout at ``theta`` fails."""
    rows = np.repeat(np.asarray(problem.window(t_end)[0]) > 0, 3)
    held = J * rows[:, None]
    theta = np.asarray(theta, float)
    last = {"x": theta, "r": np.asarray(problem.residual(theta, t_end)) if r0 is None else np.asarray(r0)}
    if not np.all(np.isfinite(last["r"])):
        solver = problem.scene.solver
        raise FitError(f"the model with {solver.nodes} nodes, dt {float(solver.dt):.3g} s does not converge")

    def residual(x):
        x = np.asarray(x, float)
        if not np.array_equal(last["x"], x):  # the accepted trial's rollout is reused
            last["x"], last["r"] = x, np.asarray(problem.residual(x, t_end))
        return last["r"]

    cost = 0.5 * float(last["r"] @ last["r"])
    ftol = 1e-6 if gain is None else gain / max(cost, 1e-300)
    theta, _, r, it, _, _ = levenberg_marquardt(
        residual, lambda x: (residual(x), held), theta, max_iter, ftol=ftol, max_step=problem.max_step, huber=problem.huber,
        progress=_iterations(progress, "whole recording, held Jacobian" if t_end is None else f"window {t_end:.3g} s"),
    )  # fmt: skip
    return theta, r, it


def chord_refit(
    problem, theta, J, window_ends=(None,), max_iter: int = CHORD_ITER, refresh: int = REFRESH, r0=None, progress=None
):
    """(theta, residuals, iterations, Jacobians, distance) minimising ``problem``'s residuals over
    the whole recording from ``theta``. Over the windows ending at ``window_ends`` before the
    last (the fit's continuation: a coarse grid's answer can be cycles of phase off over a long
    recording, as the Triskele's 150 Hz modes are at dt 0.5 ms), each from the previous one's
    answer, the Jacobian ``J`` (of another discretisation of the same problem) is held; over the
    whole recording too, for ``HELD_ITER`` iterations. Then the refined model's own Jacobian is
    taken, and while its Gauss-Newton decrement puts the parameters more than ``STILL`` standard
    errors from the optimum, Levenberg-Marquardt goes on with the refined model's Jacobian at
    every step, ``refresh`` Jacobians in all (0: ``J`` held to the end). ``distance``: that
    decrement as standard errors, sqrt(2 decrement), at the answer (None where ``J`` was held
    to the end). ``r0``: the residuals at ``theta`` over the whole recording, if known (used
    where there are no windows). ``progress(stage, i, loss, step)`` is told each iteration.
    Raises `FitError` where the refined model's rollout fails."""
    total = 0
    for t_end in window_ends[:-1]:
        theta, _, it = _held(problem, theta, J, t_end, max_iter, progress=progress)
        total += it
    still = 0.5 * STILL**2  # the decrement of a parameter STILL standard errors off a quadratic optimum
    # the held Jacobian first (cheap iterations, where it is close), then the model's own
    known = r0 if len(window_ends) == 1 else None  # the residuals at theta, where no window came first
    theta, r, it = _held(problem, theta, J, None, HELD_ITER if refresh else max_iter, still, known, progress)
    total += it
    if not refresh:
        return theta, r, total, 0, None
    r, J = (np.asarray(a) for a in problem.residual_and_jacobian(theta))
    jacobians = 1

    def own(x):
        nonlocal jacobians
        jacobians += 1
        return problem.residual_and_jacobian(x)

    # each accepted step takes the model's Jacobian again, so that the secant estimate of the
    # noise's curvature term builds up and the steps head for the optimum itself
    theta, J, r, it, _, _ = levenberg_marquardt(
        problem.residual, own, theta, refresh - 1, ftol=still / max(0.5 * float(r @ r), 1e-300),
        max_step=problem.max_step, initial=(r, J), lam0=1e-9, huber=problem.huber,
        progress=_iterations(progress, "whole recording, own Jacobian"),
    )  # fmt: skip
    return theta, np.asarray(r), total + it, jacobians, float(np.sqrt(2.0 * decrement(J, r, problem.huber)))


def _near(fine, theta, J):
    """(whether the refined model ``fine``'s optimum lies within the linearisation's reach of
    ``theta``, the residuals there over the whole recording): the Gauss-Newton step of the
    Jacobian ``J`` (the fit's) from ``theta`` on ``fine``'s residuals, sqrt(2 decrement) (all
    unknowns together, in standard errors), is ``NEAR_SE`` at most, so a refit needs no windows
    (the fit's continuation against a loss with a minimum every cycle). False where the rollout
    at ``theta`` fails."""
    r = np.asarray(fine.residual(theta))
    return bool(np.all(np.isfinite(r)) and np.sqrt(2.0 * decrement(J, r, fine.huber)) <= NEAR_SE), r


def _attempt(fine, tries, J, m, chi2, refresh=REFRESH, progress=None):
    """(theta, residuals, iterations, Jacobians, distance) of the first `chord_refit` of ``fine`` from
    ``tries`` ((start, window ends, residuals at start over the whole recording or None), in
    order) that ends within ``WORSE`` times the fit's reduced chi-square ``chi2`` (``m`` degrees
    of freedom); raises `FitError` saying why the last did not (a finer model that fits far
    worse than the coarse one: a wrong minimum). ``progress`` is told each iteration."""
    iterations = jacobians = 0
    for start, ends, r0 in tries:
        try:
            th, r, it, jac, distance = chord_refit(fine, start, J, ends, refresh=refresh, r0=r0, progress=progress)
        except FitError as e:
            why = f"failed ({e})"
            continue
        iterations, jacobians = iterations + it, jacobians + jac
        cost = 0.5 * float(r @ r)
        if 2 * cost / max(m, 1) <= WORSE * chi2:
            return th, r, iterations, jacobians, distance
        reached = f"reached a reduced chi-square of {2 * cost / max(m, 1):.3g} against the fit's {chi2:.3g}"
        if distance is not None and distance <= STILL:  # a minimum of the finer model, yet a far worse fit
            why = (
                f"{reached} at a minimum of that model ({distance:.2g} standard errors from it): a wrong minimum, or a "
                "recording that the fit's own grid made"
            )
        else:
            why = f"{reached}: it did not find that model's optimum"
    raise FitError(why)


def noise_and_errors(problem, J, fine, r, p: int) -> tuple[np.ndarray, np.ndarray]:
    """(noise levels (m, m, rad), standard errors of theta) measured on the refined model
    ``fine``'s residuals ``r`` over the whole recording (``p`` unknowns), the frames thrown off
    left out as in the fit: the levels are the residuals' RMS per column, the errors those of the
    fit's estimator (``problem`` at its Jacobian ``J``, weighted with its own levels) under them
    (`result.noise_covariance`). The fit's own levels come from its grid's residuals, which carry
    that grid's model error: on `triskele_actuator_step_r1` they were 13 nm and 2.4 urad at 10
    nodes, where the noise is 2 nm and 2 urad and the finest model's residuals 2.1 nm and 2.0
    urad."""
    res = np.asarray(robust.unhuber(r, fine.huber)).reshape(-1, 3) * fine.sigma
    m = fine.counted(None)
    noise = robust.clean_noise_levels(res, fine.keep) * np.sqrt(m / max(m - p, 1))
    cov = result_module.noise_covariance(problem, J, noise)
    return noise, np.sqrt(np.maximum(np.diag(cov), 1e-300))


def _note_stopped(notes, level):
    """A note appended where ``level``'s refit stopped more than ``STILL`` standard errors from
    its model's optimum (its Jacobians spent)."""
    if _off(level) > STILL:
        notes.append(
            f"the refit with {level.nodes} nodes, dt {level.dt:.3g} s stopped {level.distance:.2g} standard errors from that "
            f"model's optimum after {level.jacobians} Jacobians (its move is uncertain by as much)"
        )


def _announce(what, n, h, tol) -> str:
    return f"refit with {n} nodes, dt {h:.3g} s, Newton tolerance {tol:.0e} ({what} error) ..."


class _Cancelled(Exception):
    """Raised in a refit run ahead (`_Ahead`) that is no longer wanted, at its next iteration."""


class _Ahead:
    """``job(progress)`` on a thread of its own while the caller goes on: its progress is kept and
    told to ``progress`` when its result is taken (so that it does not interleave with the
    caller's); `cancel` stops it at its next iteration, without waiting for it."""

    def __init__(self, job, progress, grid=None):
        self.grid = grid  # (nodes, dt) of the refit, where it matters to the caller
        self._told, self._progress, self._outcome = [], progress, None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(job,), daemon=True)
        self._thread.start()

    def _tell(self, *line):
        if self._stop.is_set():
            raise _Cancelled
        self._told.append(line)

    def _run(self, job):
        try:
            self._outcome = (job(self._tell), None)
        except _Cancelled:
            pass
        except Exception as e:  # raised in the caller, where the result is taken
            self._outcome = (None, e)

    def result(self):
        self._thread.join()
        value, error = self._outcome
        if error is not None:
            raise error
        for line in self._told if self._progress is not None else ():
            self._progress(*line)
        return value

    def cancel(self):
        self._stop.set()


def _drop(ahead):
    """Cancel ``ahead`` (an `_Ahead` or None); returns None."""
    if ahead is not None:
        ahead.cancel()
    return None


def refine(problem, theta, J, max_levels: int = 2, progress=None, chi2: float = 1.0, window_ends=(None,), rivals=()):
    """(the `Level` list: the tolerance refit first, then the space refits, then the time
    refits; the notes: a refit that failed ends the list) for the fit ``problem`` at its
    optimum ``theta`` (Jacobian ``J``, reduced chi-square ``chi2``). Space: twice the nodes at
    the fit's dt, while the move of a measured parameter exceeds a third of a standard error, up
    to ``max_levels`` times; then time: half the dt, the same way, at the coarser grid of a
    space move below a third of an SE (else at the finest). Each move is in the standard errors
    of the finer model's noise levels (`noise_and_errors`). Then each start in ``rivals``
    (theta) that lies in another basin contests the answer on the finest grid (`_contest`).
    ``progress(stage, iteration, loss, step)`` as the fit's (loss None: a line of its own). The
    failures and the contests' findings are returned as notes."""
    m = problem.counted(None) - theta.size
    solver = problem.scene.solver
    nodes, dt, tl = solver.nodes, float(solver.dt), float(solver.newton.tol) * TOL_FACTOR
    levels, notes = [], []
    say = _messages(progress)

    def attempt(what, n, h, base, windows, predicted=None, progress=progress):
        """("ok", what `record` needs) or ("failed", the note saying why) of the refit to ``n``
        nodes and ``dt`` h from ``base``."""
        t0 = time.perf_counter()
        fine = problem.refined(nodes=n, dt=h, tol=tl)
        # over the whole recording at once from the predicted optimum, or from the coarser one
        # where the fit's Jacobian puts this grid's optimum within reach (`_near`); else (or if
        # that fails) from the coarser optimum through the windows; on the fit's own grid (a
        # tighter tolerance) the fit's Jacobian is the model's
        tries = [(predicted, (None,), None)] if predicted is not None else []
        if not tries and len(windows) > 1:
            near, r0 = _near(fine, base, J)
            if near:
                tries.append((base, (None,), r0))
        tries.append((base, windows, None))
        try:
            th, r, iterations, jacobians, distance = _attempt(
                fine, tries, J, m, chi2, 0 if what == "tolerance" else REFRESH, progress
            )
        except FitError as e:  # the fit's answer stands; the refit's failure is reported with it
            why = f"the refit with {n} nodes, dt {h:.3g} s, tolerance {tl:.0e} {e}, so its {what} error is not measured"
            return "failed", why
        noise, se = noise_and_errors(problem, J, fine, r, theta.size)
        return "ok", (fine, th, r, iterations, jacobians, distance, noise, se, time.perf_counter() - t0)

    def record(what, n, h, base, parent, outcome):
        """The refit's `Level` appended (None where it failed: its note appended)."""
        kind, found = outcome
        if kind == "failed":
            notes.append(found)
            return None
        fine, th, r, iterations, jacobians, distance, noise, se, wall = found
        levels.append(
            Level(what, n, h, tl, th, (th - base) / se, float(r @ r) / max(m, 1), iterations, wall, noise, se,
                  fine, parent, jacobians, distance)
        )  # fmt: skip
        _note_stopped(notes, levels[-1])
        say(f"  largest move {np.max(np.abs(levels[-1].move_se)):.3g} SE, reduced chi-square {levels[-1].chi2:.4g}")
        return levels[-1]

    def refit(what, n, h, base, windows, parent, predicted=None):
        say(_announce(what, n, h, tl))
        return record(what, n, h, base, parent, attempt(what, n, h, base, windows, predicted))

    def grid(i):
        return _grid(problem, levels, i)

    base = np.asarray(theta, float)
    # The first time refit (half the fit's dt, at its nodes, from its answer) is the one the time
    # chain starts with wherever the space chain settles at its first refit, as it mostly does:
    # it runs beside the tolerance and space refits, on the core they leave idle.
    ahead = None
    if max_levels > 0 and threads.WORKERS > 1:
        ahead = _Ahead(lambda told, start=base: attempt("time", nodes, dt / 2, start, window_ends, progress=told), progress)
        say(_announce("time", nodes, dt / 2, tl) + " (beside the refits below; its progress when they are done)")
    if refit("tolerance", nodes, dt, base, (None,), None) is None:
        _drop(ahead)
        return levels, notes
    n, h, parent = nodes, dt, None  # the grid refinements start from the fit's own optimum
    # the space error left at the time chain's nodes, where the space chain settled (theta: its
    # last move or that move's extrapolation, at RK4's order; zero where it did not settle), on
    # their internal grid of ``g0`` nodes: RK4's order scales it to a finer internal grid, which a
    # time refit can bring (`report` does the same)
    space_error, g0 = np.zeros_like(base), None

    def left(i):
        return space_error if g0 is None else space_error * _left_on(g0, grid(i))

    for what in ("space", "time"):
        step, prev, chain_start = None, None, len(levels)  # the chain's last move (theta), its last level, its first
        for _ in range(max_levels):
            predicted = None if step is None else base + step / 2 ** ORDER[what]
            if what == "time" and ahead is not None and parent is None:  # the refit that ran beside the others
                say(_announce(what, n, h / 2, tl) + " (ran beside the refits above)")
                lv, ahead = record(what, n, h / 2, base, parent, ahead.result()), None
            else:
                lv = refit(what, *((2 * n, h) if what == "space" else (n, h / 2)), base, window_ends, parent, predicted)
            if lv is None:
                _drop(ahead)
                return levels, notes
            if what == "time" and grid(len(levels) - 1) != grid(parent):
                # the time move without the space move it holds: the values corrected for the
                # space error left on each grid
                lv = levels[-1] = _time_move(lv, base, left, len(levels) - 1, parent)
                notes.append(
                    f"the time refit to dt {lv.dt:.3g} s also refined the internal grid from {grid(parent)} to "
                    f"{grid(len(levels) - 1)} nodes (pcrjax resolves the dynamic step's boundary layer, which narrows as dt "
                    "shrinks), so its move holds a space refinement too"
                    + (", taken out by the space chain's estimate of it" if g0 is not None else "")
                )
            settled = np.max(np.abs(lv.move_se[problem.measured])) + _move_off(levels, lv) <= THIRD
            usable = False
            if prev is not None:
                usable, error = extrapolation(prev, lv, problem.measured)
                settled = settled or (usable and np.max(error[problem.measured]) <= THIRD)
            prev = lv
            # the coarser grid's space error is this move (or its extrapolation): time refines there
            if settled and what == "space":
                space_error, g0 = _space_error(lv.theta - base), grid(parent)
                break
            if what == "space":  # the time chain will start on a finer grid than the refit beside
                ahead = _drop(ahead)
            n, h, step, base, parent = lv.nodes, lv.dt, lv.theta - base, lv.theta, len(levels) - 1
            if settled:
                break
            if what == "time" and len(levels) - chain_start == max_levels - 1:  # the next refit is the chain's last
                ahead = _rival_ahead(problem, levels, rivals, lv, tl, chi2, m, window_ends, progress)
    for k, start in enumerate(rivals):
        contested = _contest(
            problem, levels, notes, np.asarray(start, float), J, chi2, m, progress, window_ends, left, ahead if k == 0 else None
        )
        if contested:
            break
    _drop(ahead)
    return levels, notes


def _away(problem, start, level) -> float:
    """The largest distance of ``start`` from ``level``'s values in a measured parameter, in the
    level's standard errors."""
    return float(np.max(np.abs((start - level.theta) / level.se)[problem.measured]))


def _rival(problem, fine, start, anchor, answer, chi2, m, window_ends, progress):
    """The refit of ``start`` on ``fine``'s grid (`_contest`): (kind, the loss after its push and
    camera are fitted, wall time, found). Its measured values are the start's, its push and camera
    ``anchor``'s (an answer's), fitted (`Problem.fit_linear`: from the sidecar's push and the first
    frame, the start's loss was 300x the answer's on r1). Kind "weak" where that loss is more than
    ``WORSE`` times ``answer`` (found None); "failed" where the refit fails (found: the note);
    else "ok", found (fine, theta, residuals, iterations, Jacobians, the fit model's Jacobian at
    the start)."""
    t0 = time.perf_counter()
    start, cost = fine.fit_linear(np.where(problem.measured, start, anchor))
    if not cost <= WORSE * answer:
        return "weak", cost, time.perf_counter() - t0, None
    held = np.asarray(problem.residual_and_jacobian(start)[1])
    # over the whole recording at once (the start is the modal screen's: phase-true), else through the windows
    tries = [(start, (None,), None)] + ([(start, window_ends, None)] if len(window_ends) > 1 else [])
    try:
        th, r, it, jac, distance = _attempt(fine, tries, held, m, chi2, progress=progress)
    except FitError as e:
        return "failed", cost, time.perf_counter() - t0, f"the refit from the start on the finest grid {e}"
    return "ok", cost, time.perf_counter() - t0, (fine, th, r, it, jac, distance, held)


def _rival_ahead(problem, levels, rivals, lv, tol, chi2, m, window_ends, progress):
    """`_rival` of the first of ``rivals`` on the grid that the time refit after ``lv`` will
    reach, run beside that refit (an `_Ahead`, or None): where the start lies more than
    ``RIVAL_SE`` standard errors from ``lv`` and from the fit (`_contest` contests only then)."""
    if not rivals or threads.WORKERS < 2:
        return None
    start = np.asarray(rivals[0], float)
    if min(_away(problem, start, lv), _away(problem, start, levels[0])) <= RIVAL_SE:
        return None
    n, h = lv.nodes, lv.dt / 2

    def job(told):
        fine = problem.refined(nodes=n, dt=h, tol=tol)
        return _rival(problem, fine, start, lv.theta, 0.5 * lv.chi2 * m, chi2, m, window_ends, told)

    _messages(progress)(
        f"the start lies in another basin than this answer: its refit with {n} nodes, dt {h:.3g} s runs beside the next"
    )
    return _Ahead(job, progress, grid=(n, h))


def _contest(problem, levels, notes, start, J, chi2, m, progress, window_ends, left=lambda i: 0.0, ahead=None) -> bool:
    """Whether ``start`` (theta: where the fit began) takes the answer over from the chain's
    (`refine`'s module text, "Rival basins"). It contests only where the fit's grid led more than
    ``RIVAL_SE`` standard errors away from it and the chain's answer lies that far from it too.
    Then on the finest grid its push and camera are fitted
    (`Problem.fit_linear`) and, unless it then fits more than ``WORSE`` times worse than the
    answer, it is refitted over the whole recording (`chord_refit` from the fit's model's Jacobian
    at it; through the windows if that ends more than ``WORSE`` times worse than the fit). That
    optimum is appended as a "rival" `Level`; if its loss is below the answer's by more than
    ``CLOSE``, its time error is measured by refits at 2 and 4 times the finest dt (a "rival"
    level at 4 dt, then two "time" levels, coarse to fine, that end the list; their moves have
    the space error ``left(i)`` on level i's internal grid taken out, as `refine`'s time moves).
    ``notes`` gets what was found; ``progress`` as `refine`'s."""
    say = _messages(progress)
    last = levels[-1]
    if last.what != "time":
        _drop(ahead)
        return False
    far = _away(problem, start, last)
    # where the fit ended within RIVAL_SE of the start (levels[0]: the fit's grid), the fit's grid
    # kept the start's basin and the chains followed that basin to the finest grid
    if far <= RIVAL_SE or _away(problem, start, levels[0]) <= RIVAL_SE:
        _drop(ahead)
        return False
    t0 = time.perf_counter()
    say(f"the start, {far:.3g} standard errors from the answer: refit with {last.nodes} nodes, dt {last.dt:.3g} s ...")
    answer = 0.5 * last.chi2 * m
    outcome = ahead.result() if ahead is not None and ahead.grid == (last.nodes, last.dt) else None
    if outcome is None or (outcome[0] == "weak") != (outcome[1] > WORSE * answer):  # not run, or run for another answer
        _drop(ahead)
        outcome = _rival(problem, last.problem, start, last.theta, answer, chi2, m, window_ends, progress)
    else:  # run beside the last time refit: its own time
        t0 = time.perf_counter() - outcome[2]
    kind, linear, _, found = outcome
    if kind == "weak":
        say(f"  its loss {linear:.6g} against the answer's {answer:.6g}: not a rival")
        return False
    if kind == "failed":
        notes.append(found)
        return False
    fine, th, r, it, jac, distance, held = found
    cost = 0.5 * float(r @ r)
    noise, se = noise_and_errors(problem, J, fine, r, start.size)
    levels.append(
        Level("rival", last.nodes, last.dt, last.tol, th, (th - last.theta) / se, 2 * cost / m, it, time.perf_counter() - t0,
              noise, se, fine, len(levels) - 1, jac, distance)
    )  # fmt: skip
    # the losses compared at the two optima: a refit that stopped short of its own lies above it
    # by its decrement, half its distance squared
    cost, answer = cost - 0.5 * _off(levels[-1]) ** 2, answer - 0.5 * _off(last) ** 2
    say(f"  its optimum's loss {cost:.6g} against the answer's {answer:.6g}")
    _note_stopped(notes, levels[-1])
    moved = problem.labels()[int(np.argmax(np.where(problem.measured, np.abs(levels[-1].move_se), 0.0)))]
    if cost >= answer - CLOSE:
        if cost < answer + CLOSE:
            notes.append(
                f"a second optimum, {np.max(np.abs(levels[-1].move_se)):.3g} standard errors away in {moved} (the refinements' "
                f'"rival"), fits the recording as well on the finest grid (loss {cost:.6g} against {answer:.6g}): the recording '
                "does not tell the two apart"
            )
        return False
    # the rival's time error: its optimum on coarser grids (at 4 dt, 2 dt; the finest's is the one above)
    rival = levels[-1]
    coarse = [rival]
    for k in (1, 2):
        t0 = time.perf_counter()
        h = last.dt * 2**k
        say(f"refit of the better basin with {last.nodes} nodes, dt {h:.3g} s ...")
        coarser = problem.refined(nodes=last.nodes, dt=h, tol=last.tol)
        try:
            th, r, it, jac, distance = _attempt(coarser, [(coarse[-1].theta, (None,), None)], held, m, chi2, progress=progress)
        except FitError as e:
            notes.append(f"the better basin's refit with dt {h:.3g} s {e}; its time error is not measured, the answer stands")
            return False
        noise, se = noise_and_errors(problem, J, coarser, r, start.size)
        coarse.append(Level("rival", last.nodes, h, last.tol, th, np.zeros_like(th), float(r @ r) / m, it,
                            time.perf_counter() - t0, noise, se, coarser, None, jac, distance))  # fmt: skip
    for lv in coarse[:0:-1]:
        _note_stopped(notes, lv)
    base = len(levels)
    at4, at2, at1 = coarse[2], coarse[1], coarse[0]
    levels += [
        at4,
        dataclasses.replace(at2, what="time", parent=base),
        dataclasses.replace(at1, what="time", parent=base + 1, iterations=0),
    ]
    for i in (base + 1, base + 2):  # their time moves, the space move of a refined internal grid taken out as in `refine`
        levels[i] = _time_move(levels[i], levels[levels[i].parent].theta, left, i, levels[i].parent)
    notes.append(
        f"on the finest grid ({last.nodes} nodes, dt {last.dt:.3g} s) the basin the fit started in fits better than the one "
        f"the fit's grid led to (loss {cost:.6g} against {answer:.6g}; {moved} {np.max(np.abs(rival.move_se)):.3g} "
        "standard errors away): the values are from the start's basin, its time error from refits at 2 and 4 times that dt"
    )
    return True


def _sentences(parts) -> str:
    """The non-empty ``parts`` as sentences: each ends with a full stop."""
    return " ".join(p if p.endswith(".") else p + "." for p in (p.strip() for p in parts) if p)


def _change(a: dict, b: dict) -> dict:
    return {k: np.asarray(b[k]) - np.asarray(a[k]) for k in a}


def _difference(a: dict, b: dict) -> dict:
    return {k: np.abs(v) for k, v in _change(b, a).items()}


def report(problem, theta, J, result, max_levels: int = 2, progress=None, window_ends=(None,), rivals=()):
    """``result`` (the `fit.Result` of ``problem`` at ``theta``, Jacobian ``J``) with the values
    of the last model `refine` evaluated, or their extrapolation to dt 0 where the last two time
    moves allow it (`extrapolation`), their discretisation error (the last space refinement's
    move and the last time refinement's move or the extrapolation's uncertainty, combined in
    quadrature: the two errors add independently to leading order) and tolerance error, the
    model they come from and the refits made; its message says when a last refinement still
    moved a measured value (`Problem.measured`) by more than a third of its standard error.
    ``progress`` as `refine`'s."""
    levels, notes = refine(problem, theta, J, max_levels, progress, result.loss, window_ends, rivals)
    message = _sentences([result.message, *notes])
    chains = {w: [i for i, lv in enumerate(levels) if lv.what == w] for w in ("space", "time")}
    if not all(chains.values()):  # a refinement failed: the fit's own values, no error claimed
        return dataclasses.replace(result, refinements=[lv.to_json() for lv in levels], message=message)
    at_fit = problem.reported(theta)
    finest = levels[-1]
    rescaled, _ = result_module.with_noise(result, problem, theta, J, finest.noise)

    def in_final_se(level, moves):
        """Moves in ``level``'s standard errors (under its noise levels) in the finest's."""
        return moves * level.se / finest.se

    values = {None: at_fit}  # level index -> its reported values (a short rollout each); None: the fit's

    def reported(i):
        if i not in values:
            values[i] = levels[i].problem.reported(levels[i].theta)
        return values[i]

    def grid(i):
        return _grid(problem, levels, i)

    moved, notes = {}, []
    final = None  # the values reported: the time chain's last, or their extrapolation to dt 0
    # the space chain's estimate of the space error of the time chain's coarser nodes (where it
    # settled there), on their internal grid g0, and the part of it the reported values keep: none
    # where it is an extrapolation, else the part left on the time chain's finest internal grid
    correction, kept = {}, 0.0
    g0 = grid(levels[chains["time"][0]].parent)

    def corrected(i):
        """Level ``i``'s values plus the space error left on its internal grid (RK4's order
        scales the correction from the time chain's base grid to a finer one), less the part kept."""
        scale = _left_on(g0, grid(i)) - kept
        return {key: np.asarray(v) + scale * correction.get(key, 0.0) for key, v in reported(i).items()}

    def widened(errors, off):
        """``errors`` (per value) plus ``off`` of the reported standard errors: what the refits'
        distances from their optima (`_off`) leave uncertain."""
        return {key: np.asarray(e) + off * np.asarray(rescaled.standard_errors.get(key, 0.0)) for key, e in errors.items()}

    model = {}
    for what, idx in chains.items():
        last = levels[idx[-1]]
        at = corrected if what == "time" else reported  # the time chain's values carry the space correction
        off = _move_off(levels, last)
        moved[what] = widened(_difference(at(idx[-1]), at(last.parent)), off)
        moves = np.where(problem.measured, in_final_se(last, np.abs(last.move_se) + off), 0.0)
        # Richardson from the last two moves: in time, to the finest dt's values; in space, where
        # time refined at the coarser nodes of the last space move, as a correction to them
        values_from_coarser = what == "space" and levels[chains["time"][0]].nodes < last.nodes
        extrapolated = "extrapolated_from_dt" if what == "time" else "extrapolated_from_nodes"  # its key in `model`
        usable = False
        if len(idx) >= 2 and (what == "time" or values_from_coarser):
            usable, error = extrapolation(levels[idx[-2]], last, problem.measured)
            if usable:
                k = 2.0 ** ORDER[what]
                v0, v1, v2 = at(levels[idx[-2]].parent), at(idx[-2]), at(idx[-1])
                m1 = {key: np.asarray(v1[key]) - np.asarray(v0[key]) for key in v2}
                m2 = {key: np.asarray(v2[key]) - np.asarray(v1[key]) for key in v2}
                if what == "time":
                    final = {key: np.asarray(v2[key]) + m2[key] / (k - 1.0) for key in v2}
                else:
                    correction = {key: _space_error(m2[key]) for key in v2}
                off = _extrapolation_off(levels[idx[-2]], last)
                moved[what] = widened({key: np.abs(k * m2[key] - m1[key]) / (k - 1.0) for key in v2}, off)
                moves = np.where(problem.measured, in_final_se(last, error), 0.0)
                model[extrapolated] = [levels[idx[-2]].dt, last.dt] if what == "time" else [levels[idx[-2]].nodes, last.nodes]
        if values_from_coarser and not usable:  # settled by its last move: the estimate takes the time moves' space part out
            correction = {key: _space_error(m) for key, m in _change(reported(last.parent), reported(idx[-1])).items()}
            kept = _left_on(g0, grid(chains["time"][-1]))
        worst = float(np.max(moves))
        if worst > THIRD:
            label = problem.labels()[int(np.argmax(moves))]
            finer = "nodes" if what == "space" else "dt"
            grids = model.get(extrapolated)
            how = (
                f"{what} refinement (to {last.nodes} nodes, dt {last.dt:.3g} s) still moved {label} by {worst:.2g} standard errors"
                + (f" (with {off:.2g} for its refits' distances from their optima)" if off > 0 else "")
                if grids is None
                else (
                    f"extrapolation to dt 0 from dt {grids[0]:.3g} and {grids[1]:.3g} s (at {last.nodes} nodes)"
                    if what == "time"
                    else f"extrapolation to infinitely many nodes from {grids[0]} and {grids[1]} (at dt {last.dt:.3g} s)"
                )
                + f" is uncertain by {worst:.2g} standard errors of {label}"
            )
            notes.append(
                f"the last {how} (more than {THIRD:.2f}): the {what} discretisation error is not negligible; a finer "
                f"[solver] {finer} in the sidecar (or more --refine levels) would settle it"
            )
    if final is None:
        final = corrected(len(levels) - 1)
    message = _sentences([message, *notes])
    return dataclasses.replace(
        rescaled,
        values=_plain(final),
        discretisation_errors=_plain({k: np.hypot(moved["space"][k], moved["time"][k]) for k in at_fit}),
        tolerance_errors=_plain(_difference(reported(0), at_fit)),
        model=dict(nodes=finest.nodes, dt=finest.dt, tol=finest.tol, **model),
        refinements=[lv.to_json() for lv in levels],
        message=message,
    )
