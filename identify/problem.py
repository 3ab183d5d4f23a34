"""The fit of one recording as a least-squares problem: its unknowns and weighted residuals.

**Unknowns.** The physical parameters chosen with ``fit`` (``tau``: one damping time shared by
the rods; ``tau_per_rod``; ``tau_split``: ``tau_se`` and ``tau_bt``, stretch-shear and
bend-twist apart; ``lengths``: one per rod; ``youngs_modulus``, shared by the rods;
``platform_mass``) and the experiment's nuisance parameters,
always fitted: where the camera sees the robot at t = 0 (``start_position``, ``start_angle``;
the pattern frame's offset and rotation follow, `frame_transform`) and its clock offset, plus,
for a push-and-release, the push that was released (its force and moment). Positive parameters
are fitted as logarithms, the others in units of a typical size, so every unknown is O(1).

**Residuals.** ``(camera model - recording) / sigma`` per frame and column, with ``sigma`` the
noise of the position and angle columns, passed through a Huber loss (`robust`) when a
threshold is given: frames a decoding error threw far off weigh as little as their distance.

**Jacobians** come from `jax.jvp` through the whole rollout for the physical unknowns (each
Newton solve differentiated implicitly, `pcrjax.numerics.newton.solve`) and from the camera model alone
for the camera's unknowns. The implicit tangent of a step needs that step's exact Jacobian with
every node's derivative, which costs several residuals; a recording is mostly the robot at rest
or nearly so, where that Jacobian does not change, so the rollout holds it from step to step
while the unknowns move less than `pcrjax.numerics.newton.HOLD_MOVE` from where it was taken
(the solver's ``hold_tangent_jacobian``).
"""

from __future__ import annotations

import copy
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

import identify
import pcrjax
from pcrjax import traces

from . import camera, experiment, robust
from .least_squares import FitError, levenberg_marquardt
from .recording import Recording, RecordingError

PHYSICAL = ("tau", "tau_per_rod", "tau_split", "lengths", "youngs_modulus", "platform_mass")
DAMPING = ("tau", "tau_se", "tau_bt")  # the unknowns that are damping times
NOMINAL_SIGMA = np.array([1e-9, 1e-9, 1e-6])  # noise scales (m, m, rad) of the first pass
# The camera's unknowns: where it sees the robot's pose at t = 0 (the static equilibrium the
# motion starts from) and its clock offset. The pattern frame (offset, rotation) follows from the
# start pose and the model's own pose at t = 0 (`frame_transform`): a rod length that moves the
# robot's rest pose by a millimetre then needs no compensating change of a frame unknown, a
# valley of the loss 10^4 times narrower than it is long that Levenberg-Marquardt could not follow.
CAMERA_UNKNOWNS = (("start_position", 2, 1e-5), ("start_angle", 1, 1e-4), ("time_offset", 1, CLOCK_UNIT := 1e-3))
# The clock offset's starts for a push-and-camera fit (`Problem.fit_linear`): a push released
# and seen with its clock off by half a period of the platform's dominant mode looks like the
# opposite push seen on time, so a fit from one clock finds either. Every 0.5 ms (a thirteenth
# of the period of the Triskele's fastest platform mode, 155 Hz) over +-10 ms (the rollouts
# cover offsets up to 20 ms, `Problem.window`).
CLOCK_STARTS = np.arange(-10e-3, 10e-3 + 1e-9, 0.5e-3)
# The clock starts run together (`Problem._clock_scan`: this many Levenberg-Marquardt iterations
# each, in one program), and the fit goes on from the CLOCK_BEST cheapest.
CLOCK_ITER, CLOCK_BEST = 12, 3
# Unknowns the motion seen depends on (nearly) linearly: Levenberg-Marquardt's trust region does
# not bound their steps (a Gauss-Newton step is right for them however large; the start pose of a
# 1 kHz cantilever film is a millimetre from the first frame, a hundred typical units).
LINEAR = ("push_force", "push_moment", "start_position", "start_angle")
CAMERA = tuple(c[0] for c in CAMERA_UNKNOWNS)
NUISANCE = ("push_force", "push_moment", *CAMERA)  # fitted, but not what a fit is for
# The programs' frames and steps are padded up to multiples of these, so that recordings of one
# robot and experiment whose lengths differ a little (a few frames lost, a second more) share the
# compiled programs: padded frames count for nothing, padded steps are not simulated.
FRAME_BLOCK, STEP_BLOCK = 64, 512


def padded_frames(frames: int) -> int:
    """The programs' frame count for a recording of ``frames``."""
    return FRAME_BLOCK * -(-frames // FRAME_BLOCK)


def span(seconds: float, dt: float) -> float:
    """The simulated span (s) that covers ``seconds`` in whole blocks of STEP_BLOCK steps of ``dt``."""
    return STEP_BLOCK * math.ceil(seconds / dt / STEP_BLOCK - 1e-9) * dt


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

    A problem does not change: its noise levels and Huber threshold (`with_noise`) and the
    frames that count (`with_frames`) are set on a copy, which shares the compiled programs.
    Those take the scene and the frames as arguments (`_program`): a problem of another
    recording of the same robot and experiment runs them too, with no trace or compilation.
    """

    def __init__(self, rec: Recording, fit: tuple[str, ...], scene=None, initial: dict | None = None):
        unknown_fit = [f for f in fit if f not in PHYSICAL]
        if unknown_fit:
            raise RecordingError(f"--fit: unknown parameter {unknown_fit[0]!r} (choose from {', '.join(PHYSICAL)})")
        if sum(f in fit for f in ("tau", "tau_per_rod", "tau_split")) > 1:
            raise RecordingError("--fit: tau (shared), tau_per_rod and tau_split exclude each other")
        self.rec = rec
        sc = scene if scene is not None else experiment.build_scene(rec)
        self.scene = experiment.with_duration(sc, span(experiment.required_duration(rec), float(sc.solver.dt)))
        nom = experiment.nominal(self.scene)
        n_rods = int(np.size(nom["lengths"]))
        self.fit = tuple(fit)
        unknowns = []
        if "tau" in fit:
            unknowns.append(Unknown("tau", 1, True, 1.0))
        if "tau_per_rod" in fit:
            unknowns.append(Unknown("tau", n_rods, True, 1.0))
        if "tau_split" in fit:
            unknowns += [Unknown("tau_se", 1, True, 1.0), Unknown("tau_bt", 1, True, 1.0)]
        if "lengths" in fit:
            unknowns.append(Unknown("lengths", n_rods, True, 1.0))
        materials = experiment.material(self.scene, fit)
        unknowns += [Unknown(k, 1, True, 1.0) for k in materials]
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
        self.sigma = NOMINAL_SIGMA.copy()  # noise levels (m, m, rad): nominal scales until estimated
        self.huber = robust.NONE  # Huber threshold in noise levels (NONE: least squares)
        self.keep = np.ones(rec.t.size, bool)  # frames that count (all; fewer to study missing frames)
        self.sigma.flags.writeable = self.keep.flags.writeable = False
        # The programs take the scene and the frames as arguments (`_program`), beside the noise
        # and the window, so recordings of one robot and experiment share them.
        extra = padded_frames(rec.t.size) - rec.t.size
        self._frames = (
            jnp.concatenate([self.t, jnp.full(extra, self.t[-1])]),
            jnp.concatenate([self.data, jnp.zeros((extra, 3))]),
        )
        self._residual = self._program(Problem._residual_fn, "residual")
        self._residual_and_jacobian = self._program(Problem._residual_and_jacobian_fn, "jacobian")
        self._linear_residual = self._program(Problem._linear_residual_fn, "linear-residual")
        self._linear_jacobian = self._program(jax.jacfwd(Problem._linear_residual_fn, argnums=1), "linear-jacobian")
        self._clock_scan = self._program(Problem._clock_scan_fn, "clock-scan")
        self._frame = self._program(Problem._frame_fn, "frame")
        self.initial_values = self._initial_values({**nom, **materials}, initial or {})

    def _program(self, method, name: str):
        """``method(problem, *args)`` as a compiled program of the scene, the frames (padded,
        `padded_frames`) and ``args``, called with this problem's. Besides its arguments the
        program reads only the unknowns and the camera's exposure: those name its trace on disk
        (`pcrjax.traces`), and a recording of the same robot and experiment with as many padded
        frames and steps reuses it, and its compilation."""

        def program(scene, t, data, *args):
            pb = copy.copy(self)
            pb.scene, pb.t, pb.data, pb.fixed = scene, t, data, experiment.nominal(scene)
            return method(pb, *args)

        closure = (self.fit, self.unknowns, self.rec.experiment, self.rec.exposure)
        return traces.jit_over(program, f"identify-{name}", self.scene, closure, (identify,), self._frames)

    # -- parameter vector <-> values ----------------------------------------------------------
    def _initial_values(self, nom, given):
        # the robot at t = 0 is seen where the first frame saw it (up to the first frame's delay)
        vals = {"start_position": self.data[0, :2], "start_angle": self.data[0, 2], "time_offset": jnp.zeros(()), **nom}
        if "tau_per_rod" in self.fit:
            vals["tau"] = jnp.broadcast_to(nom["tau"], nom["lengths"].shape) * jnp.ones_like(nom["lengths"])
        elif "tau" in self.fit:
            vals["tau"] = jnp.mean(nom["tau"])
        elif "tau_split" in self.fit:
            vals["tau_se"] = vals["tau_bt"] = jnp.mean(nom["tau"])
        for k, v in given.items():
            vals[k] = jnp.asarray(v, jnp.float64)
        if "tau_split" in self.fit and "tau" in given:  # --tau0 starts both
            vals["tau_se"] = vals["tau_bt"] = jnp.mean(vals["tau"])
        return vals

    @property
    def damping(self) -> list:
        """The slices of theta that are damping times (logs)."""
        return [self.slices[n] for n in DAMPING if n in self.slices]

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
        tol), with the same noise levels, Huber threshold and frames counted."""
        out = Problem(self.rec, self.fit, scene=pcrjax.with_solver(self.scene, **solver))
        return out.with_noise(self.sigma, self.huber).with_frames(self.keep)

    def with_noise(self, sigma, huber: float | None = None) -> Problem:
        """This problem with noise levels ``sigma`` (m, m, rad) and Huber threshold ``huber``
        (noise levels; None: least squares)."""
        out = copy.copy(self)
        out.sigma = np.array(sigma, float)
        out.huber = robust.NONE if huber is None else float(huber)
        out.sigma.flags.writeable = False
        return out

    def with_frames(self, keep) -> Problem:
        """This problem with only the frames ``keep`` (bool (M,)) counted."""
        out = copy.copy(self)
        out.keep = np.array(keep, bool)
        if out.keep.shape != (self.t.size,):
            raise ValueError(f"keep: {self.t.size} frames, got shape {out.keep.shape}")
        out.keep.flags.writeable = False
        return out

    def _noise(self):
        return jnp.asarray(self.sigma), jnp.asarray(self.huber)

    def reported(self, theta) -> dict:
        """name -> value (float64 array) of every unknown at ``theta``, and the pattern frame's
        offset and rotation derived from the model's pose at t = 0 (one short rollout)."""
        vals = self.to_values(jnp.asarray(theta))
        out = {u.name: np.atleast_1d(np.asarray(vals[u.name], float)) for u in self.unknowns}
        offset, rotation = frame_transform(jnp.asarray(self.motion(theta, 0.0)[0]), vals)
        out.update(frame_offset=np.asarray(offset, float), frame_rotation=np.atleast_1d(np.asarray(rotation, float)))
        return out

    @property
    def measured(self) -> np.ndarray:
        """Which entries of theta are the physical parameters asked for (damping, lengths, E, mass), not
        the nuisance ones (the released push, the camera)."""
        return np.concatenate([np.full(u.size, u.name not in NUISANCE) for u in self.unknowns])

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

    def _window(self, t_end: float | None = None):
        """`window` with the mask padded to the programs' frames."""
        mask, active = self.window(t_end)
        return jnp.asarray(np.concatenate([np.asarray(mask), np.zeros(self._frames[0].size - mask.size)])), active

    def counted(self, t_end: float | None = None) -> int:
        """Residuals that count in the window up to ``t_end``."""
        return 3 * int(np.sum(np.asarray(self.window(t_end)[0])))

    def _split(self, theta):
        return theta[: self.n_physical], theta[self.n_physical :]

    def _motion(self, theta_phys, theta_cam, active, hold=False):
        """(simulated planar poses (T, 3) sampled every dt, zeros after ``active`` steps; whether
        every step's Newton solve converged). ``hold``: the forward tangents' step Jacobians are
        held while the unknowns barely move (`newton.HOLD_MOVE`)."""
        vals = self.to_values(jnp.concatenate([theta_phys, theta_cam]))
        s = experiment.apply(self.scene, vals)
        if hold:
            s = dataclasses.replace(s, solver=dataclasses.replace(s.solver, hold_tangent_jacobian=True))
        traj = pcrjax.rollout(s, active)
        return experiment.planar_pose(s, traj), jnp.all(traj.converged)

    def _observe(self, motion, theta_phys, theta_cam):
        vals = self.to_values(jnp.concatenate([theta_phys, theta_cam]))
        offset, rotation = frame_transform(motion[0], vals)
        return camera.observe(motion, self.scene.solver.dt, self.t, self.rec.exposure, offset, rotation, vals["time_offset"])

    def _whitened_fn(self, motion, theta_phys, theta_cam, sigma, mask):
        """(camera model - recording) / sigma (M * 3,), zero where ``mask`` is."""
        return ((self._observe(motion, theta_phys, theta_cam) - self.data) * (mask[:, None] / sigma)).reshape(-1)

    def _seen_residual_fn(self, motion, theta_phys, theta_cam, noise, mask):
        sigma, huber = noise
        return robust.huber(self._whitened_fn(motion, theta_phys, theta_cam, sigma, mask), huber)

    def _residual_fn(self, theta, noise, mask, active):
        tp, tc = self._split(theta)
        motion, ok = self._motion(tp, tc, active)
        # a rollout whose Newton solves failed is no model of anything: NaN, never a residual
        return jnp.where(ok, self._seen_residual_fn(motion, tp, tc, noise, mask), jnp.nan), jnp.where(ok, motion, jnp.nan)

    def _residual_and_jacobian_fn(self, theta, noise, mask, active):
        tp, tc = self._split(theta)
        sigma, huber = noise
        w = mask[:, None] / sigma
        # tangents of the motion for the physical unknowns only
        motion, dmotion, ok = jax.vmap(
            lambda v: jax.jvp(lambda x: self._motion(x, tc, active, hold=True), (tp,), (v,), has_aux=True),
            out_axes=(None, -1, None),
        )(jnp.eye(tp.size))
        # the camera is linear in the motion: push each tangent through it
        d_seen = jax.vmap(lambda dm: jax.jvp(lambda m: self._observe(m, tp, tc), (motion,), (dm,))[1], in_axes=-1, out_axes=-1)(
            dmotion
        )
        j_cam = jax.jacfwd(lambda c: self._observe(motion, tp, c))(tc)
        z = self._whitened_fn(motion, tp, tc, sigma, mask)
        J = (jnp.concatenate([d_seen, j_cam], axis=-1) * w[..., None]).reshape(-1, theta.size)
        r = jnp.where(ok, robust.huber(z, huber), jnp.nan)
        return r, J * robust.huber_slope(z, huber)[:, None], motion[0], dmotion[0]

    def _inputs(self, theta, t_end):
        """The arguments of the residual and Jacobian programs after the frames: ``theta``, the
        noise levels and the window up to ``t_end`` (None: all frames)."""
        return (jnp.asarray(theta), self._noise(), *self._window(t_end))

    def residual(self, theta, t_end=None):
        """Weighted residuals (M * 3,) at ``theta`` over the frames up to ``t_end`` (None: all)."""
        return self._residual(*self._inputs(theta, t_end))[0][: 3 * self.t.size]

    def motion(self, theta, t_end):
        """Simulated planar poses (robot frame) every dt up to ``t_end`` (same compiled program)."""
        m = self._residual(*self._inputs(theta, t_end))[1]
        return np.asarray(m)[: int(round(t_end / self.scene.solver.dt)) + 1]

    def trace_motion(self, theta, t_end):
        """Trace the program of `residual` and `motion` for these arguments, without compiling it."""
        self._residual.trace(*self._inputs(theta, t_end))

    def residual_and_jacobian(self, theta, t_end=None):
        r, J = self._residual_and_jacobian(*self._inputs(theta, t_end))[:2]
        return r[: 3 * self.t.size], J[: 3 * self.t.size]

    def frame(self, theta):
        """(values, Jacobian wrt theta) of the pattern frame's offset (2) and rotation (1), derived
        from the start pose and the model's pose at t = 0 (its tangents from the compiled
        Jacobian on the shortest window: a few steps)."""
        _, _, m0, dm0 = self._residual_and_jacobian(*self._inputs(theta, 0.0))
        f, d_m0, d_tc = (np.asarray(a) for a in self._frame(jnp.asarray(theta), m0))
        return f, np.concatenate([d_m0 @ np.asarray(dm0), d_tc], axis=1)

    def _frame_fn(self, theta, m0):
        """(the pattern frame's offset and rotation (3,) at ``theta`` from the model's pose at
        t = 0 ``m0``, its derivatives with respect to ``m0`` and to the camera's unknowns)."""
        n = self.n_physical

        def f(m0_, tc):
            off, rot = frame_transform(m0_, self.to_values(jnp.concatenate([theta[:n], tc])))
            return jnp.concatenate([off, rot[None]])

        return f(m0, theta[n:]), *jax.jacfwd(f, argnums=(0, 1))(m0, theta[n:])

    def fit_linear(self, theta, t_end=None, max_iter: int = 10, clocks=None):
        """(``theta`` with the unknowns the motion seen depends on (nearly) linearly fitted to the
        frames up to ``t_end``, the cost there): Levenberg-Marquardt on the camera's unknowns and
        the released push, the motion held at ``theta``'s and linear in the push (its tangents by
        finite differences: one rollout per push component; the camera's Jacobian costs none).
        With ``clocks`` (s), the fit starts from each of those time offsets (`CLOCK_STARTS`: the
        same rollouts serve every start; a few iterations each, together, `_clock_scan_fn`), goes
        on from the CLOCK_BEST cheapest, and the cheapest answer is kept. Cost inf where a rollout
        fails."""
        theta = np.asarray(theta, float)
        n, noise = self.n_physical, self._noise()
        mask, active = self._window(t_end)
        push = np.concatenate(
            [np.arange(n)[self.slices[k]] for k in ("push_force", "push_moment") if k in self.slices] or [np.zeros(0, int)]
        )
        motions = []
        for i in [None, *push]:
            th = theta.copy()
            if i is not None:
                th[i] += 1.0
            motions.append(np.asarray(self._residual(jnp.asarray(th), noise, mask, active)[1]))
        if not all(np.all(np.isfinite(m)) for m in motions):
            return theta, math.inf
        m0, dm = motions[0], np.stack([m - motions[0] for m in motions[1:]], axis=-1) if push.size else None
        x0 = np.concatenate([theta[push], theta[n:]])
        args = (jnp.asarray(m0), None if dm is None else jnp.asarray(dm), jnp.asarray(theta), jnp.asarray(push), noise, mask)
        rows = 3 * self.t.size  # the programs' padded frames left out
        rf = lambda x: self._linear_residual(x, *args)[:rows]  # noqa: E731
        rj = lambda x: (rf(x), self._linear_jacobian(x, *args)[:rows])  # noqa: E731
        starts = [x0]
        if clocks is not None and "time_offset" in self.slices:
            i_clock = push.size + self.slices["time_offset"].start - n
            scan = np.repeat(x0[None], len(clocks), axis=0)
            scan[:, i_clock] = np.asarray(clocks) / CLOCK_UNIT
            xs, costs = (np.asarray(a) for a in self._clock_scan(jnp.asarray(scan), *args))
            costs = np.where(np.isfinite(costs), costs, np.inf)
            starts = [xs[i] for i in np.argsort(costs, kind="stable")[:CLOCK_BEST]]
        best, cost = x0, math.inf
        for x in starts:
            try:
                x, _, r, _, _, _ = levenberg_marquardt(rf, rj, x, max_iter, ftol=1e-8, max_step=math.inf)
            except FitError:
                continue
            if 0.5 * float(r @ r) < cost:
                best, cost = x, 0.5 * float(r @ r)
        out = theta.copy()
        out[push], out[n:] = best[: push.size], best[push.size :]
        return out, cost

    def _clock_scan_fn(self, starts, m0, dm, theta, push, noise, mask):
        """(each of ``starts`` (S, unknowns) after CLOCK_ITER Levenberg-Marquardt iterations on
        `_linear_residual_fn`, its cost), in one program: a fixed number of iterations, each
        a step that is taken where it lowers the cost (the damping then falls tenfold, else it
        rises tenfold)."""
        rf = lambda x: self._linear_residual_fn(x, m0, dm, theta, push, noise, mask)  # noqa: E731
        jf = jax.jacfwd(rf)

        def one(x):
            def iteration(_, state):
                x, cost, lam = state
                r, J = rf(x), jf(x)
                A = J.T @ J
                d = jnp.diag(A) + 1e-12 * jnp.max(jnp.diag(A))
                step = -jnp.linalg.solve(A + lam * jnp.diag(d), J.T @ r)
                r_t = rf(x + step)
                cost_t = 0.5 * r_t @ r_t
                ok = jnp.isfinite(cost_t) & (cost_t < cost)
                return jnp.where(ok, x + step, x), jnp.where(ok, cost_t, cost), jnp.where(ok, 0.1 * lam, 10.0 * lam)

            r = rf(x)
            x, cost, _ = jax.lax.fori_loop(0, CLOCK_ITER, iteration, (x, 0.5 * r @ r, jnp.asarray(1e-3, x.dtype)))
            return x, cost

        # one start after the other: a batch of them would make each step's solve a batched LAPACK
        # call, which two programs run side by side must not hold (`identify.threads`)
        return jax.lax.map(one, starts)

    def _linear_residual_fn(self, x, m0, dm, theta, push, noise, mask):
        """Residuals with the motion ``m0`` moved along the push tangents ``dm`` by the push's
        change in ``x`` (push unknowns first, camera unknowns after)."""
        k = push.size
        tp = theta[: self.n_physical].at[push].set(x[:k])
        motion = m0 if k == 0 else m0 + dm @ (x[:k] - theta[push])
        return self._seen_residual_fn(motion, tp, x[k:], noise, mask)

    def seen(self, theta, t_end=None):
        """Camera poses (M, 3) at ``theta`` (frames after ``t_end``: the recording's own)."""
        plain = self.with_noise(self.sigma)  # the camera's poses themselves, without the Huber loss
        return np.asarray(self.data + plain.residual(theta, t_end).reshape(-1, 3) * plain.sigma)
