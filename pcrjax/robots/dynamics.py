"""One BDF-alpha time step of any robot: extrapolated guess, Newton solve with a restart, history update.

The Newton start is extrapolated linearly from the last two steps (the legs' segment rotations
through their Cayley parameters, the platform pose through its increment, both relative to the
last step), and the last step's Jacobian is reused. If Newton fails from the extrapolated start
(e.g. under-damped high modes flipping sign each step), it is retried from the last step's
solution with a fresh Jacobian.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..numerics import bdf_alpha, newton, rod_history
from ..numerics.rod_history import RodHistory
from ..physics import rod as rod_physics
from . import assembly
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


class StepOutput(eqx.Module):
    position: jnp.ndarray  # platform centre or first tip
    rotation: jnp.ndarray
    actuators: jnp.ndarray
    positions: jnp.ndarray  # (n, N+1, 3) at the user's nodes
    energy: jnp.ndarray
    stats: newton.Stats


def _coefficients(scene):
    s = scene.solver
    return bdf_alpha.coefficients(s.dt, s.alpha)


def initial_step_state(scene, static: StaticSolution) -> StepState:
    """Rest at the static equilibrium: rods, end and actuators at rest forever."""
    s = scene.solver
    co = _coefficients(scene)
    a = scene.actuator_values(jnp.zeros(()))
    ds = scene.legs.lengths(a) / s.grid_nodes
    nodes, z, history = rod_history.at_rest(co, scene.legs.rod, scene.effects, scene.gravity, static.nodes, ds, s.integrator)
    memory = scene.end.rest_memory(static.position, static.rotation, co)
    lay = assembly.layout(scene, True)
    sc = assembly.scales(scene, co.c0)
    xp = scene.end.pose_unknowns(static.position, static.rotation, static.position, static.rotation, scene.effects.planar, sc)
    x = assembly.unknowns(lay, sc, xp, nodes)
    return StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        memory=memory,
        a1=a,
        ah=bdf_alpha.rest_history(co, a),
        unknowns=jnp.stack([x, x]),
        jac=newton.Jacobian.empty(x.shape[0]),
        has_jac=jnp.asarray(False),
    )


def _problem(scene, state: StepState, t, co):
    a = scene.actuator_values(t)
    adot = co.c0 * a + state.ah
    F, M = scene.end.load(t)
    cfg = scene.end.step_config(state.memory, F, M, scene.end.weight(scene.effects, scene.gravity), co)
    lay = assembly.layout(scene, True)
    prob = assembly.Problem(
        scene, True, a, adot, scene.gravity, state.history, assembly.leg_rotations(lay, state.nodes), co.c0, cfg
    )
    return prob, a, adot


def step(scene, state: StepState, t):
    """Advance one time step to time ``t``; returns (new state, output)."""
    s = scene.solver
    co = _coefficients(scene)
    prob, a, adot = _problem(scene, state, t, co)
    x1, x2 = state.unknowns[0], state.unknowns[1]
    guess = jax.lax.stop_gradient(2.0 * x1 - x2)
    x, jac, stats = newton.solve(
        prob.residual, prob.jacobian, state.jac, s.newton, newton.with_restart(guess, x1, ~state.has_jac)
    )
    xp, xl = prob.split(x)
    _, tips, nodes, stages = prob.legs(xl, return_stages=True)
    after = lambda h, k, nd, st, zp: rod_history.after_step(co, h, k, scene.effects, nd, st, zp)  # noqa: E731
    z, history = jax.vmap(after)(state.history, prob.k, nodes, stages, state.z_prev)
    body = prob.pose(xp)
    memory, end_energy = scene.end.advance(prob.cfg, state.memory, body, tips, co)
    p, R = scene.end.output_pose(body, tips)
    planar = scene.effects.planar
    # Unknowns of this step and the last, relative to this step's rotations, so that the next
    # step's extrapolation compares like with like.
    x_rel = prob.unknowns(scene.end.pose_unknowns(p, R, p, R, planar, prob.sc), nodes)
    x_prev_rel = prob.unknowns(scene.end.previous_pose_unknowns(prob.cfg, p, R, planar, prob.sc), state.nodes)
    new_state = StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        memory=memory,
        a1=a,
        ah=co.c1 * a + co.c2 * state.a1 + co.d1 * adot,
        unknowns=jax.lax.stop_gradient(jnp.stack([x_rel, x_prev_rel])),
        jac=jax.lax.stop_gradient(jac),
        has_jac=jnp.asarray(True),
    )
    energy = _rods_energy(scene, prob, nodes, z) + end_energy
    out = StepOutput(position=p, rotation=R, actuators=a, positions=nodes[:, :: s.refine, 0:3], energy=energy, stats=stats)
    return new_state, out


def rest_energy(scene, state: StepState, static: StaticSolution):
    """Total energy of the initial rest state (rods' elastic energy, weights' and loads' potential)."""
    co = _coefficients(scene)
    prob, _, _ = _problem(scene, state, jnp.zeros(()), co)
    return _rods_energy(scene, prob, state.nodes, state.z_prev) + scene.end.rest_energy(
        prob.cfg, state.memory, static.nodes[:, -1]
    )


def _rods_energy(scene, prob, nodes, z):
    """Total energy of the legs (`physics.rod.energy` summed over legs)."""
    return jnp.sum(jax.vmap(lambda k, nd, zz, ds: rod_physics.energy(k, scene.effects, nd, zz, ds))(prob.k, nodes, z, prob.ds))
