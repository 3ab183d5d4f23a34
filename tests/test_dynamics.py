"""Dynamics against Euler-Bernoulli modal theory and BDF-alpha scheme theory."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import SHARED_DT, shared_rod
from oracles import first_frequency_hz, fit_sinusoids, window_amplitudes

import pcrjax
from pcrjax import simulation
from pcrjax.numerics.bdf_alpha import amplification

F1 = first_frequency_hz(0.4, 207e9, 1e-3, 8000.0)  # 8.895 Hz
W1 = 2 * math.pi * F1


def _tip_z(scene):
    tr = pcrjax.simulate(scene)
    return np.asarray(tr.t), np.asarray(tr.position)[:, 2]


def test_first_frequency_matches_euler_bernoulli():
    assert abs(F1 - 8.895) < 1e-3
    dt = 0.05 / W1  # trapezoidal period error (h^2/12) ~ 2e-4 relative
    t, z = _tip_z(shared_rod(force=(0, 0, -1e-3), dt=dt, alpha=-0.5, duration=1.2))
    (w1, _), (w2, _) = fit_sinusoids(t, z, [W1, 6.27 * W1])[0]
    f = w1 / (2 * math.pi)
    assert abs(f / 8.895 - 1) < 1e-3, f


@pytest.mark.parametrize("alpha,expected", [(-0.5, 1.000), (-0.4, 0.981), (-0.2, 0.935), (0.0, 0.886)])
def test_bdf_alpha_numerical_damping_at_h_half(alpha, expected):
    # h = omega dt = 0.5 for the first mode; amplitude ratio over one true period 2 pi / omega.
    dt = 0.5 / W1
    periods = 22 if alpha == -0.5 else 12
    t, z = _tip_z(shared_rod(force=(0, 0, -1e-3), dt=dt, alpha=alpha, duration=periods / F1))
    skip = t > 2.0 / F1  # higher modes of alpha > -0.5 are damped within two periods
    (w1, _), (w2, _) = fit_sinusoids(t[skip], z[skip], [0.97 * W1, 3.0 / dt])[0]
    centres, amps = window_amplitudes(t[skip], z[skip], w1, [w2])
    # Decay rate per true period from a straight-line fit of log amplitude over all windows.
    slope = np.polyfit(centres * F1, np.log(amps), 1)[0]
    ratio = math.exp(slope)
    z_theory = amplification(0.5, alpha)
    theory = abs(z_theory) ** (2 * math.pi / 0.5)
    assert abs(theory - expected) < 1e-3  # the scheme's own prediction (pure theory)
    assert abs(ratio / expected - 1) < 0.01, (ratio, expected)
    # The numerical frequency is the scheme's too: arg(z)/dt (trapezoid: 2 atan(h/2)/dt).
    assert abs(w1 / (np.angle(z_theory) / dt) - 1) < 2e-3, (w1, np.angle(z_theory) / dt)
    if alpha == -0.5:
        assert abs(ratio**20 - 1) < 1e-3, amps  # no decay over 20 periods


def _rest_drift(integrator):
    # Load held for the whole run: the static equilibrium should be a solution of every step.
    scene = shared_rod(force=(0, 0, -2.0), release_time=10.0, dt=5e-3, alpha=-0.2, duration=0.25, integrator=integrator)
    tr = pcrjax.simulate(scene)
    return np.abs(np.asarray(tr.position) - np.asarray(tr.position)[0]).max()


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_equilibrium_stays_put_when_load_is_held(integrator):
    # RK4 keeps the previous step's values at its stage points (rod_history.py), so a rod at
    # rest has z_t = 0 at every evaluation point and nothing moves; interpolating the whole
    # history there (thesis eq. 3.39) drifted by 1.4e-5 m at N = 10.
    assert _rest_drift(integrator) < 1e-12


def test_kelvin_voigt_damping_matches_modal_damping_ratio():
    # B = tau K: mode 1 damping ratio zeta = tau omega / 2 (Euler-Bernoulli with Kelvin-Voigt).
    tau = 2e-4
    dt = 0.05 / W1
    scene = shared_rod(force=(0, 0, -1e-3), dt=dt, alpha=-0.5, duration=0.8, tau=tau)
    t, z = _tip_z(scene)
    (w1, s1), _ = fit_sinusoids(t, z, [W1, 6.27 * W1], decaying=True)[0]
    zeta = -s1 / math.hypot(s1, w1)
    assert abs(zeta / (tau * W1 / 2) - 1) < 0.01, (zeta, tau * W1 / 2)


def test_quadratic_air_drag_matches_single_mode_theory():
    # Drag f = -R C q|q| on the first mode: m x'' + c x'|x'| + k x = 0 with
    # m = rho A int(phi^2), c = C_x int(|phi|^3) (tip-normalised mode phi). Averaging over a cycle:
    # dA/dt = -(4 omega / 3 pi)(c/m) A^2, i.e. 1/A grows linearly in time.
    from oracles import cantilever_mode1

    L, r, rho, Cx = 0.4, 1e-3, 8000.0, 2.0
    s = np.linspace(0, L, 20001)
    phi = cantilever_mode1(s, L)
    m_eff = rho * math.pi * r**2 * np.trapezoid(phi**2, s)
    c_eff = Cx * np.trapezoid(np.abs(phi) ** 3, s)
    k_theory = 4 * W1 / (3 * math.pi) * c_eff / m_eff
    dt = 0.05 / W1
    scene = shared_rod(force=(0, 0, -0.02), dt=dt, alpha=-0.5, duration=1.0, drag=(Cx, Cx, 0.0))
    t, z = _tip_z(scene)
    (w1, _), (w2, _) = fit_sinusoids(t, z, [W1, 6.27 * W1])[0]
    centres, amps = window_amplitudes(t, z, w1, [w2])
    slope = np.polyfit(centres, 1 / amps, 1)[0]
    assert amps[-1] < 0.8 * amps[0]  # the effect is strong enough to measure
    print(f"drag: 1/A slope {slope:.4g} vs single-mode theory {k_theory:.4g}")
    assert abs(slope / k_theory - 1) < 0.03, (slope, k_theory)


def test_released_rod_converges_at_second_order_in_the_time_step():
    """Scheme theory: BDF-alpha is second order, so halving dt quarters the error. A release at
    t = 0 makes the accelerations jump; started from the rest history's rates (zero, those before
    the jump) the scheme lagged the motion by dt/2, a first-order error (ratios 2.1-2.4 measured).
    The first step is backward Euler (`bdf_alpha.starting`): ratios 4.1-4.2. Every dt runs on
    one grid (the shared structure's), so the differences hold the time error alone."""
    tips = []
    for dt in (2e-3, 1e-3, 5e-4, 2.5e-4):
        scene = shared_rod(dt=dt, alpha=-0.45, duration=0.1, tau=1.9e-3)
        tips.append(np.asarray(pcrjax.simulate(scene).position)[-1])
    diffs = [np.linalg.norm(a - b) for a, b in zip(tips, tips[1:])]
    ratios = [a / b for a, b in zip(diffs, diffs[1:])]
    assert all(r > 3.5 for r in ratios), (diffs, ratios)


def test_runs_of_any_length_share_one_compiled_chunk_and_agree_step_by_step():
    """`simulate` compiles one chunk of steps per structure: a run of 6 steps (one partial chunk)
    and one of 130 (a full chunk, then a partial one) run the same program, and the short run is
    the long run's beginning, to the last bit (the held steps past a run's end change nothing)."""
    short = pcrjax.simulate(shared_rod(dt=5e-3, duration=0.03))
    compiled = len(simulation._COMPILED)
    long = pcrjax.simulate(shared_rod(dt=5e-3, duration=0.65))
    assert len(simulation._COMPILED) == compiled
    assert short.t.shape == (7,) and long.t.shape == (131,)
    for name in ("position", "rotation_vector", "energy", "iterations"):
        np.testing.assert_array_equal(
            np.asarray(getattr(short, name)), np.asarray(getattr(long, name))[: len(getattr(short, name))]
        )


def test_with_step_keeps_the_compiled_structure_and_checks_its_numbers():
    """`pcrjax.with_step`: another step, alpha and duration on the grid and segments the scene was
    built for (which `with_solver` would choose again), as float64 leaves; bad numbers refused."""
    fine = shared_rod(dt=SHARED_DT, duration=0.1)
    coarse = pcrjax.with_step(fine, 4e-3, alpha=-0.3, duration=0.2)
    kept = lambda s: (s.solver.nodes, s.solver.segments, s.solver.refine, s.solver.integrator)  # noqa: E731
    assert kept(coarse) == kept(fine) != kept(pcrjax.with_solver(coarse))
    assert coarse.solver.steps == 50 and float(coarse.solver.dt) == 4e-3 and float(coarse.solver.alpha) == -0.3
    assert coarse.solver.dt.dtype == jnp.float64 and not coarse.solver.dt.weak_type
    assert pcrjax.with_step(fine, 1e-3).solver.steps == 100  # the duration kept
    for dt in (0.0, -1e-3, float("nan")):
        with pytest.raises(pcrjax.SceneError, match="dt must be > 0"):
            pcrjax.with_step(fine, dt)
    with pytest.raises(pcrjax.SceneError, match="alpha must lie"):
        pcrjax.with_step(fine, 1e-3, alpha=0.1)
    # Newton's tolerance and cap are numbers too: scenes that differ there share their programs.
    tight = pcrjax.with_solver(fine, tol=1e-13, max_iter=8)
    assert jax.tree.structure(tight) == jax.tree.structure(fine) and float(tight.solver.newton.tol) == 1e-13
