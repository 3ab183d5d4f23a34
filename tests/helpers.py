"""Scene builders for tests (independent of the shipped TOML files), and the recordings'
generator script as a module."""

import dataclasses
import importlib.util
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp

import pcrjax
from pcrjax import scene_from_dict
from pcrjax.io.scene_file import read_toml, scene_path


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


# The shared cantilever: one structure that most dynamic cantilever tests run on, varying only
# numbers, so that they share one compiled start and one compiled chunk of steps. Every effect
# is compiled in (damping, drag and gravity at zero where a test does not want them: the same
# equations), and the grid and shooting segments are those its finest step asks for.
SHARED_DT = 2.5e-4  # s: the finest step the shared cantilever serves
SHARED_NODES = 20


def shared_rod(
    *, force=(0.0, 0.0, -2.0), dt=5e-3, alpha=-0.4, duration=0.1, tau=0.0, drag=(0.0, 0.0, 0.0), gravity=(0.0, 0.0, 0.0), **kw
):
    """A cantilever on the shared structure (`SHARED_NODES` nodes, every effect compiled, the grid
    of `SHARED_DT`) with these numbers; ``kw`` as `rod_data` (``integrator="euler"`` or other
    nodes make another structure, shared in turn by the tests that ask for it)."""
    kw.setdefault("nodes", SHARED_NODES)
    data = rod_data(
        force=force,
        dt=SHARED_DT,
        alpha=-0.5,
        duration=duration,
        effects={"damping": True, "drag": True, "gravity": True},
        rod_extra={"tau": tau, "drag_coefficients": list(drag)},
        gravity=gravity,
        **kw,
    )
    return pcrjax.with_step(scene_from_dict(data, "<test>"), dt, alpha=alpha, duration=duration)


# The shared Triskele-bot: the shipped scene at N 10 on one structure for the dynamic tests that
# vary numbers only: Kelvin-Voigt damping compiled (tau 0: the undamped equations), step actuators
# (constant where the final values are the initial ones), the grid and segments of dt 0.1 ms.
SHARED_TRISKELE_DT = 1e-4  # s: the finest step the shared Triskele serves


def shared_triskele(*, dt=1e-3, alpha=-0.2, duration=0.1, tau=0.0, final=None):
    """The shipped Triskele-bot (its push released at t = 0) on the shared structure with these
    numbers; ``final``: actuator values stepped to just after t = 0 (None: held)."""
    data = read_toml(scene_path("triskele"))
    data["effects"] = {**data.get("effects", {}), "damping": True}
    data["rod"] = {**data.get("rod", {}), "tau": 1e-3}
    sc = pcrjax.with_solver(scene_from_dict(data), nodes=10, dt=SHARED_TRISKELE_DT, alpha=-0.5, duration=duration)
    act = sc.actuation
    act = dataclasses.replace(
        act, kinds=("step",) * act.size, final=act.initial if final is None else jnp.asarray(final, jnp.float64)
    )
    sc = dataclasses.replace(sc, actuation=act)
    sc = eqx.tree_at(lambda s: s.legs.rod.damping.tau, sc, jnp.full(sc.legs.count, tau, dtype=jnp.float64))
    return pcrjax.with_step(sc, dt, alpha=alpha, duration=duration)


def committed_recording(name: str, folder) -> tuple[Path, dict]:
    """``experiments_data/tests/NAME`` (made by ``experiments_data/test_recordings.py``: its truth
    simulated finer than the fit's grid) copied into ``folder``: its path and its sidecar's truth."""
    from identify.recording import load_recording

    source = Path(__file__).resolve().parent.parent / "experiments_data" / "tests"
    for suffix in (".csv", ".toml"):
        (Path(folder) / f"{name}{suffix}").write_bytes((source / f"{name}{suffix}").read_bytes())
    path = Path(folder) / f"{name}.csv"
    return path, dict(load_recording(path).truth)
