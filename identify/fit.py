r"""Fit a recording: a modal start, then Levenberg-Marquardt on the weighted frame residuals
(`problem.Problem`) over windows of growing length, then the model error of the answer
(`discretisation`).

**Start.** `modal_start`: candidate damping and lengths whose lumped free motion (a planar
platform's released push, `platform_screen`), modes or static response to an actuator move
match the recording's (`start`), ranked by a short time-domain fit of the push
and the camera. From nominal lengths a time-domain fit falls into a wrong minimum: on the
Triskele-bot 2 % of rod length moves the modes from 86-155 Hz to 19-84 Hz.

**Noise.** Noise levels are unknown for a real log, so they are estimated from the residuals at
the optimum (over the frames that a decoding error did not throw off, `robust.spikes`) and the
fit is repeated once with them (feasible generalised least squares) under a Huber loss
(`robust`) that weighs such frames down; they are reported. The covariance of the unknowns is
then ``(J^T J)^{-1}`` of the Gauss-Newton Hessian at the optimum (rescaled by the final reduced
chi-square), propagated through the log transforms to standard errors of the values themselves
(`result.summarize`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from . import discretisation, experiment, profile, robust, start, threads, valley
from .least_squares import FitError, levenberg_marquardt, standard_errors_theta
from .problem import CLOCK_STARTS, NOMINAL_SIGMA, Problem
from .result import Result, summarize

__all__ = ["FitError", "Problem", "Result", "fit", "modal_start", "windows"]


def modal_start(
    problem: Problem,
    theta,
    progress=None,
    rank_window: float = 0.1,
    screen_window: float = 0.2,
    screen_iter: int = 8,
    screen_best: int = 2,
    warm=None,
):
    """Start values of damping and lengths (`start.initial_lengths`: the candidates whose
    lumped free motion, modes or static response match the recording's), ranked by the loss
    over the first ``rank_window`` seconds after the forcing with the push and the camera fitted
    (a rollout per push component, `Problem.fit_linear`, from every clock offset in
    `CLOCK_STARTS`); the ``screen_best`` best are screened by a short Levenberg-Marquardt fit of
    all unknowns on the first ``screen_window`` seconds, which mode shapes and amplitudes
    decide. Returns (the best, the screening: None, or its ``window`` end, ``candidates``,
    ``iterations`` and the best's loss ``history``: the fit's windows up to that end are then
    done). ``progress(stage, i, loss, step)``, loss and
    step None for a message; ``warm()`` is called once the features are known and the first
    simulation has compiled (the caller builds the Jacobian's program meanwhile)."""
    theta, found = start.initial_lengths(problem, theta, progress, warm) if "lengths" in problem.slices else (theta, [])
    if not found:
        return start.initial_tau(problem, theta, progress), None
    i_len = problem.slices["lengths"]
    t_from = experiment.forcing_end(problem.scene)
    t_screen = t_from + screen_window

    def rank(x):
        th = theta.copy()
        th[i_len] = x
        return problem.fit_linear(th, t_from + rank_window, clocks=CLOCK_STARTS)

    ranked = []
    for x, (th, cost) in zip(found, threads.map_in_threads(rank, found), strict=True):
        if progress is not None:
            progress(
                f"candidate lengths {np.round(np.exp(x) * 1e3, 3).tolist()} mm, push and camera fitted",
                len(ranked) + 1,
                cost,
                0.0,
            )
        ranked.append((cost, len(ranked), th))
    ranked = [c for c in sorted(ranked, key=lambda c: c[:2]) if np.isfinite(c[0])][:screen_best]
    if not ranked:
        raise FitError(f"{problem.rec.path}: the simulation fails at every candidate set of lengths")
    if len(ranked) == 1:  # the others' simulations fail
        return ranked[0][2], None

    def screen(th):
        try:
            return levenberg_marquardt(
                lambda a: problem.residual(a, t_screen),
                lambda a: problem.residual_and_jacobian(a, t_screen),
                th,
                screen_iter,
                ftol=1e-6,
                max_step=problem.max_step,
            )
        except FitError:  # the simulation fails there: not a candidate
            return None

    best, best_hist, iterations = None, [np.inf], 0
    # no first alone: the ranking ran the residual's program, and calls of the Jacobian's while
    # the fit's background thread compiles it wait for that one compile
    for j, out in enumerate(threads.map_in_threads(screen, [c[2] for c in ranked], first_alone=False)):
        if out is None:
            continue
        th, _, _, it, _, hist = out
        iterations += it
        if progress is not None:
            progress(f"candidate lengths {np.round(np.exp(th[i_len]) * 1e3, 3).tolist()} mm, screened", j + 1, hist[-1], 0.0)
        if hist[-1] < best_hist[-1]:
            best, best_hist = th, hist
    if best is None:
        raise FitError(f"{problem.rec.path}: the simulation fails at every set of lengths that gives the recorded features")
    return best, dict(window=t_screen, candidates=len(ranked), iterations=iterations, history=best_hist)


# The whole recording's pass stops when the Gauss-Newton decrement (what the linearised problem
# could still gain) is below 2.5e-3 of the current reduced chi-square (relative to the loss:
# FINAL_FTOL / residuals): 0.5 (delta / SE)^2 is what a parameter delta off the optimum adds to
# a loss whitened by the noise, so the parameters then lie within about 0.07 SE of its optimum.
# Over the ten shipped recordings, against a stop at 0.045 SE: one iteration fewer on four of
# them (a whole-recording Jacobian each), the values within 0.08 SE; paired whole-process fits of
# `triskele_push_release_r1` took 0.91 of the wall time.
FINAL_FTOL = 5e-3
# A window's optimum is only the next window's start, which moves by more than a window's
# standard error, so each window stops within a third of its SE (decrement below 1/18 of the
# reduced chi-square). On `triskele_push_release_r1` the windows then took 16 iterations instead
# of 21 (stopping within 0.05 SE), the answer within 0.003 standard errors, and paired fits took
# 0.87 of the wall time.
WINDOW_FTOL = 1.0 / 9.0
# The least-squares pass over the whole recording gives only the noise levels (from its
# residuals) and the start of the pass weighted by them, so it stops within about one standard
# error of its optimum (decrement below half the reduced chi-square). That adds about half a
# reduced chi-square to a sum over hundreds of residuals: the noise levels estimated from them
# move by a percent or less. The answer is the re-weighted pass's, to its own stop.
# It stops on its secant Jacobian's test, and the re-weighted pass starts from that Jacobian
# (taking the exact one where a step fails or it would stop): an exact Jacobian of the whole
# recording costs four to five of its residuals.
NOISE_PASS_FTOL = 0.5


# A released push fitted this far (relative) from the sidecar's is no measurement error: the fit
# is in a wrong minimum whose oscillations happen to fit.
PUSH_DOUBT = 0.5


def _implausible_push(problem: Problem, theta) -> str:
    """A warning where the fitted push is far from the one the sidecar records ('' if not)."""
    vals = problem.to_values(jnp.asarray(theta))
    for name in ("push_force", "push_moment"):
        if name in problem.slices:
            fitted, told = np.atleast_1d(np.asarray(vals[name], float)), np.atleast_1d(np.asarray(problem.fixed[name], float))
            if np.linalg.norm(fitted - told) > PUSH_DOUBT * np.linalg.norm(told):
                return (
                    f"the fitted {name} {np.round(fitted, 6).tolist()} is far from the recorded {np.round(told, 6).tolist()}: "
                    "the fit is likely in a wrong minimum (check the recorded push, or start from other values)"
                )
    return ""


def _summary(pb: Problem, theta, J, r, iterations, converged, history, stages, notes=()) -> Result:
    """The `Result` of the final pass's problem ``pb`` at ``theta``, with the frames its Huber
    loss threw off and a doubtful push reported."""
    z = np.asarray(robust.unhuber(r, pb.huber)).reshape(-1, 3)
    return summarize(
        pb,
        theta,
        J,
        r,
        t_end=None,
        iterations=iterations,
        converged=converged,
        history=history,
        stages=stages,
        outliers=np.asarray(pb.t)[robust.spikes(z, pb.keep)].tolist(),
        message=" ".join([*notes, _implausible_push(pb, theta)]).strip(),
    )


def _with_valley(pb: Problem, theta, J, r, result: Result) -> Result:
    """``result`` with the loss's rise along its least determined direction (`valley.check`), and
    its note where the standard errors misstate it."""
    se = standard_errors_theta(J, result.loss)
    found = valley.check(pb.residual, theta, J, r, result.loss, pb.labels(), se)
    return dataclasses.replace(result, valley=found, message=" ".join(m for m in (result.message, found["note"]) if m))


# A fit whose profiles walk into a lower minimum moves there, at most this often (a noise draw
# of `triskele_push_release_r1`'s truth on the fit's grid: the windows' fit stopped 6-8 SE along
# two lengths from a minimum 1.6 reduced chi-square lower, near the truth).
PROFILE_MOVES = 2


def _profiled(pb: Problem, theta, J, r, result: Result, max_iter, progress) -> tuple[Result, np.ndarray, np.ndarray, np.ndarray]:
    """(``result`` with the profiles of its measured values (`profile.report`), theta, J, r): where
    a profile walked into a minimum lower than the fit's by more than `profile.LEVEL`, the whole
    recording is fitted again from there and profiled about the new optimum."""
    say = (
        None
        if progress is None
        else (lambda label, v, c: progress(f"profile of {label} at {v:.6g}: loss {c:+.3g} from the fit's", 0, None, 0.0))
    )
    notes = []
    for moves in range(PROFILE_MOVES + 1):
        se = standard_errors_theta(J, result.loss)
        found, lower = profile.report(pb, theta, J, r, result.loss, se, say)
        if lower is None:
            break
        if moves == PROFILE_MOVES:
            still = (
                f"after {moves} moves the profiles still walk into a lower minimum; the fit stays at the last (see the profiles)"
            )
            result = dataclasses.replace(result, message=f"{still}. {result.message}".strip())
            break
        if progress is not None:
            progress("a profile found a lower minimum: the whole recording again from there", 0, None, 0.0)
        try:
            th, Jn, rn, it, converged, hist = levenberg_marquardt(
                pb.residual,
                pb.residual_and_jacobian,
                lower,
                max_iter,
                ftol=FINAL_FTOL / pb.counted(None),
                max_step=pb.max_step,
                huber=pb.huber,
                secant_jacobian=True,
                geodesic=True,
            )
        except FitError as e:
            notes.append(f"the fit from the profiles' lower minimum {e}")
            break
        if rn @ rn >= r @ r:
            break
        drop = 0.5 * float(r @ r - rn @ rn) / result.loss
        away = np.max(np.abs((th - theta) / se)[pb.measured])
        notes.append(
            f"the profiles found a minimum {drop:.3g} (reduced chi-square) lower than the windows' fit reached, "
            f"{away:.3g} standard errors from it, and the fit moved there"
        )
        theta, J, r = th, Jn, rn
        stages = [
            *result.stages,
            dict(
                stage="whole recording, from a profile's lower minimum", iterations=it, loss=hist[-1], converged=bool(converged)
            ),
        ]
        result = _summary(pb, theta, J, r, result.iterations + it, converged, result.history + hist, stages, notes)
    return dataclasses.replace(result, profiles=found), theta, J, r


def windows(duration: float, first: float = 0.1) -> list:
    """Window end times of the continuation: ``first``, doubling, then the whole recording (None)."""
    out, w = [], first
    while w < 0.75 * duration:
        out.append(w)
        w *= 2.0
    return out + [None]


def fit(
    problem: Problem,
    max_iter=30,
    state_dir: Path | None = None,
    progress=None,
    first_window: float = 0.1,
    modal: bool = True,
    refine_levels: int = 2,
    profiles: bool = False,
    answer=None,
) -> Result:
    """Fit by continuation in the recording's length, then once more with estimated noise levels.

    A frequency error wraps the phase of an oscillation, so over a whole recording the loss has
    a minimum every cycle; over its first ``first_window`` seconds it has one. Each window (that
    length, doubling up to the whole recording) starts from the previous window's optimum. The
    whole recording is fitted twice: with the nominal noise scales, then with noise levels
    estimated from the first pass's residuals (feasible generalised least squares). Over the whole
    recording a Jacobian (the rollout's tangents) costs four to five residuals, so an accepted
    step there updates it by Broyden's secant (``secant_jacobian``; the first pass, which only
    starts the second, stops on the secant one's test) until a step on the secant fails, and
    takes the exact one after that; every step taken on an exact Jacobian there is corrected
    for the curvature of the loss's valley by geodesic acceleration (``geodesic``). The shorter
    windows, where a Jacobian costs less beside a residual, take plain steps on the exact
    Jacobian. Progress is
    saved to ``state_dir/fit_state.json`` after every iteration; a fit started again with the
    same state folder resumes where it stopped. ``progress(stage, iteration, loss, step)``.
    Then the model error of the answer is measured on finer models (`discretisation.report`:
    up to ``refine_levels`` refinements in space and then as many in time, fewer when one
    moves no value by a third of its standard error; 0: none) and the values are those of the
    finest. With ``profiles``, the loss is first profiled along each measured value at the fit's
    own grid (`profile`: 68 % intervals that follow a curved valley, and any lower minimum).
    Before the refinements, two residuals measure the loss one standard error either side along
    its least determined combination of unknowns (`valley`): the message says where its rise
    there shows the standard errors overstating or understating the uncertainty.
    ``answer(result)``, if given, receives the answer on the fit's own grid (statistical errors
    only, its grid in ``model``) before the refinements start, which take several times the
    fit's time: a caller shows and keeps it while they run.
    """
    t0 = time.perf_counter()
    duration = float(problem.t[-1] - problem.t[0])
    stages = [(f"window {w:g} s", w) for w in windows(duration, first_window)[:-1]] + [
        ("whole recording", None),
        ("whole recording, noise re-estimated", None),
    ]
    state_file = None if state_dir is None else Path(state_dir) / "fit_state.json"
    theta = np.asarray(problem.to_theta(problem.initial_values))
    pb = problem.with_noise(NOMINAL_SIGMA)  # the noise levels and Huber loss of the current pass
    done, history, total_it, resume, summary = 0, [], 0, None, []
    start = None  # where the modal start put the fit: a rival basin on the finest grid (`discretisation`)
    if state_file is not None and state_file.is_file():
        st = json.loads(state_file.read_text())
        if st.get("labels") == problem.labels() and st.get("recording") == str(problem.rec.path):
            done, history, total_it, resume = st["stage"], st["history_before"], st["iterations_before"], st["lm"]
            theta, pb = np.asarray(st["lm"]["theta"]), problem.with_noise(st["sigma"], st.get("huber"))
            start = None if st.get("start") is None else np.asarray(st["start"])

    def save(lm_state, k):
        if state_file is not None:
            state_file.write_text(
                json.dumps(
                    dict(
                        recording=str(problem.rec.path),
                        labels=problem.labels(),
                        stage=k,
                        sigma=list(map(float, pb.sigma)),
                        huber=None if pb.huber == robust.NONE else pb.huber,
                        history_before=history,
                        iterations_before=total_it,
                        lm=lm_state,
                        start=None if start is None else start.tolist(),
                    )
                )
            )

    if modal and resume is None:
        # The Jacobian's program (20-40 s of tracing and compiling) is built in a thread while the
        # modal start matches features, once the recording's are known (a recording without modes
        # is reported before any compilation).
        background = ThreadPoolExecutor(max_workers=1)
        try:
            compiled = []
            warm = lambda: compiled.append(background.submit(pb.residual_and_jacobian, theta, 0.0))  # noqa: E731
            theta, screened = modal_start(pb, theta, progress, warm=warm)
            start = theta.copy()
            for job in compiled:
                job.result()
        finally:  # an error in the modal start is reported at once, not after the compile
            background.shutdown(wait=False)
        if screened is not None:  # the windows it covers are fitted
            done = sum(1 for _, w in stages if w is not None and w <= screened["window"] + 1e-9)
            total_it += screened["iterations"]
            history += screened["history"]
            summary.append(
                dict(
                    stage=f"screening of {screened['candidates']} candidates, window {screened['window']:g} s",
                    iterations=screened["iterations"],
                    loss=screened["history"][-1],
                    converged=True,
                )
            )
        resume = dict(theta=theta.tolist(), lam=1e-3, history=[], iteration=0)
        save(resume, done)  # an interrupted fit resumes after the modal start
    r = J = None  # the last pass's residuals and Jacobian
    for k, (label, t_end) in enumerate(stages):
        if k < done:
            continue
        initial = None
        for_noise = k == len(stages) - 2  # the least-squares pass: the noise levels and a start
        if k == len(stages) - 1 and (resume is None or k > done or resume["iteration"] == 0):
            # noise levels from the previous (whole-recording, least-squares) pass's residuals, and
            # its residuals and Jacobian reweighted under the Huber loss when it ran here: no simulation
            known = r is not None
            old = pb.sigma
            res = (r if known else np.asarray(pb.residual(theta))).reshape(-1, 3) * old
            pb = pb.with_noise(robust.clean_noise_levels(res, pb.keep), robust.HUBER)
            if known:
                z = (r.reshape(-1, 3) * (old / pb.sigma)).reshape(-1)
                slope = np.asarray(robust.huber_slope(z, pb.huber))
                w = np.tile(old / pb.sigma, r.size // 3)
                initial = (np.asarray(robust.huber(z, pb.huber)), J * (w * slope)[:, None])
        try:
            theta, J, r, it, converged, hist = levenberg_marquardt(
                lambda th, pb=pb, t_end=t_end: pb.residual(th, t_end),
                lambda th, pb=pb, t_end=t_end: pb.residual_and_jacobian(th, t_end),
                theta,
                max_iter,
                ftol=(NOISE_PASS_FTOL if for_noise else FINAL_FTOL if t_end is None else WINDOW_FTOL) / pb.counted(t_end),
                max_step=pb.max_step,
                start=resume if k == done else None,
                save=lambda st, k=k: save(st, k),
                progress=None if progress is None else (lambda i, c, st, label=label: progress(label, i, c, st)),
                initial=initial,
                huber=pb.huber,
                secant_jacobian=t_end is None,
                exact_test=t_end is None and not for_noise,  # a window's and that pass's answers start the next pass
                initial_exact=False,  # an initial comes from the least-squares pass: maybe its secant Jacobian
                geodesic=t_end is None,
                secant_test=t_end is not None,
                speculate=threads.WORKERS > 1 and t_end is None,
            )
        except FitError as e:
            at = problem.to_values(jnp.asarray(theta))
            vals = {u.name: np.round(np.asarray(at[u.name], float), 9).tolist() for u in problem.unknowns}
            raise FitError(
                f"{problem.rec.path}: {label}: {e}; values {vals}. A smaller [solver] dt in the sidecar or other start values (--tau0) may help"
            ) from None
        resume = None
        total_it += it
        history += hist
        summary.append(dict(stage=label, iterations=it, loss=hist[-1], converged=bool(converged)))
        save(dict(theta=theta.tolist(), lam=1e-3, history=[], iteration=0, converged=bool(converged)), k + 1)
    if J is None:  # resumed after the last pass: its Jacobian once more, and whether it converged
        r, J = (np.asarray(a) for a in pb.residual_and_jacobian(theta))
        converged = bool(resume.get("converged", False))
    result = _summary(pb, theta, J, r, total_it, converged, history, summary)
    if profiles:
        result, theta, J, r = _profiled(pb, theta, J, r, result, max_iter, progress)
    result = _with_valley(pb, theta, J, r, result)
    if refine_levels > 0 and answer is not None:
        solver = pb.scene.solver
        grid = dict(nodes=solver.nodes, dt=float(solver.dt), tol=float(solver.newton.tol))
        answer(dataclasses.replace(result, wall_s=time.perf_counter() - t0, model=grid))
    if refine_levels > 0:
        result = discretisation.report(
            pb,
            theta,
            J,
            result,
            refine_levels,
            progress,
            window_ends=[w for _, w in stages[:-1]],
            rivals=[] if start is None else [start],
        )
    return dataclasses.replace(result, wall_s=time.perf_counter() - t0)
