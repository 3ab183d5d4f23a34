"""`numerics.few_inputs.forward_for_few` against closed-form derivatives: every AD mode, either
side of the column limit, integer outputs, batching and second order."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pcrjax.numerics.few_inputs import forward_for_few


def f(a, b, n):
    """Outputs: a vector, a matrix and an integer count (no tangent)."""
    return {"v": jnp.sin(a) * b[0] + b[1] ** 3, "m": jnp.outer(a, b) * n, "k": n + jnp.argmax(a)}


def closed_form(a, b, n, da, db):
    """Tangents of `f` by hand."""
    return {
        "v": jnp.cos(a) * da * b[0] + jnp.sin(a) * db[0] + 3 * b[1] ** 2 * db[1],
        "m": (jnp.outer(da, b) + jnp.outer(a, db)) * n,
    }


A, B, N = jnp.array([0.3, -1.2, 2.0]), jnp.array([1.5, -0.7]), jnp.asarray(3)
DA, DB = jnp.array([0.1, 0.4, -0.2]), jnp.array([-0.3, 0.9])


@pytest.mark.parametrize("limit", [0, 2, 5, 100], ids=["none", "fewer-than-inputs", "exactly", "many"])
def test_tangents_and_cotangents_are_the_closed_form(limit):
    g = forward_for_few(f, limit)
    out, dout = jax.jvp(lambda a, b: g(a, b, N), (A, B), (DA, DB))
    ref = closed_form(A, B, N, DA, DB)
    np.testing.assert_allclose(out["v"], f(A, B, N)["v"], rtol=1e-15)
    assert int(out["k"]) == int(f(A, B, N)["k"])
    for k in ("v", "m"):
        np.testing.assert_allclose(dout[k], ref[k], rtol=1e-13, atol=1e-15)
    # reverse mode: <ct, J d> = <J^T ct, d> for the closed-form J
    ct = {"v": jnp.array([0.7, -0.1, 0.25]), "m": jnp.arange(6.0).reshape(3, 2) / 7}
    _, vjp = jax.vjp(lambda a, b: {k: g(a, b, N)[k] for k in ("v", "m")}, A, B)
    ca, cb = vjp(ct)
    lhs = sum(jnp.vdot(ct[k], ref[k]) for k in ct)
    np.testing.assert_allclose(jnp.vdot(ca, DA) + jnp.vdot(cb, DB), lhs, rtol=1e-13)
    # gradient with respect to one input only (the other held): 3 columns
    gr = jax.jit(jax.grad(lambda a: jnp.sum(g(a, B, N)["v"])))(A)
    np.testing.assert_allclose(gr, jnp.cos(A) * B[0], rtol=1e-14)


def test_batched_tangents_and_second_order():
    g = forward_for_few(f, 5)
    dirs = jnp.stack([DA, 2 * DA, -DA])
    d = jax.vmap(lambda t: jax.jvp(lambda a: g(a, B, N)["v"], (A,), (t,))[1])(dirs)
    np.testing.assert_allclose(d, jnp.cos(A) * B[0] * dirs, rtol=1e-14)
    h = jax.hessian(lambda a: jnp.sum(g(a, B, N)["v"]))(A)
    np.testing.assert_allclose(h, jnp.diag(-jnp.sin(A) * B[0]), rtol=1e-14, atol=1e-16)
    # batched primals: one program per member's columns
    ab = jnp.stack([A, A + 1.0])
    gb = jax.vmap(jax.grad(lambda a: jnp.sum(g(a, B, N)["v"])))(ab)
    np.testing.assert_allclose(gb, jnp.cos(ab) * B[0], rtol=1e-14)


def test_only_reverse_mode_takes_the_forward_columns():
    """`jax.grad` evaluates the five columns (arrays with a leading axis of 5 in its program); a
    plain `jax.jvp` asks for one direction and gets ``f``'s own tangent (no such arrays)."""
    g = forward_for_few(f, 5)
    rev = str(jax.make_jaxpr(jax.grad(lambda a, b: jnp.sum(g(a, b, N)["v"]), argnums=(0, 1)))(A, B))
    fwd = str(jax.make_jaxpr(lambda a, b: jax.jvp(lambda x, y: g(x, y, N)["v"], (a, b), (DA, DB)))(A, B))
    assert "f64[5,3]" in rev
    assert "f64[5," not in fwd
