"""Shooting for one rod: unknown layout, multiple-shooting segments and continuity residuals.

Single shooting from the clamp amplifies errors like $e^{\\lambda L}$, with
$\\lambda = \\max((\\rho A c_0^2/EI)^{1/4}, c_0\\sqrt{\\rho/G})$ in dynamics: at
$\\delta t = 10^{-5}$ s the thesis cantilever has $\\lambda L \\approx 107$ ($10^{46}$), which no
float64 Newton can solve, and which is why the thesis failed at $\\delta t \\le 1$ ms. pcrjax
therefore splits the rod into segments of $\\lambda \\ell \\lesssim 6$ (`solver.make_solver`), each
with its own start state as unknowns, and adds continuity residuals. At the usual step sizes
one segment (plain single shooting, 6 unknowns) is enough; a single rod still takes two equal
ones, which `spatial.integrate` runs side by side (a scan half as long, 24 unknowns), while a
robot of several legs keeps one (`solver.auto_segments`).

Unknowns are scaled: positions by L, forces by $F_c = EI/L^2$, moments by $F_c L$, linear
velocities by $L c_0$ and angular velocities by $c_0$ (a change of one step's displacement);
rotations of segment starts are Cayley parameters relative to a reference rotation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..physics.rod import DYNAMIC_DIM, STATIC_DIM
from ..physics.rotations import cayley, cayley_inverse, matmul, skew_vee, transpose_matmul
from .spatial import Rods, integrate, integrate_tangents

SEGMENT_CONDITIONING = 6.0  # target lambda * segment length (error growth e^6 = 400)


class Scales(eqx.Module):
    length: jnp.ndarray
    force: jnp.ndarray
    velocity: jnp.ndarray
    angular: jnp.ndarray

    @property
    def moment(self):
        return self.force * self.length


def make_scales(rod, c0=None) -> Scales:
    L = rod.length
    c0 = jnp.ones_like(L) if c0 is None else c0
    return Scales(length=L, force=rod.bending_stiffness / L**2, velocity=L * c0, angular=c0)


class Layout(eqx.Module):
    """Static description of the unknowns of one rod: segment start nodes and sizes."""

    nodes: int = eqx.field(static=True)
    segments: int = eqx.field(static=True)
    inertia: bool = eqx.field(static=True)

    @property
    def starts(self) -> tuple[int, ...]:
        """Start nodes of segments 1..M-1 (segment 0 starts at the clamp)."""
        return tuple(int(round(k * self.nodes / self.segments)) for k in range(1, self.segments))

    @property
    def state_dim(self) -> int:
        return DYNAMIC_DIM if self.inertia else STATIC_DIM

    @property
    def segment_dim(self) -> int:
        """Unknowns of a segment start: p, rotation, n, m (and q, w in dynamics)."""
        return 18 if self.inertia else 12

    @property
    def size(self) -> int:
        return 6 + (self.segments - 1) * self.segment_dim

    @property
    def segment_columns(self) -> list[slice]:
        """Each segment's unknowns in the unknown vector: the base's 6, then each start's."""
        d = self.segment_dim
        return [slice(0, 6)] + [slice(6 + (k - 1) * d, 6 + k * d) for k in range(1, self.segments)]

    def colouring(self, extra_rows: int = 6):
        """Column colours and sparsity mask for the residual [junctions..., tip rows]."""
        d = self.segment_dim
        colours = [6 + j for j in range(6)]  # segment 0: n, m share colours with n, m below
        for k in range(1, self.segments):
            colours += [(k % 2) * d + j for j in range(d)]
        rows = (self.segments - 1) * d + extra_rows
        mask = np.zeros((rows, self.size), dtype=bool)
        for k, cols in enumerate(self.segment_columns):
            if k > 0:
                mask[(k - 1) * d : k * d, cols] = True  # junction k-1 sees segment k directly
            mask[k * d : (k + 1) * d if k < self.segments - 1 else rows, cols] = True
        return np.asarray(colours), mask


def segment_rotations(layout: Layout, nodes):
    """Rotations (M-1, 3, 3) of ``nodes`` at the starts of segments 1.. (the references of their
    rotation unknowns)."""
    idx = np.asarray(layout.starts, dtype=int)
    return nodes[idx, 3:12].reshape(-1, 3, 3)


def restart_states(layout: Layout, x, R_ref, sc: Scales):
    """Unscaled start states (M-1, dim) of segments 1.. from the unknown vector."""
    d = layout.segment_dim
    xs = x[6:].reshape(layout.segments - 1, d)

    def one(xk, Rr):
        parts = [xk[0:3] * sc.length, matmul(Rr, cayley(xk[3:6])).reshape(9), xk[6:9] * sc.force, xk[9:12] * sc.moment]
        if layout.inertia:
            parts += [xk[12:15] * sc.velocity, xk[15:18] * sc.angular]
        return jnp.concatenate(parts)

    return jax.vmap(one)(xs, R_ref)


def junction_residuals(layout: Layout, arrivals, restarts, sc: Scales):
    """Scaled mismatch between the state arriving at each segment start and its unknown start."""

    def one(a, s):
        Ra, Rs = a[3:12].reshape(3, 3), s[3:12].reshape(3, 3)
        parts = [
            (a[0:3] - s[0:3]) / sc.length,
            skew_vee(transpose_matmul(Rs, Ra)),
            (a[12:15] - s[12:15]) / sc.force,
            (a[15:18] - s[15:18]) / sc.moment,
        ]
        if layout.inertia:
            parts += [(a[18:21] - s[18:21]) / sc.velocity, (a[21:24] - s[21:24]) / sc.angular]
        return jnp.concatenate(parts)

    return jax.vmap(one)(arrivals, restarts).reshape(-1)


def _starts(base_state, x, sc: Scales):
    """(n, dim) start states: the base states with each leg's scaled base wrench x[:, 0:6]."""
    return base_state.at[:, 12:15].set(x[:, 0:3] * sc.force).at[:, 15:18].set(x[:, 3:6] * sc.moment)


def _restarts(layout: Layout, x, R_ref, sc: Scales):
    return jax.vmap(lambda xi, Ri: restart_states(layout, xi, Ri, sc))(x, R_ref)


def shoot(layout: Layout, x, base_state, R_ref, rods: Rods, sc: Scales, return_stages=False, all_nodes=True):
    """Integrate every leg for unknowns ``x`` (n, size); returns (nodes (n, N+1, dim), junction
    residuals (n, (M-1) d)[, stage states]).

    ``base_state`` (n, dim): the states at s = 0 with zero wrench; x[:, 0:6] sets the scaled base
    wrenches. ``R_ref`` (n, M-1, 3, 3); ``rods``: histories, coefficients and step lengths per leg
    (`spatial.Rods`). Without ``all_nodes`` only the last node is returned, (n, 1, dim).
    """
    y0 = _starts(base_state, x, sc)
    if layout.segments == 1:
        out = integrate(y0, rods, return_stages=return_stages, all_nodes=all_nodes)
        junctions = jnp.zeros((x.shape[0], 0), x.dtype)
    else:
        restarts = _restarts(layout, x, R_ref, sc)
        out = integrate(y0, rods, layout.starts, restarts, return_stages, all_nodes)
        junctions = jax.vmap(lambda a, r: junction_residuals(layout, a, r, sc))(out[1], restarts)
    return (out[0], junctions) + ((out[2],) if return_stages else ())


def shoot_jacobian(layout: Layout, x, seeds, base_state, R_ref, rods: Rods, sc: Scales, everywhere=False):
    """Tip states (n, 18) and directional derivatives (n, C, rows) of each leg's [junction
    residuals, tip state (18)] along the C rows of ``seeds`` (C, size, a NumPy array: which
    segments each seed moves is static), by forward sensitivities integrated with the rods
    (`integrate_tangents`, which carries the states themselves too). With ``everywhere``, also
    the nodes' and stages' derivatives along the seeds, (n, C, N+1, dim) and (n, C, N, 3|0, dim)."""
    seeds = np.asarray(seeds)

    def lin(fn, *args):  # fn's value at x and its derivatives along the seeds, per leg
        def one(x_i, *a):
            return jax.vmap(lambda t: jax.jvp(lambda z: fn(z, *a), (x_i,), (t,)), out_axes=(None, 0))(seeds)

        return jax.vmap(one)(x, *args)

    y0, Y0 = lin(lambda z, b: _starts(b[None], z[None], sc)[0], base_state)
    if layout.segments == 1:
        out = integrate_tangents(y0, Y0, rods, everywhere=everywhere)
        tips, cols = out[0][:, :18], out[1][..., :18]
        return (tips, cols, out[5]) if everywhere else (tips, cols)
    restarts, RT = lin(lambda z, R: restart_states(layout, z, R, sc), R_ref)
    RT = jnp.swapaxes(RT, 1, 2)  # (n, M-1, C, dim)
    directions = tuple(tuple(int(c) for c in np.flatnonzero(seeds[:, cl].any(axis=1))) for cl in layout.segment_columns)
    out = integrate_tangents(y0, Y0, rods, layout.starts, restarts, RT, directions, everywhere, _translations(layout, seeds))
    y_last, Y_last, arr, arr_t = out[:4]

    def junction_tangents(a, a_t, r, r_t):  # one leg: (C, (M-1) d)
        jvp = lambda at, rt: jax.jvp(lambda aa, rr: junction_residuals(layout, aa, rr, sc), (a, r), (at, rt))[1]  # noqa: E731
        return jax.vmap(jvp)(jnp.swapaxes(a_t, 0, 1), jnp.swapaxes(r_t, 0, 1))

    cols = jnp.concatenate([jax.vmap(junction_tangents)(arr, arr_t, restarts, RT), Y_last[..., :18]], axis=2)
    return (y_last[:, :18], cols, out[5]) if everywhere else (y_last[:, :18], cols)


def _translations(layout: Layout, seeds):
    """Per segment, the seeds (rows of ``seeds``) that move its start's position alone (the first
    3 of a restart's unknowns, `restart_states`); none for segment 0, whose start is the base."""
    out = [()]
    for cl in layout.segment_columns[1:]:
        moved = seeds[:, cl] != 0
        out.append(tuple(int(c) for c in np.flatnonzero(moved.any(axis=1) & ~moved[:, 3:].any(axis=1))))
    return tuple(out)


def node_segments(layout: Layout):
    """The segment (NumPy, static) of each node (N+1,) and of each node step (N,): node j belongs
    to the segment whose start it is or follows; the last node to the last segment."""
    k = np.searchsorted(np.asarray(layout.starts, dtype=int), np.arange(layout.nodes + 1), side="right")
    return k, k[:-1]


def unknowns_from_nodes(layout: Layout, nodes, R_ref, sc: Scales):
    """Scaled unknown vector that reproduces ``nodes`` (e.g. a previous step's solution)."""
    parts = [nodes[0, 12:15] / sc.force, nodes[0, 15:18] / sc.moment]
    if layout.segments > 1:
        idx = np.asarray(layout.starts)
        S = nodes[idx]

        def one(s, Rr):
            Rs = s[3:12].reshape(3, 3)
            q = [s[0:3] / sc.length, cayley_inverse(transpose_matmul(Rr, Rs)), s[12:15] / sc.force, s[15:18] / sc.moment]
            if layout.inertia:
                q += [s[18:21] / sc.velocity, s[21:24] / sc.angular]
            return jnp.concatenate(q)

        parts.append(jax.vmap(one)(S, R_ref).reshape(-1))
    return jnp.concatenate(parts)
