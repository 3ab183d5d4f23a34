r"""Derivatives with respect to few inputs by forward mode, whichever mode JAX is asked for.

Reverse mode through a rollout transposes every step's Newton solve and node scans: on Till's
cantilever (RK4 N 20, 200 steps) `jax.grad` costs about 6 forward runs. Forward mode pays one
exact Jacobian per step for all its directions, then each direction a node scan: 2.5 runs for
the first direction and about 0.1 for each further one there (more where Newton needs fewer
iterations a step: the rollout's `FORWARD_COLUMNS`). So for a gradient with respect to a few
numbers (a damping time, the rods' lengths) forward mode is the cheaper one, and what reverse
mode keeps is the Jacobian's columns of the outputs it uses (under `jit` the others are never
computed), not every step's intermediates.

`forward_for_few(fn, max_columns)` is ``fn`` with a `jax.custom_jvp` rule that, when it is
linearised for reverse mode (`jax.grad`, `jax.vjp`, `jax.linearize`) and at most
``max_columns`` input scalars carry tangents, computes the Jacobian of ``fn``'s outputs with
respect to those scalars by forward mode (one `jax.jvp` batched over unit directions) and
returns its product with the tangents. That product is linear in the tangents, so reverse mode
transposes it into a product with the same Jacobian and gets the forward columns' cost.
Otherwise (more perturbed scalars, or a plain `jax.jvp` that asks for its own directions) the
rule is ``fn``'s own `jax.jvp`. Values and derivatives are those of ``fn`` either way (to
rounding).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.interpreters import partial_eval as pe


def _inexact(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def linearizing(tangents) -> bool:
    """Whether the rule is being linearised for a transpose (`jax.grad`, `jax.vjp`,
    `jax.linearize`): its tangents are then partial-evaluation tracers of unknown values. A
    plain `jax.jvp` (`jax.jacfwd`, a batch of directions) passes values or other tracers, and
    gets ``fn``'s own tangents: as many directions as it asks for, not one per input scalar."""
    return any(isinstance(t, pe.JaxprTracer) for t in tangents)


def _put(seq, where, values) -> list:
    """A copy of ``seq`` with ``values`` at the indices ``where``."""
    out = list(seq)
    for i, v in zip(where, values, strict=True):
        out[i] = v
    return out


def forward_for_few(fn, max_columns: int):
    """``fn(*args)`` (pytrees in, a pytree out) whose derivatives with respect to at most
    ``max_columns`` perturbed input scalars are computed by forward mode in every AD mode.
    The arguments' array leaves are the differentiable inputs; other leaves are held fixed."""

    def call(*args):
        leaves, treedef = jax.tree.flatten(args)
        where = [i for i, x in enumerate(leaves) if isinstance(x, jax.Array | np.ndarray)]

        def of_arrays(*arrays):
            return fn(*jax.tree.unflatten(treedef, _put(leaves, where, arrays)))

        return _with_forward_rule(of_arrays, max_columns)(*(leaves[i] for i in where))

    return call


def _with_forward_rule(fn, max_columns: int):
    """``fn(*arrays)`` with the rule of `forward_for_few`."""

    @jax.custom_jvp
    def wrapped(*args):
        return fn(*args)

    def rule(primals, tangents):
        live = [i for i, t in enumerate(tangents) if not isinstance(t, SymbolicZero) and _inexact(primals[i])]

        def with_live(*values):  # fn of the perturbed inputs, the others held
            return fn(*_put(primals, live, values))

        live_primals = tuple(primals[i] for i in live)
        live_tangents = tuple(tangents[i] for i in live)
        columns = sum(int(np.size(p)) for p in live_primals)
        if columns == 0 or columns > max_columns or not linearizing(live_tangents):
            return jax.jvp(with_live, live_primals, live_tangents)

        shapes = [jnp.shape(p) for p in live_primals]
        ends = np.cumsum([0] + [int(np.prod(s)) for s in shapes])
        meta = {}  # the outputs' structure and which leaves are inexact, recorded while tracing

        def of_live(*values):
            leaves, meta["treedef"] = jax.tree.flatten(with_live(*values))
            meta["smooth"] = [_inexact(x) for x in leaves]
            return [x for x in leaves if _inexact(x)], [x for x in leaves if not _inexact(x)]

        def column(e):
            dirs = tuple(
                e[a:b].reshape(s).astype(jnp.result_type(p))
                for a, b, s, p in zip(ends[:-1], ends[1:], shapes, live_primals, strict=True)
            )
            return jax.jvp(of_live, live_primals, dirs, has_aux=True)

        smooth, cols, rest = jax.vmap(column, out_axes=(None, 0, None))(jnp.eye(columns))
        dtheta = jnp.concatenate([jnp.ravel(t) for t in live_tangents])
        it_s, it_c, it_r = iter(smooth), iter(cols), iter(rest)
        leaves, dleaves = [], []
        for is_smooth in meta["smooth"]:
            if is_smooth:
                c = next(it_c)
                leaves.append(next(it_s))
                dleaves.append(jnp.tensordot(dtheta.astype(c.dtype), c, axes=1))
            else:  # integer outputs (counts, codes) have no tangents
                leaves.append(next(it_r))
                dleaves.append(np.zeros(jnp.shape(leaves[-1]), dtype=jax.dtypes.float0))
        return jax.tree.unflatten(meta["treedef"], leaves), jax.tree.unflatten(meta["treedef"], dleaves)

    wrapped.defjvp(rule, symbolic_zeros=True)
    return wrapped
