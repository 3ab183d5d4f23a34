r"""Spatial integration of the rod ODE as one jitted `lax.scan` over the nodes.

RK4 (thesis eq. 3.39) or explicit Euler. RK4 evaluates the ODE at half steps, where BDF-alpha
needs the history $f^h$. The thesis averages the two nodes there (second order in ds); since the
history is of size $c_0 f$ with $c_0 \propto 1/\delta t$, that error grows as the step shrinks and
broke the trapezoidal rule's energy conservation: the thesis cantilever's first mode *grew* 3 %
in 12 periods at $h = \omega\delta t = 0.5$ and 20 % at $h = 0.1$ (N = 20). pcrjax interpolates
the history cubically (4th order, like RK4): the growth is gone and the first frequency is
within 1e-4 at N = 40. The remaining error is $O(c_0\,ds^4)$, so very small time steps need
more nodes (N growing like $\delta t^{-1/4}$); `rod_history.py` keeps the previous step's value
exactly at every stage point, so that this error multiplies a velocity, not $c_0$.

One scan integrates every leg of a robot at once: the carried state has a leading leg axis and
the right-hand side is mapped over it inside the loop body, so the loop is traced once (mapping a
whole `lax.scan` over legs traces and batches its body several times) and each kernel of a node
step serves all legs. The scan supports multiple shooting: at the first node of each segment the
carried state is replaced by that segment's unknown start state, and the state arriving there is
returned so that the caller can form continuity residuals. Segments of equal length are not
integrated one after the other but side by side, as extra legs of one shorter scan: every kernel
of a node step then serves all segments, and the scan is M times shorter.

**Rotations stay on SO(3).** RK4 integrating $R' = R\hat u$ drifts off the rotations
at the scheme's order: $|R^T R - I|$ reached 4e-6 along the thesis cantilever at N = 10 in a
dynamic step. A segment's start rotation is an exact rotation (its unknowns are Cayley
parameters), so every segment start reset that drift, and the discrete solution depended on how
many segments the shooting used, by RK4's $O(ds^4)$: the released cantilever's tip moved 1.3e-7 m
(N 10) from 2 to 4 segments in one step, the Triskele-bot's platform 64 nm (N 20, 0.3 s, 32x the
noise of its recordings), and a refinement in dt that changed the segment count moved with it.
Each RK4 node step therefore ends with one Newton-Schulz step $R \leftarrow R (3I - R^T R)/2$,
which takes the defect $\varepsilon$ to $O(\varepsilon^2)$: the solution is the same for every
segmentation (to round-off), and the scheme's order is unchanged (a projection onto the manifold
the exact solution lies on). Explicit Euler is left as it was (its drift, and so its dependence
on the segments, is first order like its error; projected, its observed order on the static
cantilever at N 16-64 was 1.4 and 1.2, not yet its asymptotic 1).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..physics.rod import rhs

INTEGRATORS = ("rk4", "euler")


def _on_rotations(y):
    """States ``y`` (..., dim) with the rotation y[..., 3:12] (row-major) taken back towards SO(3)
    by one Newton-Schulz step, R (3I - R^T R) / 2 (module doc)."""
    R = y[..., 3:12].reshape(y.shape[:-1] + (3, 3))
    RtR = jnp.sum(R[..., :, :, None] * R[..., :, None, :], axis=-3)  # (R^T R)_jk = sum_i R_ij R_ik
    E = 0.5 * (jnp.eye(3, dtype=y.dtype) - RtR)
    corrected = R + jnp.sum(R[..., :, :, None] * E[..., None, :, :], axis=-2)
    return y.at[..., 3:12].set(corrected.reshape(y.shape[:-1] + (9,)))


def _on_rotations_with_tangents(state):
    """`_on_rotations` of ``(y (n, dim), Y (n, C, dim))``: the states and their C tangents."""
    y, Y = state
    return jax.vmap(lambda t: jax.jvp(_on_rotations, (y,), (t,)), in_axes=1, out_axes=(None, 1))(Y)


def midpoints(history):
    """History at the N half steps by cubic interpolation (one-sided at the ends; linear if N < 3)."""
    h = history
    if h.shape[0] < 4:
        return 0.5 * (h[:-1] + h[1:])
    inner = (-h[:-3] + 9.0 * h[1:-2] + 9.0 * h[2:-1] - h[3:]) / 16.0
    first = (5.0 * h[0] + 15.0 * h[1] - 5.0 * h[2] + h[3]) / 16.0
    last = (5.0 * h[-1] + 15.0 * h[-2] - 5.0 * h[-3] + h[-4]) / 16.0
    return jnp.concatenate([first[None], inner, last[None]])


def _scan(F, state0, rods, segment_starts, restarts, return_stages, collect=True, project=_on_rotations):
    """RK4 or Euler along the nodes for a state with a leading leg axis (a PyTree: a point and
    its tangents). ``F(state, h)`` is the derivative along s given the histories ``h`` (n, 12)
    (`Rods` gives the histories and step lengths); ``restarts`` the states (n, M-1, ...) that replace the carried one at
    ``segment_starts``. Returns ``(last state, per-node outputs (N, ...): state entering, state
    arriving[, stages])`` (no outputs unless ``collect``). ``project`` ends every RK4 node step
    (`_on_rotations`, or its tangent form for a (state, tangents) pair)."""
    ds, integrator = rods.ds, rods.integrator
    n_steps = rods.history.shape[1] - 1
    tmap = jax.tree.map
    F = jax.jit(F)  # traced once for the four RK4 stages (the same shapes), not four times

    def axpy(a, x, y):  # y + a x per leg, leaf by leaf
        return tmap(lambda xx, yy: yy + a.reshape(a.shape + (1,) * (xx.ndim - 1)) * xx, x, y)

    def step(y, h0, hs):
        if integrator == "euler":
            return axpy(ds, F(y, h0), y), None
        k1 = F(y, h0)
        y2 = axpy(0.5 * ds, k1, y)
        k2 = F(y2, hs[:, 0])
        y3 = axpy(0.5 * ds, k2, y)
        k3 = F(y3, hs[:, 1])
        y4 = axpy(ds, k3, y)
        k4 = F(y4, hs[:, 2])
        incr = tmap(lambda a, b, c, d: a + 2.0 * (b + c) + d, k1, k2, k3, k4)
        return project(axpy(ds / 6.0, incr, y)), tmap(lambda *z: jnp.stack(z, axis=1), y2, y3, y4)

    xs = (jnp.swapaxes(rods.history[:, :-1], 0, 1), jnp.swapaxes(rods.stage_history, 0, 1))
    if segment_starts:
        flags = np.zeros(n_steps, dtype=bool)
        flags[list(segment_starts)] = True
        idx = np.asarray(segment_starts)
        replace = tmap(
            lambda r: jnp.zeros((n_steps,) + r.shape[:1] + r.shape[2:], r.dtype).at[idx].set(jnp.swapaxes(r, 0, 1)), restarts
        )
        xs = xs + (jnp.asarray(flags), replace)

    def body(y, x):
        y_in = tmap(lambda r, c: jnp.where(x[2], r, c), x[3], y) if segment_starts else y
        y_next, stages = step(y_in, x[0], x[1])
        out = (y_in, y) + ((stages,) if return_stages and stages is not None else ())
        return y_next, out if collect else None

    # Reverse mode recomputes each node step from its carried state (`jax.checkpoint`) instead of
    # storing every intermediate of the right-hand side: a linearised RK4 node step saves some 600
    # small arrays, each written and read by a kernel of its own, which made the gradient's
    # program several times larger than the forward one. Forward runs are unchanged.
    return jax.lax.scan(jax.checkpoint(body, prevent_cse=False), state0, xs, unroll=rods.unroll)


def _per_leg(fn, n: int):
    """``fn`` mapped over the leading leg axis of its arguments. One leg is computed unbatched
    (a (1, 24) state sliced along its minor axis costs XLA:CPU a third more kernels per node)."""
    if n == 1:
        return lambda *args: jax.tree.map(lambda a: a[None], fn(*jax.tree.map(lambda a: a[0], args)))
    return jax.vmap(fn)


class Rods(eqx.Module):
    """What integrating n legs needs besides their start states: BDF-alpha histories at the nodes
    (n, N+1, 12) and RK4 stage points (n, N, 3|0, 12), coefficients ``k`` and step lengths ``ds``
    (n,) per leg, and the static effect switches, integrator and scan unroll."""

    history: jnp.ndarray
    stage_history: jnp.ndarray
    k: object  # rod.RodCoefficients, leaves per leg
    ds: jnp.ndarray
    effects: object = eqx.field(static=True)
    integrator: str = eqx.field(static=True, default="rk4")
    unroll: int = eqx.field(static=True, default=1)


def _equal_segments(rods: Rods, segment_starts) -> int:
    """The number of segments M if ``segment_starts`` split the N steps into M equal runs, else 0."""
    if not segment_starts:
        return 0
    n_steps = rods.history.shape[1] - 1
    M = len(segment_starts) + 1
    return M if n_steps % M == 0 and tuple(segment_starts) == tuple(range(n_steps // M, n_steps, n_steps // M)) else 0


def _side_by_side(rods: Rods, M: int) -> Rods:
    """``rods`` (n legs of N steps) as n M legs of N / M steps: leg i's segment k becomes leg i M + k,
    with the histories of its nodes (its end node included) and leg i's coefficients."""
    n, n1 = rods.history.shape[:2]
    L = (n1 - 1) // M
    body = rods.history[:, :-1].reshape(n, M, L, -1)
    ends = rods.history[:, L::L][:, :, None]  # nodes L, 2L, .., N: each segment's last node
    history = jnp.concatenate([body, ends], axis=2).reshape(n * M, L + 1, -1)
    stage_history = rods.stage_history.reshape((n * M, L) + rods.stage_history.shape[2:])
    repeat = lambda a: jnp.repeat(a, M, axis=0)  # noqa: E731
    return Rods(history, stage_history, jax.tree.map(repeat, rods.k), repeat(rods.ds), rods.effects, rods.integrator, rods.unroll)


def _segment_starts(first, restarts, M: int):
    """(n M, ...) start states of every segment: leg i's ``first`` (n, ...), then its ``restarts`` (n, M-1, ...)."""
    return jax.tree.map(lambda a, r: jnp.concatenate([a[:, None], r], axis=1).reshape((-1,) + a.shape[1:]), first, restarts)


def _per_segment(a, M: int):
    """(n M, ...) -> (n, M, ...)."""
    return a.reshape((a.shape[0] // M, M) + a.shape[1:])


def integrate(y0, rods: Rods, segment_starts=None, restarts=None, return_stages=False, all_nodes=True):
    r"""Integrate n legs from node 0 to node N.

    **Arguments** (every array with a leading leg axis n):
    - ``y0``: (n, dim) states at s = 0.
    - ``rods``: histories (zeros in statics; stage histories per `rod_history.py`), coefficients,
      step lengths L/N and the static settings (`Rods`).
    - ``segment_starts``: static tuple of node indices (>0) where a new segment starts.
    - ``restarts``: (n, len(segment_starts), dim) start states of those segments.
    - ``return_stages``: also return the (n, N, 3, dim) states at which stages 2, 3, 4 were evaluated.
    - ``all_nodes``: False returns only the last node (nothing is stored per node unless segments
      need their arrivals).

    **Returns:** ``(nodes, arrivals)`` (and ``stages`` if asked): the states (n, N+1, dim) at all
    nodes (after restarts; (n, 1, dim), the last, unless ``all_nodes``) and those (n, M-1, dim)
    arriving at each segment start before the restart (or None).
    """
    M = _equal_segments(rods, segment_starts)
    if M:
        return _integrate_side_by_side(y0, rods, M, restarts, return_stages, all_nodes)
    F = _per_leg(lambda y, h, kk: rhs(y, h, kk, rods.effects), y0.shape[0])
    collect = all_nodes or return_stages or bool(segment_starts)
    y_last, outs = _scan(lambda y, h: F(y, h, rods.k), y0, rods, segment_starts, restarts, return_stages, collect)
    nodes = jnp.swapaxes(jnp.concatenate([outs[0], y_last[None]]), 0, 1) if all_nodes else y_last[:, None]
    arrivals = jnp.swapaxes(outs[1][np.asarray(segment_starts)], 0, 1) if segment_starts else None
    if return_stages:
        n, n_steps = y0.shape[0], rods.history.shape[1] - 1
        stages = jnp.swapaxes(outs[2], 0, 1) if rods.integrator == "rk4" else jnp.zeros((n, n_steps, 0, y0.shape[1]), y0.dtype)
        return nodes, arrivals, stages
    return nodes, arrivals


def _integrate_side_by_side(y0, rods: Rods, M: int, restarts, return_stages, all_nodes):
    """`integrate` for M equal segments, run side by side (`_side_by_side`)."""
    n, dim = y0.shape
    seg = _side_by_side(rods, M)
    F = _per_leg(lambda y, h, kk: rhs(y, h, kk, rods.effects), n * M)
    collect = all_nodes or return_stages
    y_last, outs = _scan(lambda y, h: F(y, h, seg.k), _segment_starts(y0, restarts, M), seg, None, None, return_stages, collect)
    ends = _per_segment(y_last, M)  # (n, M, dim): each segment's last node
    arrivals = ends[:, :-1]
    if all_nodes:  # node j of segment k is node k L + j; each segment's end is the next one's arrival
        entering = _per_segment(jnp.swapaxes(outs[0], 0, 1), M).reshape(n, -1, dim)
        nodes = jnp.concatenate([entering, ends[:, -1:]], axis=1)
    else:
        nodes = ends[:, -1:]
    if not return_stages:
        return nodes, arrivals
    if rods.integrator == "rk4":
        stages = _per_segment(jnp.swapaxes(outs[2], 0, 1), M).reshape((n, -1) + outs[2].shape[2:])
    else:
        stages = jnp.zeros((n, rods.history.shape[1] - 1, 0, dim), y0.dtype)
    return nodes, arrivals, stages


# Directions integrated as complex legs at most (`integrate_tangents`): beyond, the arithmetic of
# the complex legs (each a state of its own, complex products costing four real ones) outweighs
# the kernels it saves. Measured per legs' Jacobian: Till's cantilever (24 complex legs of 20
# node steps) 621 against 700 us, the Triskele-bot (18 of 10) 228 against 226, the
# Stewart-Gough platform (36 of 50) 2296 against 1708.
COMPLEX_STEP_LEGS = 24
# The complex step: a power of two (so dividing by it is exact) small enough that products of two
# perturbations (h^2 ~ 1e-181) vanish beside any state's round-off, and large enough that no
# tangent times h underflows.
_STEP = 2.0**-300


def _legs(rods: Rods, idx) -> Rods:
    """The legs ``idx`` (an index array) of ``rods``."""
    take = lambda a: a[idx]  # noqa: E731
    return dataclasses.replace(
        rods, history=take(rods.history), stage_history=take(rods.stage_history), k=jax.tree.map(take, rods.k), ds=take(rods.ds)
    )


def integrate_tangents(
    y0,
    Y0,
    rods: Rods,
    segment_starts=None,
    restarts=None,
    restart_tangents=None,
    directions=None,
    everywhere=False,
    translations=None,
):
    r"""Integrate n legs and C tangent directions each together (forward sensitivities).

    ``Y0`` (n, C, dim): tangents of the start states; ``restart_tangents`` (n, M-1, C, dim): of the
    segment restarts. ``directions``: for equal segments, a static tuple per segment of the
    directions whose tangents may be nonzero there (None: all); the others' come out zero.
    ``translations``: for equal segments, a static tuple per segment of those directions whose
    start tangent there moves the position y[0:3] alone. The right-hand side and the rotation
    step never read the position, so along such a direction every node of the segment moves
    as its start does: the tangent is carried, not integrated (on Till's cantilever, 3 of the
    24 complex legs of a step's Jacobian).

    **By the complex step** where that makes at most ``COMPLEX_STEP_LEGS`` legs: each direction
    is integrated as a leg of its own from the complex start $y_0 + i h Y_0$. The right-hand
    side and the rotation step are polynomials and rational functions of the state, analytic,
    so the imaginary part of the end state is $h$ times its derivative along $Y_0$ up to
    $O(h^3)$, with no difference taken (no cancellation: exact to round-off, like forward-mode
    AD), and its real part is the state itself. The scan is then the residual's own (some 19
    kernels per RK4 node step, each over the directions), where a batched `jax.jvp` of the
    right-hand side compiles to some 77 (each primal slice that the tangents read becomes a
    kernel of its own): on Till's cantilever the compiled dynamic step shrank by a quarter, and
    the cold compile of a simulation by a sixth.

    **Otherwise by `jax.jvp`**: each RK4 stage evaluates the ODE once and its derivative along
    the C directions (batched), so the scan is traced and compiled once for all directions,
    unlike a `jax.jvp` of the whole `lax.scan`.

    **Returns:** ``(y_N, Y_N, arrivals, arrival tangents)``: the last states (n, dim) and their
    tangents (n, C, dim), and the states (n, M-1, dim) and tangents (n, M-1, C, dim) arriving at
    each segment start (or None). With ``everywhere``, also ``((nodes, stages), (node tangents,
    stage tangents))``: `integrate`'s nodes (n, N+1, dim) and stages (n, N, 3|0, dim), and their
    tangents (n, C, N+1, dim) and (n, C, N, 3|0, dim).
    """
    n, C, dim = Y0.shape
    M = _equal_segments(rods, segment_starts)
    if M:
        directions = [tuple(range(C)) if directions is None or not directions[k] else tuple(directions[k]) for k in range(M)]
        carried = [tuple(c for c in directions[k] if translations is not None and c in translations[k]) for k in range(M)]
        # a segment keeps one integrated direction at least: its complex legs carry its states too
        carried = [t if len(t) < len(d) else () for t, d in zip(carried, directions, strict=True)]
        integrated = [tuple(c for c in d if c not in t) for d, t in zip(directions, carried, strict=True)]
        if n * sum(map(len, integrated)) <= COMPLEX_STEP_LEGS:
            return _complex_side_by_side(y0, Y0, rods, M, restarts, restart_tangents, integrated, everywhere, carried)
        return _jvp_side_by_side(y0, Y0, rods, M, restarts, restart_tangents, integrated, everywhere, carried)
    if n * C <= COMPLEX_STEP_LEGS:
        return _complex_step(y0, Y0, rods, segment_starts, restarts, restart_tangents, everywhere)
    return _tangents_by_jvp(y0, Y0, rods, segment_starts, restarts, restart_tangents, everywhere)


def _no_stages(nodes):
    """The (..., N, 0, dim) stages of an Euler grid, for ``nodes`` (..., N+1, dim)."""
    return jnp.zeros(nodes.shape[:-2] + (nodes.shape[-2] - 1, 0, nodes.shape[-1]), nodes.dtype)


def _complex_step(y0, Y0, rods: Rods, segment_starts, restarts, restart_tangents, everywhere=False):
    """`integrate_tangents` by the complex step in one scan (one segment, or unequal ones)."""
    n, C, dim = Y0.shape
    lift = lambda y, Y: (y[:, None] + 1j * _STEP * Y).reshape((n * C,) + y.shape[1:])  # noqa: E731
    split = lambda z: (z.reshape((n, C) + z.shape[1:])[:, 0].real, z.reshape((n, C) + z.shape[1:]).imag / _STEP)  # noqa: E731
    legs = _legs(rods, np.repeat(np.arange(n), C))
    zr = lift(restarts, jnp.swapaxes(restart_tangents, 1, 2)) if segment_starts else None  # (n C, M-1, dim)
    out = integrate(lift(y0, Y0), legs, segment_starts, zr, return_stages=everywhere, all_nodes=everywhere)
    (y_end, Y_end), arr = split(out[0][:, -1]), out[1]
    arr = (split(arr)[0], jnp.swapaxes(split(arr)[1], 1, 2)) if segment_starts else (None, None)
    if not everywhere:
        return y_end, Y_end, *arr
    (nodes, T), (stages, Ts) = split(out[0]), split(out[2])
    return y_end, Y_end, *arr, (nodes, stages), (T, Ts)


def _complex_side_by_side(y0, Y0, rods: Rods, M: int, restarts, restart_tangents, directions, everywhere, carried):
    """`integrate_tangents` by the complex step for M equal segments side by side: segment k of
    each leg integrates only the directions ``directions[k]``, each as a complex leg of N / M
    steps, and holds the start tangents of the directions ``carried[k]`` (translations) at
    every node."""
    n = Y0.shape[0]
    seg = _side_by_side(rods, M)
    starts, tangents = _segment_starts((y0, Y0), (restarts, restart_tangents), M)  # (n M, dim), (n M, C, dim)
    leg = np.asarray([i * M + k for i in range(n) for k in range(M) for _ in directions[k]])
    direction = np.asarray([c for _ in range(n) for k in range(M) for c in directions[k]])
    first = np.searchsorted(leg, np.arange(n * M))  # each segment's first complex leg: its states
    out = integrate(
        starts[leg] + 1j * _STEP * tangents[leg, direction], _legs(seg, leg), return_stages=everywhere, all_nodes=everywhere
    )

    def spread(z):  # complex legs' (L, ...) -> states (n, M, L, ...) and tangents (n, M, C, L, ...)
        return _per_segment(z[first].real, M), _per_segment(_all_directions(z.imag / _STEP, leg, direction, tangents, carried), M)

    y_end, Y_end = spread(out[0][:, -1])
    if not everywhere:
        return y_end[:, -1], Y_end[:, -1], y_end[:, :-1], Y_end[:, :-1]
    (nodes, T), (stages, Ts) = spread(out[0]), _join_segments(*spread(out[2]))
    # each segment's end is the next one's arrival: its entering nodes, then the last end
    nodes, T = _join_segments(nodes[:, :, :-1], T[:, :, :, :-1])
    nodes, T = jnp.concatenate([nodes, y_end[:, -1:]], axis=1), jnp.concatenate([T, Y_end[:, -1, :, None]], axis=2)
    return y_end[:, -1], Y_end[:, -1], y_end[:, :-1], Y_end[:, :-1], (nodes, stages), (T, Ts)


def _all_directions(values, leg, direction, tangents, carried):
    """Tangents (n M, C, ...) of the n M segment legs side by side along all C directions, from
    ``values`` integrated along some of them: ``values[i]`` is leg ``leg[i]``'s tangent along
    ``direction[i]`` (index arrays that broadcast together; direction C is padding, dropped).
    Directions neither integrated nor ``carried`` are zero; along segment k's ``carried[k]``
    (translations) every node and stage has the start tangent (``tangents`` (n M, C, dim)).
    One gather from static indices: XLA:CPU runs a scatter into zeros far slower."""
    nM, C = tangents.shape[:2]
    rest = values.shape[np.broadcast(leg, direction).ndim :]
    leg, direction = (np.ravel(a) for a in np.broadcast_arrays(leg, direction))
    source = np.full((nM, C), leg.size)  # the pieces' row leg.size is zero
    keep = direction < C
    source[leg[keep], direction[keep]] = np.flatnonzero(keep)
    pieces = [values.reshape((leg.size,) + rest), jnp.zeros((1,) + rest, values.dtype)]
    M = len(carried)
    held = [(i, c) for i in range(nM) for c in carried[i % M]]
    if held:
        hl, hd = (np.asarray(a, dtype=int) for a in zip(*held))
        t = tangents[hl, hd]  # (K, dim), the same at every node and stage
        pieces.append(jnp.broadcast_to(t.reshape((t.shape[0],) + (1,) * (len(rest) - 1) + t.shape[1:]), (t.shape[0],) + rest))
        source[hl, hd] = leg.size + 1 + np.arange(len(held))
    return jnp.concatenate(pieces)[source]


def _join_segments(states, tangents):
    """States (n, M, L, ...) and tangents (n, M, C, L, ...) of M consecutive segments of L node
    steps as those of the whole grid: (n, M L, ...) and (n, C, M L, ...) (node j of segment k is
    node k L + j)."""
    n, M, L = states.shape[:3]
    C = tangents.shape[2]
    return states.reshape((n, M * L) + states.shape[3:]), jnp.swapaxes(tangents, 1, 2).reshape((n, C, M * L) + tangents.shape[4:])


def _rhs_and_tangents(effects):
    """The right-hand side at ``y`` and its derivatives along the rows of ``Y`` (one batched `jax.jvp`)."""

    def one(y, Y, h, kk):
        g = lambda z: rhs(z, h, kk, effects)  # noqa: E731
        return jax.vmap(lambda t: jax.jvp(g, (y,), (t,)), out_axes=(None, 0))(Y)

    return one


def _jvp_side_by_side(y0, Y0, rods: Rods, M: int, restarts, restart_tangents, directions, everywhere, carried):
    """`integrate_tangents` by a batched `jax.jvp` for M equal segments side by side: segment k
    of each leg integrates its ``directions[k]`` alone, as many per segment as the largest
    (the others padded with a zero tangent), and holds the start tangents of ``carried[k]``.
    With the colouring of `shooting.Layout`, a segment's own seeds are about half of all."""
    n, C = Y0.shape[:2]
    seg = _side_by_side(rods, M)
    F = _per_leg(_rhs_and_tangents(rods.effects), n * M)
    starts, tangents = _segment_starts((y0, Y0), (restarts, restart_tangents), M)  # (n M, dim), (n M, C, dim)
    D = max(map(len, directions))
    own = np.asarray([list(directions[k]) + [C] * (D - len(directions[k])) for _ in range(n) for k in range(M)])  # (n M, D)
    rows = np.arange(n * M)[:, None]
    padded = jnp.concatenate([tangents, jnp.zeros_like(tangents[:, :1])], axis=1)

    def widen(Y, leg_axis, dir_axis):  # tangents along each segment's own D directions -> along all C
        W = _all_directions(jnp.moveaxis(Y, (leg_axis, dir_axis), (0, 1)), rows, own, tangents, carried)
        return jnp.moveaxis(W, (0, 1), (leg_axis, dir_axis))

    (y_end, Y_end), outs = _scan(
        lambda st, h: F(st[0], st[1], h, seg.k),
        (starts, padded[rows, own]),
        seg,
        None,
        None,
        everywhere,
        everywhere,
        _on_rotations_with_tangents,
    )
    y_end, Y_end = _per_segment(y_end, M), _per_segment(widen(Y_end, 0, 1), M)
    ends = (y_end[:, -1], Y_end[:, -1], y_end[:, :-1], Y_end[:, :-1])
    if not everywhere:
        return ends
    (y_in, Y_in), rest = outs[0], outs[2:]
    if rest:  # RK4's stages (L, n M, 3, D, dim)
        rest = ((rest[0][0], widen(rest[0][1], 1, 3)),)
    outs = ((y_in, widen(Y_in, 1, 2)), outs[1]) + rest
    return ends + _everywhere(outs, ends[0], ends[1], M)


def _tangents_by_jvp(y0, Y0, rods: Rods, segment_starts, restarts, restart_tangents, everywhere=False):
    """`integrate_tangents` by a batched `jax.jvp` of the right-hand side at every stage, in one
    scan (one segment, or unequal ones)."""
    F = _per_leg(_rhs_and_tangents(rods.effects), y0.shape[0])
    state = (y0, Y0)
    collect = bool(segment_starts) or everywhere
    (y_last, Y_last), outs = _scan(
        lambda st, h: F(st[0], st[1], h, rods.k),
        state,
        rods,
        segment_starts,
        (restarts, restart_tangents),
        everywhere,
        collect,
        _on_rotations_with_tangents,
    )
    if segment_starts:
        idx = np.asarray(segment_starts)
        ends = (y_last, Y_last, jnp.swapaxes(outs[1][0][idx], 0, 1), jnp.swapaxes(outs[1][1][idx], 0, 1))
    else:
        ends = (y_last, Y_last, None, None)
    return ends + _everywhere(outs, y_last, Y_last, 1) if everywhere else ends


def _everywhere(outs, y_last, Y_last, M: int):
    """``((nodes, stages), (node tangents, stage tangents))`` of n legs from `_scan`'s outputs
    for a (state, tangents) pair, run as n M legs of N / M steps (M equal segments side by side;
    M = 1: one scan along the whole grid, restarts included)."""
    (y_in, Y_in), stages = outs[0], (outs[2] if len(outs) > 2 else None)
    nodes, T = _join_segments(_per_segment(jnp.swapaxes(y_in, 0, 1), M), _per_segment(jnp.moveaxis(Y_in, 0, 2), M))
    nodes, T = jnp.concatenate([nodes, y_last[:, None]], axis=1), jnp.concatenate([T, Y_last[:, :, None]], axis=2)
    if stages is None:  # Euler
        return (nodes, _no_stages(nodes)), (T, _no_stages(T))
    y_s, Y_s = stages  # (L, n M, 3, dim), (L, n M, 3, C, dim)
    stages, Ts = _join_segments(_per_segment(jnp.swapaxes(y_s, 0, 1), M), _per_segment(jnp.transpose(Y_s, (1, 3, 0, 2, 4)), M))
    return (nodes, stages), (T, Ts)
