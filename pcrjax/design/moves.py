r"""Point-to-point moves designed by gradient through the differentiable rollout.

The platform is to go from its rest pose to a target pose in a given
time ``T`` and stay there. The plain move drives each actuator from its rest value $a_0$ to the
static inverse solution at the target, $a_1$, along the quintic smooth step $s(t/T)$ (zero
velocity and acceleration at both ends); the platform, pushed through its own dynamics, then
rings. The designed move adds smooth corrections that vanish with their first two derivatives
at both ends of the move:
$$a(t) = a_0 + (a_1 - a_0)\,s(t/T) + \sum_k c_k\,B_k(t/T),$$
with $B_k$ the quintic B-splines on uniform knots over [0, 1] whose value, velocity and
acceleration are zero at 0 and 1 (the first and last three of the clamped basis are dropped).
The coefficients minimise the residual vibration: the platform's pose error against the target
over a settling window after the move (positions in metres, the rotation times a lever arm),
as least squares through `rollout` (implicit gradients). Where the scene's actuators have
limits, their penalty rows (`least_squares.limit_rows`, scaled by the move's duration) join the
residual.

Two optimisers: Levenberg-Marquardt on the residual vector with its Jacobian by forward mode
(`jax.jacfwd`, one JVP per coefficient, the per-step factorisation shared), or optax's Adam on
the sum of squares by reverse mode. The forward solve's actuators are a table at the step
times; a finer independent run evaluates the same curve at its own step times.
"""

from __future__ import annotations

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConvergenceError, SceneError
from ..io.scene_file import with_solver
from ..numerics import results
from ..physics.rotations import exp_map, matmul, rotation_vector, transpose_matmul
from ..replay import with_actuator_table
from ..robots.inverse import check_square, solve_static_inverse
from ..simulation import rollout, simulate, solve_static
from .least_squares import levenberg_marquardt, limit_rows
from .splines import correction_basis, smooth_step


@dataclasses.dataclass(frozen=True)
class Move:
    """A point-to-point move: rest actuator values ``a0`` (n,), the target's static ones ``a1``,
    the target pose ``p1`` (3,), ``R1`` (3, 3), its duration and the settling window after it."""

    a0: jnp.ndarray
    a1: jnp.ndarray
    p1: jnp.ndarray
    R1: jnp.ndarray
    duration: float
    settle: float
    count: int  # correction coefficients per actuator

    def actuators(self, t, coeffs):
        """(len(t), n) actuator values at times ``t`` for coefficients ``coeffs`` (count, n)."""
        t = np.asarray(t, np.float64)
        plain = self.a0 + (self.a1 - self.a0) * smooth_step(jnp.asarray(t) / self.duration)[:, None]
        return plain + jnp.asarray(correction_basis(t, self.duration, self.count)) @ coeffs


def plan_move(scene, dp, dtheta, duration: float, settle: float, count: int = 4) -> tuple[Move, object]:
    """The move of the platform by ``dp`` (3,) m and rotation vector ``dtheta`` (3,) rad (planar:
    dtheta about z only) from its initial rest pose, and the scene set up for it (its duration is
    the move's plus the settling window). The target's actuator values hold the platform there
    under the loads at the end of the settling window (a load released at t = 0 is gone by then,
    and the design cancels its ringing too)."""
    check_square(scene)
    if duration <= 0 or settle <= 0:
        raise SceneError(f"move duration and settling window must be > 0 (got {duration}, {settle})")
    rest = solve_static(scene)
    p1 = rest.position + jnp.asarray(dp, jnp.float64)
    R1 = matmul(rest.rotation, exp_map(jnp.asarray(dtheta, jnp.float64)))
    target = jax.jit(solve_static_inverse, static_argnums=3)(scene, p1, R1, None, duration + settle)
    if int(target.stats.result) != results.SUCCESSFUL:
        raise ConvergenceError("no static equilibrium at the move's target pose (outside the workspace?)", 0.0)
    a0 = scene.actuator_values(jnp.zeros(()))
    _check_reachable(scene, a0, target.actuators, duration)
    move = Move(a0=a0, a1=target.actuators, p1=p1, R1=R1, duration=float(duration), settle=float(settle), count=int(count))
    return move, with_solver(scene, duration=float(duration + settle))


def shortest_duration(a0, a1, limits) -> float:
    """The least time any trajectory from ``a0`` to ``a1`` (n,) needs within ``limits``: the
    stroke at the top speed, or accelerating for half of it and braking for the other half."""
    if limits is None:
        return 0.0
    d = np.abs(np.asarray(a1) - np.asarray(a0))
    with np.errstate(divide="ignore", invalid="ignore"):
        by_speed = np.nan_to_num(d / np.asarray(limits.max_speed))
        by_acceleration = np.nan_to_num(2.0 * np.sqrt(d / np.asarray(limits.max_acceleration)))
    return float(max(by_speed.max(initial=0.0), by_acceleration.max(initial=0.0)))


def _check_reachable(scene, a0, a1, duration: float):
    """Raise `SceneError` if no trajectory meets the actuator limits: the target outside the
    range, or a stroke that even at the top speed and acceleration takes longer than ``duration``."""
    lim = scene.actuation.limits if scene.actuation is not None else None
    if lim is None:
        return
    a0, a1 = np.asarray(a0), np.asarray(a1)
    for i in range(a1.shape[0]):
        lo, hi = float(lim.low[i]), float(lim.high[i])
        if not lo <= a1[i] <= hi:
            raise SceneError(
                f"the move's target needs actuator {i + 1} at {a1[i]:.6g} m, outside its range [{lo:.6g}, {hi:.6g}] m"
            )
    need = shortest_duration(a0, a1, lim)
    if need > duration:
        raise SceneError(
            f"no trajectory makes the move in {duration:.3g} s within the actuators' max_speed and max_acceleration "
            f"(strokes {np.array2string(np.abs(a1 - a0), precision=3)} m need at least {need:.3g} s): allow more time"
        )


class MoveTables(eqx.Module):
    """A move on a scene's step times (T,): the plain move's actuator values ``plain`` (T, n),
    the corrections ``basis`` (T, count), ``after`` (T,) 1 in the settling window and 0 before,
    the target ``p1``, ``R1``, and ``time_scale`` (the move's duration, s). Arrays only, so that
    one compiled design program serves moves of every duration on the same steps."""

    plain: jnp.ndarray
    basis: jnp.ndarray
    after: jnp.ndarray
    p1: jnp.ndarray
    R1: jnp.ndarray
    time_scale: jnp.ndarray


def step_times(scene) -> np.ndarray:
    return np.arange(scene.solver.steps + 1) * float(scene.solver.dt)


def move_tables(scene, move: Move) -> MoveTables:
    t = step_times(scene)
    return MoveTables(
        plain=jnp.asarray(move.actuators(t, jnp.zeros((move.count, move.a0.shape[0])))),
        basis=jnp.asarray(correction_basis(t, move.duration, move.count)),
        after=jnp.asarray(t > move.duration + 0.5 * float(scene.solver.dt), jnp.float64),
        p1=move.p1,
        R1=move.R1,
        time_scale=jnp.asarray(move.duration, jnp.float64),
    )


def _settling_rows(scene, tab: MoveTables, coeffs, lever):
    """(T, 4) rows: the position error (m) and rotation error times ``lever`` (m) against the
    target in the settling window, zero before it; the actuator table; the rollout's codes."""
    a = tab.plain + tab.basis @ coeffs
    traj = rollout(with_actuator_table(scene, step_times(scene), a))
    on = tab.after[:, None] > 0.0
    dp = traj.position - tab.p1
    dR = jax.vmap(lambda rv: rotation_vector(transpose_matmul(tab.R1, exp_map(rv))))(traj.rotation_vector)
    dR = jnp.where(on, dR, 1.0)  # no norm at zero (rest before a pure translation), whose gradient is NaN
    rows = jnp.concatenate([dp, lever * jnp.linalg.norm(dR, axis=1, keepdims=True)], axis=1)
    return jnp.where(on, rows, 0.0), a, traj.result


def vibration(scene, move: Move, coeffs, lever: float):
    """Residuals (settling steps x 4): the platform's position error (m) and rotation error times
    ``lever`` (m) against the target at every step of the settling window."""
    t = step_times(scene)
    rows, _, code = _settling_rows(scene, move_tables(scene, move), coeffs, lever)
    return rows[t > move.duration + 0.5 * float(scene.solver.dt)], code


def move_residual(scene, lever: float):
    """``residual(c, tables) -> (r, code)``: the settling rows and, where the scene's actuators
    have limits, the penalty rows (`limit_rows`) of the coefficients ``c`` (count * n,)."""
    limits = scene.actuation.limits if scene.actuation is not None else None
    dt = scene.solver.dt

    def residual(c, tab):
        rows, a, code = _settling_rows(scene, tab, c.reshape(tab.basis.shape[1], -1), lever)
        r = rows.reshape(-1)
        if limits is not None:
            r = jnp.concatenate([r, limit_rows(a, dt, limits, tab.time_scale)])
        return r, jnp.max(code)

    return residual


def settling(traj, move: Move, band: float = 1e-6) -> dict:
    """Residual vibration after the move (largest position error in the settling window) and the
    settling time: from the end of the move until the error stays inside +-``band`` m."""
    t = np.asarray(traj.t)
    err = np.linalg.norm(np.asarray(traj.position) - np.asarray(move.p1), axis=1)
    after = t > move.duration + 1e-12
    outside = np.flatnonzero(after & (err > band))
    settle = float(t[outside[-1]] - move.duration) if outside.size else 0.0
    return {
        "residual_vibration_m": float(err[after].max()),
        "settling_time_s": settle if outside.size == 0 or outside[-1] < len(t) - 1 else float("inf"),
    }


class MovePrograms:
    """The compiled residual and Jacobian (forward mode) of moves on ``scene``'s steps, kept for
    every move of the same step count and number of coefficients."""

    def __init__(self, scene, lever: float):
        residual = move_residual(scene, lever)
        self.residual = jax.jit(residual)
        self.jacobian = jax.jit(jax.jacfwd(lambda c, tab: residual(c, tab)[0]))
        self.gradient = jax.jit(jax.value_and_grad(lambda c, tab: jnp.sum(residual(c, tab)[0] ** 2)))


def default_lever(scene) -> float:
    """The arm (m) that turns platform rotation errors into distances: its largest attachment radius."""
    return float(jnp.max(jnp.linalg.norm(scene.end.attachment, axis=1)))


def design_move(
    scene, move: Move, *, method: str = "lm", iterations: int = 10, lever: float | None = None, log=print, programs=None
) -> dict:
    """Optimise the move's correction coefficients from zero (the plain move). Returns a dict:
    ``coefficients`` (count, n), ``objective`` (sum of squares, m^2, per iteration, the plain
    move's first), ``compile_s``, ``optimise_s``, ``method``: "lm" (Levenberg-Marquardt,
    forward-mode Jacobian) or "adam" (optax, reverse-mode gradient). Trial steps whose rollout
    does not converge are rejected; a plain move that does not converge raises. ``programs``
    (`MovePrograms`) reuses compiled programs across calls."""
    if method not in ("lm", "adam"):
        raise SceneError(f"unknown design method {method!r}: 'lm' or 'adam'")
    n = move.a0.shape[0]
    progs = programs or MovePrograms(scene, default_lever(scene) if lever is None else lever)
    tab = move_tables(scene, move)
    c = jnp.zeros(move.count * n)
    t0 = time.perf_counter()
    r, code = progs.residual(c, tab)
    compile_s = time.perf_counter() - t0
    if int(code) != 0:
        raise ConvergenceError("the plain move's rollout did not converge", 0.0)
    t1 = time.perf_counter()
    if method == "lm":
        c, r, history = levenberg_marquardt(
            lambda c: progs.residual(c, tab), lambda c: progs.jacobian(c, tab), c, iterations=iterations, log=log
        )
    else:
        import optax

        history = [float(jnp.sum(r**2))]
        opt = optax.adam(1e-2 * float(jnp.max(jnp.abs(move.a1 - move.a0))))
        state = opt.init(c)
        for _ in range(iterations):
            _, g = progs.gradient(c, tab)
            upd, state = opt.update(g, state)
            c = optax.apply_updates(c, upd)
            history.append(float(jnp.sum(progs.residual(c, tab)[0] ** 2)))
            log(f"  Adam {len(history) - 1}: sum of squares {history[-1]:.3e} m^2")
    return {
        "coefficients": c.reshape(move.count, n),
        "objective": history,
        "compile_s": compile_s,
        "optimise_s": time.perf_counter() - t1,
        "method": method,
    }


def verify(scene, move: Move, coeffs, finer: bool = True):
    """Forward run of the move (``coeffs``) on the same grid, or on a finer one (2N nodes, dt/2)
    with the actuator curve evaluated at its own step times: a design must not exploit the
    discretisation."""
    if finer:
        s = scene.solver
        scene = with_solver(scene, nodes=2 * s.nodes, dt=float(s.dt) / 2.0)
    t = step_times(scene)
    return simulate(with_actuator_table(scene, t, move.actuators(t, jnp.asarray(coeffs))))
