r"""Fit a recording: a modal start, then Levenberg-Marquardt on the weighted frame residuals
over windows of growing length (optax Adam is kept for comparison).

**Unknowns.** The physical parameters chosen with ``fit`` (``tau``: one damping time shared by
the rods; ``tau_per_rod``; ``lengths``: one per rod) and the experiment's nuisance parameters,
always fitted: where the camera sees the robot at t = 0 (``start_position``, ``start_angle``;
the pattern frame's offset and rotation follow, `frame_transform`) and its clock offset, plus,
for a push-and-release, the push that was released (its force and moment). Positive parameters
are fitted as logarithms, the others in units of a typical size, so every unknown is O(1).

**Start.** `modal_start`: candidate damping and lengths whose modes (or static response to an
actuator move) match the recording's (`start`), ranked by a short time-domain fit of the push
and the camera. From nominal lengths a time-domain fit falls into a wrong minimum: on the
Triskele-bot 2 % of rod length moves the modes from 86-155 Hz to 19-84 Hz.

**Residuals.** ``(camera model - recording) / sigma`` per frame and column, with ``sigma`` the
noise of the position and angle columns. Noise levels are unknown for a real log, so they are
estimated from the residuals at the optimum and the fit is repeated once with them (feasible
generalised least squares); the covariance of the unknowns is then ``(J^T J)^{-1}`` of the
Gauss-Newton Hessian at the optimum (rescaled by the final reduced chi-square), propagated
through the log transforms to standard errors of the values themselves.

**Jacobians** come from `jax.jvp` through the whole rollout for the physical unknowns (each
Newton solve differentiated implicitly, `pcrjax.numerics.newton.solve`) and from the camera model alone
for the camera's unknowns.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import pcrjax

from . import camera, discretisation, experiment, start
from .recording import Recording, RecordingError

PHYSICAL = ("tau", "tau_per_rod", "lengths")
NOMINAL_SIGMA = np.array([1e-9, 1e-9, 1e-6])  # noise scales (m, m, rad) of the first pass
# The camera's unknowns: where it sees the robot's pose at t = 0 (the static equilibrium the
# motion starts from) and its clock offset. The pattern frame (offset, rotation) follows from the
# start pose and the model's own pose at t = 0 (`frame_transform`): a rod length that moves the
# robot's rest pose by a millimetre then needs no compensating change of a frame unknown, a
# valley of the loss 10^4 times narrower than it is long that Levenberg-Marquardt could not follow.
CAMERA_UNKNOWNS = (("start_position", 2, 1e-5), ("start_angle", 1, 1e-4), ("time_offset", 1, 1e-3))
# Unknowns the motion seen depends on (nearly) linearly: Levenberg-Marquardt's trust region does
# not bound their steps (a Gauss-Newton step is right for them however large; the start pose of a
# 1 kHz cantilever film is a millimetre from the first frame, a hundred typical units).
LINEAR = ("push_force", "push_moment", "start_position", "start_angle")
CAMERA = tuple(c[0] for c in CAMERA_UNKNOWNS)


def frame_transform(robot_start, vals):
    """(offset (2,), rotation) of the pattern frame that shows the robot's planar pose at t = 0,
    ``robot_start`` (3,), at ``vals["start_position"]``, ``vals["start_angle"]``."""
    rotation = vals["start_angle"] - robot_start[2]
    rotated = camera.to_camera(robot_start[None], jnp.zeros(2), rotation)[0, :2]
    return vals["start_position"] - rotated, rotation


@dataclasses.dataclass(frozen=True)
class Unknown:
    name: str  # parameter name in `experiment`
    size: int
    log: bool
    unit: float  # value = unit * theta (linear) or exp(theta) (log)

    @property
    def max_step(self) -> float:
        """Trust region of one Levenberg-Marquardt step in this unknown's theta."""
        return math.inf if self.name in LINEAR else 0.5


class Problem:
    """The fit of one recording: unknowns, residual function and bookkeeping.

    The unknowns are ordered physical first (they need tangents through the rollout), camera
    last (they act on the simulated motion only, so their Jacobian columns cost no rollout).
    Residuals and Jacobians take a window, the end time of the frames that count: later frames
    get zero residuals and the rollout stops after the steps they need (`pcrjax.rollout`'s
    ``active_steps``), so every window runs through the same two compiled programs.
    """

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
        unknowns += [Unknown(n, k, False, unit) for n, k, unit in CAMERA_UNKNOWNS]
        self.unknowns = unknowns
        self.slices, i = {}, 0  # name -> its slice of theta
        for u in unknowns:
            self.slices[u.name] = slice(i, i + u.size)
            i += u.size
        self.n_physical = sum(u.size for u in unknowns if u.name not in CAMERA)
        self.max_step = np.concatenate([np.full(u.size, u.max_step) for u in unknowns])
        self.fixed = dict(nom)
        self.t = jnp.asarray(rec.t)
        self.data = jnp.asarray(rec.pose)
        self.sigma = NOMINAL_SIGMA.copy()  # replaced by estimates after the first pass
        self.keep = np.ones(rec.t.size, bool)  # frames that count (all; fewer to study missing frames)
        # compiled once per problem: sigma and the window are arguments
        self._residual = jax.jit(self._residual_fn)
        self._residual_and_jacobian = jax.jit(self._residual_and_jacobian_fn)
        self._linear_residual = jax.jit(self._linear_residual_fn)
        self._linear_jacobian = jax.jit(jax.jacfwd(self._linear_residual_fn))
        self.initial_values = self._initial_values(nom, initial or {})

    # -- parameter vector <-> values ----------------------------------------------------------
    def _initial_values(self, nom, given):
        # the robot at t = 0 is seen where the first frame saw it (up to the first frame's delay)
        vals = {"start_position": self.data[0, :2], "start_angle": self.data[0, 2], "time_offset": jnp.zeros(()), **nom}
        if "tau_per_rod" in self.fit:
            vals["tau"] = jnp.broadcast_to(nom["tau"], nom["lengths"].shape) * jnp.ones_like(nom["lengths"])
        elif "tau" in self.fit:
            vals["tau"] = jnp.mean(nom["tau"])
        for k, v in given.items():
            vals[k] = jnp.asarray(v, jnp.float64)
        return vals

    def to_theta(self, vals) -> jnp.ndarray:
        parts = []
        for u in self.unknowns:
            v = jnp.reshape(jnp.asarray(vals[u.name], jnp.float64), (u.size,))
            parts.append(jnp.log(v) if u.log else v / u.unit)
        return jnp.concatenate(parts)

    def to_values(self, theta) -> dict:
        vals = dict(self.fixed)
        for u in self.unknowns:
            x = theta[self.slices[u.name]]
            v = jnp.exp(x) if u.log else x * u.unit
            vals[u.name] = v[0] if u.size == 1 else v
        return vals

    def refined(self, **solver) -> Problem:
        """This problem on another discretisation (`pcrjax.with_solver` settings: nodes, dt,
        tol), with the same noise levels and frames counted."""
        out = Problem(self.rec, self.fit, scene=pcrjax.with_solver(self.scene, **solver))
        out.sigma, out.keep = np.array(self.sigma), self.keep.copy()
        return out

    def reported(self, theta) -> dict:
        """name -> value (float64 array) of every unknown at ``theta``, and the pattern frame's
        offset and rotation derived from the model's pose at t = 0 (one short rollout)."""
        vals = self.to_values(jnp.asarray(theta))
        out = {u.name: np.atleast_1d(np.asarray(vals[u.name], float)) for u in self.unknowns}
        offset, rotation = frame_transform(jnp.asarray(self.motion(theta, 0.0)[0]), vals)
        out.update(frame_offset=np.asarray(offset, float), frame_rotation=np.atleast_1d(np.asarray(rotation, float)))
        return out

    def labels(self) -> list[str]:
        out = []
        for u in self.unknowns:
            out += [u.name] if u.size == 1 else [f"{u.name}[{k}]" for k in range(u.size)]
        return out

    # -- model --------------------------------------------------------------------------------
    def window(self, t_end: float | None = None):
        """(mask of the frames counted, rollout steps needed): the frames in ``keep`` up to
        ``t_end`` (all: None)."""
        n = self.t.size if t_end is None else int(np.searchsorted(np.asarray(self.t), t_end, side="right"))
        n = max(n, 1)
        dt, steps = self.scene.solver.dt, self.scene.solver.steps
        need = float(self.t[n - 1]) + self.rec.exposure + 0.02  # time offsets up to 20 ms
        mask = self.keep & (np.arange(self.t.size) < n)
        return jnp.asarray(mask, jnp.float64), jnp.asarray(min(steps, int(math.ceil(need / dt)) + 3), jnp.int32)

    def counted(self, t_end: float | None = None) -> int:
        """Residuals that count in the window up to ``t_end``."""
        return 3 * int(np.sum(np.asarray(self.window(t_end)[0])))

    def _split(self, theta):
        return theta[: self.n_physical], theta[self.n_physical :]

    def _motion(self, theta_phys, theta_cam, active):
        """(simulated planar poses (T, 3) sampled every dt, zeros after ``active`` steps; whether
        every step's Newton solve converged)."""
        vals = self.to_values(jnp.concatenate([theta_phys, theta_cam]))
        s = experiment.apply(self.scene, vals)
        traj = pcrjax.rollout(s, active)
        return experiment.planar_pose(s, traj), jnp.all(traj.converged)

    def _observe(self, motion, theta_phys, theta_cam):
        vals = self.to_values(jnp.concatenate([theta_phys, theta_cam]))
        offset, rotation = frame_transform(motion[0], vals)
        return camera.observe(motion, self.scene.solver.dt, self.t, self.rec.exposure, offset, rotation, vals["time_offset"])

    def _seen_residual_fn(self, motion, theta_phys, theta_cam, sigma, mask):
        return ((self._observe(motion, theta_phys, theta_cam) - self.data) * (mask[:, None] / sigma)).reshape(-1)

    def _residual_fn(self, theta, sigma, mask, active):
        tp, tc = self._split(theta)
        motion, ok = self._motion(tp, tc, active)
        # a rollout whose Newton solves failed is no model of anything: NaN, never a residual
        return jnp.where(ok, self._seen_residual_fn(motion, tp, tc, sigma, mask), jnp.nan), jnp.where(ok, motion, jnp.nan)

    def _residual_and_jacobian_fn(self, theta, sigma, mask, active):
        tp, tc = self._split(theta)
        w = mask[:, None] / sigma
        # tangents of the motion for the physical unknowns only
        motion, dmotion, ok = jax.vmap(
            lambda v: jax.jvp(lambda x: self._motion(x, tc, active), (tp,), (v,), has_aux=True), out_axes=(None, -1, None)
        )(jnp.eye(tp.size))
        # the camera is linear in the motion: push each tangent through it
        d_seen = jax.vmap(lambda dm: jax.jvp(lambda m: self._observe(m, tp, tc), (motion,), (dm,))[1], in_axes=-1, out_axes=-1)(
            dmotion
        )
        j_cam = jax.jacfwd(lambda c: self._observe(motion, tp, c))(tc)
        J = jnp.concatenate([d_seen, j_cam], axis=-1) * w[..., None]
        r = jnp.where(ok, self._seen_residual_fn(motion, tp, tc, sigma, mask), jnp.nan)
        return r, J.reshape(-1, theta.size), motion[0], dmotion[0]

    def residual(self, theta, sigma=None, t_end=None):
        sigma = jnp.asarray(self.sigma if sigma is None else sigma)
        return self._residual(jnp.asarray(theta), sigma, *self.window(t_end))[0]

    def motion(self, theta, t_end):
        """Simulated planar poses (robot frame) every dt up to ``t_end`` (same compiled program)."""
        m = self._residual(jnp.asarray(theta), jnp.asarray(self.sigma), *self.window(t_end))[1]
        return np.asarray(m)[: int(round(t_end / self.scene.solver.dt)) + 1]

    def residual_and_jacobian(self, theta, sigma=None, t_end=None):
        sigma = jnp.asarray(self.sigma if sigma is None else sigma)
        return self._residual_and_jacobian(jnp.asarray(theta), sigma, *self.window(t_end))[:2]

    def frame(self, theta):
        """(values, Jacobian wrt theta) of the pattern frame's offset (2) and rotation (1), derived
        from the start pose and the model's pose at t = 0 (its tangents from the compiled
        Jacobian on the shortest window: a few steps)."""
        _, _, m0, dm0 = self._residual_and_jacobian(jnp.asarray(theta), jnp.asarray(self.sigma), *self.window(0.0))
        m0, dm0 = np.asarray(m0), np.asarray(dm0)
        n = self.n_physical

        def f(m0_, tc):
            vals = self.to_values(jnp.concatenate([jnp.asarray(theta[:n]), tc]))
            off, rot = frame_transform(m0_, vals)
            return jnp.concatenate([off, rot[None]])

        tc = jnp.asarray(theta[n:])
        d_m0, d_tc = jax.jacfwd(f, argnums=(0, 1))(jnp.asarray(m0), tc)
        return np.asarray(f(jnp.asarray(m0), tc)), np.concatenate([np.asarray(d_m0) @ dm0, np.asarray(d_tc)], axis=1)

    def fit_linear(self, theta, t_end=None, max_iter: int = 10):
        """(``theta`` with the unknowns the motion seen depends on (nearly) linearly fitted to the
        frames up to ``t_end``, the cost there): Levenberg-Marquardt on the camera's unknowns and
        the released push, the motion held at ``theta``'s and linear in the push (its tangents by
        finite differences: one rollout per push component; the camera's Jacobian costs none).
        Cost inf where a rollout fails."""
        theta = np.asarray(theta, float)
        n, sigma = self.n_physical, jnp.asarray(self.sigma)
        mask, active = self.window(t_end)
        push = np.concatenate(
            [np.arange(n)[self.slices[k]] for k in ("push_force", "push_moment") if k in self.slices] or [np.zeros(0, int)]
        )
        motions = []
        for i in [None, *push]:
            th = theta.copy()
            if i is not None:
                th[i] += 1.0
            motions.append(self._residual(jnp.asarray(th), sigma, mask, active)[1])
        if not all(bool(jnp.all(jnp.isfinite(m))) for m in motions):
            return theta, math.inf
        m0, dm = motions[0], jnp.stack([m - motions[0] for m in motions[1:]], axis=-1) if push.size else None
        x0 = np.concatenate([theta[push], theta[n:]])
        args = (m0, dm, jnp.asarray(theta), jnp.asarray(push), sigma, mask)
        rf = lambda x: self._linear_residual(x, *args)  # noqa: E731
        rj = lambda x: (rf(x), self._linear_jacobian(x, *args))  # noqa: E731
        x, _, r, _, _, _ = levenberg_marquardt(rf, rj, x0, max_iter, ftol=1e-8, max_step=math.inf)
        out = theta.copy()
        out[push], out[n:] = x[: push.size], x[push.size :]
        return out, 0.5 * float(r @ r)

    def _linear_residual_fn(self, x, m0, dm, theta, push, sigma, mask):
        """Residuals with the motion ``m0`` moved along the push tangents ``dm`` by the push's
        change in ``x`` (push unknowns first, camera unknowns after)."""
        k = push.size
        tp = theta[: self.n_physical].at[push].set(x[:k])
        motion = m0 if k == 0 else m0 + dm @ (x[:k] - theta[push])
        return self._seen_residual_fn(motion, tp, x[k:], sigma, mask)

    def seen(self, theta, t_end=None):
        """Camera poses (M, 3) at ``theta`` (frames after ``t_end``: the recording's own)."""
        sigma = jnp.asarray(self.sigma)
        return self.data + self.residual(theta, sigma, t_end).reshape(-1, 3) * sigma


class FitError(RuntimeError):
    """The fit cannot go on (a simulation that does not converge at the values it must start from)."""


@dataclasses.dataclass
class Result:
    labels: list
    values: dict  # name -> value (list or float)
    standard_errors: dict
    correlation: list  # (p, p) of the fitted unknowns, in `labels` order (log space for log unknowns)
    sigma: list  # noise estimates: position (m), angle (rad)
    loss: float  # final reduced chi-square
    rms: list  # RMS residual per column, in m, m, rad
    iterations: int = 0
    wall_s: float = 0.0
    converged: bool = True
    history: list = dataclasses.field(default_factory=list)  # loss per iteration (all stages)
    stages: list = dataclasses.field(default_factory=list)  # per stage: window, iterations, final loss
    message: str = ""
    # the model error of the values (`discretisation`): how far each moved on the last grid
    # refinement and with a tenth of the Newton tolerance; the model the values come from
    discretisation_errors: dict = dataclasses.field(default_factory=dict)
    tolerance_errors: dict = dataclasses.field(default_factory=dict)
    model: dict = dataclasses.field(default_factory=dict)  # nodes, dt, tol
    refinements: list = dataclasses.field(default_factory=list)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    def uncertainty(self, name):
        """The statistical and discretisation errors of ``name`` combined (root sum of squares)."""
        return np.hypot(self.standard_errors[name], self.discretisation_errors.get(name, 0.0))


def _covariance(J):
    JtJ = J.T @ J
    d = 1.0 / np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    return d[:, None] * np.linalg.pinv(d[:, None] * JtJ * d[None, :], rcond=1e-14) * d[None, :]


def levenberg_marquardt(
    rf: Callable,
    rj: Callable,
    theta0,
    max_iter=30,
    xtol=1e-8,
    ftol=1e-10,
    max_step=0.5,
    start: dict | None = None,
    save=None,
    progress=None,
    initial=None,
):
    """Minimise ``0.5 |rf(theta)|^2``, with ``rj(theta) = (residual, Jacobian)``.

    Steps are bounded to ``max_step`` (a number, or one per unknown: they are O(1), logs and
    typical units), a trust region that keeps the first steps from a poor guess out of far minima. ``start`` (a
    state that ``save`` was given) resumes an interrupted run; ``save(state)`` is called after
    every accepted step; ``initial``, ``rj(theta0)`` if already known. Returns (theta, J, r,
    iterations, converged, history)."""
    theta = np.asarray(theta0, float)
    lam, history, it0 = 1e-3, [], 0
    if start is not None:
        theta, lam, history, it0 = np.asarray(start["theta"], float), start["lam"], list(start["history"]), start["iteration"]
    r, J = (np.asarray(a) for a in (rj(jnp.asarray(theta)) if initial is None or start is not None else initial))
    cost = 0.5 * float(r @ r)
    if not (np.isfinite(cost) and np.all(np.isfinite(J))):
        raise FitError(
            "the residual or its Jacobian at the start is not finite (a simulation whose Newton solves did not converge)"
        )
    if not history:
        history.append(cost)
    converged = False
    it = it0
    for it in range(it0 + 1, max_iter + 1):
        g = J.T @ r
        A = J.T @ J
        accepted = False
        scale = np.diag(np.diag(A) + 1e-12 * np.max(np.diag(A)))
        for _ in range(12):
            step = np.linalg.solve(A + lam * scale, -g)
            while np.any(np.abs(step) > max_step):  # raise the damping until the step fits the region
                lam *= 4.0
                step = np.linalg.solve(A + lam * scale, -g)
            r_t = np.asarray(rf(jnp.asarray(theta + step)))
            cost_t = 0.5 * float(r_t @ r_t) if np.all(np.isfinite(r_t)) else math.inf
            if cost_t < cost:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            converged = True  # no decrease along any damped step: a minimum to the precision of the model
            it -= 1
            break
        rel = (cost - cost_t) / max(cost, 1e-300)
        theta = theta + step
        lam = max(lam / 10.0, 1e-12)
        r, J = (np.asarray(a) for a in rj(jnp.asarray(theta)))
        cost = 0.5 * float(r @ r)
        history.append(cost)
        if save is not None:
            save(dict(theta=theta.tolist(), lam=lam, history=history, iteration=it))
        if progress is not None:
            progress(it, cost, float(np.max(np.abs(step))))
        if rel < ftol or np.max(np.abs(step)) < xtol * (1.0 + np.max(np.abs(theta))):
            converged = True
            break
    return theta, J, r, it, converged, history


def adam(fun: Callable, theta0, steps=300, learning_rate=3e-2, progress=None):
    """Minimise ``0.5 |fun(theta)|^2`` with optax Adam (reverse-mode gradients); for comparison.
    Stops at a non-finite loss (a step into parameters where the simulation fails: Adam has no
    way to reject a step), the NaN last in the history."""
    import optax

    loss = jax.jit(jax.value_and_grad(lambda th: 0.5 * jnp.sum(fun(th) ** 2)))
    opt = optax.adam(learning_rate)
    theta = jnp.asarray(theta0)
    state = opt.init(theta)
    history = []
    for k in range(steps):
        val, g = loss(theta)
        history.append(float(val))
        if not np.isfinite(history[-1]):
            break
        upd, state = opt.update(g, state)
        theta = optax.apply_updates(theta, upd)
        if progress is not None:
            progress(k + 1, float(val), float(jnp.max(jnp.abs(upd))))
    return np.asarray(theta), history


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
    features match the recording's), ranked by the loss over the first ``rank_window`` seconds
    after the forcing with the push and the camera fitted (a rollout per push component,
    `Problem.fit_linear`); the ``screen_best`` best are screened by a short Levenberg-Marquardt
    fit of all unknowns on the first ``screen_window`` seconds, which mode shapes and amplitudes
    decide. Returns (the best, the screening: None, or its ``window`` end, ``candidates``,
    ``iterations`` and the best's loss ``history``: the fit's windows up to that end are then
    done). ``progress(stage, i, loss, step)``, loss and
    step None for a message; ``warm()`` is called once the features are known and the first
    simulation has compiled (the caller builds the Jacobian's program meanwhile)."""
    theta, found = start.initial_lengths(problem, theta, progress, warm) if "lengths" in problem.slices else (theta, [])
    if not found:
        return start.initial_tau(problem, theta, progress), None
    i_len = problem.slices["lengths"]
    if len(found) == 1:
        theta[i_len] = found[0]
        return theta, None
    t_from = experiment.forcing_end(problem.scene)
    t_screen = t_from + screen_window
    ranked = []
    for x in found:
        th = theta.copy()
        th[i_len] = x
        th, cost = problem.fit_linear(th, t_from + rank_window)
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
    best, best_hist, iterations = None, [np.inf], 0
    for j, (_, _, th) in enumerate(ranked):
        try:
            th, _, _, it, _, hist = levenberg_marquardt(
                lambda a: problem.residual(a, None, t_screen),
                lambda a: problem.residual_and_jacobian(a, None, t_screen),
                th,
                screen_iter,
                ftol=1e-6,
                max_step=problem.max_step,
            )
        except FitError:  # the simulation fails there: not a candidate
            continue
        iterations += it
        if progress is not None:
            progress(f"candidate lengths {np.round(np.exp(th[i_len]) * 1e3, 3).tolist()} mm, screened", j + 1, hist[-1], 0.0)
        if hist[-1] < best_hist[-1]:
            best, best_hist = th, hist
    if best is None:
        raise FitError(f"{problem.rec.path}: the simulation fails at every set of lengths that gives the recorded features")
    return best, dict(window=t_screen, candidates=len(ranked), iterations=iterations, history=best_hist)


# The whole recording's passes stop when an iteration lowers the loss by less than 1e-3 of the
# current reduced chi-square (relative decrease < FINAL_FTOL / residuals): 0.5 (delta / SE)^2 is
# what a parameter delta off the optimum adds to a loss whitened by the noise, so the parameters
# then lie within about 0.05 SE of the optimum.
FINAL_FTOL = 2e-3


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
    refine_levels: int = 0,
) -> Result:
    """Fit by continuation in the recording's length, then once more with estimated noise levels.

    A frequency error wraps the phase of an oscillation, so over a whole recording the loss has
    a minimum every cycle; over its first ``first_window`` seconds it has one. Each window (that
    length, doubling up to the whole recording) starts from the previous window's optimum. The
    whole recording is fitted twice: with the nominal noise scales, then with noise levels
    estimated from the first pass's residuals (feasible generalised least squares). Progress is
    saved to ``state_dir/fit_state.json`` after every iteration; a fit started again with the
    same state folder resumes where it stopped. ``progress(stage, iteration, loss, step)``.
    Then the model error of the answer is measured on finer models (`discretisation.report`,
    up to ``refine_levels`` grid refinements; 0: none) and the values are those of the finest.
    """
    t0 = time.perf_counter()
    duration = float(problem.t[-1] - problem.t[0])
    stages = [(f"window {w:g} s", w) for w in windows(duration, first_window)[:-1]] + [
        ("whole recording", None),
        ("whole recording, noise re-estimated", None),
    ]
    state_file = None if state_dir is None else Path(state_dir) / "fit_state.json"
    theta = np.asarray(problem.to_theta(problem.initial_values))
    problem.sigma = NOMINAL_SIGMA.copy()
    done, history, total_it, resume, summary = 0, [], 0, None, []
    if state_file is not None and state_file.is_file():
        st = json.loads(state_file.read_text())
        if st.get("labels") == problem.labels() and st.get("recording") == str(problem.rec.path):
            done, history, total_it, resume = st["stage"], st["history_before"], st["iterations_before"], st["lm"]
            theta, problem.sigma = np.asarray(st["lm"]["theta"]), np.asarray(st["sigma"])

    def save(lm_state, k):
        if state_file is not None:
            state_file.write_text(
                json.dumps(
                    dict(
                        recording=str(problem.rec.path),
                        labels=problem.labels(),
                        stage=k,
                        sigma=list(map(float, problem.sigma)),
                        history_before=history,
                        iterations_before=total_it,
                        lm=lm_state,
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
            warm = lambda: compiled.append(background.submit(problem.residual_and_jacobian, theta, None, 0.0))  # noqa: E731
            theta, screened = modal_start(problem, theta, progress, warm=warm)
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
        if k == len(stages) - 1 and (resume is None or k > done or resume["iteration"] == 0):
            # the previous (whole-recording) pass's residuals and Jacobian, reweighted, when it ran
            # here: no simulation
            known = r is not None
            old = problem.sigma
            res = ((r if known else np.asarray(problem.residual(theta))).reshape(-1, 3) * old)[problem.keep]
            problem.sigma = np.maximum([np.sqrt(np.mean(res[:, :2] ** 2))] * 2 + [np.sqrt(np.mean(res[:, 2] ** 2))], 1e-15)
            if known:
                w = old / problem.sigma
                initial = ((r.reshape(-1, 3) * w).reshape(-1), (J.reshape(-1, 3, J.shape[1]) * w[None, :, None]).reshape(J.shape))
        sigma = jnp.asarray(problem.sigma)
        final = t_end is None

        try:
            theta, J, r, it, converged, hist = levenberg_marquardt(
                lambda th: problem.residual(th, sigma, t_end),
                lambda th: problem.residual_and_jacobian(th, sigma, t_end),
                theta,
                max_iter,
                ftol=FINAL_FTOL / problem.counted(None) if final else 1e-6,
                max_step=problem.max_step,
                start=resume if k == done else None,
                save=lambda st, k=k: save(st, k),
                progress=None if progress is None else (lambda i, c, st, label=label: progress(label, i, c, st)),
                initial=initial,
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
        r, J = (np.asarray(a) for a in problem.residual_and_jacobian(theta))
        converged = bool(resume.get("converged", False))
    result = summarize(
        problem, theta, J, r, t_end=None, iterations=total_it, converged=converged, history=history, stages=summary
    )
    if refine_levels > 0:
        result = discretisation.report(
            problem, theta, J, result, refine_levels, None if progress is None else (lambda msg: progress(msg, 0, None, 0.0))
        )
    return dataclasses.replace(result, wall_s=time.perf_counter() - t0)


def standard_errors_theta(J, chi2: float):
    """Standard errors of theta from the Gauss-Newton covariance rescaled by ``chi2``."""
    return np.sqrt(np.maximum(np.diag(_covariance(J) * chi2), 0.0))


def summarize(problem: Problem, theta, J, r, t_end=None, **info) -> Result:
    """The `Result` at an optimum ``theta`` (with its Jacobian ``J`` and residuals ``r`` over the
    window up to ``t_end``): values, standard errors from the Gauss-Newton covariance rescaled by
    the reduced chi-square, correlations, and the pattern frame derived with its errors."""
    keep = np.asarray(problem.window(t_end)[0]) > 0
    m, p = problem.counted(t_end), theta.size
    chi2 = float(r @ r) / max(m - p, 1)
    cov = _covariance(J) * chi2
    se_theta = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = cov / np.outer(se_theta, se_theta)
    vals = problem.to_values(jnp.asarray(theta))
    values, errors = {}, {}
    for u in problem.unknowns:
        v = np.atleast_1d(np.asarray(vals[u.name], float))
        s = se_theta[problem.slices[u.name]] * (v if u.log else u.unit)  # d exp(x) = exp(x) dx
        values[u.name] = v.tolist() if u.size > 1 else float(v[0])
        errors[u.name] = s.tolist() if u.size > 1 else float(s[0])
    frame, G = problem.frame(theta)  # the pattern frame, derived: errors by the delta method
    frame_se = np.sqrt(np.maximum(np.diag(G @ cov @ G.T), 0.0))
    values.update(frame_offset=frame[:2].tolist(), frame_rotation=float(frame[2]))
    errors.update(frame_offset=frame_se[:2].tolist(), frame_rotation=float(frame_se[2]))
    res = (r.reshape(-1, 3) * problem.sigma)[keep]
    return Result(
        labels=problem.labels(),
        values=values,
        standard_errors=errors,
        correlation=corr.tolist(),
        sigma=[float(problem.sigma[0]), float(problem.sigma[2])],
        loss=chi2,
        rms=np.sqrt(np.mean(res**2, axis=0)).tolist(),
        **info,
    )
