"""Parallel robots (Stewart-Gough, Triskele-bot) against symmetry, rigid kinematics, statics,
energy conservation and finite differences."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import shared_triskele

import pcrjax
from pcrjax import load_scene, with_solver

NO_LOAD = (jnp.zeros(3), jnp.zeros(3))


def _rz(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def noise(position):
    """Thesis eq. 4.15-4.17: mean over x, y, z of log10 of the RMS deviation from the mean."""
    p = np.asarray(position)
    rmse = np.sqrt(np.mean((p - p.mean(axis=0)) ** 2, axis=0))
    with np.errstate(divide="ignore"):
        return float(np.mean(np.log10(rmse)))


def triskele(nodes=10, **solver):
    return with_solver(load_scene("triskele"), nodes=nodes, **solver)


# ----------------------------------------------------------------------------------------------
# Stewart-Gough


def test_stewart_gough_vertical_load_keeps_threefold_symmetry():
    sc = with_solver(load_scene("stewart_gough"), nodes=10)
    free = pcrjax.solve_static(sc)
    loaded = pcrjax.solve_static(eqx.tree_at(lambda s: s.load.force, sc, jnp.array([0.0, 0.0, -2.0])))
    tol = sc.solver.newton.tol  # scaled residual: positions in units of L = 0.17 m
    for res in (free, loaded):
        p, rv = np.asarray(res.position), np.asarray(res.rotation_vector)
        assert np.abs(p[:2]).max() < tol * 0.17 and np.abs(rv).max() < tol, (p, rv)  # moves only vertically
        W = np.asarray(res.base_wrenches)  # (6, 2, 3): leg i+2 is leg i turned by 120 degrees
        Rz = _rz(120.0)
        for i in range(4):
            assert np.abs(W[i + 2] - W[i] @ Rz.T).max() < 1e-9 * np.abs(W).max(), (i, W)
    assert float(loaded.position[2]) < float(free.position[2]) - 1e-6  # the load pushes it down (2.3 um)
    # Legs share the platform's weight plus the load (and carry their own weight to the base).
    rods_weight = 6 * 0.17 * 8000.0 * math.pi * 1e-6 * 9.81
    assert abs(-np.asarray(loaded.base_wrenches)[:, 0, 2].sum() - (0.0921 * 9.81 + 2.0 + rods_weight)) < 1e-8


@pytest.mark.parametrize("nodes", [5, pytest.param(10, marks=pytest.mark.slow)])
def test_stewart_gough_equilibrium_has_no_noise(nodes):
    # Thesis Tables 4.3-4.4: noise -3.5 .. -8.5; the issue asks <= -11 in every cell. The cheap
    # cells run here (alpha and dt are leaves and every run has 100 steps: one compiled program
    # per N); the full table with N = 50, 85, 170 is `pcrjax bench stewart_gough --noise`.
    base = with_solver(load_scene("stewart_gough"), nodes=nodes, duration=0.5)
    for dt in (5e-3, 1e-2):
        for alpha in (0.0, -0.2, -0.4, -0.5):
            tr = pcrjax.simulate(with_solver(base, dt=dt, alpha=alpha, duration=100 * dt))
            assert noise(tr.position) <= -11, (dt, alpha, noise(tr.position))


# ----------------------------------------------------------------------------------------------
# Triskele-bot


def test_triskele_small_motion_matches_rigid_strut_kinematics():
    # Rigid struts of fixed length from A_i = Q_i + a_i d_i to the attachment b_i (global frame):
    # d_i . dp + (b_i x d_i)_z dtheta = da_i, i.e. J [dx, dy, dtheta] = da. The rods also resist
    # bending at their clamps; relative to their axial stiffness (EA/L) that is the
    # clamped-clamped ratio 12 EI / L^3 / (EA / L) = 3 r^2 / L^2 = 1.1e-5, amplified at most by
    # cond(J) = 51, so the compliant and rigid maps may differ by up to cond(J) 3 r^2/L^2 = 5.8e-4.
    sc = eqx.tree_at(lambda s: (s.load.force, s.load.moment), triskele(), NO_LOAD)

    def pose(a):
        r = pcrjax.solve_static(eqx.tree_at(lambda s: s.actuation.initial, sc, a))
        return jnp.stack([r.position[0], r.position[1], r.rotation_vector[2]])

    G = np.asarray(jax.jacfwd(pose)(jnp.zeros(3)))
    d = np.asarray(sc.legs.base_rotation[:, :, 2])
    b = np.asarray(sc.end.attachment) @ np.asarray(sc.end.reference_rotation).T
    J = np.stack([[d[i, 0], d[i, 1], b[i, 0] * d[i, 1] - b[i, 1] * d[i, 0]] for i in range(3)])
    r, L = 62.5e-6, 0.032
    bound = np.linalg.cond(J) * 3 * r**2 / L**2
    dev = np.abs(G - np.linalg.inv(J)).max() / np.abs(np.linalg.inv(J)).max()
    print(f"strut kinematics: relative deviation {dev:.3g}, bound {bound:.3g}")
    assert dev < bound
    # and the implicit derivative is the derivative: central differences of the static solve
    h = 1e-7
    fd = (np.asarray(pose(jnp.array([h, 0.0, 0.0]))) - np.asarray(pose(jnp.array([-h, 0.0, 0.0])))) / (2 * h)
    assert np.abs(fd - G[:, 0]).max() < 1e-6 * np.abs(G[:, 0]).max()


def with_damping(sc, taus):
    sc = dataclasses.replace(sc, effects=dataclasses.replace(sc.effects, damping=True))
    return eqx.tree_at(
        lambda s: s.legs.rod.damping, sc, pcrjax.physics.rod.TauDamping(tau=jnp.asarray(taus)), is_leaf=lambda x: x is None
    )


def test_triskele_settles_to_statics_after_actuator_step():
    # Kelvin-Voigt damping tau = 2 ms (modal damping ratio about 0.6 at the 90-160 Hz platform
    # modes) and BDF2: after 0.25 s the motion has died out and the dynamic rest state must be
    # the static equilibrium of the new actuator values.
    # On the shared Triskele's structure (`helpers.shared_triskele`: N 10, the grid of dt 0.1 ms).
    final = jnp.array([2e-6, -1e-6, 0.5e-6])
    sc = shared_triskele(dt=1e-3, alpha=0.0, duration=0.25, tau=2e-3, final=final)
    sc = eqx.tree_at(lambda s: (s.load.force, s.load.moment), sc, NO_LOAD)
    tr = pcrjax.simulate(sc)
    st = pcrjax.solve_static(eqx.tree_at(lambda s: s.actuation.initial, sc, final))
    moved = np.abs(np.asarray(tr.position)[-1] - np.asarray(tr.position)[0]).max()
    err = np.abs(np.asarray(tr.position)[-1] - np.asarray(st.position)).max()
    err_th = abs(float(tr.rotation_vector[-1, 2]) - float(st.rotation_vector[2]))
    print(f"settled: moved {moved:.3g} m, off statics by {err:.3g} m and {err_th:.3g} rad")
    assert moved > 1e-6
    assert err < 1e-9 and err_th < 1e-9 / 0.05  # 1 nm at the 50 mm platform rim


def test_triskele_energy_conserved_by_trapezoid_and_dissipated_otherwise():
    # Push-and-release, no damping. BDF-alpha sees a load released between t = 0 and the first
    # step as ramped off over that step, so energy is measured from the first step on. The
    # dissipated energy falls to 2e-13 of its start over the 2 s; the default Newton tolerance
    # (1e-10) leaves the solution off by enough that the energy rises by 1e-12 of its start near
    # 1e-11 of it, so the solve is made 100 times tighter for a monotonic claim that far down.
    sc = triskele(nodes=20, alpha=-0.5, duration=2.0, tol=1e-12)
    tr = pcrjax.simulate(sc)
    E = np.asarray(tr.energy)[1:]
    dev = np.abs(E / E[0] - 1).max()
    print(f"alpha -0.5: energy within {dev:.3g} over {len(E)} steps")
    assert dev < 1e-3
    tr = pcrjax.simulate(with_solver(sc, alpha=-0.2, duration=2.0))  # same steps: same compiled program
    E = np.asarray(tr.energy)[1:]
    assert np.all(np.diff(E) <= 1e-12 * E[0]) and E[-1] < 0.5 * E[0]


def _stepped(alpha, taus, dt):
    """Damped Triskele, 50 steps after a 2 um (and -1, 0.5 um) actuator step at t = 0, tol 1e-12."""
    sc = with_damping(triskele(alpha=alpha, dt=dt, duration=50 * dt, tol=1e-12), taus)
    sc = eqx.tree_at(lambda s: (s.load.force, s.load.moment), sc, NO_LOAD)
    return dataclasses.replace(
        sc, actuation=dataclasses.replace(sc.actuation, final=jnp.array([2e-6, -1e-6, 0.5e-6]), kinds=("step",) * 3)
    )


@pytest.mark.slow  # 3-3.5 min cold (compiling the gradient); passes: see the issue note
def test_gradient_after_50_steps_wrt_each_leg_length_and_damping_matches_fd():
    """jax.grad of the platform pose 50 steps after an actuator step vs central differences.

    dt = 0.1 ms: the 50 steps span about half a period of the 90-160 Hz platform modes, where
    Kelvin-Voigt damping of tau = 0.5-1.5 ms (modal ratio 0.15-0.7) shapes the response most.
    Damping uses the 4-point rule (exact to O(h^4)), which allows a step large enough that the
    rollout's round-off (~2e-14 in the loss) stays below 1e-7 relative; lengths need only 2 points.
    One compiled gradient serves both."""
    sc = _stepped(-0.2, [5e-4, 1e-3, 1.5e-3], dt=1e-4)
    L = float(sc.legs.rod.length[0])

    def loss(lengths, taus):
        s2 = eqx.tree_at(lambda s: (s.legs.rod.length, s.legs.rod.damping.tau), sc, (lengths, taus))
        tr = pcrjax.rollout(s2)
        p, th = tr.position[-1], tr.rotation_vector[-1, 2]
        return p[0] / L + 2.0 * p[1] / L + 0.05 * th

    x0 = (sc.legs.rod.length, sc.legs.rod.damping.tau)
    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(*x0)
    f = jax.jit(loss)
    for arg, name, rel, weights in ((0, "L", 1e-6, {1: 0.5}), (1, "tau", 3e-3, {1: 2.0 / 3.0, 2: -1.0 / 12.0})):
        for i in range(3):
            h = rel * float(x0[arg][i])

            def at(shift):
                return float(f(*(x.at[i].add(shift) if k == arg else x for k, x in enumerate(x0))))

            fd = sum(w * (at(m * h) - at(-m * h)) for m, w in weights.items()) / h
            g = float(grads[arg][i])
            print(f"d/d{name}{i + 1}: grad {g:.10g}, central difference {fd:.10g}, relative {abs(g - fd) / abs(fd):.2g}")
            assert abs(g - fd) <= 1e-6 * abs(fd), (name, i, g, fd)
