"""The single rod clamped at its base with a load on its free tip (thesis 4.1; `robot = "rod"`).

Unknowns: the base wrench $n(0), m(0)$ (and multiple-shooting segment starts); residuals: the tip
wrench against the applied load, $n(L) = F$, $m(L) = M$ (and segment continuity).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from . import bdf_alpha, newton, rod_history
from .rod import coefficients
from .rod_history import RodHistory
from .rotations import cross
from .shooting import Layout, make_scales, segment_rotations, shoot, unknowns_from_nodes


def tip_load(scene, t):
    """Tip force and moment at time t: held while t <= release_time, zero after."""
    on = t <= scene.tip.release_time
    return jnp.where(on, scene.tip.force, 0.0), jnp.where(on, scene.tip.moment, 0.0)


def base_state(scene, inertia: bool):
    R0 = scene.base.rotation
    y = jnp.concatenate([scene.base.position, R0.reshape(9), jnp.zeros(6)])
    return jnp.concatenate([y, jnp.zeros(6)]) if inertia else y


def _colouring(layout: Layout):
    colours, mask = layout.colouring()
    return lambda f, x: newton.dense_jacobian(f, x, colours, mask)


def _tip_residual(nodes, F, M, sc):
    return jnp.concatenate([(nodes[-1, 12:15] - F) / sc.force, (nodes[-1, 15:18] - M) / sc.moment])


class StaticSolution(eqx.Module):
    nodes: jnp.ndarray  # (N+1, 18)
    unknowns: jnp.ndarray
    stats: newton.Stats


def solve_static(scene, t=0.0) -> StaticSolution:
    """Static equilibrium of the rod under the tip load at time ``t`` (gravity if switched on)."""
    s = scene.solver
    effects = dataclasses.replace(scene.effects, inertia=False)
    layout = Layout(nodes=s.grid_nodes, segments=1, inertia=False)
    rod = scene.rod
    k = coefficients(rod, effects, jnp.zeros(()), scene.gravity)
    sc = make_scales(rod)
    ds = rod.length / s.grid_nodes
    F, M = tip_load(scene, jnp.asarray(t, jnp.float64))
    y0 = base_state(scene, False)
    hist = RodHistory.zeros(s.grid_nodes, s.integrator)
    R_ref = jnp.zeros((0, 3, 3))

    def homotopy(x, lam):
        # Loads and weight scaled by lam: lam = 0 is the unloaded rod, whose root is x = 0.
        kk = k if k.gravity is None else dataclasses.replace(k, gravity=lam * k.gravity)
        nodes, _ = shoot(layout, x, y0, R_ref, hist, kk, effects, ds, s.integrator, sc, s.unroll)
        return _tip_residual(nodes, lam * F, lam * M, sc)

    # Guess: the straight rod's exact global balance (n0 = F + weight, m0 = M + moments of F, weight).
    d = scene.base.rotation[:, 2]
    L = rod.length
    w = k.gravity * L if k.gravity is not None else jnp.zeros(3)
    n0 = F + w
    m0 = M + cross(L * d, F) + cross(0.5 * L * d, w)
    x0 = jnp.concatenate([n0 / sc.force, m0 / sc.moment])
    residual = lambda x: homotopy(x, 1.0)  # noqa: E731
    fallback = newton.continuation(homotopy, 10, layout.size)
    x, _, stats = newton.solve(residual, jax.lax.stop_gradient(x0), newton.Jacobian.empty(6), _colouring(layout), s.newton, True, fallback)
    nodes, _ = shoot(layout, x, y0, R_ref, hist, k, effects, ds, s.integrator, sc, s.unroll)
    return StaticSolution(nodes=nodes, unknowns=x, stats=stats)


class StepState(eqx.Module):
    """What one dynamic step hands to the next."""

    nodes: jnp.ndarray  # (N+1, 24) state at t_{i-1}
    z_prev: jnp.ndarray  # (N+1, 12) [v, u, q, w] at t_{i-1}
    history: RodHistory  # BDF-alpha history for step i (nodes and RK4 stage points)
    unknowns: jnp.ndarray  # (2, size) steps i-1 and i-2, both relative to step i-1's rotations
    jac: newton.Jacobian
    has_jac: jnp.ndarray


def dynamic_layout(scene) -> Layout:
    return Layout(nodes=scene.solver.grid_nodes, segments=scene.solver.segments, inertia=True)


def initial_step_state(scene, static: StaticSolution) -> StepState:
    """Rest at the static equilibrium: zero velocities, history of a rod at rest forever."""
    layout = dynamic_layout(scene)
    s = scene.solver
    co = bdf_alpha.coefficients(s.dt, s.alpha)
    ds = scene.rod.length / s.grid_nodes
    nodes, z, history = rod_history.at_rest(co, scene.rod, scene.effects, scene.gravity, static.nodes, ds, s.integrator)
    sc = make_scales(scene.rod, co.c0)
    R_ref = segment_rotations(layout, nodes)
    x = unknowns_from_nodes(layout, nodes, R_ref, sc)
    return StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        unknowns=jnp.stack([x, x]),
        jac=newton.Jacobian.empty(layout.size),
        has_jac=jnp.asarray(False),
    )


class StepOutput(eqx.Module):
    tip_position: jnp.ndarray
    tip_rotation: jnp.ndarray
    positions: jnp.ndarray  # (N+1, 3)
    stats: newton.Stats


def step(scene, state: StepState, t, extrapolate: bool = True):
    """Advance one time step to time ``t``; returns (new state, output).

    The Newton start is extrapolated linearly from the last two steps (rotations through their
    Cayley parameters relative to the last step), and the last step's Jacobian is reused.
    """
    layout = dynamic_layout(scene)
    s = scene.solver
    co = bdf_alpha.coefficients(s.dt, s.alpha)
    k = coefficients(scene.rod, scene.effects, co.c0, scene.gravity)
    sc = make_scales(scene.rod, co.c0)
    ds = scene.rod.length / s.grid_nodes
    F, M = tip_load(scene, t)
    y0 = base_state(scene, True)
    R_ref = segment_rotations(layout, state.nodes)

    def residual(x):
        nodes, junctions = shoot(layout, x, y0, R_ref, state.history, k, scene.effects, ds, s.integrator, sc, s.unroll)
        return jnp.concatenate([junctions, _tip_residual(nodes, F, M, sc)])

    x1, x2 = state.unknowns[0], state.unknowns[1]
    guess = jax.lax.stop_gradient(2.0 * x1 - x2 if extrapolate else x1)
    # If Newton fails from the extrapolated start (e.g. under-damped high modes flipping sign each
    # step), it is retried from the last step's solution with a fresh Jacobian.
    retry = (None, jnp.ones(1), jax.lax.stop_gradient(x1)[None], jnp.zeros(1, bool))
    x, jac, stats = newton.solve(residual, guess, state.jac, _colouring(layout), s.newton, ~state.has_jac, retry)
    nodes, _, stages = shoot(layout, x, y0, R_ref, state.history, k, scene.effects, ds, s.integrator, sc, s.unroll, return_stages=True)
    z, history = rod_history.after_step(co, state.history, k, scene.effects, nodes, stages, state.z_prev)
    # Unknowns of this step expressed relative to this step's reference rotations, so that the
    # next step's extrapolation compares like with like.
    R_new = segment_rotations(layout, nodes)
    x_rel = unknowns_from_nodes(layout, nodes, R_new, sc)
    x_prev_rel = unknowns_from_nodes(layout, state.nodes, R_new, sc)
    new_state = StepState(
        nodes=nodes,
        z_prev=z,
        history=history,
        unknowns=jax.lax.stop_gradient(jnp.stack([x_rel, x_prev_rel])),
        jac=jax.lax.stop_gradient(jac),
        has_jac=jnp.asarray(True),
    )
    out = StepOutput(tip_position=nodes[-1, 0:3], tip_rotation=nodes[-1, 3:12].reshape(3, 3), positions=nodes[:: s.refine, 0:3], stats=stats)
    return new_state, out
