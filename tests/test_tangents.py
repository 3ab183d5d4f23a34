"""The legs' forward sensitivities (`spatial.integrate_tangents`) against JAX's forward-mode AD
of the plain integration (`jax.jacfwd` of the legs' junctions and tips): equal to round-off by
the complex step (one segment and several legs; equal segments side by side, each carrying only
its own directions; unequal segments in one scan; quadratic drag, whose |q| must stay analytic)
and by the batched `jax.jvp` that takes over beyond `COMPLEX_STEP_LEGS` directions."""

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
        "two equal": (2, 2, 24),
        "two unequal": (2, 0, 24),
        "four": (4, 4, 60),
        "three": (3, 0, 36),
        "drag": (2, 2, 24),
    }
    key = next(k for k in legs if name.startswith(k))
    C = len(np.unique(lay.colouring(extra_rows=18)[0]))  # seeds per leg; equal segments carry only their own
    complex_legs = xl.shape[0] * (6 + 18 * (lay.segments - 1) if equal else C)
    assert (lay.segments, equal, complex_legs) == legs[key]  # complex step up to 24, jvp beyond
    scale = np.abs(np.asarray(ref)).max(axis=2, keepdims=True) + 1e-300  # per row
    err = np.abs(np.asarray(J) - np.asarray(ref)) / scale
    assert err.max() < 1e-11, (name, err.max())
    np.testing.assert_allclose(
        np.asarray(tips), np.asarray(rows(xl))[:, -18:], rtol=0, atol=1e-13 * np.abs(np.asarray(tips)).max()
    )
