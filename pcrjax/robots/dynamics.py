"""One BDF-alpha time step of any robot: extrapolated guess, Newton solve with a restart, history update.

Forward dynamics solves for the end's pose under the scene's actuation; inverse dynamics
(`inverse.py`) for the actuator values under a prescribed pose. Both share everything else.

The Newton start is extrapolated linearly from the last two steps: the platform pose through its
increment relative to the last step, the legs' base wrenches and segment-start positions, loads
and velocities as numbers; their segment rotations are held at the last step's (extrapolating
them as well did not reduce the Newton iterations consistently). The last step's Jacobian is
reused. If Newton fails from the extrapolated start (e.g. under-damped high modes flipping sign
each step), it is retried from the last step's solution with a fresh Jacobian.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

from ..numerics import bdf_alpha, newton, rod_history
from ..numerics.rod_history import RodHistory
from ..physics import rod as rod_physics
from . import assembly, inverse
from .statics import StaticSolution


class StepState(eqx.Module):
    """What one dynamic step hands to the next."""

    nodes: jnp.ndarray  # (n, N+1, 24) legs at t_{i-1}
    z_prev: jnp.ndarray  # (n, N+1, 12) [v, u, q, w] at t_{i-1}
    history: RodHistory  # per leg: BDF-alpha history for step i (nodes and RK4 stage points)
    memory: eqx.Module | None  # the end's BDF-alpha memory (platform motion; None for a free tip)
    a1: jnp.ndarray  # actuator values at t_{i-1}
    ah: jnp.ndarray  # actuator history: adot_i = c0 a_i + ah
    unknowns: jnp.ndarray  # (2, size): steps i-1 and i-2, both relative to step i-1's rotations
    jac: newton.Jacobian
    has_jac: jnp.ndarray
    started: jnp.ndarray  # False before the first step (backward Euler: `bdf_alpha.starting`)
    held: tuple | None = None  # the tangent solve's Jacobians and where taken (`newton.HOLD_MOVE`), if the solver holds them


class StepOutput(eqx.Module):
    position: jnp.ndarray  # platform centre or first tip
    rotation: jnp.ndarray
    actuators: jnp.ndarray
    positions: jnp.ndarray  # (n, N+1, 3) at the user's nodes
    base_wrenches: jnp.ndarray  # (n, 2, 3) [n(0), m(0)] of each leg
    energy: jnp.ndarray
    stats: newton.Stats


def _coefficients(scene, state: StepState | None = None):
    """BDF-alpha's coefficients, or those of the step that ``state`` starts (`bdf_alpha.starting`
    for the first)."""
    s = scene.solver
    if state is None:
        return bdf_alpha.coefficients(s.dt, s.alpha)
    return bdf_alpha.step_coefficients(s.dt, s.alpha, ~state.started)


def initial_step_state(scene, static: StaticSolution, inverse_dynamics: bool = False) -> StepState:
    """Rest at the static equilibrium: rods, end and actuators at rest forever. With
    ``inverse_dynamics`` the unknowns are those of inverse dynamics (actuators for the pose)."""
    s = scene.solver
    co = bdf_alpha.starting(s.dt)  # the first step's scheme: the rest history is -c0 z
    a = static.actuators
    nodes, z, history = rod_history.at_rest(co, scene.legs.rod, scene.effects, scene.gravity, static.nodes, static.stages)
    memory = scene.end.rest_memory(static.position, static.rotation, co)
    lay = assembly.layout(scene, True)
    sc = assembly.scales(scene, True)
    if inverse_dynamics:
        x = _inverse_unknowns(lay, sc, nodes, jnp.zeros_like(a))
    else:
        xp = scene.end.pose_unknowns(static.position, static.rotation, static.position, static.rotation, scene.effects.planar, sc)
        x = assembly.unknowns(lay, sc, xp, nodes)
    state = StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        memory=memory,
        a1=a,
        ah=bdf_alpha.rest_history(co, a),
        unknowns=jnp.stack([x, x]),
        jac=newton.Jacobian.empty(x.shape[0]),
        has_jac=jnp.asarray(False),
        started=jnp.asarray(False),
    )
    if inverse_dynamics or not s.hold_tangent_jacobian:
        return state
    shapes = jax.eval_shape(lambda: _Forward(scene, state, jnp.zeros(()), co).prob.jacobian_and_legs(x))
    never = (jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), shapes), jnp.full_like(x, jnp.nan))
    return dataclasses.replace(state, held=never)


def _inverse_unknowns(lay, sc, nodes, xa):
    """Inverse-dynamics unknowns (`InverseProblem`) reproducing ``nodes``, with scaled actuator
    unknowns ``xa``."""
    xl = assembly.unknowns(lay, sc, jnp.zeros((0,), nodes.dtype), nodes).reshape(nodes.shape[0], lay.size)
    return inverse.join(xa, xl)


def _problem(scene, state: StepState, co, a, t):
    """The forward problem of the step to time ``t`` with actuator values ``a``."""
    F, M = scene.end.load(t)
    cfg = scene.end.step_config(state.memory, F, M, scene.end.weight(scene.effects, scene.gravity), co)
    lay = assembly.layout(scene, True)
    R_ref = assembly.leg_rotations(lay, state.nodes)
    return assembly.Problem(scene, True, a, co.c0 * a + state.ah, scene.gravity, state.history, R_ref, co.c0, cfg)


class _Forward:
    """Forward dynamics: the actuators follow the scene's actuation; the end's pose is unknown."""

    def __init__(self, scene, state: StepState, t, co):
        self.scene, self.state = scene, state
        self.a = scene.actuator_values(t)
        self.prob = _problem(scene, state, co, self.a, t)

    def solution(self, x):
        """(forward problem at the solution, end pose, leg unknowns, actuator values)."""
        xp, xl = self.prob.split(x)
        return self.prob, self.prob.pose(xp), xl, self.a

    def aux_tangents(self):
        """`newton.solve`'s ``aux_tangents``: the legs' nodes at the root get their derivatives
        from the Jacobian's own leg integrations."""
        prob = self.prob
        return prob.jacobian_and_legs, partial(assembly.legs_tangent, prob.layout, prob.P)

    def legs(self, prob, xl, legs_at_root):
        """(tips, nodes, stages) of the legs at the root, with their derivatives."""
        return legs_at_root[1:]

    def relative_unknowns(self, prob, p, R, nodes, a):
        """This step's and the last step's unknowns, relative to this step's pose and rotations."""
        end, planar = self.scene.end, self.scene.effects.planar
        x_rel = prob.unknowns(end.pose_unknowns(p, R, p, R, planar, prob.sc), nodes)
        x_prev_rel = prob.unknowns(end.previous_pose_unknowns(prob.cfg, p, R, planar, prob.sc), self.state.nodes)
        return x_rel, x_prev_rel


class _Inverse(_Forward):
    """Inverse dynamics: the end follows ``path`` (`signals.PosePath`); the actuators are unknown."""

    def __init__(self, scene, state: StepState, t, co, path):
        self.scene, self.state = scene, state
        ref = _problem(scene, state, co, state.a1, t)
        p, R = path.pose(t, ref.cfg.p_prev[2])
        h, R_ref, cfg = state.history, ref.leg_R_ref, ref.cfg
        self.prob = inverse.InverseProblem(scene, True, state.a1, state.ah, scene.gravity, h, R_ref, co.c0, cfg, p, R)

    def solution(self, x):
        xa, xl = self.prob.split(x)
        prob = self.prob.problem(xa)
        return prob, prob.pose(self.prob.xp), xl, self.prob.actuators(xa)

    def aux_tangents(self):
        return None

    def legs(self, prob, xl, legs_at_root):
        return prob.recorded_legs(xl, legs_at_root)[1:]

    def relative_unknowns(self, prob, p, R, nodes, a):
        """Leg unknowns as in `_Forward`; actuators relative to this step's values."""
        xa_prev = (self.state.a1 - a) / self.prob.sc.length
        x_rel = _inverse_unknowns(prob.layout, prob.sc, nodes, jnp.zeros_like(a))
        return x_rel, _inverse_unknowns(prob.layout, prob.sc, self.state.nodes, xa_prev)


def step(scene, state: StepState, t, path=None):
    """Advance one time step to time ``t``; returns (new state, output). With a ``path``
    (`signals.PosePath`) the end follows it and the actuator values are solved for (the state
    must then come from ``initial_step_state(..., inverse_dynamics=True)``)."""
    s = scene.solver
    co, co_next = _coefficients(scene, state), _coefficients(scene)
    form = _Forward(scene, state, t, co) if path is None else _Inverse(scene, state, t, co, path)
    x1, x2 = state.unknowns[0], state.unknowns[1]
    guess = jax.lax.stop_gradient(2.0 * x1 - x2)
    start = newton.with_restart(guess, x1, ~state.has_jac)
    solved = newton.solve(
        lambda z: form.prob.residual(z, True),
        form.prob.jacobian,
        state.jac,
        s.newton,
        start,
        has_aux=True,
        aux_tangents=form.aux_tangents(),
        held=state.held if path is None else None,
    )
    x, jac, stats, legs_at_root = solved[:4]
    held = solved[4] if len(solved) > 4 else None
    if held is not None:  # the first step's scheme (backward Euler) is not the next steps': nothing held from it
        held = jax.lax.stop_gradient((held[0], jnp.where(state.started, held[1], jnp.nan)))
    prob, body, xl, a = form.solution(x)
    tips, nodes, stages = form.legs(prob, xl, legs_at_root)
    after = lambda h, k, nd, st, zp: rod_history.after_step(co_next, h, k, scene.effects, nd, st, zp, co)  # noqa: E731
    z, history = jax.vmap(after)(state.history, prob.k, nodes, stages, state.z_prev)
    memory, end_energy = scene.end.advance(prob.cfg, state.memory, body, tips, co_next)
    p, R = scene.end.output_pose(body, tips)
    # Unknowns of this step and the last, the pose relative to this step's, so that the next
    # step's extrapolation compares like with like (segment rotations: each relative to its own).
    x_rel, x_prev_rel = form.relative_unknowns(prob, p, R, nodes, a)
    new_state = StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        memory=memory,
        a1=a,
        ah=bdf_alpha.next_history(co_next, a, state.a1, state.ah, co),
        unknowns=jax.lax.stop_gradient(jnp.stack([x_rel, x_prev_rel])),
        jac=jax.lax.stop_gradient(jac),
        has_jac=jnp.asarray(True),
        started=jnp.asarray(True),
        held=held,
    )
    energy = _rods_energy(scene, prob, nodes, z) + end_energy
    out = StepOutput(
        position=p,
        rotation=R,
        actuators=a,
        positions=nodes[:, :: s.refine, 0:3],
        base_wrenches=jnp.stack([nodes[:, 0, 12:15], nodes[:, 0, 15:18]], axis=1),
        energy=energy,
        stats=stats,
    )
    return new_state, out


def rest_energy(scene, state: StepState, static: StaticSolution):
    """Total energy of the initial rest state (rods' elastic energy, weights' and loads' potential)."""
    prob = _problem(scene, state, _coefficients(scene, state), state.a1, jnp.zeros(()))
    return _rods_energy(scene, prob, state.nodes, state.z_prev) + scene.end.rest_energy(
        prob.cfg, state.memory, static.nodes[:, -1]
    )


def _rods_energy(scene, prob, nodes, z):
    """Total energy of the legs (`physics.rod.energy` summed over legs)."""
    return jnp.sum(jax.vmap(lambda k, nd, zz, ds: rod_physics.energy(k, scene.effects, nd, zz, ds))(prob.k, nodes, z, prob.ds))
