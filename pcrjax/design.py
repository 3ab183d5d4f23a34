r"""Trajectory design by gradient through the differentiable rollout.

**Point-to-point moves.** The platform is to go from its rest pose to a target pose in a given
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
as least squares through `rollout` (implicit gradients).

Two optimisers: Levenberg-Marquardt on the residual vector with its Jacobian by forward mode
(`jax.jacfwd`, one JVP per coefficient, the per-step factorisation shared), or optax's Adam on
the sum of squares by reverse mode. The forward solve's actuators are a table at the step
times; a finer independent run evaluates the same curve at its own step times.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConvergenceError, SceneError
from .io.scene_file import with_solver
from .numerics import results
from .physics.rotations import exp_map, matmul, rotation_vector, transpose_matmul
from .replay import with_actuator_table
from .robots.inverse import check_square, solve_static_inverse
from .simulation import rollout, simulate, solve_static


def _bspline_basis(u, n_basis: int, degree: int = 5) -> np.ndarray:
    """(len(u), n_basis) clamped uniform B-spline basis of ``degree`` on [0, 1] (Cox-de Boor)."""
    u = np.clip(np.asarray(u, np.float64), 0.0, 1.0)
    inner = np.linspace(0.0, 1.0, n_basis - degree + 1)
    knots = np.concatenate([np.zeros(degree), inner, np.ones(degree)])
    B = np.zeros((u.size, knots.size - 1))
    for j in range(knots.size - 1):
        B[:, j] = (knots[j] <= u) & (u < knots[j + 1])
    B[u >= 1.0, n_basis - 1] = 1.0  # the right end belongs to the last non-empty span
    B[u >= 1.0, n_basis:] = 0.0
    for d in range(1, degree + 1):
        for j in range(knots.size - 1 - d):
            left = knots[j + d] - knots[j]
            right = knots[j + d + 1] - knots[j + 1]
            a = (u - knots[j]) / left * B[:, j] if left > 0 else 0.0
            b = (knots[j + d + 1] - u) / right * B[:, j + 1] if right > 0 else 0.0
            B[:, j] = a + b
    return B[:, :n_basis]


def correction_basis(t, duration: float, count: int) -> np.ndarray:
    """(len(t), count) smooth corrections on [0, duration], zero with their first two derivatives
    at both ends and outside: the interior quintic B-splines of ``count + 6`` on [0, 1]."""
    t = np.asarray(t, np.float64)
    B = _bspline_basis(t / duration, count + 6)[:, 3:-3]
    return np.where(((t >= 0.0) & (t <= duration))[:, None], B, 0.0)


def smooth_step(u):
    u = jnp.clip(u, 0.0, 1.0)
    return u**3 * (10.0 - 15.0 * u + 6.0 * u**2)


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


def _check_reachable(scene, a0, a1, duration: float):
    """Raise `SceneError` if no trajectory meets the actuator limits: the target outside the
    range, or a stroke that even a constant speed cannot cover in ``duration``."""
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
        need = abs(a1[i] - a0[i]) / duration
        if need > float(lim.max_speed[i]):
            raise SceneError(
                f"no trajectory moves actuator {i + 1} by {abs(a1[i] - a0[i]):.3g} m in {duration:.3g} s within its max_speed "
                f"{float(lim.max_speed[i]):.3g} m/s (it needs at least {need:.3g} m/s on average): allow more time"
            )


def _driven(scene, move: Move, coeffs):
    t = np.arange(scene.solver.steps + 1) * float(scene.solver.dt)
    return with_actuator_table(scene, t, move.actuators(t, coeffs))


def vibration(scene, move: Move, coeffs, lever: float):
    """Residuals (settling steps x 4): the platform's position error (m) and rotation error times
    ``lever`` (m) against the target at every step of the settling window."""
    traj = rollout(_driven(scene, move, coeffs))
    t = np.arange(scene.solver.steps + 1) * float(scene.solver.dt)
    after = t > move.duration + 0.5 * float(scene.solver.dt)
    dp = traj.position[after] - move.p1
    dR = jax.vmap(lambda rv: rotation_vector(transpose_matmul(move.R1, exp_map(rv))))(traj.rotation_vector[after])
    return jnp.concatenate([dp, lever * jnp.linalg.norm(dR, axis=1, keepdims=True)], axis=1), traj.result


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


def design_move(scene, move: Move, *, method: str = "lm", iterations: int = 10, lever: float | None = None, log=print) -> dict:
    """Optimise the move's correction coefficients from zero (the plain move). Returns a dict:
    ``coefficients`` (count, n), ``objective`` (sum of squares, m^2, per iteration, the plain
    move's first), ``compile_s``, ``optimise_s``, ``method``: "lm" (Levenberg-Marquardt,
    forward-mode Jacobian) or "adam" (optax, reverse-mode gradient). Trial steps whose rollout
    does not converge are rejected; a plain move that does not converge raises."""
    n = move.a0.shape[0]
    lever = float(jnp.max(jnp.linalg.norm(scene.end.attachment, axis=1))) if lever is None else lever

    def residual(c):
        r, code = vibration(scene, move, c.reshape(move.count, n), lever)
        return r.reshape(-1), jnp.max(code)

    res_fn = jax.jit(residual)
    t0 = time.perf_counter()
    c = jnp.zeros(move.count * n)
    r, code = res_fn(c)
    compile_s = time.perf_counter() - t0
    history = [float(jnp.sum(r**2))]
    if int(code) != 0:
        raise ConvergenceError("the plain move's rollout did not converge", 0.0)
    t1 = time.perf_counter()
    if method == "lm":
        jac_fn = jax.jit(jax.jacfwd(lambda c: residual(c)[0]))
        lam = 1e-3
        for _ in range(iterations):
            J = jac_fn(c)
            g, H = J.T @ r, J.T @ J
            while True:
                step = -jnp.linalg.solve(H + lam * jnp.diag(jnp.diag(H) + 1e-30), g)
                r_new, code = res_fn(c + step)
                f_new = float(jnp.sum(r_new**2))
                if int(code) == 0 and f_new < history[-1]:
                    c, r, lam = c + step, r_new, max(lam / 10.0, 1e-12)
                    break
                lam *= 10.0
                if lam > 1e8:
                    break
            history.append(float(jnp.sum(r**2)))
            log(f"  LM {len(history) - 1}: sum of squares {history[-1]:.3e} m^2")
            if lam > 1e8 or history[-1] > 0.999 * history[-2]:
                break
    elif method == "adam":
        import optax

        scale = float(jnp.max(jnp.abs(move.a1 - move.a0)))
        opt = optax.adam(1e-2 * scale)
        state = opt.init(c)
        grad_fn = jax.jit(jax.value_and_grad(lambda c: jnp.sum(residual(c)[0] ** 2)))
        for _ in range(iterations):
            f, g = grad_fn(c)
            upd, state = opt.update(g, state)
            c = optax.apply_updates(c, upd)
            history.append(float(jnp.sum(res_fn(c)[0] ** 2)))
            log(f"  Adam {len(history) - 1}: sum of squares {history[-1]:.3e} m^2")
    else:
        raise SceneError(f"unknown design method {method!r}: 'lm' or 'adam'")
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
    return simulate(_driven(scene, move, jnp.asarray(coeffs)))
