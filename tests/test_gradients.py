"""Implicit gradients through statics and rollouts against central finite differences.

Each gradient is taken with respect to all parameters in one call (one compilation): `jax.grad`
for the tau-damped rollout (forward columns by default, reverse mode asked for), `jax.jacfwd`
for the Bse/Bbt one.
"""

import functools

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


def _params(scene):
    rod = scene.legs.rod
    return {"length": rod.length[0], "E": rod.youngs_modulus[0], "tau": rod.damping.tau[0]}


@functools.cache
def _rollout_gradient(checkpoint, forward_columns, batched=False):
    """``jax.value_and_grad`` of the end's final z after 50 steps of the tau-damped rod with
    respect to its length, E and tau, jitted once a process (the tests below share it)."""
    scene = _dyn_scene({"tau": 2e-4})

    def end_z(p):
        return pcrjax.rollout(apply(scene, p), checkpoint=checkpoint, forward_columns=forward_columns).position[-1, 2]

    vg = jax.value_and_grad(end_z)
    return scene, jax.jit(jax.vmap(vg) if batched else vg)


# Three scalars: by default `rollout` takes their derivatives in forward mode whatever the AD mode
# (`numerics.few_inputs`); ``forward_columns=0`` asks for JAX's reverse mode, here through
# checkpointed chunks of 7 steps (the last one partial). Plain reverse mode is slow to save a compile.
@pytest.mark.parametrize(
    "checkpoint, forward_columns",
    [(None, None), (7, 0), pytest.param(None, 0, marks=pytest.mark.slow)],
    ids=["forward-for-few", "reverse-checkpointed", "reverse"],
)
def test_rollout_gradient_after_50_steps_length_E_tau(checkpoint, forward_columns):
    scene, vg = _rollout_gradient(checkpoint, forward_columns)
    assert scene.solver.steps == 50
    params = _params(scene)
    g = vg(params)[1]  # one program for both: the differences evaluate its value half
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
    """`jax.vmap(jax.grad(...))` over three rods (lengths, E and tau apart; forward columns,
    batched Newton) equals each member's gradient by JAX's reverse mode (``forward_columns=0``,
    checkpointed: the program the test above checks against central differences), to 1e-12."""
    scene, batched = _rollout_gradient(None, None, batched=True)
    _, reverse = _rollout_gradient(7, 0)
    one = _params(scene)
    scale = {"length": [1.0, 1.05, 0.95], "E": [1.0, 0.9, 1.1], "tau": [1.0, 2.0, 0.5]}
    members = {k: one[k] * np.array(scale[k]) for k in one}
    values, grads = batched(members)
    for i in range(3):
        value, grad = reverse({k: members[k][i] for k in one})
        np.testing.assert_allclose(values[i], value, rtol=1e-12)
        for k in one:
            np.testing.assert_allclose(grads[k][i], grad[k], rtol=1e-12, err_msg=k)
