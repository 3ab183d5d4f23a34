r"""Rod lengths and damping of a planar platform's push-release recording: a screen of the prior
against the recorded free motion, through the platform's lumped modes.

**The lumped modes.** The rods weigh 1e-5 of the platform, so after a release the platform moves
as three coupled oscillators: the stiffness ``K`` is the inverse of the static compliance
d(x, y, theta)/d(Fx, Fy, Mz) at the rest (statics only, a few milliseconds per set of lengths),
the mass ``M = diag(m, m, I_z)`` the platform's. Kelvin-Voigt damping of massless linear rods is
the damping matrix ``tau K`` exactly (a rod's strain is linear in the pose, so its stress
``K (eps + tau eps')`` is the stiffness acting on ``x + tau x'``): mode k decays at
``tau w_k^2 / 2`` and oscillates at ``w_k sqrt(1 - zeta_k^2)``, ``zeta_k = tau w_k / 2``.

**The comparison** is made at the frame times, so the aliasing (114 frames/s show 70-160 Hz
modes) and the missing frames are the recording's own and no frequency is unfolded::

    pose(t) - settled = sum_k [R(beta) phi_k] e^{-s_k t} (a_k cos w_k t + b_k sin w_k t)

``R(beta)`` is the camera's rotation (the settled angle minus the model's rest angle), ``phi_k``
the mode shapes; the amplitudes ``(a_k, b_k)`` are free, since the push, the exposure and the
camera's clock offset each only scale and rephase every mode, and are solved by linear least
squares for each candidate (variable projection). The remaining weighted sum of squares ranks
candidate lengths and tau: it uses every mode's frequency, decay and shape in the three
channels at once, where matching a few frequencies read off the recording left 30 % of the
prior "matching".

**The stages** (`screen`): the nominal lengths and a seeded Latin hypercube of the prior, each
with tau on a log grid over ``TAU_RANGE``; the best few are polished by Levenberg-Marquardt on
(log lengths, log tau) (finite differences: a model evaluation is a static solve); the distinct
polished ones close to the best go on to the time-domain ranking with the full model.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import identify
from pcrjax import traces
from pcrjax.numerics import results
from pcrjax.physics.rotations import rotation_vector
from pcrjax.robots import statics

from . import experiment, threads
from .least_squares import FitError, levenberg_marquardt
from .problem import padded_frames

SCREENED = 1024  # sets of lengths screened (the nominal ones and a Latin hypercube)
TAUS = 25  # tau values screened per set of lengths, log-spaced over the prior's range
POLISHED = 8  # the best screened polished by Levenberg-Marquardt
KEPT = 3  # polished candidates passed on to the full model's ranking ...
CLOSE = 3.0  # ... if their sum of squares is within this factor of the best's
HORIZON = 0.5  # s of free motion compared (the modes have decayed by then)
FD_STEP = 1e-6  # finite-difference step in log lengths and log tau


def planar_rest(scene, near=None):
    """(x, y, theta of the static equilibrium at t = 0, whether its solve converged, its
    unknowns). ``near``: a neighbouring equilibrium's unknowns to start Newton from
    (`pcrjax.robots.statics.solve_static`)."""
    st = statics.solve_static(scene, near=near)
    pose = jnp.concatenate([st.position[:2], rotation_vector(st.rotation)[2:]])
    return pose, st.stats.result == results.SUCCESSFUL, st.unknowns


def for_screening(scene):
    """``scene`` whose static solve, where its continuation loses its path, ends there and is
    marked unconverged, without a retry: in a screen of many candidates such a set of lengths is
    only passed over."""
    newton = dataclasses.replace(scene.solver.newton, stop_when_lost=True)
    return dataclasses.replace(scene, solver=dataclasses.replace(scene.solver, newton=newton))


def lumped_modes(scene, from_push: bool = False):
    """Jitted ``log lengths -> (rest pose (3,), angular frequencies w (3,) rad/s, mode shapes
    phi (3, 3) (columns, M-orthonormal), whether the static solve converged)`` of a planar
    platform on massless rods (see the module's text). ``from_push``: the rest is reached as
    the release reaches it, from the pushed equilibrium (the scene's load at t = 0) with the
    push halved and then gone, Newton from each; a static solve falls back on its own
    continuation where that fails. The continuation from straight rods to the assembly loses
    its path near some lengths (a third of those within 0.2 % of triskele_push_release_r2's
    truth), which the path from the push does not. Over the whole prior it costs about twice as
    much, so the screen does without it and the polish takes it where the plain solve fails."""
    return jax.jit(lambda log_lengths: lumped(scene, log_lengths, from_push))


def lumped(scene, log_lengths, from_push: bool = False):
    """`lumped_modes` of ``scene`` at ``log lengths`` (traceable in both)."""
    body = scene.end.body
    mass = jnp.stack([body.mass, body.mass, body.inertia[2]])
    scene = for_screening(scene)

    def loaded(lengths, scale, wrench):  # the recorded load (the push at t = 0) times scale, plus wrench
        s = experiment.apply(scene, {"lengths": lengths})
        force = scale * s.load.force + jnp.zeros(3).at[:2].set(wrench[:2])
        moment = scale * s.load.moment + jnp.zeros(3).at[2].set(wrench[2])
        return eqx.tree_at(lambda s: (s.load.force, s.load.moment), s, (force, moment))

    L = jnp.exp(log_lengths)

    near = None
    if from_push:
        _, _, pushed = planar_rest(loaded(L, 1.0, jnp.zeros(3)))
        _, _, near = planar_rest(loaded(L, 0.5, jnp.zeros(3)), near=pushed)

    def pose(wrench):  # the rest pose and its convergence ride along as aux: one static solve
        p, ok, _ = planar_rest(loaded(L, 0.0, wrench), near=near)
        return p, (p, ok)

    C, (rest, ok) = jax.jacfwd(pose, has_aux=True)(jnp.zeros(3))
    K = jnp.linalg.inv(C)
    K = 0.5 * (K + K.T)
    r = 1.0 / jnp.sqrt(mass)
    w2, v = jnp.linalg.eigh(r[:, None] * K * r[None, :])
    return rest, jnp.sqrt(jnp.maximum(w2, 0.0)), r[:, None] * v, ok & jnp.all(jnp.isfinite(w2))


def platform_modes(scene):
    """Jitted ``log lengths -> (frequencies Hz (3,), shapes (3,))`` of the lumped modes; shape =
    |planar| / |angular| amplitude (m/rad). NaN where the static solve fails."""
    modes_of = lumped_modes(scene)

    @jax.jit
    def of(log_lengths):
        _, w, phi, ok = modes_of(log_lengths)
        shape = jnp.hypot(phi[0], phi[1]) / jnp.abs(phi[2])
        return jnp.where(ok, w / (2 * jnp.pi), jnp.nan), jnp.where(ok, shape, jnp.nan)

    return of


class FreeMotion:
    """The recording's motion after the release at ``t_from``, about its settled pose (the mean
    of the last half of the frames after the release) and in units of its noise (their
    scatter: one level for the two positions, one for the angle), over ``HORIZON`` seconds."""

    def __init__(self, rec, t_from: float):
        after = rec.t >= t_from
        t, pose = rec.t[after], rec.pose[after]
        if t.size < 12:
            raise ValueError(f"{rec.path}: {t.size} frames after the release at t = {t_from:g} s: too short to screen the prior")
        late = t >= 0.5 * (t[0] + t[-1])
        self.settled = np.mean(pose[late], axis=0)
        spread = np.std(pose[late], axis=0)
        self.sigma = np.maximum([np.hypot(*spread[:2]) / np.sqrt(2)] * 2 + [spread[2]], 1e-15)
        active = t < t_from + HORIZON
        self.t = jnp.asarray(t[active] - t_from)
        self.data = jnp.asarray(((pose[active] - self.settled) / self.sigma).reshape(-1))
        self.rows = int(self.data.size)

    def arrays(self, frames: int | None = None):
        """(times, whitened data, weights, noise levels, settled pose): what `free_residual`
        reads, padded with frames of weight 0 up to ``frames``."""
        n = int(self.t.size)
        extra = (n if frames is None else frames) - n
        return (
            jnp.concatenate([self.t, jnp.zeros(extra)]),
            jnp.concatenate([self.data, jnp.zeros(3 * extra)]),
            jnp.concatenate([jnp.ones(n), jnp.zeros(extra)]),
            jnp.asarray(self.sigma),
            jnp.asarray(self.settled),
        )

    def residual(self, rest, w, phi, log_tau):
        """Whitened residuals (rows,) of the best amplitudes for the modes ``(w, phi)`` about the
        rest pose ``rest`` at damping ``exp(log_tau)``."""
        return free_residual(self.arrays(), rest, w, phi, log_tau)


def free_residual(motion, rest, w, phi, log_tau):
    """`FreeMotion.residual` of the free ``motion`` (`FreeMotion.arrays`; a frame of weight 0
    counts for nothing and its residuals are 0)."""
    t, data, weight, sigma, settled = motion
    beta = settled[2] - rest[2]
    c, s = jnp.cos(beta), jnp.sin(beta)
    seen = jnp.stack([c * phi[0] - s * phi[1], s * phi[0] + c * phi[1], phi[2]]) / sigma[:, None]
    zeta = 0.5 * jnp.exp(log_tau) * w
    decay, wd = zeta * w, w * jnp.sqrt(jnp.clip(1.0 - zeta**2, 1e-12))
    env = jnp.exp(-decay[None, :] * t[:, None]) * weight[:, None]
    phase = wd[None, :] * t[:, None]
    waves = jnp.stack([env * jnp.cos(phase), env * jnp.sin(phase)], axis=-1)  # (frames, modes, 2)
    A = (seen[None, :, :, None] * waves[:, None, :, :]).reshape(data.size, -1)  # rows: frames x channels
    amps = jnp.linalg.lstsq(A, data)[0]
    return data - A @ amps


def modes_program(from_push: bool):
    """``(scene, log lengths) -> `lumped` `` (``from_push``: `lumped_modes`): the program that
    the screen runs once per candidate and the polish once per set of lengths it tries. The
    screen calls it candidate by candidate rather than as a batch, so that the screen and the
    polish share one compiled static solve (a program of a batch is another program, and the
    static solve is most of either's compile). Each solve runs the platform's load continuation:
    Newton started from a solved neighbour instead misses a few percent of the prior, in the
    corner where one rod is short (triskele_push_release_r2's truth lies there)."""

    def of(scene, log_lengths):
        return lumped(scene, log_lengths, from_push)

    return of


def tau_residuals(free, rest, w, phi, ok, log_taus):
    """`free_residual` of the modes ``(rest, w, phi)`` at each of ``log_taus`` (len(log_taus),
    rows; NaN where ``ok``, their static solve's convergence, is false): one least-squares fit of
    the amplitudes after another (`jax.lax.map`), so that each is one LAPACK call and the
    programs run side by side in threads (`identify.threads`). It takes `lumped`'s outputs as
    they come, so a caller queues it behind the static solve without waiting for that."""
    w, phi = jnp.where(ok, w, 1.0), jnp.where(ok, phi, jnp.eye(3))  # a failed solve's NaN kept out of LAPACK
    r = jax.lax.map(lambda lt: free_residual(free, rest, w, phi, lt), log_taus)
    return jnp.where(ok, r, jnp.nan)


def screen(problem, theta, i_len, say, prior_length: float, tau_range: float, seed: int = 0, warm=None):
    """(log tau, the candidate log lengths worth ranking with the full model, best first) of a
    planar push-release recording (see the module's text). ``theta``: the start (its lengths
    the nominal ones, its damping the scene's); ``warm()`` is called once the recording is
    known to hold enough free motion and the static solve's program is traced."""
    from .start import latin_hypercube  # noqa: PLC0415 (start imports this module)

    load = problem.scene.load  # free from the last event: a push released, or a load stepped on
    events = [float(np.asarray(v)) for v in (load.apply_time, load.release_time) if np.isfinite(np.asarray(v))]
    motion = FreeMotion(problem.rec, max([experiment.forcing_end(problem.scene), *events]))
    x0 = np.asarray(theta[i_len], float)
    tau0 = float(np.mean(np.asarray(problem.fixed["tau"])))
    log_taus = np.log(tau0) + np.linspace(-1.0, 1.0, TAUS) * np.log(tau_range)
    # The programs take the scene and the free motion (padded like the full model's frames,
    # `problem.padded_frames`) as arguments: recordings of one robot share them.
    free = motion.arrays(padded_frames(int(motion.t.size)))

    # One static solve per set of lengths gives the modes (a program with its trace kept on
    # disk; where its continuation is lost, the rest reached from the push, `lumped_modes`, a
    # program compiled only then), and one small program their residuals at each of a row of
    # log tau: the screen's tau grid, or the polish's tau and its finite difference.
    plain = traces.jit_over(modes_program(False), "identify-modes", problem.scene, (), (identify,))
    pushed = traces.jit_over(modes_program(True), "identify-modes-push", problem.scene, (), (identify,))
    at_taus = traces.jit(tau_residuals, "identify-tau-residuals", (), (identify,))
    # The static solve traced first, alone: it compiles while ``warm`` traces the fit's programs.
    plain.trace(x0)
    if warm is not None:
        warm()

    def residuals(modes, taus):
        """Residuals (len(taus), rows) of ``modes`` (NaN where their static solve failed)."""
        padded = np.full(TAUS, taus[-1])
        padded[: len(taus)] = taus
        return np.asarray(at_taus(free, *modes, jnp.asarray(padded)))[: len(taus), : motion.rows]

    def solved(x, taus, first, then):
        """(residuals at log lengths ``x`` and each of ``taus`` by the program ``first``, or by
        ``then`` where its solve fails; whether ``then`` gave them)"""
        r = residuals(first(x), taus)
        if np.all(np.isfinite(r)):
            return r, False
        return residuals(then(x), taus), True

    def residual(y):
        return solved(jnp.asarray(y[:-1]), [y[-1]], plain, pushed)[0][0]

    def with_jacobian(y):
        # the differences take the rest the way the centre took it: where the plain solve failed
        # there, it fails a step of 1e-6 away too, and a failed continuation costs twice a solve;
        # the step in tau needs no static solve of its own
        y = np.asarray(y, float)
        (r, r_tau), by_push = solved(jnp.asarray(y[:-1]), [y[-1], y[-1] + FD_STEP], plain, pushed)
        order = (pushed, plain) if by_push else (plain, pushed)
        near = [solved(jnp.asarray(y[:-1] + FD_STEP * e), [y[-1]], *order)[0][0] for e in np.eye(y.size - 1)]
        return r, np.stack([(n - r) / FD_STEP for n in [*near, r_tau]], axis=1)

    def polish(y):
        try:
            y, _, r, *_ = levenberg_marquardt(residual, with_jacobian, y, 20, ftol=1e-8, max_step=0.2)
        except FitError:
            return y, np.inf
        inside = np.all(np.abs(np.exp(y[:-1]) - np.exp(x0)) <= 1.5 * prior_length)
        return y, float(r @ r) if inside else np.inf

    cands = np.log(latin_hypercube(np.exp(x0), prior_length, SCREENED, seed))

    # one candidate at a time on one thread per core (the first alone: it compiles the programs)
    def costs(x):
        return np.sum(np.square(residuals(plain(x), log_taus)), axis=1)

    screened = np.stack(list(threads.map_in_threads(costs, list(cands))))
    screened[~np.isfinite(screened)] = np.inf
    best = np.min(screened, axis=1)
    order = [i for i in np.argsort(best, kind="stable") if np.isfinite(best[i])]
    dof = max(motion.rows - 2 * 3, 1)
    say(
        f"start: screened {len(cands)} sets of lengths within ±{prior_length * 1e3:g} mm and {TAUS} values of tau "
        f"against {motion.rows // 3} frames of free motion (lumped modes): the model holds at {len(order)}"
        + (f", the best reduced chi-square {best[order[0]] / dof:.4g}" if order else "")
    )
    if not order:
        raise FitError(
            f"{problem.rec.path}: the static solve fails at every one of {len(cands)} sets of lengths within ±{prior_length:g} m of nominal"
        )
    starts = [np.append(cands[i], log_taus[int(np.argmin(screened[i]))]) for i in order[:POLISHED]]
    polished = sorted(threads.map_in_threads(polish, starts, first_alone=False), key=lambda p: p[1])
    kept = []
    for y, cost in polished:
        if np.isfinite(cost) and cost <= CLOSE * polished[0][1] and not any(np.max(np.abs(y - k)) < 1e-3 for k in kept):
            kept.append(y)
    if not kept:  # every polish failed or left the prior: the screened best
        kept = [starts[0]]
        say("start: no polished candidate stayed within the prior; going on from the screened best")
    kept = kept[:KEPT]
    top = polished[0]
    say(
        f"start: polished the {len(starts)} best: reduced chi-square {top[1] / (dof - 4):.4g} at lengths "
        f"{np.round(np.exp(top[0][:-1]) * 1e3, 3).tolist()} mm, tau {np.exp(top[0][-1]):.4g} s; "
        f"{len(kept)} go on to the full model"
    )
    return float(kept[0][-1]), [y[:-1] for y in kept]
