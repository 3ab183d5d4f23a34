"""The legs' forward sensitivities (`spatial.integrate_tangents`) against JAX's forward-mode AD
of the plain integration (`jax.jacfwd` of the legs' junctions and tips): equal to round-off by
the complex step (one segment and several legs; equal segments side by side, each carrying only
its own directions; unequal segments in one scan; quadratic drag, whose |q| must stay analytic)
and by the batched `jax.jvp` that takes over beyond `COMPLEX_STEP_LEGS` directions (equal
segments again each integrating their own seeds alone). A segment start's position seeds are
carried, not integrated, on both paths."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import rod_scene

import pcrjax
from pcrjax import simulation
from pcrjax.io.scene_file import load_scene
from pcrjax.numerics import spatial
from pcrjax.robots import dynamics


def _problem(scene):
    _, state = simulation._initial(scene)  # at rest the histories are not zero
    prob = dynamics._problem(scene, state, dynamics._coefficients(scene, state), state.a1, scene.solver.dt)
    return prob, state.unknowns[0]


def _scenes():
    drag = rod_scene(
        nodes=12, dt=2e-3, effects={"drag": True, "damping": True}, rod_extra={"drag_coefficients": [2.0, 2.0, 0.5], "tau": 1e-3}
    )
    return {
        "one segment, three legs": pcrjax.with_solver(load_scene("triskele"), nodes=10, dt=5e-4),
        "two equal segments": pcrjax.with_solver(rod_scene(nodes=20, dt=2e-3), segments=2),
        "four equal segments": pcrjax.with_solver(rod_scene(nodes=12, dt=1e-3), segments=4),
        "two unequal segments": pcrjax.with_solver(rod_scene(nodes=23, dt=1e-3), segments=2),
        "three unequal segments": pcrjax.with_solver(rod_scene(nodes=23, dt=1e-3), segments=3),
        "drag and damping": pcrjax.with_solver(drag, segments=2),
    }


@pytest.mark.parametrize("name", list(_scenes()))
def test_legs_tangents_equal_forward_mode_ad(name):
    scene = _scenes()[name]
    prob, x = _problem(scene)
    lay = prob.layout
    xl = prob.split(x)[1]
    xl = xl + 1e-3 * jnp.cos(jnp.arange(xl.size)).reshape(xl.shape)  # off the solution

    def rows(z):  # each leg's [junctions, tip state] (n, S-6+18)
        junc, tips, _ = prob.legs(z, all_nodes=False)
        return jnp.concatenate([junc, tips], axis=1)

    tips, J = jax.jit(prob.leg_jacobians)(xl)
    ref = jax.jit(jax.jacfwd(rows))(xl)  # (n, rows, n, S): legs are independent
    ref = jnp.stack([ref[i, :, i] for i in range(xl.shape[0])])
    equal = spatial._equal_segments(prob.rods, lay.starts)
    legs = {
        "one": (1, 0, 18),
        "two equal": (2, 2, 21),
        "two unequal": (2, 0, 24),
        "four": (4, 4, 51),
        "three": (3, 0, 36),
        "drag": (2, 2, 21),
    }
    key = next(k for k in legs if name.startswith(k))
    C = len(np.unique(lay.colouring(extra_rows=18)[0]))  # seeds per leg
    # equal segments integrate only their own seeds, less a restart's 3 translations
    complex_legs = xl.shape[0] * (6 + 15 * (lay.segments - 1) if equal else C)
    assert (lay.segments, equal, complex_legs) == legs[key]  # complex step up to 24, jvp beyond
    scale = np.abs(np.asarray(ref)).max(axis=2, keepdims=True) + 1e-300  # per row
    err = np.abs(np.asarray(J) - np.asarray(ref)) / scale
    assert err.max() < 1e-11, (name, err.max())
    np.testing.assert_allclose(
        np.asarray(tips), np.asarray(rows(xl))[:, -18:], rtol=0, atol=1e-13 * np.abs(np.asarray(tips)).max()
    )


def _euler_scene():
    return pcrjax.with_solver(rod_scene(nodes=12, dt=1e-3, integrator="euler"), segments=2)


@pytest.mark.parametrize("name", [*_scenes(), "euler, two equal segments"])
def test_every_nodes_tangent_from_the_jacobians_integration_equals_forward_mode_ad(name):
    """`Problem.jacobian_and_legs` keeps every node's and stage's tangent of the legs' Jacobian
    integration; `assembly.legs_tangent` turns them into the derivative of the legs (junctions,
    tips, nodes, stages) along a change of all the unknowns, which a time step's gradient uses
    instead of a second pass along the legs. Against `jax.jvp` of the legs themselves, on every
    layout above (coloured seeds shared between segments included) and on an Euler grid."""
    from pcrjax.robots import assembly

    scene = _euler_scene() if name.startswith("euler") else _scenes()[name]
    prob, x = _problem(scene)
    x = x + 1e-3 * jnp.cos(jnp.arange(x.size))  # off the solution
    dx = jnp.asarray(np.random.default_rng(2).standard_normal(x.size))
    J, legs_jacobian = jax.jit(prob.jacobian_and_legs)(x)
    got = assembly.legs_tangent(prob.layout, prob.P, legs_jacobian, dx)
    _, ref = jax.jit(lambda z, t: jax.jvp(lambda w: prob.legs(prob.split(w)[1], return_stages=True), (z,), (t,)))(x, dx)
    for part, g, r in zip(("junctions", "tips", "nodes", "stages"), got, ref, strict=True):
        r = np.asarray(r)
        assert np.shape(g) == r.shape, (name, part)
        if r.size == 0:  # no junctions: one segment
            continue
        scale = np.abs(r).max(axis=tuple(range(r.ndim - 1)), keepdims=True) + 1e-300  # per state component
        assert np.abs(np.asarray(g) - r).max() / scale.max() < 1e-11, (name, part)
        assert (np.abs(np.asarray(g) - r) / scale).max() < 1e-9, (name, part)
    J0 = np.asarray(jax.jit(prob.jacobian)(x))
    np.testing.assert_allclose(np.asarray(J), J0, rtol=0, atol=1e-13 * np.abs(J0).max())
