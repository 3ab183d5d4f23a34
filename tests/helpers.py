"""Scene builders for tests (independent of the shipped TOML files), and the recordings'
generator script as a module."""

import importlib.util
from pathlib import Path

import pcrjax
from pcrjax import scene_from_dict


def rod_scene(**kw):
    return scene_from_dict(rod_data(**kw), "<test>")


def rod_data(
    *,
    L=0.4,
    r=1e-3,
    E=207e9,
    G=79.61e9,
    rho=8000.0,
    force=(0.0, 0.0, -2.0),
    moment=(0.0, 0.0, 0.0),
    release_time=0.0,
    nodes=20,
    integrator="rk4",
    dt=5e-3,
    alpha=-0.4,
    duration=0.1,
    tol=1e-10,
    effects=None,
    rod_extra=None,
    gravity=(0.0, 0.0, -9.81),
    **solver_extra,
):
    """The scene dict of a cantilever (a rod along x, clamped at the origin, a tip load)."""
    eff = {"inertia": True, "gravity": False, "damping": False, "drag": False, "shear_extension": True}
    eff.update(effects or {})
    rod = {"length": L, "radius": r, "youngs_modulus": E, "shear_modulus": G, "density": rho}
    rod.update(rod_extra or {})
    return {
        "name": "test",
        "robot": "rod",
        "solver": {
            "nodes": nodes,
            "integrator": integrator,
            "dt": dt,
            "alpha": alpha,
            "duration": duration,
            "tol": tol,
            **solver_extra,
        },
        "effects": eff,
        "environment": {"gravity": list(gravity)},
        "rod": rod,
        "base": {"position": [0.0, 0.0, 0.0], "direction": [1.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]},
        "tip": {"force": list(force), "moment": list(moment), "release_time": release_time},
    }


def static_tip(scene):
    return pcrjax.solve_static(scene)


def recording_generator():
    """``experiments_data/generate.py`` as a module (it is a script, not a package)."""
    spec = importlib.util.spec_from_file_location(
        "generate", Path(__file__).resolve().parent.parent / "experiments_data" / "generate.py"
    )
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    return gen
