r"""The one assembly: residual and structured Jacobian of a robot's shooting problem.

**Unknowns** $x = [\text{pose}, x_1, \dots, x_n]$: the end's pose unknowns (none for a free tip;
`ends.py`) and, per leg, its scaled base wrench $n_i(0), m_i(0)$ (plus its multiple-shooting
segment starts, if the step needs them). **Residuals**: the end's balance rows, then per leg its
segment continuity and its 6 tip rows (a free tip's load, or the platform clamp's position and
orientation).

**Jacobian by legs.** A leg's integration depends only on its own unknowns and actuator; the
pose enters the residual only algebraically. So the Jacobian is assembled from (a) each leg's
Jacobian of [junctions, tip state] with respect to its unknowns, computed for all legs at once
(`vmap` of coloured forward-mode JVPs: 6 for a single segment) and (b) the cheap Jacobian of the
algebraic rows with respect to the pose and the tip states, by the chain rule: 6 leg JVPs
instead of one full-residual JVP per unknown ($6 + 6n$: 42 for the Stewart-Gough platform).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import bdf_alpha, newton
from ..numerics.rod_history import RodHistory
from ..numerics.shooting import (
    Layout,
    make_scales,
    node_segments,
    segment_rotations,
    shoot,
    shoot_jacobian,
    unknowns_from_nodes,
)
from ..numerics.spatial import Rods
from ..physics.rod import coefficients

TIP = 18  # tip state the end sees: p, R, n, m


def layout(scene, inertia: bool) -> Layout:
    """Unknowns of one leg: multiple-shooting segments in dynamics only."""
    s = scene.solver
    return Layout(nodes=s.grid_nodes, segments=s.segments if inertia else 1, inertia=inertia)


def scales(scene, dynamic: bool = False):
    """Units of the unknowns and residuals, from the first leg's rod (`shooting.make_scales`);
    in dynamics the rates' units use BDF-alpha's $c_0$ at every step (also the first, which is
    backward Euler: the unknowns of successive steps must mean the same)."""
    s = scene.solver
    return make_scales(scene.legs.first_rod(), bdf_alpha.coefficients(s.dt, s.alpha).c0 if dynamic else None)


def leg_rotations(lay: Layout, nodes):
    """(n, M-1, 3, 3) rotations of each leg at its segment starts (references of their unknowns)."""
    return jax.vmap(lambda nd: segment_rotations(lay, nd))(nodes)


def zero_histories(scene):
    s = scene.solver
    return jax.vmap(lambda _: RodHistory.zeros(s.grid_nodes, s.integrator))(jnp.arange(scene.legs.count))


class Problem:
    """Residual and structured Jacobian of one shooting problem (Python-level, traced inside jit).

    ``a``, ``adot``: actuator values and rates; ``gravity``: the rods' weight direction (scaled in
    a homotopy); ``history`` and ``leg_R_ref``: per leg; ``end_cfg``: the end's data for this solve.
    """

    def __init__(self, scene, inertia: bool, a, adot, gravity, history, leg_R_ref, c0, end_cfg):
        self.scene = scene
        self.end = scene.end
        self.cfg = end_cfg
        self.inertia = inertia
        self.effects = dataclasses.replace(scene.effects, inertia=inertia)
        self.layout = layout(scene, inertia)
        self.P = scene.end.pose_size(scene.effects)
        self.S = self.layout.size
        self.n = scene.legs.count
        self.sc = scales(scene, inertia)
        legs = scene.legs
        self.k = jax.vmap(lambda rod: coefficients(rod, self.effects, c0, gravity))(legs.rod)
        self.ds = legs.lengths(a) / scene.solver.grid_nodes
        self.y0 = legs.base_states(a, adot, inertia)
        self.leg_R_ref = leg_R_ref
        s = scene.solver
        self.rods = Rods(history.nodes, history.stages, self.k, self.ds, self.effects, s.integrator, s.unroll)

    @property
    def size(self) -> int:
        return self.P + self.n * self.S

    # -- legs ---------------------------------------------------------------------------------
    def legs(self, xl, return_stages=False, all_nodes=True):
        """(junctions (n, S-6), tips (n, 18), nodes (n, N+1, dim)[, stages]) of all legs at once
        (nodes (n, 1, dim), the tips, unless ``all_nodes``)."""
        out = shoot(self.layout, xl, self.y0, self.leg_R_ref, self.rods, self.sc, return_stages, all_nodes)
        return (out[1], out[0][:, -1, :TIP], out[0]) + out[2:]

    def recorded_legs(self, xl, value):
        """`legs` at ``xl`` with the stages, from ``value``: what `residual` with ``record`` gave at
        the same unknowns (a Newton solve's aux at its root). A forward run integrates nothing;
        derivatives are those of `legs` (`newton.recorded`)."""
        return newton.recorded(lambda z: self.legs(z, return_stages=True), xl, value)

    def leg_jacobians(self, xl, everywhere=False):
        """(tips (n, 18), (n, S-6+18, S)): the legs' tip states and each leg's Jacobian of
        [junctions, tip state] with respect to its own unknowns, by forward sensitivities along
        coloured seeds (columns sharing a colour never share a nonzero row), decompressed by the
        sparsity mask. With ``everywhere``, also the nodes' and stages' derivatives along the
        seeds (`shooting.shoot_jacobian`)."""
        colours, mask = self.layout.colouring(extra_rows=TIP)
        _, colours = np.unique(colours, return_inverse=True)
        out = shoot_jacobian(self.layout, xl, _seeds(self.layout), self.y0, self.leg_R_ref, self.rods, self.sc, everywhere)
        return (out[0], jnp.swapaxes(out[1], 1, 2)[:, :, colours] * jnp.asarray(mask, out[1].dtype)) + out[2:]

    def jacobian_and_legs(self, x):
        """`jacobian`, and what `legs_tangent` needs to give the derivative of `legs` (with every
        node and stage) along a change of the unknowns: the same leg integrations, keeping every
        node's tangent."""
        xp, xl = self.split(x)
        tips, Jl, node_tangents = self.leg_jacobians(xl, everywhere=True)
        return self.assemble(xp, tips, Jl), (Jl, node_tangents)

    # -- end ----------------------------------------------------------------------------------
    def pose(self, xp):
        return self.end.pose(self.cfg, xp, self.sc, self.scene.effects.planar)

    def algebraic(self, xp, tips):
        """[balance (P), tip rows (6 per leg)] from the pose unknowns and the leg tips."""
        bal, cons = self.end.rows(self.cfg, tips, self.sc, self.scene.effects, self.inertia, self.pose(xp))
        return jnp.concatenate([bal, cons.reshape(-1)])

    # -- whole problem ------------------------------------------------------------------------
    def split(self, x):
        return x[: self.P], x[self.P :].reshape(self.n, self.S)

    def residual(self, x, record=False):
        """The residual; with ``record``, ``(residual, legs)``: `legs` with every node and stage,
        at no extra cost (a solve's root then needs no second pass along the legs)."""
        xp, xl = self.split(x)
        legs = self.legs(xl, return_stages=record, all_nodes=record)
        junc, tips = legs[0], legs[1]
        A = self.algebraic(xp, tips)
        cons = A[self.P :].reshape(self.n, 6)
        r = jnp.concatenate([A[: self.P], jnp.concatenate([junc, cons], axis=1).reshape(-1)])
        return (r, legs) if record else r

    def jacobian(self, x):
        xp, xl = self.split(x)
        tips, Jl = self.leg_jacobians(xl)  # the tips come with their tangents
        return self.assemble(xp, tips, Jl)

    def assemble(self, xp, tips, Jl, pose_columns=True):
        """The whole Jacobian from the legs' blocks ``Jl`` (n, S-6+18, C) of [junctions, tip
        state] over each leg's own C unknowns: columns [pose (P, unless not ``pose_columns``),
        then C per leg], rows [balance (P), then per leg its junctions and 6 tip rows]."""
        P, S, n = self.P, self.S, self.n
        C = Jl.shape[2]
        Jjun, Jtip = Jl[:, : S - 6], Jl[:, S - 6 :]
        if P:
            dA_dp, dA_dt = jax.jacfwd(self.algebraic, argnums=(0, 1))(xp, tips)  # (P+6n, P), (P+6n, n, 18)
        else:
            dA_dt = jax.jacfwd(lambda t: self.algebraic(xp, t))(tips)
        if not (P and pose_columns):
            dA_dp = jnp.zeros((P + 6 * n, 0), tips.dtype)
        Pc = dA_dp.shape[1]
        via = jnp.einsum("rnt,nts->rns", dA_dt, Jtip)  # (P+6n, n, C), leg-block structure
        top = jnp.concatenate([dA_dp[:P], via[:P].reshape(P, n * C)], axis=1)
        eye = jnp.eye(n, dtype=tips.dtype)
        jun = jnp.einsum("ij,irs->irjs", eye, Jjun).reshape(n, S - 6, n * C)
        jun = jnp.concatenate([jnp.zeros((n, S - 6, Pc), tips.dtype), jun], axis=2)
        cons_via = jnp.einsum("ij,irs->irjs", eye, via[P:].reshape(n, 6, n, C).diagonal(axis1=0, axis2=2).transpose(2, 0, 1))
        cons = jnp.concatenate([dA_dp[P:].reshape(n, 6, Pc), cons_via.reshape(n, 6, n * C)], axis=2)
        rows = jnp.concatenate([jun, cons], axis=1).reshape(n * S, Pc + n * C)
        return jnp.concatenate([top, rows], axis=0)

    def unknowns(self, pose_unknowns, nodes):
        return unknowns(self.layout, self.sc, pose_unknowns, nodes)


def _seeds(lay: Layout):
    """(C, S) coloured seeds of one leg's unknowns (`Layout.colouring`)."""
    _, colours = np.unique(lay.colouring(extra_rows=TIP)[0], return_inverse=True)
    return np.eye(int(colours.max()) + 1)[colours].T


def legs_tangent(lay: Layout, P: int, legs_jacobian, dx):
    """The derivative of `Problem.legs` (junctions, tips, nodes, stages) along ``dx``, a change of
    the whole unknown vector (pose P first), from `Problem.jacobian_and_legs`'s ``legs_jacobian``.

    A node of segment k depends on that segment's start unknowns only, and no two of those
    share a seed's colour, so a seed's tangent there is the derivative along the one unknown
    of its colour in segment k: each seed's coefficient per segment is that unknown's change."""
    Jl, (T, Ts) = legs_jacobian
    n = T.shape[0]
    dxl = dx[P:].reshape(n, -1)
    rows = jnp.einsum("nrs,ns->nr", Jl, dxl)
    in_segment = np.zeros((lay.segments, lay.size))
    for k, cols in enumerate(lay.segment_columns):
        in_segment[k, cols] = 1.0
    W = _seeds(lay)[:, None, :] * in_segment[None]  # (C, M, S)
    coef = jnp.einsum("cks,ns->nck", jnp.asarray(W, dx.dtype), dxl)
    node_k, step_k = node_segments(lay)
    nodes = jnp.einsum("ncjd,ncj->njd", T, coef[:, :, node_k])
    stages = jnp.einsum("ncjsd,ncj->njsd", Ts, coef[:, :, step_k])
    return rows[:, : lay.size - 6], rows[:, lay.size - 6 :], nodes, stages


def unknowns(lay: Layout, sc, pose_unknowns, nodes):
    """Scaled unknowns that reproduce ``nodes`` of every leg (segment starts relative to their own
    rotations) after the end's ``pose_unknowns``."""
    xl = jax.vmap(lambda nd, Rr: unknowns_from_nodes(lay, nd, Rr, sc))(nodes, leg_rotations(lay, nodes))
    return jnp.concatenate([pose_unknowns, xl.reshape(-1)])
