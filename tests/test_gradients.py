"""Implicit gradients through statics and rollouts against central finite differences.

Each gradient is taken with respect to all parameters in one call (one compilation): `jax.grad`
for the tau-damped rollout (forward columns by default, reverse mode asked for), `jax.jacfwd`
for the Bse/Bbt one.
"""

import equinox as eqx
import jax
import numpy as np
import pytest
from helpers import rod_scene

import pcrjax
from pcrjax.physics.rod import DiagonalDamping

REL = 1e-6


def _central(f, params, key, index=None, rel=1e-4):
    x = params[key] if index is None else params[key][index]
    h = rel * abs(float(x))

    def shifted(d):
        p = dict(params)
        p[key] = x + d if index is None else params[key].at[index].add(d)
        return float(f(p))

    return (shifted(h) - shifted(-h)) / (2 * h)


def _check(grad, fd, label):
    grad, fd = float(grad), float(fd)
    assert fd != 0.0, f"{label}: zero sensitivity cannot test a gradient"
    assert abs(grad - fd) <= REL * abs(fd), (label, grad, fd, abs(grad / fd - 1))


def _setter(paths):
    def apply(scene, params):
        # The rod scene's one leg: scalar parameters fill the leading leg axis.
        return eqx.tree_at(lambda s: [paths[k](s) for k in params], scene, [params[k][None] for k in params])

    return apply


PATHS = {
    "length": lambda s: s.legs.rod.length,
    "E": lambda s: s.legs.rod.youngs_modulus,
    "tau": lambda s: s.legs.rod.damping.tau,
    "bbt": lambda s: s.legs.rod.damping.bbt,
    "bse": lambda s: s.legs.rod.damping.bse,
}
apply = _setter(PATHS)


def test_static_tip_gradient_length_and_E():
    scene = rod_scene(force=(0, 0, -1.0), nodes=16, tol=1e-13, effects={"inertia": False})
    params = {"length": scene.legs.rod.length[0], "E": scene.legs.rod.youngs_modulus[0]}
    f = jax.jit(lambda p: pcrjax.solve_static(apply(scene, p)).position[2])
    g = jax.grad(f)(params)
    for k in params:
        _check(g[k], _central(f, params, k), k)
    # Forward mode agrees with reverse mode.
    J = jax.jacfwd(f)(params)
    for k in params:
        np.testing.assert_allclose(J[k], g[k], rtol=1e-10)


def _dyn_scene(damping):
    return rod_scene(
        force=(0, 0, -0.5),
        nodes=8,
        dt=2e-3,
        alpha=-0.2,
        duration=0.1,
        tol=1e-13,
        effects={"damping": True},
        rod_extra=damping,
    )


# Three scalars: by default `rollout` takes their derivatives in forward mode whatever the AD mode
# (`numerics.few_inputs`); ``forward_columns=0`` asks for JAX's reverse mode, here through
# checkpointed chunks of 7 steps (the last one partial). Plain reverse mode is slow to save a compile.
@pytest.mark.parametrize(
    "checkpoint, forward_columns",
    [(None, None), (7, 0), pytest.param(None, 0, marks=pytest.mark.slow)],
    ids=["forward-for-few", "reverse-checkpointed", "reverse"],
)
def test_rollout_gradient_after_50_steps_length_E_tau(checkpoint, forward_columns):
    scene = _dyn_scene({"tau": 2e-4})
    assert scene.solver.steps == 50
    params = {"length": scene.legs.rod.length[0], "E": scene.legs.rod.youngs_modulus[0], "tau": scene.legs.rod.damping.tau[0]}

    def end_z(p):
        return pcrjax.rollout(apply(scene, p), checkpoint=checkpoint, forward_columns=forward_columns).position[-1, 2]

    # One program for both: the differences evaluate the value half of value_and_grad.
    vg = jax.jit(jax.value_and_grad(end_z))
    g = vg(params)[1]
    for k in params:
        _check(g[k], _central(lambda p: vg(p)[0], params, k), k)


@pytest.mark.slow  # ~1 min cold; reverse-mode rollout gradients stay in the default run
def test_rollout_jacfwd_after_50_steps_bbt():
    scene = _dyn_scene({"bse": [1e-2, 1e-2, 5e-2], "bbt": [2e-5, 2e-5, 1e-5]})
    assert isinstance(scene.legs.rod.damping, DiagonalDamping)
    params = {"bbt": scene.legs.rod.damping.bbt[0]}
    f = jax.jit(lambda p: pcrjax.rollout(apply(scene, p)).position[-1, 2])
    J = jax.jit(jax.jacfwd(f))(params)
    # The motion is in the x-z plane: bending about local y (bbt[1]) is the damped one.
    _check(J["bbt"][1], _central(f, params, "bbt", 1), "bbt[1]")
    # Out-of-plane bending and torsion are never strained in planar motion: exactly zero.
    assert float(J["bbt"][0]) == 0.0 and float(J["bbt"][2]) == 0.0


def test_batched_rollout_gradients_are_each_members_reverse_mode_gradient():
    """`jax.vmap(jax.grad(...))` over three rod lengths (forward columns, batched Newton) equals
    each member's gradient by JAX's reverse mode (``forward_columns=0``), to 1e-12."""
    scene = pcrjax.with_solver(rod_scene(force=(0, 0, -0.5), nodes=6, dt=2e-3, duration=0.03), tol=1e-12)

    def end_z(length, columns=None):
        return pcrjax.rollout(apply(scene, {"length": length}), forward_columns=columns).position[-1, 2]

    lengths = scene.legs.rod.length[0] * np.array([1.0, 1.05, 0.95])
    batched = jax.jit(jax.vmap(jax.grad(end_z)))(lengths)
    reverse = jax.jit(jax.grad(lambda length: end_z(length, 0)))
    for L, g in zip(lengths, batched, strict=True):
        np.testing.assert_allclose(g, reverse(L), rtol=1e-12)
