"""Benchmark cases: the scenes `pcrjax bench` times, and the grids it times them on.

* ``cantilever``: the thesis cantilever (Table 4.1, 2 N tip load released, dt 5 ms, alpha -0.4)
  and Till's public C++ reference case (L 0.5 m, r 1 mm, E 200 GPa, G 80 GPa, rho 8000, gravity
  along the rod's normal, a 0.02 kg tip weight released at t = 0, dt 2 ms, alpha -0.2). Till's
  C++ on this machine class: N = 40 Euler, 78 us/step (real-time factor 27; 63 hand-optimised),
  1 % static error.
* ``stewart_gough``, Till's settings (dt = 1/120 s, alpha = -0.2): legs 1-3 lengthen by 10 mm in
  a 0.25 s smooth step. Till's C++ (6 x 200 Euler nodes): 80 ms/step on this machine class
  (real-time factor 0.06); his paper reports 7-8 with three threads.
* ``triskele``: the shipped push-and-release scene (alpha = -0.2; the platform moves about
  0.2 um, so the rods stay nearly straight), then an actuator move (``triskele_move``: bases slide
  by +1, -0.5, +0.25 mm in a 0.2 s smooth step, slow enough that no fibre is pushed near its
  32 mN buckling load), which bends the rods.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from ..io.scene_file import load_scene, scene_from_dict, with_solver


@dataclasses.dataclass
class Case:
    """A scene to time on a grid of (integrator, N) at each dt, against a converged reference
    (finest RK4 grid, tol 1e-12, same dt)."""

    label: str
    scene: object
    grid: list
    dts: list
    reference_nodes: int
    note: str = ""


def _grid(rk4: str | None, euler: str | None, default_rk4: str, default_euler: str):
    rk4 = default_rk4 if rk4 is None else rk4
    euler = default_euler if euler is None else euler
    return [("rk4", int(n)) for n in rk4.split(",") if n] + [("euler", int(n)) for n in euler.split(",") if n]


def _cantilever_dicts() -> dict:
    thesis = {
        "name": "thesis_cantilever",
        "solver": {"dt": 5e-3, "alpha": -0.4, "duration": 1.0},
        "rod": {"length": 0.4, "radius": 1e-3, "youngs_modulus": 207e9, "shear_modulus": 79.61e9, "density": 8000.0},
        "base": {"direction": [1.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
        "tip": {"force": [0.0, 0.0, -2.0], "release_time": 0.0},
    }
    till = {
        "name": "till_cpp_reference",
        "solver": {"dt": 2e-3, "alpha": -0.2, "duration": 1.0},
        "effects": {"gravity": True},
        "environment": {"gravity": [0.0, 0.0, -9.81]},
        "rod": {"length": 0.5, "radius": 1e-3, "youngs_modulus": 200e9, "shear_modulus": 80e9, "density": 8000.0},
        # Rod along +x, gravity along -z: the rod's normal.
        "base": {"direction": [1.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
        "tip": {"force": [0.0, 0.0, -0.02 * 9.81], "release_time": 0.0},
    }
    return {"thesis": thesis, "till": till}


def _sg_motion(scene):
    act = scene.actuation
    final = act.initial.at[:3].add(0.01)
    moved = dataclasses.replace(act, final=final, start=jnp.full(6, 0.05), duration=jnp.full(6, 0.25), kinds=("smooth_step",) * 6)
    return dataclasses.replace(scene, actuation=moved)


def _triskele_move(scene):
    act = scene.actuation
    moved = dataclasses.replace(
        act,
        final=act.initial + jnp.array([1e-3, -0.5e-3, 0.25e-3]),
        start=jnp.full(3, 0.05),
        duration=jnp.full(3, 0.2),
        kinds=("smooth_step",) * 3,
    )
    zero = jnp.zeros(3)
    return dataclasses.replace(
        scene,
        actuation=moved,
        end=dataclasses.replace(scene.end, load=dataclasses.replace(scene.end.load, force=zero, moment=zero)),
    )


TILL = "Till's C++ (N = 40 Euler): 78 us/step, RTF 27 (63 hand-optimised)."


def cases(robot: str, nodes=None, euler_nodes=None, reference_nodes=None) -> list[Case]:
    """The benchmark cases of ``robot`` (cantilever | stewart_gough | triskele)."""
    if robot == "cantilever":
        grid = _grid(nodes, euler_nodes, "5,10,20,40,80,160", "5,10,20,40,80,160")
        out = []
        for label, d in _cantilever_dicts().items():
            scene = scene_from_dict(d, f"<bench {d['name']}>")
            out.append(
                Case(label, scene, grid, [float(scene.solver.dt)], reference_nodes or 320, TILL if label == "till" else "")
            )
        return out
    if robot == "stewart_gough":
        base = with_solver(_sg_motion(load_scene("stewart_gough")), alpha=-0.2)
        grid = _grid(nodes, euler_nodes, "10,20,40", "50,100,200")
        note = "Till's C++ (6 x 200 Euler, dt 1/120 s, alpha -0.2): 80 ms/step, RTF 0.06 on this machine class."
        return [Case("stewart_gough", base, grid, [1.0 / 120.0], reference_nodes or 80, note)]
    base = load_scene("triskele")
    grid = _grid(nodes, euler_nodes, "10,20,50", "50,200")
    note = "Target: real time (RTF >= 1) at N = 50 RK4, dt = 1 ms (thesis section 4.3.2)."
    return [
        Case("triskele", base, grid, [1e-3, 5e-4], reference_nodes or 100, note),
        Case("triskele_move", _triskele_move(base), grid, [1e-3], reference_nodes or 100),
    ]
