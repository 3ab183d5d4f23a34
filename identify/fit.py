r"""Fit a recording: Levenberg-Marquardt on the weighted frame residuals, or optax Adam.

**Unknowns.** The physical parameters chosen with ``fit`` (``tau``: one damping time shared by
the rods; ``tau_per_rod``; ``lengths``: one per rod) and the experiment's nuisance parameters,
always fitted: the camera's frame offset and rotation and its clock offset, plus, for a
push-and-release, the push that was released (its force and moment). Positive parameters are
fitted as logarithms; the others in units of a typical size (mm, mrad, ms, mN), so every unknown
is O(1).

**Residuals.** ``(camera model - recording) / sigma`` per frame and column, with ``sigma`` the
noise of the position and angle columns. Noise levels are unknown for a real log, so they are
estimated from the residuals at the optimum and the fit is repeated once with them (feasible
generalised least squares); the covariance of the unknowns is then ``(J^T J)^{-1}`` of the
Gauss-Newton Hessian at the optimum (rescaled by the final reduced chi-square), propagated
through the log transforms to standard errors of the values themselves.

**Jacobians** come from `jax.jacfwd` through the whole rollout: one forward-mode tangent per
unknown, each Newton solve differentiated implicitly (`jax.lax.custom_root`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import camera, experiment
from .recording import Recording, RecordingError

PHYSICAL = ("tau", "tau_per_rod", "lengths")


@dataclasses.dataclass(frozen=True)
class Unknown:
    name: str  # parameter name in `experiment`
    size: int
    log: bool
    unit: float  # value = unit * theta (linear) or exp(theta) (log)


class Problem:
    """The fit of one recording: unknowns, residual function and bookkeeping."""

    def __init__(self, rec: Recording, fit: tuple[str, ...], scene=None, initial: dict | None = None):
        unknown_fit = [f for f in fit if f not in PHYSICAL]
        if unknown_fit:
            raise RecordingError(f"--fit: unknown parameter {unknown_fit[0]!r} (choose from {', '.join(PHYSICAL)})")
        if "tau" in fit and "tau_per_rod" in fit:
            raise RecordingError("--fit: tau (shared) and tau_per_rod exclude each other")
        self.rec = rec
        sc = scene if scene is not None else experiment.build_scene(rec)
        self.scene = experiment.with_duration(sc, experiment.required_duration(rec))
        nom = experiment.nominal(self.scene)
        n_rods = int(np.size(nom["lengths"]))
        self.fit = tuple(fit)
        unknowns = []
        if "tau" in fit:
            unknowns.append(Unknown("tau", 1, True, 1.0))
        if "tau_per_rod" in fit:
            unknowns.append(Unknown("tau", n_rods, True, 1.0))
        if "lengths" in fit:
            unknowns.append(Unknown("lengths", n_rods, True, 1.0))
        if rec.experiment in ("push_release", "release"):
            unknowns.append(Unknown("push_force", 2, False, 1e-3))
            if not experiment.is_rod(self.scene):
                unknowns.append(Unknown("push_moment", 1, False, 1e-4))
        unknowns += [Unknown("frame_offset", 2, False, 1e-3), Unknown("frame_rotation", 1, False, 1e-3), Unknown("time_offset", 1, False, 1e-3)]
        self.unknowns = unknowns
        self.fixed = dict(nom)
        self.t = jnp.asarray(rec.t)
        self.data = jnp.asarray(rec.pose)
        self.initial_values = self._initial_values(nom, initial or {})
        self.sigma = np.array([1e-9, 1e-9, 1e-6])  # replaced by estimates after the first pass
        # compiled once per problem (sigma is an argument, so the second pass reuses them)
        self.residual_jit = jax.jit(self.residual)
        self.residual_and_jacobian = jax.jit(lambda th, sg: (self.residual(th, sg), jax.jacfwd(self.residual)(th, sg)))

    # -- parameter vector <-> values ----------------------------------------------------------
    def _initial_values(self, nom, given):
        vals = {"frame_offset": jnp.zeros(2), "frame_rotation": jnp.zeros(()), "time_offset": jnp.zeros(()), **nom}
        if "tau_per_rod" in self.fit:
            vals["tau"] = jnp.broadcast_to(nom["tau"], nom["lengths"].shape) * jnp.ones_like(nom["lengths"])
        elif "tau" in self.fit:
            vals["tau"] = jnp.mean(nom["tau"])
        for k, v in given.items():
            vals[k] = jnp.asarray(v, jnp.float64)
        if not any(k in given for k in ("frame_offset", "frame_rotation")):
            # The first frame fixes the frame transform up to the model's start: compare it with
            # the model's first frame in the robot frame (one rollout, identity transform).
            robot = self.predict_values(vals)[:1]
            vals["frame_rotation"] = self.data[0, 2] - robot[0, 2]
            vals["frame_offset"] = self.data[0, :2] - camera.to_camera(robot, jnp.zeros(2), vals["frame_rotation"])[0, :2]
        return vals

    def to_theta(self, vals) -> jnp.ndarray:
        parts = []
        for u in self.unknowns:
            v = jnp.reshape(jnp.asarray(vals[u.name], jnp.float64), (u.size,))
            parts.append(jnp.log(v) if u.log else v / u.unit)
        return jnp.concatenate(parts)

    def to_values(self, theta) -> dict:
        vals = dict(self.fixed)
        i = 0
        for u in self.unknowns:
            x = theta[i : i + u.size]
            v = jnp.exp(x) if u.log else x * u.unit
            vals[u.name] = v[0] if u.size == 1 else v
            i += u.size
        return vals

    def labels(self) -> list[str]:
        out = []
        for u in self.unknowns:
            out += [u.name] if u.size == 1 else [f"{u.name}[{k}]" for k in range(u.size)]
        return out

    # -- model --------------------------------------------------------------------------------
    def predict_values(self, vals):
        seen, _ = experiment.predict(self.scene, vals, self.t, self.rec.exposure)
        return seen

    def seen(self, theta):
        """Camera poses (M, 3) at ``theta``, through the compiled residual (no new compilation)."""
        sigma = jnp.asarray(self.sigma)
        return self.data + self.residual_jit(jnp.asarray(theta), sigma).reshape(-1, 3) * sigma

    def residual(self, theta, sigma):
        vals = self.to_values(theta)
        return ((self.predict_values(vals) - self.data) / sigma).reshape(-1)


@dataclasses.dataclass
class Result:
    labels: list
    values: dict  # name -> value (list or float)
    standard_errors: dict
    correlation: list  # (p, p) of the fitted unknowns, in `labels` order (log space for log unknowns)
    sigma: list  # noise estimates: position (m), angle (rad)
    loss: float  # final reduced chi-square
    rms: list  # RMS residual per column, in m, m, rad
    iterations: int
    wall_s: float
    converged: bool
    history: list  # loss per iteration
    message: str = ""

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def _covariance(J):
    JtJ = J.T @ J
    d = 1.0 / np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    return d[:, None] * np.linalg.pinv(d[:, None] * JtJ * d[None, :], rcond=1e-14) * d[None, :]


def levenberg_marquardt(rf: Callable, rj: Callable, theta0, max_iter=30, xtol=1e-8, ftol=1e-10, state_file: Path | None = None, progress=None, max_step=0.5):
    """Minimise ``0.5 |rf(theta)|^2``, with ``rj(theta) = (residual, Jacobian)``. Returns (theta, J,
    r, iterations, converged, history). Progress is saved to ``state_file`` after each iteration
    (resume: pass it again)."""
    theta = np.asarray(theta0, float)
    lam, history, it0 = 1e-3, [], 0
    if state_file is not None and state_file.is_file():
        st = json.loads(state_file.read_text())
        if len(st["theta"]) == theta.size:
            theta, lam, history, it0 = np.asarray(st["theta"]), st["lam"], st["history"], st["iteration"]
    r, J = (np.asarray(a) for a in rj(jnp.asarray(theta)))
    cost = 0.5 * float(r @ r)
    if not history:
        history.append(cost)
    converged = False
    it = it0
    for it in range(it0 + 1, max_iter + 1):
        g = J.T @ r
        A = J.T @ J
        accepted = False
        for _ in range(12):
            step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12 * np.max(np.diag(A))), -g)
            big = np.max(np.abs(step))
            if big > max_step:  # unknowns are O(1) (logs, typical units): a trust region on each
                step = step * (max_step / big)
            r_t = np.asarray(rf(jnp.asarray(theta + step)))
            cost_t = 0.5 * float(r_t @ r_t) if np.all(np.isfinite(r_t)) else math.inf
            if cost_t < cost:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            break
        rel = (cost - cost_t) / max(cost, 1e-300)
        theta = theta + step
        lam = max(lam / 10.0, 1e-12)
        r, J = (np.asarray(a) for a in rj(jnp.asarray(theta)))
        cost = 0.5 * float(r @ r)
        history.append(cost)
        if state_file is not None:
            state_file.write_text(json.dumps(dict(theta=theta.tolist(), lam=lam, history=history, iteration=it)))
        if progress is not None:
            progress(it, cost, float(np.max(np.abs(step))))
        if rel < ftol or np.max(np.abs(step)) < xtol * (1.0 + np.max(np.abs(theta))):
            converged = True
            break
    return theta, J, r, it, converged, history


def adam(fun: Callable, theta0, steps=300, learning_rate=3e-2, progress=None):
    """Minimise ``0.5 |fun(theta)|^2`` with optax Adam (reverse-mode gradients); for comparison."""
    import optax

    loss = jax.jit(jax.value_and_grad(lambda th: 0.5 * jnp.sum(fun(th) ** 2)))
    opt = optax.adam(learning_rate)
    theta = jnp.asarray(theta0)
    state = opt.init(theta)
    history = []
    for k in range(steps):
        val, g = loss(theta)
        history.append(float(val))
        upd, state = opt.update(g, state)
        theta = optax.apply_updates(theta, upd)
        if progress is not None:
            progress(k + 1, float(val), float(jnp.max(jnp.abs(upd))))
    return np.asarray(theta), history


def fit(problem: Problem, max_iter=30, state_dir: Path | None = None, progress=None) -> Result:
    """Two LM passes (the second with noise levels estimated from the first's residuals)."""
    t0 = time.perf_counter()
    theta = np.asarray(problem.to_theta(problem.initial_values))
    total_it, history, converged = 0, [], False
    for k in range(2):
        sigma = jnp.asarray(problem.sigma)
        state = None if state_dir is None else state_dir / f"lm_state_pass{k}.json"
        theta, J, r, it, converged, hist = levenberg_marquardt(
            lambda th: problem.residual_jit(th, sigma), lambda th: problem.residual_and_jacobian(th, sigma), theta, max_iter, state_file=state, progress=progress
        )
        total_it += it
        history += hist
        res = r.reshape(-1, 3) * problem.sigma
        problem.sigma = np.array([np.sqrt(np.mean(res[:, :2] ** 2)), np.sqrt(np.mean(res[:, :2] ** 2)), np.sqrt(np.mean(res[:, 2] ** 2))])
        problem.sigma = np.maximum(problem.sigma, [1e-15, 1e-15, 1e-15])
    m, p = r.size, theta.size
    chi2 = float(r @ r) / max(m - p, 1)
    cov = _covariance(J) * chi2
    se_theta = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = cov / np.outer(se_theta, se_theta)
    vals = problem.to_values(jnp.asarray(theta))
    values, errors = {}, {}
    i = 0
    for u in problem.unknowns:
        v = np.atleast_1d(np.asarray(vals[u.name], float))
        s = se_theta[i : i + u.size] * (v if u.log else u.unit)  # d exp(x) = exp(x) dx
        values[u.name] = v.tolist() if u.size > 1 else float(v[0])
        errors[u.name] = s.tolist() if u.size > 1 else float(s[0])
        i += u.size
    res = r.reshape(-1, 3) * problem.sigma
    return Result(
        labels=problem.labels(),
        values=values,
        standard_errors=errors,
        correlation=corr.tolist(),
        sigma=[float(problem.sigma[0]), float(problem.sigma[2])],
        loss=chi2,
        rms=np.sqrt(np.mean(res**2, axis=0)).tolist(),
        iterations=total_it,
        wall_s=time.perf_counter() - t0,
        converged=bool(converged),
        history=history,
    )
