"""The lumped low-fidelity model of a rod scene (thesis 3.1), integrated with diffrax.

`lumped_static` finds the chain's equilibrium under the scene's loads at t = 0 (Newton with load
continuation); `lumped_rollout` starts there and integrates the node ODE with an adaptive diffrax
solver to the scene's duration, saving at the scene's time grid so that the result lines up with
`pcrjax.rollout`. Covers single-rod scenes (``robot = "rod"``); drag is not modelled.

Solvers: ``tsit5`` (explicit, the default) is held by stability to steps of about 1/rho, rho
the spectral radius of the ODE's Jacobian (the axial and shear waves across one segment, ~c/l,
so it grows as N); `step_budget` sizes diffrax's step limit from rho. ``kvaerno5`` (implicit,
L-stable) could in principle step over those waves, but on the released cantilever its
simplified Newton iterations fail at steps near 1/rho and the step size collapses (at 4
segments, rtol 1e-6: as many steps rejected as accepted, more steps than tsit5 takes).
"""

from __future__ import annotations

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .errors import ConvergenceError, SceneError
from .physics.lumped import Chain, displaced, normalised, qmul, qrotate_inverse
from .physics.rotations import quaternion

METHODS = ("kvaerno5", "tsit5")
RTOL = 1e-6  # the integration's default relative tolerance (see `lumped_rollout`)


class LumpedTrajectory(eqx.Module):
    """Time series of the lumped chain: ``t`` (T,), tip ``position`` (T, 3), node ``positions``
    (T, N+1, 3), total ``energy`` (T,) J (elastic + kinetic + potential of gravity and of the
    load the ODE sees at t; a load released at t0 counts as released in every row), and the integrator's accepted and rejected ``steps`` and ``rejected``,
    and whether it reached the end (``converged``)."""

    t: jnp.ndarray
    position: jnp.ndarray
    positions: jnp.ndarray
    energy: jnp.ndarray
    steps: jnp.ndarray
    rejected: jnp.ndarray
    converged: jnp.ndarray


def check_scene(scene):
    if scene.robot != "rod" or scene.actuation is not None or scene.legs.base_position.shape[0] != 1:
        raise SceneError(f"{scene.name}: the lumped model covers single-rod scenes (robot = 'rod'), not {scene.robot!r}")
    if scene.effects.drag:
        raise SceneError(f"{scene.name}: the lumped model has no drag; set effects.drag = false")
    if not scene.effects.shear_extension:
        raise SceneError(f"{scene.name}: the lumped model always has shear and axial springs; set effects.shear_extension = true")


def chain_of(scene, segments: int) -> Chain:
    """The scene's rod as a `Chain` of ``segments`` rigid segments."""
    check_scene(scene)
    if segments < 1:
        raise SceneError(f"segments must be at least 1, got {segments}")
    q0 = quaternion(scene.legs.base_rotation[0])
    rod = jax.tree.map(lambda a: a[0], scene.legs.rod)  # the legs' rods carry a leg axis
    return Chain.of_rod(rod, scene.effects, segments, scene.legs.base_position[0], q0)


def _external(scene, chain: Chain, q, t):
    """Node forces (N, 3) and body-axis moments (N, 3): weights and the tip load at ``t``."""
    F, M = scene.load(t)
    force = jnp.zeros((chain.segments, 3)).at[-1].add(F)
    if scene.effects.gravity:
        force = force + chain.mass[:, None] * scene.gravity
    moment = jnp.zeros((chain.segments, 3)).at[-1].set(qrotate_inverse(q[-1], M))
    return force, moment


def _potential(scene, chain: Chain, p, t):
    F, _ = scene.load(t)
    e = -jnp.dot(F, p[-1])
    if scene.effects.gravity:
        e = e - jnp.sum(chain.mass * (p @ scene.gravity))
    return e


def lumped_static(scene, segments: int, *, load_steps: int = 8, max_iterations: int = 40, tol: float = 1e-13):
    """Equilibrium (positions (N, 3), quaternions (N, 4), converged) of the chain under the
    scene's loads at t = 0, reached in ``load_steps`` equal load increments by Newton's method
    (converged when node forces / EA and moments / (EA l) are below ``tol``)."""
    chain = chain_of(scene, segments)
    t0 = jnp.zeros((), jnp.float64)
    f_scale = chain.kse[2]  # EA: the stiff springs set the rounding floor of the residual
    scale = jnp.concatenate([jnp.full(3, f_scale), jnp.full(3, f_scale * chain.l)])

    def residual(d, p, q, lam):
        pp, qq = displaced(p, q, d)
        fp, ft = chain.elastic_forces(pp, qq)
        force, moment = _external(scene, chain, qq, t0)
        return (jnp.concatenate([fp - lam * force, ft - lam * moment], axis=1) / scale).reshape(-1)

    zero = jnp.zeros((segments, 6))

    def newton(carry, lam):
        p, q, ok = carry

        def cond(c):
            return (c[2] < max_iterations) & (c[3] > tol)

        def body(c):  # the residual and its Jacobian in one forward-mode pass
            p, q, k, _ = c
            J, r = jax.jacfwd(lambda d: (residual(d, p, q, lam),) * 2, has_aux=True)(zero)
            d = -jnp.linalg.solve(J.reshape(r.size, r.size), r).reshape(segments, 6)
            return *displaced(p, q, d), k + 1, jnp.max(jnp.abs(r))

        # The loop stops once the residual before a step is below tol: that step is still taken.
        p, q, _, res = jax.lax.while_loop(cond, body, (p, q, 0, jnp.inf))
        return (p, q, ok & (res <= tol)), res

    p, q = chain.straight()
    lams = jnp.arange(1, load_steps + 1) / load_steps
    (p, q, ok), _ = jax.lax.scan(newton, (p, q, jnp.array(True)), lams)
    return p, q, ok


def _after(scene, t0):
    """A billionth of a step after t0 (XLA:CPU flushes subnormals, so nextafter(0) would be 0)."""
    return t0 + 1e-9 * scene.solver.dt


def _vector_field(scene, chain: Chain, t0):
    after = _after(scene, t0)

    def f(t, y, args):
        p, q, v, w = y
        qn = normalised(q)
        # The ODE sees the loads just after t0 (a load released at t0 acts only on the equilibrium).
        force, moment = _external(scene, chain, qn, jnp.maximum(t, after))
        a, alpha = chain.accelerations(p, qn, v, w, force, moment)
        qdot = 0.5 * jax.vmap(qmul)(q, jnp.concatenate([jnp.zeros((w.shape[0], 1)), w], axis=1))
        return v, qdot, a, alpha

    return f


def _jacobian_at_rest(scene, segments: int):
    """The ODE's Jacobian (flattened state) at the static equilibrium, just after t = 0."""
    chain = chain_of(scene, segments)
    p, q, _ = lumped_static(scene, segments)
    y0, unflatten = ravel_pytree((p, q, jnp.zeros_like(p), jnp.zeros_like(p)))
    f = _vector_field(scene, chain, jnp.zeros((), jnp.float64))
    t = _after(scene, jnp.zeros((), jnp.float64))
    return jax.jacfwd(lambda y: ravel_pytree(f(t, unflatten(y), None))[0])(y0)


def step_budget(scene, segments: int, rtol: float = RTOL) -> int:
    """diffrax's step limit (accepted and rejected steps) for `lumped_rollout` over the scene's
    duration T: 4 rho T (1e-6/rtol)^(1/5) + 10 000, rho the spectral radius of the ODE's Jacobian
    at the static equilibrium. Explicit steps are held to about 1/rho by stability (the released
    cantilever at 8 and 16 segments, rtol 1e-6, took 1.9 and 2.0 rho T steps, accepted and rejected),
    and below ``rtol`` 1e-6 by accuracy as the fifth root of the tolerance. Needs a concrete scene
    (not traced)."""
    try:
        jac = np.asarray(eqx.filter_jit(_jacobian_at_rest)(scene, segments))
    except jax.errors.TracerArrayConversionError:
        raise SceneError(
            "the lumped model's step budget needs a concrete scene: pass max_steps when you trace "
            "lumped_rollout (step_budget(scene, segments, rtol) outside the trace gives one)"
        ) from None
    rho = float(np.max(np.abs(np.linalg.eigvals(jac))))
    duration = float(scene.solver.steps) * float(scene.solver.dt)
    return int(math.ceil(4.0 * rho * duration * max(1.0, (1e-6 / rtol) ** 0.2))) + 10_000


def lumped_rollout(
    scene,
    segments: int = 20,
    *,
    method: str = "tsit5",
    rtol: float = RTOL,
    atol: float | None = None,
    max_steps: int | None = None,
) -> LumpedTrajectory:
    """Integrate the lumped chain from rest at its static equilibrium over the scene's duration,
    saving at the scene's steps (``t = i dt``). ``rtol``/``atol`` (default ``1e-3 rtol``) go to
    diffrax's PID step-size controller (on the released cantilever at 8 segments, rtol 1e-6 and
    1e-8 give tip paths 3e-7 of the swing apart, far below the chain's own error against the
    rod). ``max_steps`` defaults to `step_budget` (which needs a concrete scene: pass it when the
    scene is traced). Pure (jit and vmap work); check ``.converged``."""
    if method not in METHODS:
        raise SceneError(f"unknown lumped method {method!r}; choose one of {', '.join(METHODS)}")
    chain = chain_of(scene, segments)
    if max_steps is None:
        max_steps = step_budget(scene, segments, rtol)
    p, q, ok = lumped_static(scene, segments)
    t = jnp.arange(scene.solver.steps + 1) * scene.solver.dt
    y0 = (p, q, jnp.zeros_like(p), jnp.zeros_like(p))
    solver = diffrax.Kvaerno5() if method == "kvaerno5" else diffrax.Tsit5()
    atol = 1e-3 * rtol if atol is None else atol
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field(scene, chain, t[0])),
        solver,
        t0=t[0],
        t1=t[-1],
        dt0=None,
        y0=y0,
        saveat=diffrax.SaveAt(ts=t),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        throw=False,
    )
    ps, qs, vs, ws = sol.ys

    after = _after(scene, t[0])

    def energy(p, q, v, w, ti):
        return chain.energy(p, normalised(q)) + chain.kinetic(v, w) + _potential(scene, chain, p, jnp.maximum(ti, after))

    e = jax.vmap(energy)(ps, qs, vs, ws, t)
    base = jnp.broadcast_to(chain.base_position, (t.shape[0], 1, 3))
    return LumpedTrajectory(
        t=t,
        position=ps[:, -1],
        positions=jnp.concatenate([base, ps], axis=1),
        energy=e,
        steps=sol.stats["num_accepted_steps"],
        rejected=sol.stats["num_rejected_steps"],
        converged=ok & (sol.result == diffrax.RESULTS.successful),
    )


def simulate_lumped(scene, segments: int = 20, *, max_steps: int | None = None, **kw) -> LumpedTrajectory:
    """`lumped_rollout` under `jit`, raising `ConvergenceError` if the equilibrium or the
    integration failed (step budget spent, step size collapsed)."""
    if max_steps is None:
        max_steps = step_budget(scene, segments, kw.get("rtol", RTOL))
    traj = eqx.filter_jit(lumped_rollout)(scene, segments, max_steps=max_steps, **kw)
    if not bool(traj.converged):
        raise ConvergenceError(
            f"{scene.name}: the lumped model ({segments} segments) did not converge "
            f"({int(traj.steps)} steps accepted, {int(traj.rejected)} rejected, budget {max_steps})",
            reason="lumped",
        )
    return traj


def natural_frequencies(scene, segments: int):
    """Natural frequencies (Hz, ascending, 6N of them) of the unloaded chain about its straight
    rest shape: $\\sqrt{\\mathrm{eig}(M^{-1/2} K M^{-1/2})}/2\\pi$ with K the Hessian of the
    elastic energy in node displacements and small body-axis rotations, M the node masses and
    inertias."""
    chain = chain_of(scene, segments)
    p, q = chain.straight()

    def e(d):
        return chain.energy(*displaced(p, q, d))

    n = 6 * segments
    K = jax.hessian(e)(jnp.zeros((segments, 6))).reshape(n, n)
    m = jnp.concatenate([jnp.broadcast_to(chain.mass[:, None], (segments, 3)), chain.inertia], axis=1).reshape(-1)
    w2 = jnp.linalg.eigvalsh(K / jnp.sqrt(m[:, None] * m[None, :]))
    return jnp.sqrt(jnp.maximum(w2, 0.0)) / (2 * jnp.pi)
