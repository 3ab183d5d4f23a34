"""The lumped model (thesis 3.1) against closed forms: Euler-Bernoulli's first frequency and tip
deflection, the elastica at large load, and energy conservation of its diffrax integration.

The Cosserat model's first frequency matches the same Euler-Bernoulli value (test_dynamics), so
convergence of the lumped frequency to it is convergence to the Cosserat model's."""

import jax
import numpy as np
import pytest
from helpers import rod_scene
from oracles import elastica_tip, euler_bernoulli_tip, first_frequency_hz

from pcrjax import SceneError, load_scene
from pcrjax.lumped import _jacobian_at_rest, lumped_rollout, lumped_static, natural_frequencies, step_budget

L, E, R, RHO = 0.4, 207e9, 1e-3, 8000.0


def test_first_frequency_within_one_percent_at_8_segments_and_second_order():
    f1 = first_frequency_hz(L, E, R, RHO)
    freq = jax.jit(natural_frequencies, static_argnums=1)
    err = np.array([abs(float(freq(rod_scene(), n)[0]) / f1 - 1) for n in (4, 8, 16)])
    assert err[1] < 0.01, err
    order = np.log2(err[:-1] / err[1:])
    assert np.all((order > 1.9) & (order < 2.1)), order


def test_small_load_deflection_matches_euler_bernoulli():
    F = 2e-3  # 2 mN: deflection 0.1 % of L, linear
    static = jax.jit(lumped_static, static_argnums=1)
    w = np.array([-float(static(rod_scene(force=(0.0, 0.0, -F)), n)[0][-1, 2]) for n in (8, 16)])
    err = np.abs(w / euler_bernoulli_tip(F, L, E, R) - 1)
    assert err[1] < 2e-3, err
    assert 3.5 < err[0] / err[1] < 4.5, err  # second order in the segment length


def test_large_deflection_matches_the_elastica():
    load = 3.0  # P L^2 / EI
    P = load * E * np.pi * R**4 / 4 / L**2
    p, _, ok = jax.jit(lumped_static, static_argnums=1)(rod_scene(force=(0.0, 0.0, -P)), 32)
    assert ok
    defl, short, _ = elastica_tip(load)
    # The elastica is inextensible: the axial strain P/EA ~ 1e-6 is below the 1e-3 tolerance.
    assert abs(-float(p[-1, 2]) / L - defl) < 1e-3 * defl
    assert abs((L - float(p[-1, 0])) / L - short) < 2e-3 * short


def test_diffrax_rollout_conserves_energy_and_damping_dissipates():
    """One program for both runs: the damped rod's, with tau 0 for the conservative one."""

    def rod(tau):
        return rod_scene(force=(0.0, 0.0, -0.2), dt=2e-3, duration=0.03, effects={"damping": True}, rod_extra={"tau": tau})

    scene = rod(0.0)
    roll = jax.jit(lumped_rollout, static_argnums=1, static_argnames=("method", "rtol", "max_steps"))
    budget = step_budget(scene, 4, rtol=1e-9)
    tr = roll(scene, 4, method="tsit5", rtol=1e-9, max_steps=budget)
    assert bool(tr.converged)
    e = np.asarray(tr.energy)
    assert np.max(np.abs(e - e[0])) < 1e-6 * e[0], e
    assert np.max(np.abs(np.asarray(tr.position)[:, 2] - float(tr.position[0, 2]))) > 0.5 * abs(float(tr.position[0, 2]))
    ed = np.asarray(roll(rod(2e-4), 4, method="tsit5", rtol=1e-9, max_steps=budget).energy)
    assert np.all(np.diff(ed) <= 1e-12 * ed[0]) and ed[-1] < 0.99 * ed[0], ed


@pytest.mark.parametrize(
    "make, kw, match",
    [
        (lambda: load_scene("stewart_gough"), {}, "single-rod"),
        (lambda: rod_scene(), {"segments": 0}, "at least 1"),
        (lambda: rod_scene(), {"method": "rk45"}, "unknown lumped method"),
    ],
)
def test_bad_input(make, kw, match):
    kw = {"segments": 4, **kw}
    with pytest.raises(SceneError, match=match):
        lumped_rollout(make(), **kw)


def test_ode_linearisation_oscillates_at_the_modal_frequencies():
    """The ODE's Jacobian at the unloaded rest state (what `step_budget` reads) has eigenvalues
    +-i 2 pi f for each of the 6N natural frequencies, which come from the energy's Hessian: the
    vector field and the energy agree. Its spectral radius sets the explicit step."""
    scene = rod_scene(force=(0.0, 0.0, 0.0))
    jac = np.asarray(jax.jit(_jacobian_at_rest, static_argnums=1)(scene, 8))
    ev = np.linalg.eigvals(jac)
    f = np.sort(np.asarray(natural_frequencies(scene, 8))) * 2 * np.pi
    up = np.sort(ev.imag[ev.imag > 1e-3 * f[0]])
    assert up.size == f.size == 48
    np.testing.assert_allclose(up, f, rtol=1e-8)
    assert np.max(np.abs(ev.real)) < 1e-8 * f[-1]


def test_traced_scene_needs_a_step_budget():
    with pytest.raises(SceneError, match="pass max_steps"):
        jax.jit(lumped_rollout, static_argnums=1)(rod_scene(duration=0.01), 4)
