"""The cantilever through the parallel robots' path: its tip clamped to a one-leg rigid platform.

A rod whose tip is clamped to a rigid body at the tip, loaded there, is the same cantilever as
the free tip under that load; with the body's mass it is a cantilever carrying a tip mass. Both
go through the platform end (pose unknowns, balance rows, clamp constraints, continuation from
straight legs, platform BDF-alpha rates) and are held against independent oracles.
"""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from helpers import rod_scene
from oracles import elastica_tip, fit_sinusoids, tip_mass_frequency_hz

import pcrjax
from pcrjax.physics.platform import Platform
from pcrjax.robots.ends import RigidPlatform

L, R, E, G, RHO = 0.4, 1e-3, 207e9, 79.61e9, 8000.0
EI = E * math.pi * R**4 / 4


def on_platform(scene, mass, inertia):
    """``scene``'s one rod with its tip clamped to a rigid body at the straight rod's tip; the
    tip load acts on the body's centre."""
    legs = scene.legs
    tip = legs.base_position[0] + legs.rod.length[0] * legs.base_rotation[0, :, 2]
    end = RigidPlatform(
        body=Platform(mass=jnp.asarray(mass), inertia=jnp.full(3, inertia)),
        attachment=jnp.zeros((1, 3)),
        clamp=jnp.eye(3)[None],
        reference_position=tip,
        reference_rotation=legs.base_rotation[0],
        load=scene.load,
    )
    return dataclasses.replace(scene, end=end)


def test_elastica_through_the_platform_path():
    P = EI / L**2  # P L^2 / EI = 1
    free = rod_scene(force=(0, 0, -P), nodes=64, effects={"inertia": False, "shear_extension": False})
    clamped = pcrjax.solve_static(on_platform(free, 1e-3, 1e-9))
    p = np.asarray(clamped.position)
    tangent = np.asarray(clamped.rotation)[:, 2]
    got = (-p[2] / L, 1 - p[0] / L, math.atan2(-tangent[2], tangent[0]))
    np.testing.assert_allclose(got, elastica_tip(1.0), rtol=1e-5)
    # The same equilibrium as the free tip's, to the solver's tolerance.
    np.testing.assert_allclose(p, np.asarray(pcrjax.solve_static(free).position), atol=1e-9 * L)
    assert int(clamped.newton_iterations) > 0 and clamped.base_wrenches.shape == (1, 2, 3)


def test_tip_mass_frequency_through_the_platform_path():
    mass = 0.5 * RHO * math.pi * R**2 * L  # half the rod's mass, carried at its tip
    f_theory = tip_mass_frequency_hz(L, E, R, RHO, mass)
    w = 2 * math.pi * f_theory
    dt = 0.05 / w  # trapezoidal period error (h^2/12) ~ 2e-4 relative
    scene = on_platform(rod_scene(force=(0, 0, -1e-3), nodes=40, dt=dt, alpha=-0.5, duration=1.3), mass, 1e-12)
    tr = pcrjax.simulate(scene)
    t, z = np.asarray(tr.t), np.asarray(tr.position)[:, 2]
    (w1, _), _ = fit_sinusoids(t, z, [w, 4.0 * w])[0]
    assert abs(w1 / w - 1) < 1e-3, (w1 / (2 * math.pi), f_theory)
    # Energy: undamped trapezoidal rule, load released at t = 0: conserved after the first step.
    e = np.asarray(tr.energy)[1:]
    assert np.max(np.abs(e - e[0])) < 1e-3 * np.max(np.abs(e))
