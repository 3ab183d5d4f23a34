r"""Shooting for a parallel continuum robot: statics with continuation and BDF-alpha dynamics.

**Unknowns** $x = [\text{pose}, x_1, \dots, x_n]$: the platform pose (6, or 3 with the planar
bearing; `platform.pose`) and, per leg, its scaled base wrench $n_i(0), m_i(0)$ (plus its
multiple-shooting segment starts, if the step needs them). **Residuals**: the platform's force and
moment balance (planar: $F_x, F_y, M_z$), then per leg its segment continuity and its tip
constraint: position $p_e + R_e r_i - p_i(L_i)$ and orientation
$\mathrm{vee}((R_e R_{c,i})^T R_i(L_i))$ (thesis eq. 4.7-4.13, 4.18-4.22).

**Jacobian by legs.** A leg's integration depends only on its own unknowns and actuator; the
pose enters the residual only algebraically. So the Jacobian is assembled from (a) each leg's
Jacobian of [junctions, tip state] with respect to its unknowns, computed for all legs at once
(`vmap` of coloured forward-mode JVPs: 6 for a single segment) and (b) the cheap Jacobian of the
algebraic residual with respect to the pose and the tip states, by the chain rule: 6 leg JVPs
instead of $6 + 6n$ full-residual JVPs (42 for the Stewart-Gough platform).

**Initial equilibrium.** Newton from straight legs diverges (DESIGN §7), so the static solve is
a homotopy in $s \in [0, 1]$: at $s = 0$ each leg's attachment point and clamp rotation are moved
to where its straight, unloaded rod ends when the platform sits at its reference pose, and loads
and weights are off, so the root is known exactly (reference pose, zero wrenches). Attachments,
clamp rotations (along the geodesic), loads and weights then move linearly to their true values in
``solver.continuation`` stages, each a Newton solve from the last; the final solve at $s = 1$ is
the one differentiated (implicit function theorem).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import bdf_alpha, newton, platform, rod_history
from .rod import coefficients
from .rod_history import RodHistory
from .rotations import exp_map, matmul, matvec, rotation_vector, skew_vee, transpose_matmul
from .shooting import Layout, make_scales, segment_rotations, shoot, unknowns_from_nodes

TIP = 18  # tip state used by the platform: p, R, n, m


def pose_size(scene) -> int:
    return 3 if scene.effects.planar else 6


def leg_layout(scene, inertia: bool) -> Layout:
    segments = scene.solver.segments if inertia else 1
    return Layout(nodes=scene.solver.grid_nodes, segments=segments, inertia=inertia)


def scales(scene, c0=None):
    rod0 = jax.tree.map(lambda a: a[0], scene.legs.rod)
    return make_scales(rod0, c0)


def _weight(scene):
    if scene.effects.gravity:
        return scene.platform.mass * scene.gravity
    return jnp.zeros(3, scene.gravity.dtype)


class _Config(eqx.Module):
    """Everything one residual evaluation needs besides the unknowns."""

    a: jnp.ndarray  # actuator values (n,)
    adot: jnp.ndarray  # actuator rates (n,)
    attachment: jnp.ndarray
    clamp: jnp.ndarray
    F: jnp.ndarray
    M: jnp.ndarray
    weight: jnp.ndarray
    gravity: jnp.ndarray  # rods' weight per length direction (scaled in the homotopy)
    p_prev: jnp.ndarray
    R_prev: jnp.ndarray
    leg_R_ref: jnp.ndarray  # (n, M-1, 3, 3) segment reference rotations
    history: RodHistory  # per leg
    c0: jnp.ndarray
    motion: platform.PlatformMotion | None
    co: bdf_alpha.Coefficients | None


class _Problem:
    """Residual and structured Jacobian of one shooting problem (Python-level, traced inside jit)."""

    def __init__(self, scene, cfg: _Config, inertia: bool):
        self.scene = scene
        self.cfg = cfg
        self.inertia = inertia
        self.effects = dataclasses.replace(scene.effects, inertia=inertia)
        self.layout = leg_layout(scene, inertia)
        self.P = pose_size(scene)
        self.S = self.layout.size
        self.n = scene.legs.count
        self.sc = scales(scene, cfg.c0 if inertia else None)
        legs = scene.legs
        self.k = jax.vmap(lambda rod: coefficients(rod, self.effects, cfg.c0, cfg.gravity))(legs.rod)
        self.ds = legs.lengths(cfg.a) / scene.solver.grid_nodes
        pos = legs.base_positions(cfg.a)
        R_b = legs.base_rotation
        parts = [pos, R_b.reshape(-1, 9), jnp.zeros((self.n, 6))]
        if inertia:
            z = jnp.zeros_like(cfg.adot)
            parts += [jnp.stack([z, z, cfg.adot], axis=1), jnp.zeros((self.n, 3))]
        self.y0 = jnp.concatenate(parts, axis=1)

    # -- legs ---------------------------------------------------------------------------------
    def _leg(self, x_i, y0, R_ref, hist, k, ds, return_stages=False):
        s = self.scene.solver
        return shoot(self.layout, x_i, y0, R_ref, hist, k, self.effects, ds, s.integrator, self.sc, s.unroll, return_stages)

    def legs(self, xl, return_stages=False):
        """(junctions (n, S-6), tips (n, 18), nodes (n, N+1, dim)[, stages])."""
        c = self.cfg

        def one(x_i, y0, R_ref, hist, k, ds):
            out = self._leg(x_i, y0, R_ref, hist, k, ds, return_stages)
            return (out[1], out[0][-1, :TIP], out[0]) + out[2:]

        return jax.vmap(one)(xl, self.y0, c.leg_R_ref, c.history, self.k, self.ds)

    def leg_jacobians(self, xl):
        colours, mask = self.layout.colouring(extra_rows=TIP)
        c = self.cfg

        def one(x_i, y0, R_ref, hist, k, ds):
            def f(z):
                nodes, junc = self._leg(z, y0, R_ref, hist, k, ds)
                return jnp.concatenate([junc, nodes[-1, :TIP]])

            return newton.dense_jacobian(f, x_i, colours, mask)

        return jax.vmap(one)(xl, self.y0, c.leg_R_ref, c.history, self.k, self.ds)

    # -- platform -----------------------------------------------------------------------------
    def pose(self, xp):
        return platform.pose(xp, self.scene.effects.planar, self.cfg.p_prev, self.cfg.R_prev, self.sc.length)

    def algebraic(self, xp, tips):
        """[balance (P), tip constraints (6 per leg)] from the pose unknowns and the leg tips."""
        c, sc = self.cfg, self.sc
        p, R, dp, theta = self.pose(xp)
        r = platform.rates(c.co, c.motion, dp, theta) if self.inertia else None
        force, moment = platform.balance(self.scene.platform, R, c.attachment, tips[:, 12:15], tips[:, 15:18], c.F, c.M, c.weight, r)
        bal = jnp.concatenate([force / sc.force, moment / sc.moment])
        if self.scene.effects.planar:
            bal = bal[np.array([0, 1, 5])]

        def constraint(tip, r_i, Rc):
            target = matmul(R, Rc)
            return jnp.concatenate([(p + matvec(R, r_i) - tip[0:3]) / sc.length, skew_vee(transpose_matmul(target, tip[3:12].reshape(3, 3)))])

        cons = jax.vmap(constraint)(tips, c.attachment, c.clamp)
        return jnp.concatenate([bal, cons.reshape(-1)])

    # -- full problem -------------------------------------------------------------------------
    def split(self, x):
        return x[: self.P], x[self.P :].reshape(self.n, self.S)

    def residual(self, x):
        xp, xl = self.split(x)
        junc, tips, _ = self.legs(xl)
        A = self.algebraic(xp, tips)
        cons = A[self.P :].reshape(self.n, 6)
        return jnp.concatenate([A[: self.P], jnp.concatenate([junc, cons], axis=1).reshape(-1)])

    def jacobian(self, x):
        P, S, n = self.P, self.S, self.n
        xp, xl = self.split(x)
        _, tips, _ = self.legs(xl)
        Jl = self.leg_jacobians(xl)  # (n, S-6+18, S)
        Jjun, Jtip = Jl[:, : S - 6], Jl[:, S - 6 :]
        dA_dp, dA_dt = jax.jacfwd(self.algebraic, argnums=(0, 1))(xp, tips)  # (P+6n, P), (P+6n, n, 18)
        via = jnp.einsum("rnt,nts->rns", dA_dt, Jtip)  # (P+6n, n, S), leg-block structure
        top = jnp.concatenate([dA_dp[:P], via[:P].reshape(P, n * S)], axis=1)
        eye = jnp.eye(n, dtype=x.dtype)
        jun = jnp.einsum("ij,irs->irjs", eye, Jjun).reshape(n, S - 6, n * S)
        jun = jnp.concatenate([jnp.zeros((n, S - 6, P), x.dtype), jun], axis=2)
        cons_via = jnp.einsum("ij,irs->irjs", eye, via[P:].reshape(n, 6, n, S).diagonal(axis1=0, axis2=2).transpose(2, 0, 1))
        cons = jnp.concatenate([dA_dp[P:].reshape(n, 6, P), cons_via.reshape(n, 6, n * S)], axis=2)
        rows = jnp.concatenate([jun, cons], axis=1).reshape(n * S, P + n * S)
        return jnp.concatenate([top, rows], axis=0)


def _jac_fn(problem: _Problem):
    return lambda _f, x: problem.jacobian(x)


def _leg_R_ref(layout: Layout, nodes):
    """(n, M-1, 3, 3) rotations of each leg at its segment starts."""
    return jax.vmap(lambda nd: segment_rotations(layout, nd))(nodes)


# ----------------------------------------------------------------------------------------------
# statics


class StaticSolution(eqx.Module):
    position: jnp.ndarray
    rotation: jnp.ndarray
    nodes: jnp.ndarray  # (n, N+1, 18)
    unknowns: jnp.ndarray
    stats: newton.Stats


def straight_assembly(scene, a):
    """Attachments and clamp rotations (platform frame) at which straight unloaded legs meet the
    platform at its reference pose: the homotopy's start."""
    legs = scene.legs
    R_ref, p_ref = scene.reference_rotation, scene.reference_position
    tips = legs.base_positions(a) + legs.lengths(a)[:, None] * legs.base_rotation[:, :, 2]
    attach0 = jax.vmap(lambda q: matvec(R_ref.T, q - p_ref))(tips)
    clamp0 = jax.vmap(lambda Rb: transpose_matmul(R_ref, Rb))(legs.base_rotation)
    return attach0, clamp0


def solve_static(scene, t=0.0) -> StaticSolution:
    """Static equilibrium under the actuator values and loads at time ``t``."""
    s = scene.solver
    legs = scene.legs
    n = legs.count
    t = jnp.asarray(t, jnp.float64)
    a = scene.actuation(t)
    F, M = scene.load(t)
    attach0, clamp0 = straight_assembly(scene, a)
    clamp_log = jax.vmap(lambda C0, C: rotation_vector(transpose_matmul(C0, C)))(clamp0, legs.clamp)
    layout = leg_layout(scene, False)
    hist = jax.vmap(lambda _: RodHistory.zeros(s.grid_nodes, s.integrator))(jnp.arange(n))

    def problem(lam):
        cfg = _Config(
            a=a,
            adot=jnp.zeros_like(a),
            attachment=(1.0 - lam) * attach0 + lam * legs.attachment,
            clamp=jax.vmap(lambda C0, w: matmul(C0, exp_map(lam * w)))(clamp0, clamp_log),
            F=lam * F,
            M=lam * M,
            weight=lam * _weight(scene),
            gravity=lam * scene.gravity,
            p_prev=scene.reference_position,
            R_prev=scene.reference_rotation,
            leg_R_ref=jnp.zeros((n, 0, 3, 3)),
            history=hist,
            c0=jnp.zeros(()),
            motion=None,
            co=None,
        )
        return _Problem(scene, cfg, inertia=False)

    prob1 = problem(jnp.asarray(1.0))
    x0 = jax.lax.stop_gradient(jnp.zeros(pose_size(scene) + n * layout.size))  # reference pose, zero wrenches

    def stage(carry, lam):
        x, jac, total = carry
        pr = problem(lam)
        x, jac, st = newton.newton(pr.residual, x, jac, _jac_fn(pr), s.newton, need_jacobian=False)
        return (x, jac, newton.accumulate(total, st)), None

    k = max(1, s.continuation)
    lams = jnp.arange(1, k, dtype=jnp.float64) / k
    zero = newton.Stats(jnp.asarray(0), jnp.asarray(0.0), jnp.asarray(0), jnp.asarray(0))
    jac_start = newton.Jacobian.factor(problem(jnp.asarray(0.0)).jacobian(x0))
    (x_c, jac_c, cont), _ = jax.lax.scan(stage, (x0, jac_start, zero), lams)
    x_c = jax.lax.stop_gradient(x_c)
    x, _, stats = newton.solve(prob1.residual, x_c, jac_c, _jac_fn(prob1), s.newton, False)
    stats = newton.accumulate(cont, stats)
    xp, xl = prob1.split(x)
    _, _, nodes = prob1.legs(xl)
    p, R, _, _ = prob1.pose(xp)
    return StaticSolution(position=p, rotation=R, nodes=nodes, unknowns=x, stats=stats)


# ----------------------------------------------------------------------------------------------
# dynamics


class StepState(eqx.Module):
    nodes: jnp.ndarray  # (n, N+1, 24) legs at t_{i-1}
    z_prev: jnp.ndarray  # (n, N+1, 12)
    history: RodHistory  # per leg
    motion: platform.PlatformMotion
    a1: jnp.ndarray  # actuator values at t_{i-1}
    ah: jnp.ndarray  # actuator history: adot_i = c0 a_i + ah
    unknowns: jnp.ndarray  # (2, size): steps i-1 and i-2 relative to step i-1's rotations
    jac: newton.Jacobian
    has_jac: jnp.ndarray


class StepOutput(eqx.Module):
    position: jnp.ndarray
    rotation: jnp.ndarray
    actuators: jnp.ndarray
    positions: jnp.ndarray  # (n, N+1, 3)
    energy: jnp.ndarray
    stats: newton.Stats


def initial_step_state(scene, static: StaticSolution) -> StepState:
    """Rest at the static equilibrium (rods, platform and actuators at rest forever)."""
    s = scene.solver
    co = bdf_alpha.coefficients(s.dt, s.alpha)
    a = scene.actuation(jnp.zeros(()))
    ds = scene.legs.lengths(a) / s.grid_nodes
    rest = lambda rod, nd, ds_i: rod_history.at_rest(co, rod, scene.effects, scene.gravity, nd, ds_i, s.integrator)  # noqa: E731
    nodes, z, history = jax.vmap(rest)(scene.legs.rod, static.nodes, ds)
    motion = platform.PlatformMotion.rest(co, static.position, static.rotation)
    layout = leg_layout(scene, True)
    sc = scales(scene, co.c0)
    x = _unknowns(scene, layout, sc, static.position, static.rotation, static.position, static.rotation, nodes)
    return StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        motion=motion,
        a1=a,
        ah=bdf_alpha.rest_history(co, a),
        unknowns=jnp.stack([x, x]),
        jac=newton.Jacobian.empty(x.shape[0]),
        has_jac=jnp.asarray(False),
    )


def _unknowns(scene, layout, sc, p, R, p_ref, R_ref, nodes):
    """Scaled unknowns reproducing platform pose (p, R) (relative to (p_ref, R_ref)) and leg ``nodes``."""
    xp = platform.pose_unknowns(p, R, p_ref, R_ref, scene.effects.planar, sc.length)
    R_legs = _leg_R_ref(layout, nodes)
    xl = jax.vmap(lambda nd, Rr: unknowns_from_nodes(layout, nd, Rr, sc))(nodes, R_legs)
    return jnp.concatenate([xp, xl.reshape(-1)])


def rod_energy(scene, k, nodes, z, ds):
    """Elastic and kinetic energy of each leg (n,), trapezoidal rule over the nodes."""

    def one(kk, nd, zz, ds_i):
        v, u, q, w = zz[:, 0:3], zz[:, 3:6], nd[:, 18:21], nd[:, 21:24]
        e = 0.5 * jnp.sum(kk.kbt * (u - (0.0 if kk.ustar is None else kk.ustar)) ** 2, axis=1)
        if scene.effects.shear_extension:
            e = e + 0.5 * jnp.sum(kk.kse * (v - jnp.array([0.0, 0.0, 1.0])) ** 2, axis=1)
        e = e + 0.5 * kk.rho_a * jnp.sum(q * q, axis=1) + 0.5 * jnp.sum(kk.rho_j * w * w, axis=1)
        if kk.gravity is not None:
            e = e - nd[:, 0:3] @ kk.gravity
        return ds_i * (jnp.sum(e) - 0.5 * (e[0] + e[-1]))

    return jax.vmap(one)(k, nodes, z, ds)


def step(scene, state: StepState, t, extrapolate: bool = True):
    """Advance one time step to time ``t``; returns (new state, output)."""
    s = scene.solver
    co = bdf_alpha.coefficients(s.dt, s.alpha)
    layout = leg_layout(scene, True)
    a = scene.actuation(t)
    adot = co.c0 * a + state.ah
    F, M = scene.load(t)
    cfg = _Config(
        a=a,
        adot=adot,
        attachment=scene.legs.attachment,
        clamp=scene.legs.clamp,
        F=F,
        M=M,
        weight=_weight(scene),
        gravity=scene.gravity,
        p_prev=state.motion.p1,
        R_prev=state.motion.R1,
        leg_R_ref=_leg_R_ref(layout, state.nodes),
        history=state.history,
        c0=co.c0,
        motion=state.motion,
        co=co,
    )
    prob = _Problem(scene, cfg, inertia=True)
    x1, x2 = state.unknowns[0], state.unknowns[1]
    guess = jax.lax.stop_gradient(2.0 * x1 - x2 if extrapolate else x1)
    retry = (None, jnp.ones(1), jax.lax.stop_gradient(x1)[None], jnp.zeros(1, bool))  # restart from the last step
    x, jac, stats = newton.solve(prob.residual, guess, state.jac, _jac_fn(prob), s.newton, ~state.has_jac, retry)
    xp, xl = prob.split(x)
    _, _, nodes, stages = prob.legs(xl, return_stages=True)
    after = lambda h, k, nd, st, zp: rod_history.after_step(co, h, k, scene.effects, nd, st, zp)  # noqa: E731
    z, history = jax.vmap(after)(state.history, prob.k, nodes, stages, state.z_prev)
    p, R, dp, theta = prob.pose(xp)
    r = platform.rates(co, state.motion, dp, theta)
    motion = platform.advance(co, state.motion, p, R, dp, r)
    x_rel = _unknowns(scene, layout, prob.sc, p, R, p, R, nodes)
    x_prev_rel = _unknowns(scene, layout, prob.sc, state.motion.p1, state.motion.R1, p, R, state.nodes)
    new_state = StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        motion=motion,
        a1=a,
        ah=co.c1 * a + co.c2 * state.a1 + co.d1 * adot,
        unknowns=jax.lax.stop_gradient(jnp.stack([x_rel, x_prev_rel])),
        jac=jax.lax.stop_gradient(jac),
        has_jac=jnp.asarray(True),
    )
    energy = jnp.sum(rod_energy(scene, prob.k, nodes, z, prob.ds)) + platform.kinetic_energy(scene.platform, r) - jnp.dot(_weight(scene), p)
    out = StepOutput(position=p, rotation=R, actuators=a, positions=nodes[:, :: s.refine, 0:3], energy=energy, stats=stats)
    return new_state, out


def rest_energy(scene, state: StepState):
    """Total energy of the initial rest state (rods' elastic energy and weights' potential)."""
    s = scene.solver
    co = bdf_alpha.coefficients(s.dt, s.alpha)
    k = jax.vmap(lambda rod: coefficients(rod, scene.effects, co.c0, scene.gravity))(scene.legs.rod)
    ds = scene.legs.lengths(state.a1) / s.grid_nodes
    return jnp.sum(rod_energy(scene, k, state.nodes, state.z_prev, ds)) - jnp.dot(_weight(scene), state.motion.p1)
