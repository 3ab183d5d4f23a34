"""Scenes: the PyTree that describes a robot, its effects, loads and solver settings, and its TOML form.

Structure (effect switches, node counts, integrator, number of steps) is static; every number
you may differentiate, fit or `vmap` over (lengths, moduli, density, damping, loads, dt, alpha)
is a float64 leaf. Keys follow DESIGN §3; unknown keys are rejected with the key and file named.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from importlib import resources
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from . import bdf_alpha
from .newton import NewtonSettings
from .rod import DiagonalDamping, Effects, Rod, TauDamping
from .shooting import auto_segments, boundary_layer_rate
from .spatial import INTEGRATORS, refinement


class SceneError(ValueError):
    """A scene file or value that pcrjax cannot use; the message names the cause."""


class Base(eqx.Module):
    """Clamp of the rod: position (m) and rotation (3x3, columns = local x, y, z; z is the tangent)."""

    position: jnp.ndarray
    rotation: jnp.ndarray


class TipLoad(eqx.Module):
    """Force (N) and moment (N m) on the free tip, held while t <= release_time (s)."""

    force: jnp.ndarray
    moment: jnp.ndarray
    release_time: jnp.ndarray


class Solver(eqx.Module):
    """Discretisation and Newton settings. ``dt`` (s) and ``alpha`` are differentiable leaves."""

    dt: jnp.ndarray
    alpha: jnp.ndarray
    nodes: int = eqx.field(static=True)
    integrator: str = eqx.field(static=True)
    steps: int = eqx.field(static=True)
    segments: int = eqx.field(static=True)
    unroll: int = eqx.field(static=True)
    refine: int = eqx.field(static=True, default=1)
    continuation: int = eqx.field(static=True, default=10)  # stages of the parallel robots' initial static solve
    newton: NewtonSettings = NewtonSettings()

    @property
    def grid_nodes(self) -> int:
        """Nodes of the internal integration grid: ``nodes * refine`` (outputs use every refine-th)."""
        return self.nodes * self.refine

    @property
    def duration(self):
        return self.steps * self.dt


class Scene(eqx.Module):
    rod: Rod
    base: Base
    tip: TipLoad
    gravity: jnp.ndarray
    effects: Effects
    solver: Solver
    name: str = eqx.field(static=True, default="scene")
    robot: str = eqx.field(static=True, default="rod")


def _f(x):
    return jnp.asarray(x, dtype=jnp.float64)


# ----------------------------------------------------------------------------------------------
# TOML schema

_SCHEMA = {
    "": {"name", "robot", "solver", "effects", "environment", "rod", "rods", "base", "tip"},
    "solver": {"nodes", "integrator", "dt", "alpha", "duration", "tol", "max_iter", "segments", "unroll", "continuation"},
    "effects": {"inertia", "gravity", "damping", "drag", "shear_extension", "planar"},
    "environment": {"gravity"},
    "rod": {"length", "radius", "youngs_modulus", "shear_modulus", "density", "tau", "bse", "bbt", "drag_coefficients", "precurvature"},
    "base": {"position", "direction", "normal"},
    "tip": {"force", "moment", "release_time"},
    "geometry": {
        "base_radius", "platform_radius", "base_angles", "platform_angles",  # stewart_gough
        "actuator_radius", "gamma", "phi", "clamp_angles", "attachment",  # triskele
    },
    "platform": {"mass", "inertia", "position", "rotation_vector", "angle"},
    "actuation": {"initial", "final", "kind", "start_time", "duration", "file"},
    "load": {"force", "moment", "release_time", "step_time", "file"},
}
_PARALLEL_TOP = {"name", "robot", "solver", "effects", "environment", "rod", "rods", "geometry", "platform", "actuation", "load"}
_REQUIRED_ROD = ("length", "radius", "youngs_modulus", "shear_modulus", "density")
ROBOTS = ("rod", "stewart_gough", "triskele")


class _Reader:
    def __init__(self, data: dict, source: str):
        self.data = data
        self.source = source

    def fail(self, where: str, msg: str):
        raise SceneError(f"{self.source}: {where}: {msg}")

    def table(self, name: str) -> dict:
        t = self.data.get(name, {})
        if not isinstance(t, dict):
            self.fail(f"[{name}]", "must be a table")
        allowed = _SCHEMA[name]
        for key in t:
            if key not in allowed:
                self.fail(f"[{name}]", f"unknown key '{key}' (allowed: {', '.join(sorted(allowed))})")
        return t

    def number(self, table: dict, tname: str, key: str, default=None, *, positive=False, nonneg=False, required=False):
        where = f"[{tname}] {key}"
        if key not in table:
            if required:
                self.fail(where, "missing required key")
            return default
        v = table[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(where, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            self.fail(where, f"must be finite, got {v}")
        if positive and v <= 0:
            self.fail(where, f"must be > 0, got {v}")
        if nonneg and v < 0:
            self.fail(where, f"must be >= 0, got {v}")
        return v

    def vector(self, table: dict, tname: str, key: str, default=None, *, nonneg=False):
        """A 3-vector (numbers, finite; ``nonneg``: none negative)."""
        a = self.numbers(table, tname, key, None, default)
        if a is default:
            return a
        if a.shape != (3,):
            self.fail(f"[{tname}] {key}", f"must be a list of 3 numbers, got {table[key]!r}")
        if nonneg and np.any(a < 0):
            self.fail(f"[{tname}] {key}", f"must be >= 0, got {table[key]}")
        return a

    def numbers(self, table: dict, tname: str, key: str, length: int | None = None, default=None, *, required=False):
        """A list of numbers (``length`` of them if given: one per leg) as a finite float array."""
        where = f"[{tname}] {key}"
        if key not in table:
            if required:
                self.fail(where, "missing required key")
            return default
        v = table[key]
        if not isinstance(v, list) or any(isinstance(a, bool) or not isinstance(a, (int, float)) for a in v):
            self.fail(where, f"must be a list of numbers, got {v!r}")
        if length is not None and len(v) != length:
            self.fail(where, f"must have {length} entries (one per leg), got {len(v)}")
        a = np.asarray(v, dtype=float)
        if not np.all(np.isfinite(a)):
            self.fail(where, f"must be finite, got {v}")
        return a

    def flag(self, table: dict, tname: str, key: str, default: bool) -> bool:
        if key not in table:
            return default
        v = table[key]
        if not isinstance(v, bool):
            self.fail(f"[{tname}] {key}", f"must be true or false, got {v!r}")
        return v


def _frame(r: _Reader, direction, normal) -> np.ndarray:
    nd = np.linalg.norm(direction)
    if nd == 0:
        r.fail("[base] direction", "must not be zero")
    z = direction / nd
    x = normal - np.dot(normal, z) * z
    nx = np.linalg.norm(x)
    if nx < 1e-9 * max(1.0, np.linalg.norm(normal)):
        r.fail("[base] normal", "must not be parallel to direction (or zero)")
    x = x / nx
    return np.stack([x, np.cross(z, x), z], axis=1)


def scene_from_dict(data: dict, source: str = "<scene>"):
    """Build and validate a scene from parsed TOML (raises `SceneError` naming the cause)."""
    r = _Reader(data, source)
    robot = data.get("robot", "rod")
    if robot not in ROBOTS:
        r.fail("robot", f"must be one of {', '.join(ROBOTS)}, got {robot!r}")
    allowed = _SCHEMA[""] if robot == "rod" else _PARALLEL_TOP
    for key in data:
        if key not in allowed:
            r.fail("top level", f"unknown key '{key}' for robot '{robot}' (allowed: {', '.join(sorted(allowed))})")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        r.fail("name", "must be a string")
    if robot != "rod":
        from .scene_parallel import parallel_scene

        return parallel_scene(r, robot, name)
    if "rods" in data:
        r.fail("[[rods]]", "per-rod overrides apply to parallel robots; a 'rod' scene has one [rod]")
    ef = r.table("effects")
    if "planar" in ef:
        r.fail("[effects] planar", "applies to parallel robots only")
    effects = read_effects(r, planar=False)
    if "rod" not in data:
        r.fail("[rod]", "missing required table")
    rod = read_rod(r, r.table("rod"), "rod", effects)
    bs = r.table("base")
    tp = r.table("tip")
    R0 = _frame(r, r.vector(bs, "base", "direction", np.array([1.0, 0, 0])), r.vector(bs, "base", "normal", np.array([0, 0, 1.0])))
    base = Base(position=_f(r.vector(bs, "base", "position", np.zeros(3))), rotation=_f(R0))
    tip = TipLoad(
        force=_f(r.vector(tp, "tip", "force", np.zeros(3))),
        moment=_f(r.vector(tp, "tip", "moment", np.zeros(3))),
        release_time=_f(r.number(tp, "tip", "release_time", 0.0)),
    )
    gravity = read_gravity(r)
    solver = make_solver(rod, **read_solver(r))
    return Scene(rod=rod, base=base, tip=tip, gravity=gravity, effects=effects, solver=solver, name=name, robot=robot)


def read_effects(r: _Reader, planar: bool) -> Effects:
    ef = r.table("effects")
    return Effects(
        inertia=r.flag(ef, "effects", "inertia", True),
        gravity=r.flag(ef, "effects", "gravity", False),
        damping=r.flag(ef, "effects", "damping", False),
        drag=r.flag(ef, "effects", "drag", False),
        shear_extension=r.flag(ef, "effects", "shear_extension", True),
        planar=r.flag(ef, "effects", "planar", planar),
    )


def read_gravity(r: _Reader):
    return _f(r.vector(r.table("environment"), "environment", "gravity", np.array([0.0, 0.0, -9.81])))


def rod_values(r: _Reader, rd: dict, tname: str, base: dict | None = None) -> dict:
    """Validated numbers of a [rod] table (or a [[rods]] entry overriding ``base``)."""
    base = base or {}
    vals = {k: r.number(rd, tname, k, base.get(k), required=k not in base, positive=True) for k in _REQUIRED_ROD}
    tau = r.number(rd, tname, "tau", None, nonneg=True)
    bse = r.vector(rd, tname, "bse", nonneg=True)
    bbt = r.vector(rd, tname, "bbt", nonneg=True)
    if (bse is None) != (bbt is None):
        r.fail(f"[{tname}] bse/bbt", "give both bse and bbt (or tau)")
    if tau is not None and bse is not None:
        r.fail(f"[{tname}] tau", "give either tau or bse/bbt, not both")
    if tau is None and bse is None:
        tau, bse, bbt = base.get("tau"), base.get("bse"), base.get("bbt")
    vals.update(tau=tau, bse=bse, bbt=bbt)
    vals["drag_coefficients"] = r.vector(rd, tname, "drag_coefficients", base.get("drag_coefficients", np.zeros(3)), nonneg=True)
    vals["precurvature"] = r.vector(rd, tname, "precurvature", base.get("precurvature"))
    return vals


def make_rod(vals: dict, effects: Effects) -> Rod:
    damping = None
    if vals["bse"] is not None:
        damping = DiagonalDamping(bse=_f(vals["bse"]), bbt=_f(vals["bbt"]))
    elif vals["tau"] is not None:
        damping = TauDamping(tau=_f(vals["tau"]))
    if effects.damping and damping is None:
        damping = TauDamping(tau=_f(0.0))
    ustar = vals["precurvature"]
    return Rod(
        length=_f(vals["length"]),
        radius=_f(vals["radius"]),
        youngs_modulus=_f(vals["youngs_modulus"]),
        shear_modulus=_f(vals["shear_modulus"]),
        density=_f(vals["density"]),
        damping=damping if effects.damping else None,
        drag=_f(vals["drag_coefficients"]) if effects.drag else None,
        precurvature=None if ustar is None else _f(ustar),
    )


def read_rod(r: _Reader, rd: dict, tname: str, effects: Effects) -> Rod:
    return make_rod(rod_values(r, rd, tname), effects)


def read_solver(r: _Reader) -> dict:
    """Solver settings as keyword arguments of `make_solver` (validated)."""
    sv = r.table("solver")
    nodes = sv.get("nodes", 50)
    if isinstance(nodes, bool) or not isinstance(nodes, int) or nodes < 1:
        r.fail("[solver] nodes", f"must be a positive integer, got {nodes!r}")
    integrator = sv.get("integrator", "rk4")
    if integrator not in INTEGRATORS:
        r.fail("[solver] integrator", f"must be one of {', '.join(INTEGRATORS)}, got {integrator!r}")
    dt = r.number(sv, "solver", "dt", 5e-3, positive=True)
    alpha = r.number(sv, "solver", "alpha", -0.2)
    if not -0.5 <= alpha <= 0.0:
        r.fail("[solver] alpha", f"must lie in [-0.5, 0] (-0.5 trapezoidal, 0 BDF2), got {alpha}")
    duration = r.number(sv, "solver", "duration", 1.0, nonneg=True)
    tol = r.number(sv, "solver", "tol", 1e-10, positive=True)
    out = dict(nodes=nodes, integrator=integrator, dt=dt, alpha=alpha, duration=duration, tol=tol)
    for key, default in (("max_iter", 50), ("continuation", 10)):
        v = sv.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            r.fail(f"[solver] {key}", f"must be a positive integer, got {v!r}")
        out[key] = v
    segments = sv.get("segments", "auto")
    if segments != "auto" and (isinstance(segments, bool) or not isinstance(segments, int) or not 1 <= segments <= nodes):
        r.fail("[solver] segments", f"must be \"auto\" or an integer in [1, nodes], got {segments!r}")
    unroll = sv.get("unroll", None)
    if unroll is not None and (isinstance(unroll, bool) or not isinstance(unroll, int) or unroll < 1):
        r.fail("[solver] unroll", f"must be a positive integer, got {unroll!r}")
    out.update(segments=segments, unroll=unroll)
    return out


def make_solver(rod: Rod, nodes, integrator, dt, alpha, duration, tol=1e-10, max_iter=50, segments="auto", unroll=None, continuation=10) -> Solver:
    """Solver settings; ``segments="auto"`` picks the multiple-shooting split from dt and alpha.

    ``rod`` may hold several legs (leaves with a leading axis): the most demanding leg decides.
    """
    c0 = float(bdf_alpha.coefficients(dt, alpha).c0)
    radius, E, G, rho, length = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (rod.radius, rod.youngs_modulus, rod.shear_modulus, rod.density, rod.length))
    lam = max(boundary_layer_rate(*vals, c0) for vals in zip(radius, E, G, rho))
    L = float(length.max())
    # Node spacing longer than the boundary layer: integrate on a finer internal grid (spatial.py).
    refine = refinement(lam * L / nodes)
    if segments == "auto":
        segments = auto_segments(nodes * refine, L, lam)
    elif refine > 1:
        segments = segments * refine if segments > 1 else segments
    if unroll is None:
        unroll = default_unroll(nodes)
    return Solver(
        dt=_f(dt),
        alpha=_f(alpha),
        nodes=int(nodes),
        integrator=integrator,
        steps=int(round(duration / dt)),
        segments=int(segments),
        unroll=int(unroll),
        refine=int(refine),
        newton=NewtonSettings(tol=float(tol), max_iter=int(max_iter)),
        continuation=int(continuation),
    )


def default_unroll(nodes: int) -> int:
    """Scan unroll factor. Unrolling did not speed up N = 40..150 on XLA:CPU (the cost is in the
    fused kernels, not the loop) but multiplied compile time (3x at unroll 5), so it is off."""
    return 1


def with_solver(scene: Scene, **changes) -> Scene:
    """A copy of ``scene`` with solver settings changed (nodes, integrator, dt, alpha, duration,
    tol, max_iter, segments, unroll); segments are re-chosen unless given."""
    s = scene.solver
    cur = dict(
        nodes=s.nodes,
        integrator=s.integrator,
        dt=float(s.dt),
        alpha=float(s.alpha),
        duration=float(s.steps * s.dt),
        tol=s.newton.tol,
        max_iter=s.newton.max_iter,
        segments="auto",
        unroll=None if "nodes" in changes else s.unroll,
        continuation=s.continuation,
    )
    unknown = set(changes) - set(cur)
    if unknown:
        raise SceneError(f"with_solver: unknown setting(s) {', '.join(sorted(unknown))}")
    cur.update(changes)
    if not -0.5 <= cur["alpha"] <= 0.0:
        raise SceneError(f"alpha must lie in [-0.5, 0], got {cur['alpha']}")
    if cur["dt"] <= 0:
        raise SceneError(f"dt must be > 0, got {cur['dt']}")
    rod = scene.rod if hasattr(scene, "rod") else scene.legs.rod
    return dataclasses.replace(scene, solver=make_solver(rod, **cur))


def scene_path(path) -> Path:
    """The TOML file of ``path``: a path, or the name of a shipped scene (raises `SceneError`)."""
    p = Path(path)
    if not p.exists() and not p.suffix:
        shipped = resources.files("pcrjax") / "scenes" / f"{path}.toml"
        if shipped.is_file():
            p = Path(str(shipped))
    if not p.exists():
        raise SceneError(f"{path}: no such file (shipped scenes: {', '.join(shipped_scenes())})")
    return p


def read_toml(p: Path, error: type[Exception] = SceneError) -> dict:
    """Parse the TOML file ``p``; a malformed or binary file raises ``error`` naming it."""
    try:
        return tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise error(f"{p}: malformed TOML: {e}") from None
    except UnicodeDecodeError:
        raise error(f"{p}: not a text file") from None


def load_scene(path) -> Scene:
    """Read and validate a scene TOML file (a path, or the name of a shipped scene)."""
    p = scene_path(path)
    return scene_from_dict(read_toml(p), str(p))


def shipped_scenes() -> list[str]:
    return sorted(f.name[:-5] for f in (resources.files("pcrjax") / "scenes").iterdir() if f.name.endswith(".toml"))
