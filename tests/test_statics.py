"""Statics against closed forms and an independent scipy elastica solver."""

import math

import numpy as np
import pytest
from helpers import rod_scene
from oracles import elastica_tip, euler_bernoulli_tip

import pcrjax

L, R, E, G = 0.4, 1e-3, 207e9, 79.61e9
EI = E * math.pi * R**4 / 4


def test_small_load_matches_euler_bernoulli():
    F = 1e-3
    res = pcrjax.solve_static(rod_scene(force=(0, 0, -F), nodes=20, effects={"inertia": False}))
    deflection = -float(res.position[2])
    expected = euler_bernoulli_tip(F, L, E, R)
    assert abs(deflection / expected - 1) <= 1e-4
    # Global balance at the clamp: n(0) = F, m(0) = L e_x x F.
    n0, m0 = np.asarray(res.base_wrenches[0])
    np.testing.assert_allclose(n0, [0, 0, -F], atol=1e-15)
    np.testing.assert_allclose(m0, [0, F * L, 0], rtol=1e-3)


@pytest.fixture(scope="module")
def elastica_reference():
    return elastica_tip(1.0)


def _elastica(shear_extension, nodes=64):
    P = EI / L**2  # P L^2 / EI = 1
    scene = rod_scene(force=(0, 0, -P), nodes=nodes, effects={"inertia": False, "shear_extension": shear_extension})
    res = pcrjax.solve_static(scene)
    p = np.asarray(res.position)
    R_tip = np.asarray(res.rotation)
    tangent = R_tip[:, 2]
    return -p[2] / L, 1 - p[0] / L, math.atan2(-tangent[2], tangent[0])


def test_large_deflection_kirchhoff_matches_elastica(elastica_reference):
    got = _elastica(False)
    # The independent solver agrees with Bisshopp & Drucker's printed digits ...
    np.testing.assert_allclose(elastica_reference, (0.30172, 0.05643, 0.46135), atol=0.5e-5)
    # ... and pcrjax's inextensible rod with it, to 1e-5 relative (RK4 N = 64 is ~1e-9).
    np.testing.assert_allclose(got, elastica_reference, rtol=1e-5)


def test_cosserat_differs_from_kirchhoff_only_by_shear_extension(elastica_reference):
    got = np.asarray(_elastica(True))
    rel = np.abs(got / np.asarray(elastica_reference) - 1)
    # Shear/extension compliance relative to bending: EI/(GA L^2) ~ r^2/L^2 ~ 1e-5.
    assert np.all(rel < 1e-4)
    assert np.max(rel) > 1e-7  # the effect exists


def _order(integrator, Ns):
    P = 0.5 * EI / L**2
    ref = pcrjax.solve_static(rod_scene(force=(0, 0, -P), nodes=512, integrator="rk4", effects={"inertia": False}))
    errs = []
    for N in Ns:
        res = pcrjax.solve_static(rod_scene(force=(0, 0, -P), nodes=N, integrator=integrator, effects={"inertia": False}))
        errs.append(float(np.linalg.norm(np.asarray(res.position) - np.asarray(ref.position))))
    errs = np.asarray(errs)
    return np.log2(errs[:-1] / errs[1:])


def test_rk4_is_fourth_order():
    orders = _order("rk4", [8, 16, 32])
    assert np.all((orders > 3.5) & (orders < 4.5)), orders


def test_euler_is_first_order():
    orders = _order("euler", [16, 32, 64])
    assert np.all((orders > 0.8) & (orders < 1.2)), orders


def test_gravity_uniform_load_matches_euler_bernoulli():
    # Small rod weight only: tip deflection w L^4 / (8 EI) with w = rho A g.
    rho = 8000.0
    w = rho * math.pi * R**2 * 1e-3
    res = pcrjax.solve_static(
        rod_scene(force=(0, 0, 0), rho=rho, gravity=(0, 0, -1e-3), nodes=20, effects={"inertia": False, "gravity": True})
    )
    assert abs(-float(res.position[2]) / (w * L**4 / (8 * EI)) - 1) < 1e-4


def test_precurved_rod_is_a_circular_arc():
    kappa = 2.0  # 1/m about local y: the arc bends the tangent from +x towards ...
    res = pcrjax.solve_static(
        rod_scene(force=(0, 0, 0), nodes=20, effects={"inertia": False}, rod_extra={"precurvature": [0.0, kappa, 0.0]})
    )
    # Local frame at the clamp: x = +z (normal), y = -y, z = +x. A curvature about local y
    # rotates the tangent towards local x = +z: tip = (sin(kL), 0, 1 - cos(kL)) / k.
    expected = np.array([math.sin(kappa * L), 0.0, 1 - math.cos(kappa * L)]) / kappa
    np.testing.assert_allclose(np.asarray(res.position), expected, atol=1e-12)


def test_a_platform_continuation_that_loses_its_path_is_retried():
    """The Triskele-bot of the shipped push-release recording at lengths 31.196, 33.034 and
    30.692 mm under a push of 15 mN and 0.375 mN m, planned as a two-stage continuation: the
    first stage's Newton wanders off (after its 50 directions the scaled residual is still
    0.2-0.5). The static solve retries in four stages, and converges to the equilibrium that a
    20-stage continuation reaches. Round-off does not decide this case: with the lengths moved
    by 1e-12 relative, 12 draws lost the path and converged on the retry alike (the 2-stage
    continuation of the full 20 mN push loses or keeps its path by round-off)."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from identify import experiment
    from identify.recording import load_recording

    scene = experiment.build_scene(load_recording("experiments_data/triskele_push_release.csv"))
    vals = dict(
        tau=jnp.asarray(0.000383),
        lengths=jnp.array([0.031195964042652822, 0.03303446703341804, 0.030692295523611954]),
        push_force=jnp.array([0.015, 0.0]),
        push_moment=jnp.asarray(0.000375),
    )

    def static(v, stages, stop_when_lost=False):
        s = experiment.apply(scene, v)
        newton = dataclasses.replace(s.solver.newton, stop_when_lost=stop_when_lost)  # True: no retry
        return pcrjax.solve_static(
            dataclasses.replace(s, solver=dataclasses.replace(s.solver, continuation=stages, newton=newton))
        )

    max_iter = scene.solver.newton.max_iter
    lost = jax.jit(lambda v: static(v, 2, stop_when_lost=True))(vals)
    assert not bool(lost.converged) and float(lost.residual_norm) > 1e-3, float(lost.residual_norm)
    got = jax.jit(lambda v: static(v, 2))(vals)
    assert bool(got.converged) and int(got.newton_iterations) > max_iter  # the lost stage, then the retry
    ref = jax.jit(lambda v: static(v, 20))(vals)
    assert bool(ref.converged)
    np.testing.assert_allclose(got.position, ref.position, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.rotation, ref.rotation, rtol=0, atol=1e-10)


def test_a_static_solve_from_a_neighbouring_equilibrium_is_the_continuations():
    """`statics.solve_static(scene, near=...)` (the modal start's static response to an actuator
    move): the Triskele-bot of the shipped actuator step, its rods 0.2-0.4 mm off nominal, at rest
    after the recorded actuator move, Newton started from the rest before the move: the rest that
    the continuation from straight legs reaches (1e-12 m, 1e-11 rad), in a few iterations
    instead of the continuation's tens."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from identify import experiment
    from identify.recording import load_recording
    from pcrjax.robots import statics

    before = experiment.build_scene(load_recording("experiments_data/triskele_actuator_step.csv"))
    after = eqx.tree_at(lambda s: s.actuation.initial, before, before.actuation.final)
    lengths = jnp.asarray(experiment.nominal(before)["lengths"]) + jnp.array([4e-4, -3e-4, 2e-4])

    cont = jax.jit(lambda sc, L: statics.solve_static(experiment.apply(sc, {"lengths": L})))
    rest, cont = cont(before, lengths), cont(after, lengths)  # one program: the scenes differ in values only
    near = jax.jit(lambda L, x: statics.solve_static(experiment.apply(after, {"lengths": L}), near=x))(lengths, rest.unknowns)
    assert int(near.stats.result) == int(cont.stats.result) == 0
    assert int(near.stats.iterations) <= 5 < 20 <= int(cont.stats.iterations)  # measured: 3 and 49
    np.testing.assert_allclose(near.position, cont.position, rtol=0, atol=1e-12)
    np.testing.assert_allclose(near.rotation, cont.rotation, rtol=0, atol=1e-11)
    assert np.max(np.abs(near.position - rest.position)) > 1e-6  # the move moved the platform
