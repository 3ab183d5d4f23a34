r"""Discretisation and Newton settings of a scene, and the compiled structure they imply.

Two settings decide the shape of the compiled program and are derived from the rods' numbers
when a scene is built: the number of multiple-shooting **segments** per rod and the **grid
refinement** (internal nodes per output node). Both follow the fastest spatial rate of a dynamic
step's rod equations,
$\lambda = \max((\rho A c_0^2/EI)^{1/4},\ c_0\sqrt{\rho/\min(E, G)})$: segments keep
$\lambda\ell \le 6$ (error growth $e^6$ across a segment) and refinement keeps
$\lambda\,ds \le 1$. When a step's boundary layer ($1/\lambda$, millimetres at
$\delta t = 10^{-5}$ s) is thinner than the node spacing, one explicit step amplifies the
decaying solution instead of damping it and the shooting problem is ill-posed; inside RK4's
stability interval but above 1 (e.g. 1.9) the misrepresented decay still makes undamped
trapezoidal runs blow up, so the limit is 1 for both integrators. The internal grid keeps
histories at every internal node and reports the user's nodes. The step count is structure too;
the simulated duration is ``steps * dt``.

A scene changed leaf by leaf (``eqx.tree_at`` on a length, ``dt`` or ``E``) keeps its structure.
`structure_result` checks the numbers against it, under `jit` as well, and every solve reports
`results.STALE_STRUCTURE` when the numbers ask for clearly more than the structure gives
(``STALE_MARGIN`` past either limit); `pcrjax.with_solver(scene)` rebuilds the structure.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from . import bdf_alpha, results
from .newton import NewtonSettings
from .shooting import SEGMENT_CONDITIONING

REFINED_SPACING = 1.0  # lambda * ds on the internal grid
STALE_MARGIN = 1.5  # numbers needing this much more than the structure make a solve report stale


class Solver(eqx.Module):
    """Discretisation and Newton settings. ``dt`` (s) and ``alpha`` are differentiable leaves."""

    dt: jnp.ndarray
    alpha: jnp.ndarray
    nodes: int = eqx.field(static=True)
    integrator: str = eqx.field(static=True)
    steps: int = eqx.field(static=True)
    segments: int = eqx.field(static=True)
    unroll: int = eqx.field(static=True)
    refine: int = eqx.field(static=True, default=1)
    continuation: int = eqx.field(static=True, default=10)  # load/geometry continuation stages of the static solve
    auto_segments: bool = eqx.field(static=True, default=True)
    hold_tangent_jacobian: bool = eqx.field(static=True, default=False)  # forward tangents: `newton.HOLD_MOVE`
    newton: NewtonSettings = NewtonSettings()

    @property
    def grid_nodes(self) -> int:
        """Nodes of the internal integration grid: ``nodes * refine`` (outputs use every refine-th)."""
        return self.nodes * self.refine

    @property
    def duration(self):
        return self.steps * self.dt


def boundary_layer_rate(radius, E, G, rho, c0):
    r"""$\lambda$ (1/m): fastest spatial growth/decay rate of a dynamic step's rod equations
    (elementwise; numbers or arrays, traced or not)."""
    A = jnp.pi * radius**2
    EI = E * 0.25 * jnp.pi * radius**4
    return jnp.maximum((rho * A * c0**2 / EI) ** 0.25, c0 * jnp.sqrt(rho / jnp.minimum(E, G)))


def _rate_and_length(rod, lengths, dt, alpha):
    c0 = bdf_alpha.coefficients(dt, alpha).c0
    lam = jnp.max(boundary_layer_rate(rod.radius, rod.youngs_modulus, rod.shear_modulus, rod.density, c0))
    return lam, jnp.max(lengths)


def _divisor_at_least(n: int, m: int) -> int:
    """The smallest divisor of ``n`` not below ``m`` (``n`` if m > n): equal segments, which
    `spatial.integrate` runs side by side."""
    return next((d for d in range(max(1, m), n + 1) if n % d == 0), n)


def auto_segments(steps: int, need: int, legs: int = 1) -> int:
    """Shooting segments for a grid of ``steps`` node steps whose conditioning needs ``need``,
    equal so that they run side by side: the smallest divisor of ``steps`` from ``need``,
    unless that is more than twice as many, when the ``need`` unequal segments run one after
    the other. A single rod (``legs`` 1) takes two at least (where the grid has four steps or
    more): a step then runs 1.4-1.7x faster than with one (half the scan, a better conditioned
    Jacobian, fewer refreshes). A robot of several legs does not: each segment adds 18 unknowns
    per leg to the Newton's dense algebra, and the Triskele's and the Stewart-Gough's steps ran
    1.2-1.4x slower with two."""
    want = max(need, 2) if steps >= 4 and legs == 1 else need
    d = _divisor_at_least(steps, want)
    return d if d <= 2 * want else min(need, steps)


def make_solver(
    rod, lengths, nodes, integrator, dt, alpha, duration, tol=1e-10, max_iter=50, segments="auto", unroll=1, continuation=10
) -> Solver:
    """Solver settings for rods ``rod`` (leaves with a leading leg axis) of free ``lengths`` (m);
    ``segments="auto"`` picks the multiple-shooting split from dt and alpha (the most demanding
    leg decides; `auto_segments`)."""
    lam, L = (
        float(v)
        for v in _rate_and_length(
            rod, jnp.asarray(lengths, jnp.float64), jnp.asarray(dt, jnp.float64), jnp.asarray(alpha, jnp.float64)
        )
    )
    refine = max(1, int(np.ceil(lam * L / nodes / REFINED_SPACING)))
    auto = segments == "auto"
    if auto:
        legs = int(np.shape(rod.length)[0]) if np.ndim(rod.length) else 1
        segments = auto_segments(nodes * refine, max(1, math.ceil(lam * L / SEGMENT_CONDITIONING)), legs)
    elif refine > 1 and segments > 1:
        segments = segments * refine
    return Solver(
        dt=jnp.asarray(dt, jnp.float64),
        alpha=jnp.asarray(alpha, jnp.float64),
        nodes=int(nodes),
        integrator=integrator,
        steps=int(round(duration / dt)),
        segments=int(segments),
        unroll=int(unroll),
        refine=int(refine),
        continuation=int(continuation),
        auto_segments=auto,
        newton=NewtonSettings(tol=float(tol), max_iter=int(max_iter)),
    )


def structure_result(solver: Solver, rod, lengths):
    """`results.STALE_STRUCTURE` where the numbers of ``rod``, ``lengths`` and ``solver`` need
    ``STALE_MARGIN`` times more refinement or segments than ``solver`` has, else SUCCESSFUL."""
    lam, L = _rate_and_length(rod, lengths, solver.dt, solver.alpha)
    stale = lam * L / solver.grid_nodes > STALE_MARGIN * REFINED_SPACING
    if solver.auto_segments:
        stale = stale | (lam * L / solver.segments > STALE_MARGIN * SEGMENT_CONDITIONING)
    return jnp.where(stale, results.STALE_STRUCTURE, results.SUCCESSFUL)
