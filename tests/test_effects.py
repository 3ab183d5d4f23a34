"""Only the effects a scene turns on are compiled; numbers never retrace."""

import jax
import jax.numpy as jnp
import pytest
from helpers import rod_scene

import pcrjax
from pcrjax import simulation
from pcrjax.robots import dynamics


def _step_hlo(scene):
    state = jax.eval_shape(simulation._start, scene)[1]  # the step's state, traced and lowered, never compiled
    fn = jax.jit(lambda sc, st: dynamics.step(sc, st, jnp.asarray(0.01)))
    return fn.lower(scene, state).as_text(debug_info=True)


EFFECTS = {"damping": {"tau": 1e-4}, "gravity": {}, "drag": {"drag_coefficients": [1e-3, 1e-3, 1e-3]}}


@pytest.fixture(scope="module")
def plain_hlo():
    return _step_hlo(rod_scene(nodes=5))


@pytest.mark.parametrize("effect", list(EFFECTS))
def test_effect_absent_unless_switched_on(effect, plain_hlo):
    assert effect not in plain_hlo
    on = _step_hlo(rod_scene(nodes=5, effects={effect: True}, rod_extra=EFFECTS[effect]))
    assert effect in on


def _damped(**kw):
    return rod_scene(nodes=5, duration=0.02, effects={"damping": True}, rod_extra={"tau": kw.pop("tau", 1e-4)}, **kw)


# The end's final position of a rollout, jitted once for the two tests below (one program).
_final = jax.jit(lambda scene: pcrjax.rollout(scene).position[-1])


def test_changing_numbers_does_not_retrace():
    _final(_damped())
    traced = _final._cache_size()
    _final(_damped(L=0.35, E=190e9, dt=5e-3, alpha=-0.3, tau=3e-4))
    assert _final._cache_size() == traced


def test_vmap_over_scenes_matches_loop():
    scenes = [_damped(E=E, force=(0, 0, -0.5)) for E in (180e9, 207e9, 230e9)]
    batched = jax.tree.map(lambda *a: jnp.stack(a), *scenes)
    out = jax.jit(jax.vmap(pcrjax.rollout))(batched).position[:, -1]
    for i, s in enumerate(scenes):  # the loop: one compiled program for the three scenes
        assert jnp.allclose(out[i], _final(s), rtol=1e-10, atol=1e-14)
