r"""BDF-alpha history of a rod at its nodes and at RK4's stage points, exact at rest.

At a point, BDF-alpha gives $z_t = c_0 z + h$ (`bdf_alpha.py`). Split the history as
$h = g - c_0 z_{prev}$, where $z_{prev}$ is the previous step's value at that point and
$g = c_0 z_{prev} + h$ carries the motion ($g = -c_2 (z_{i-1} - z_{i-2}) + d_1 \dot z_{i-1}$,
of the size of a velocity: zero at rest, never multiplied by $c_0$).

RK4 evaluates the rod equations at three points per interval besides the node: two at the half
step (with different states) and one at the next node (with the state $y + ds\,k_3$, not the node
value). pcrjax keeps, at each of these stage points, the previous step's value $z_{prev}$
exactly, and interpolates only $g$ (cubically, `spatial.midpoints`). Hence:

* at rest, every stage point has $z_t = 0$ exactly and a held equilibrium stays put to round-off
  (interpolating the whole history, as thesis eq. 3.39 does, gave an $O(c_0\,ds^4)$ drift:
  1.4e-5 m at N = 10 on the thesis cantilever);
* in motion, the interpolation error is $O(ds^4)$ times a velocity, not times $c_0$;
* no new memory is introduced: the stage values are functions of the previous step's nodes.
  (A full recurrence of its own at every stage point, velocity part included, makes the
  trapezoidal rule unstable: a parasitic mode that alpha = -0.5 does not damp.)

Euler evaluates at nodes only; there the split changes nothing.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from ..physics.rod import coefficients, kinematic_state
from . import bdf_alpha
from .spatial import midpoints


class RodHistory(eqx.Module):
    """``nodes`` (N+1, 12) and ``stages`` (N, 3, 12) for RK4 (N, 0, 12) for Euler: $h$ such that
    $z_t = c_0 z + h$ at each evaluation point."""

    nodes: jnp.ndarray
    stages: jnp.ndarray

    @classmethod
    def zeros(cls, n_nodes: int, integrator: str, dim: int = 12, dtype=jnp.float64):
        n_st = 3 if integrator == "rk4" else 0
        return cls(jnp.zeros((n_nodes + 1, dim), dtype), jnp.zeros((n_nodes, n_st, dim), dtype))


def rest(co: bdf_alpha.Coefficients, z_nodes, z_stages) -> RodHistory:
    """History of a rod that has rested forever with values ``z`` at its nodes and stage points."""
    return RodHistory(bdf_alpha.rest_history(co, z_nodes), bdf_alpha.rest_history(co, z_stages))


def advance(co: bdf_alpha.Coefficients, hist: RodHistory, z_nodes, z_stages, z_prev_nodes, now=None) -> RodHistory:
    """History for the next step (scheme ``co``) from this step's values at nodes and stages
    (this step's scheme ``now``, default ``co``).

    Nodes follow the BDF-alpha recurrence; stage points get $g$ interpolated from the nodes minus
    $c_0$ times their own value.
    """
    h_nodes = bdf_alpha.next_history(co, z_nodes, z_prev_nodes, hist.nodes, now)
    if z_stages.shape[1] == 0:
        return RodHistory(h_nodes, hist.stages)
    g = co.c0 * z_nodes + h_nodes
    gm = midpoints(g)
    g_st = jnp.stack([gm, gm, g[1:]], axis=1)
    return RodHistory(h_nodes, g_st - co.c0 * z_stages)


def at_rest(co: bdf_alpha.Coefficients, rod, effects, gravity, static_nodes, static_stages):
    """Legs that have rested forever in the static solution: ``static_nodes`` (n, N+1, 18) and
    the states at the integrator's stage points, ``static_stages`` (n, N, stages, 18), as the
    static solve's legs give them (``rod`` leaves per leg).

    Returns ``(nodes (n, N+1, 24), z (n, N+1, 12), history)``. At rest the dynamic equations
    reduce to the static ones, so the stage states are the static ones with zero velocities.
    Strains follow from the loads with any history satisfying $h = -c_0 z$; z is computed with the
    damping-free law (identical at rest), then the rest history.
    """

    def with_velocities(a):
        return jnp.concatenate([a, jnp.zeros(a.shape[:-1] + (6,), a.dtype)], axis=-1)

    nodes, stages = with_velocities(static_nodes), with_velocities(static_stages)
    k_rest = jax.vmap(lambda r: coefficients(r, dataclasses.replace(effects, damping=False), co.c0, gravity))(rod)

    def z_of(kk, ys):  # one leg's points (..., 24)
        flat = ys.reshape(-1, ys.shape[-1])
        z = jax.vmap(lambda y: kinematic_state(y, jnp.zeros(12, y.dtype), kk, effects))(flat)
        return z.reshape(ys.shape[:-1] + (12,))

    z = jax.vmap(z_of)(k_rest, nodes)
    z_st = jax.vmap(z_of)(k_rest, stages)
    return nodes, z, rest(co, z, z_st)


def after_step(co: bdf_alpha.Coefficients, hist: RodHistory, k, effects, nodes, stages, z_prev, now=None):
    """``(z, next history)`` from a solved step's ``nodes`` (N+1, 24) and RK4 ``stages`` (N, 3, 24)
    (the next step's scheme ``co``; this step's ``now``, default ``co``)."""
    kin = lambda y, h: kinematic_state(y, h, k, effects)  # noqa: E731
    z = jax.vmap(kin)(nodes, hist.nodes)
    z_st = jax.vmap(jax.vmap(kin))(stages, hist.stages)
    return z, advance(co, hist, z, z_st, z_prev, now)
