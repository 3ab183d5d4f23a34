"""Scene files: the TOML form of every robot, read and validated into a `Scene`.

One schema with a section per kind of robot: every scene has ``[solver]``, ``[effects]``,
``[environment]`` and ``[rod]``; ``robot = "rod"`` adds ``[base]`` and ``[tip]`` (one fixed leg,
free tip); ``"stewart_gough"`` and ``"triskele"`` add ``[[rods]]``, ``[geometry]``,
``[platform]``, ``[actuation]`` and ``[load]`` (legs that actuators move, rigid platform).
Unknown keys are rejected with the key and file named.

Stewart-Gough: rods rise vertically through holes at ``base_radius``/``base_angles`` (z = 0) and
are clamped perpendicular to the platform at ``platform_radius``/``platform_angles``; rod frames
at base and platform are both the global axes at the reference pose (no built-in twist).
Actuator values are the free leg lengths.

Triskele-bot: actuator origins ``Q_i = r_a (cos gamma_i, sin gamma_i, 0)``, rods leaving along
``d_i = (cos phi_i, sin phi_i, 0)`` from ``A_i = Q_i + q_i d_i``; platform clamps along
``clamp_angles`` (platform frame), attachments ``B_i = Q_i + L_i d_i`` in the reference pose
unless given. Rod frames have local x along global z (out of the plane). Actuator values are the
base displacements ``q_i``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..config import require_x64
from ..errors import SceneError
from ..numerics.solver import make_solver
from ..numerics.spatial import INTEGRATORS
from ..physics.platform import Platform
from ..physics.rod import DiagonalDamping, Effects, Rod, TauDamping
from ..robots.ends import FreeTip, RigidPlatform
from ..robots.legs import Legs
from ..robots.scene import Scene
from ..robots.signals import KINDS, Actuation, ActuatorLimits, Load
from .tables import TableError, read_table

LOAD_COLUMNS = ("t_s", "fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")


def _f(x):
    return jnp.asarray(x, dtype=jnp.float64)


# ----------------------------------------------------------------------------------------------
# TOML schema: keys of each table, and the tables each kind of robot adds to the common ones

_SCHEMA = {
    "solver": {"nodes", "integrator", "dt", "alpha", "duration", "tol", "max_iter", "segments", "unroll", "continuation"},
    "effects": {"inertia", "gravity", "damping", "drag", "shear_extension", "planar"},
    "environment": {"gravity"},
    "rod": {
        "length",
        "radius",
        "youngs_modulus",
        "shear_modulus",
        "density",
        "tau",
        "bse",
        "bbt",
        "drag_coefficients",
        "precurvature",
    },
    "base": {"position", "direction", "normal"},
    "tip": {"force", "moment", "release_time"},
    "geometry": {
        "base_radius",
        "platform_radius",
        "base_angles",
        "platform_angles",  # stewart_gough
        "actuator_radius",
        "gamma",
        "phi",
        "clamp_angles",
        "attachment",  # triskele
    },
    "platform": {"mass", "inertia", "position", "rotation_vector", "angle"},
    "actuation": {"initial", "final", "kind", "start_time", "duration", "file", "range", "max_speed", "max_acceleration"},
    "load": {"force", "moment", "release_time", "step_time", "file"},
}
_COMMON = {"name", "robot", "solver", "effects", "environment", "rod"}
_PARALLEL = {"rods", "geometry", "platform", "actuation", "load"}
_SECTIONS = {"rod": {"base", "tip", "rods"}, "stewart_gough": _PARALLEL, "triskele": _PARALLEL}
_REQUIRED_ROD = ("length", "radius", "youngs_modulus", "shear_modulus", "density")
ROBOTS = tuple(_SECTIONS)


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


def scene_from_dict(data: dict, source: str = "<scene>") -> Scene:
    """Build and validate a scene from parsed TOML (raises `SceneError` naming the cause)."""
    require_x64()
    r = _Reader(data, source)
    robot = data.get("robot", "rod")
    if robot not in ROBOTS:
        r.fail("robot", f"must be one of {', '.join(ROBOTS)}, got {robot!r}")
    allowed = _COMMON | _SECTIONS[robot]
    for key in data:
        if key not in allowed:
            r.fail("top level", f"unknown key '{key}' for robot '{robot}' (allowed: {', '.join(sorted(allowed))})")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        r.fail("name", "must be a string")
    if "rod" not in data:
        r.fail("[rod]", "missing required table")
    return _BUILDERS[robot](r, robot, name)


def _rod_robot(r: _Reader, robot: str, name: str) -> Scene:
    """One rod clamped at ``[base]``, free tip under ``[tip]``: one fixed leg."""
    if "rods" in r.data:
        r.fail("[[rods]]", "per-rod overrides apply to parallel robots; a 'rod' scene has one [rod]")
    if "planar" in r.table("effects"):
        r.fail("[effects] planar", "applies to parallel robots only")
    effects = read_effects(r, planar=False)
    rod = read_rod(r, r.table("rod"), "rod", effects)
    bs = r.table("base")
    tp = r.table("tip")
    R0 = _frame(
        r, r.vector(bs, "base", "direction", np.array([1.0, 0, 0])), r.vector(bs, "base", "normal", np.array([0, 0, 1.0]))
    )
    legs = Legs(
        rod=jax.tree.map(lambda a: a[None], rod),
        base_position=_f(r.vector(bs, "base", "position", np.zeros(3)))[None],
        base_rotation=_f(R0)[None],
        kind="fixed",
    )
    load = Load.held_until(
        _f(r.vector(tp, "tip", "force", np.zeros(3))),
        _f(r.vector(tp, "tip", "moment", np.zeros(3))),
        _f(r.number(tp, "tip", "release_time", 0.0)),
    )
    solver = make_solver(legs.rod, legs.rod.length, **read_solver(r))
    return Scene(
        legs=legs,
        end=FreeTip(load=load),
        actuation=None,
        gravity=read_gravity(r),
        effects=effects,
        solver=solver,
        name=name,
        robot=robot,
    )


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
        r.fail("[solver] segments", f'must be "auto" or an integer in [1, nodes], got {segments!r}')
    unroll = sv.get("unroll", 1)
    if isinstance(unroll, bool) or not isinstance(unroll, int) or unroll < 1:
        r.fail("[solver] unroll", f"must be a positive integer, got {unroll!r}")
    out.update(segments=segments, unroll=unroll)
    return out


def _check_step(dt, alpha):
    """BDF-alpha's step and alpha as `with_solver` and `with_step` accept them (NaN refused)."""
    if not -0.5 <= float(alpha) <= 0.0:
        raise SceneError(f"alpha must lie in [-0.5, 0], got {float(alpha)}")
    if not float(dt) > 0:
        raise SceneError(f"dt must be > 0, got {float(dt)}")


def with_solver(scene: Scene, **changes) -> Scene:
    """A copy of ``scene`` with solver settings changed (nodes, integrator, dt, alpha, duration,
    tol, max_iter, segments, unroll, continuation); the shooting segments and the internal grid are
    chosen again from the scene's current numbers unless ``segments`` is given (call it with no
    changes to refresh them after ``eqx.tree_at`` on a length, modulus, density, dt or alpha)."""
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
        unroll=s.unroll,
        continuation=s.continuation,
    )
    unknown = set(changes) - set(cur)
    if unknown:
        raise SceneError(f"with_solver: unknown setting(s) {', '.join(sorted(unknown))}")
    cur.update(changes)
    _check_step(cur["dt"], cur["alpha"])
    lengths = scene.legs.lengths(scene.actuator_values(jnp.zeros(())))
    return dataclasses.replace(scene, solver=make_solver(scene.legs.rod, lengths, **cur))


def with_step(scene: Scene, dt, *, alpha=None, duration=None) -> Scene:
    """A copy of ``scene`` with another time step (and alpha, duration), its compiled structure
    kept: the shooting segments and the internal grid stay those it was built for, which serve a
    coarser step too (build the scene for the finest step it will take). Runs at several steps then
    share one compiled program, and one spatial grid."""
    s = scene.solver
    duration = float(s.steps * s.dt) if duration is None else float(duration)
    alpha = s.alpha if alpha is None else alpha
    _check_step(dt, alpha)
    solver = dataclasses.replace(
        s, dt=jnp.asarray(dt, jnp.float64), alpha=jnp.asarray(alpha, jnp.float64), steps=int(round(duration / float(dt)))
    )
    return dataclasses.replace(scene, solver=solver)


SG_DEFAULTS = dict(
    base_radius=0.087,
    platform_radius=0.087,
    base_angles=[-10.0, 10.0, 110.0, 130.0, 230.0, 250.0],
    platform_angles=[-50.0, 50.0, 70.0, 170.0, 190.0, 290.0],
)
TRISKELE_DEFAULTS = dict(
    actuator_radius=0.080, gamma=[-30.0, 210.0, 90.0], phi=[140.0, 20.0, -100.0], clamp_angles=[130.0, 10.0, -110.0]
)


def _rz(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _planar_frame(angle_deg):
    """Rod frame with tangent (cos, sin, 0) in the plane and local x along global z."""
    d = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg)), 0.0])
    x = np.array([0.0, 0.0, 1.0])
    return np.stack([x, np.cross(d, x), d], axis=1)


def _rotation_from_vector(v):
    th = float(np.linalg.norm(v))
    if th == 0:
        return np.eye(3)
    k = v / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def _rods(r: _Reader, n: int, effects: Effects, nominal_lengths=None):
    base = rod_values(r, r.table("rod"), "rod")
    entries = r.data.get("rods", [])
    if not isinstance(entries, list) or any(not isinstance(e, dict) for e in entries):
        r.fail("[[rods]]", "must be an array of tables")
    if entries and len(entries) != n:
        r.fail("[[rods]]", f"has {len(entries)} entries but the robot has {n} legs")
    vals = []
    for i in range(n):
        e = entries[i] if entries else {}
        for key in e:
            if key not in _SCHEMA["rod"]:
                r.fail(f"[[rods]] entry {i + 1}", f"unknown key '{key}' (allowed: {', '.join(sorted(_SCHEMA['rod']))})")
        vals.append(rod_values(r, e, f"rods {i + 1}", base) if e else base)
    kinds = {("bse" if v["bse"] is not None else "tau" if v["tau"] is not None else None) for v in vals}
    if effects.damping and len(kinds - {None}) > 1:
        r.fail("[[rods]]", "give every rod the same kind of damping (tau, or bse and bbt)")
    if effects.damping:
        kind = (kinds - {None} or {"tau"}).pop()
        for v in vals:  # rods without damping values get zeros of the common kind
            if kind == "bse" and v["bse"] is None:
                v.update(bse=np.zeros(3), bbt=np.zeros(3), tau=None)
            if kind == "tau" and v["tau"] is None:
                v.update(tau=0.0)
    rods = [make_rod(v, effects) for v in vals]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *rods), np.array([v["length"] for v in vals])


def _actuation(r: _Reader, n: int, default_initial, base_dir: Path) -> Actuation:
    t = r.table("actuation")
    initial = r.numbers(t, "actuation", "initial", n, default_initial)
    table_t = table_a = None
    if "file" in t:
        f = t["file"]
        if not isinstance(f, str):
            r.fail("[actuation] file", "must be a path string")
        for key in ("final", "kind", "start_time", "duration"):
            if key in t:
                r.fail(f"[actuation] {key}", "cannot be combined with file (the file gives the whole signal)")
        try:
            table_t, table_a = read_table(base_dir / f, ("t_s",) + tuple(f"a{i + 1}" for i in range(n)))
        except TableError as e:
            raise SceneError(f"{r.source}: [actuation] file: {e}") from None
        initial = table_a[0]
    kind = t.get("kind", "constant")
    kinds = [kind] * n if isinstance(kind, str) else kind
    if not isinstance(kinds, list) or len(kinds) != n or any(k not in KINDS for k in kinds):
        r.fail("[actuation] kind", f"must be one of {', '.join(KINDS)} or a list of {n} of them, got {kind!r}")
    final = r.numbers(t, "actuation", "final", n, None)
    if final is None:
        if any(k != "constant" for k in kinds):
            r.fail("[actuation] final", f"missing: needed by kind {kind!r}")
        final = initial
    start = _per_leg(r, t, "start_time", n, 0.0)
    duration = _per_leg(r, t, "duration", n, 0.0)
    for i, k in enumerate(kinds):
        if k in ("ramp", "smooth_step") and duration[i] <= 0:
            r.fail("[actuation] duration", f"must be > 0 for a {k} (actuator {i + 1})")
    return Actuation(
        initial=_f(initial),
        final=_f(final),
        start=_f(start),
        duration=_f(np.where(duration > 0, duration, 1.0)),
        table_t=None if table_t is None else _f(table_t),
        table_a=None if table_a is None else _f(table_a),
        kinds=tuple(kinds) if table_t is None else (),
        limits=_limits(r, t, n),
    )


def _limits(r: _Reader, t: dict, n: int) -> ActuatorLimits | None:
    """[actuation] range = [low, high] (or one pair per actuator), max_speed, max_acceleration."""
    if not any(k in t for k in ("range", "max_speed", "max_acceleration")):
        return None
    low, high = np.full(n, -np.inf), np.full(n, np.inf)
    if "range" in t:
        v = t["range"]
        pairs = v if v and isinstance(v[0], list) else [v] * n
        if len(pairs) != n or any(not isinstance(p, list) or len(p) != 2 for p in pairs):
            r.fail("[actuation] range", f"must be [low, high] or {n} such pairs, got {v!r}")
        arr = np.array([r.numbers({"range": p}, "actuation", "range", 2) for p in pairs])
        if np.any(arr[:, 0] >= arr[:, 1]):
            r.fail("[actuation] range", f"low must be below high, got {v!r}")
        low, high = arr[:, 0], arr[:, 1]
    speed = _per_leg(r, t, "max_speed", n, np.inf)
    accel = _per_leg(r, t, "max_acceleration", n, np.inf)
    for key, vals in (("max_speed", speed), ("max_acceleration", accel)):
        if np.any(vals <= 0):
            r.fail(f"[actuation] {key}", f"must be > 0, got {t[key]!r}")
    return ActuatorLimits(low=_f(low), high=_f(high), max_speed=_f(speed), max_acceleration=_f(accel))


def _per_leg(r, t, key, n, default):
    v = t.get(key, default)
    if isinstance(v, list):
        return r.numbers(t, "actuation", key, n)
    return np.full(n, r.number(t, "actuation", key, default))


def _load(r: _Reader, base_dir: Path) -> Load:
    t = r.table("load")
    table_t = table_w = None
    if "file" in t:
        if not isinstance(t["file"], str):
            r.fail("[load] file", "must be a path string")
        try:
            table_t, table_w = read_table(base_dir / t["file"], LOAD_COLUMNS)
        except TableError as e:
            raise SceneError(f"{r.source}: [load] file: {e}") from None
    return Load(
        force=_f(r.vector(t, "load", "force", np.zeros(3))),
        moment=_f(r.vector(t, "load", "moment", np.zeros(3))),
        apply_time=_f(r.number(t, "load", "step_time", -math.inf)),
        release_time=_f(r.number(t, "load", "release_time", math.inf)),
        table_t=None if table_t is None else _f(table_t),
        table_w=None if table_w is None else _f(table_w),
    )


def _platform(r: _Reader, default_position, planar: bool):
    t = r.table("platform")
    mass = r.number(t, "platform", "mass", required=True, positive=True)
    inertia = r.vector(t, "platform", "inertia", None)
    if inertia is None:
        r.fail("[platform] inertia", "missing required key")
    if np.any(inertia <= 0):
        r.fail("[platform] inertia", f"must be > 0, got {list(inertia)}")
    position = r.vector(t, "platform", "position", np.asarray(default_position, float))
    if planar:
        if "rotation_vector" in t:
            r.fail("[platform] rotation_vector", "a planar robot's platform angle is [platform] angle (degrees)")
        R = _rz(r.number(t, "platform", "angle", 0.0))
    else:
        if "angle" in t:
            r.fail("[platform] angle", "applies to planar robots; use rotation_vector (rad)")
        R = _rotation_from_vector(r.vector(t, "platform", "rotation_vector", np.zeros(3)))
    return Platform(mass=_f(mass), inertia=_f(inertia)), position, R


def _parallel_robot(r: _Reader, robot: str, name: str) -> Scene:
    """Legs moved by actuators, clamped to a rigid platform."""
    effects = read_effects(r, planar=robot == "triskele")
    g = r.table("geometry")
    base_dir = Path(r.source).parent
    if robot == "stewart_gough":
        for key in ("actuator_radius", "gamma", "phi", "clamp_angles", "attachment"):
            if key in g:
                r.fail(f"[geometry] {key}", "applies to the triskele robot, not stewart_gough")
        rb = r.number(g, "geometry", "base_radius", SG_DEFAULTS["base_radius"], positive=True)
        rp = r.number(g, "geometry", "platform_radius", SG_DEFAULTS["platform_radius"], positive=True)
        ba = r.numbers(g, "geometry", "base_angles", None, np.array(SG_DEFAULTS["base_angles"]))
        pa = r.numbers(g, "geometry", "platform_angles", None, np.array(SG_DEFAULTS["platform_angles"]))
        n = len(ba)
        if n < 1 or len(pa) != n:
            r.fail("[geometry] platform_angles", f"must have as many entries as base_angles ({n}), got {len(pa)}")
        rod, lengths = _rods(r, n, effects)
        base_pos = np.stack([[rb * math.cos(math.radians(a)), rb * math.sin(math.radians(a)), 0.0] for a in ba])
        base_R = np.stack([np.eye(3)] * n)
        attach = np.stack([[rp * math.cos(math.radians(a)), rp * math.sin(math.radians(a)), 0.0] for a in pa])
        clamp = np.stack([np.eye(3)] * n)
        kind, default_initial = "length", lengths
        platform, p_ref, R_ref = _platform(r, [0.0, 0.0, float(lengths.mean())], effects.planar)
    else:
        for key in ("base_radius", "platform_radius", "base_angles", "platform_angles"):
            if key in g:
                r.fail(f"[geometry] {key}", "applies to the stewart_gough robot, not triskele")
        ra = r.number(g, "geometry", "actuator_radius", TRISKELE_DEFAULTS["actuator_radius"], positive=True)
        gamma = r.numbers(g, "geometry", "gamma", None, np.array(TRISKELE_DEFAULTS["gamma"]))
        n = len(gamma)
        phi = r.numbers(g, "geometry", "phi", n, np.array(TRISKELE_DEFAULTS["phi"]))
        clamp_angles = r.numbers(g, "geometry", "clamp_angles", n, np.array(TRISKELE_DEFAULTS["clamp_angles"]))
        rod, lengths = _rods(r, n, effects)
        platform, p_ref, R_ref = _platform(r, [0.0, 0.0, 0.0], effects.planar)
        Q = np.stack([[ra * math.cos(math.radians(a)), ra * math.sin(math.radians(a)), 0.0] for a in gamma])
        base_pos = Q
        base_R = np.stack([_planar_frame(a) for a in phi])
        if "attachment" in g:
            att = g["attachment"]
            ok = (
                isinstance(att, list)
                and len(att) == n
                and all(
                    isinstance(p, list)
                    and len(p) == 2
                    and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in p)
                    for p in att
                )
            )
            if not ok:
                r.fail("[geometry] attachment", f"must be {n} pairs [x, y] of numbers (m, platform frame)")
            attach = np.array([[p[0], p[1], 0.0] for p in att])
        else:
            B = Q + lengths[:, None] * base_R[:, :, 2]
            attach = (B - p_ref) @ R_ref  # R_ref^T (B - p_ref), row-wise
        clamp = np.stack([_planar_frame(a) for a in clamp_angles])
        kind, default_initial = "prismatic", np.zeros(n)
    actuation = _actuation(r, n, default_initial, base_dir)
    load = _load(r, base_dir)
    legs = Legs(rod=rod, base_position=_f(base_pos), base_rotation=_f(base_R), kind=kind)
    a0 = np.asarray(actuation(jnp.zeros(())))
    if kind == "length" and np.any(a0 <= 0):
        r.fail("[actuation] initial", f"leg lengths must be > 0, got {list(a0)}")
    _check_closure(r, legs, attach, a0, p_ref, R_ref, effects.planar)
    solver = make_solver(rod, legs.lengths(_f(a0)), **read_solver(r))
    end = RigidPlatform(
        body=platform,
        attachment=_f(attach),
        clamp=_f(clamp),
        reference_position=_f(p_ref),
        reference_rotation=_f(R_ref),
        load=load,
    )
    return Scene(
        legs=legs, end=end, actuation=actuation, gravity=read_gravity(r), effects=effects, solver=solver, name=name, robot=robot
    )


_BUILDERS = {"rod": _rod_robot, "stewart_gough": _parallel_robot, "triskele": _parallel_robot}


def _check_closure(r: _Reader, legs: Legs, attachment, a0, p_ref, R_ref, planar: bool):
    """Reject geometries whose legs cannot reach the platform at its reference pose.

    Planar: the in-plane distance from base to attachment may exceed the rod length by at most
    1 % (a stretch no elastic rod takes). Otherwise the distance across the base tangent (the
    platform may still move along the legs) must be less than the length.
    """
    base = np.asarray(legs.base_positions(jnp.asarray(a0)))
    L = np.asarray(legs.lengths(jnp.asarray(a0))) * np.ones(len(a0))
    tips = p_ref + np.asarray(attachment) @ R_ref.T
    d = tips - base
    if planar:
        dist = np.linalg.norm(d, axis=1)
        bad = dist > 1.01 * L
    else:
        tangent = np.asarray(legs.base_rotation)[:, :, 2]
        dist = np.linalg.norm(d - np.sum(d * tangent, axis=1)[:, None] * tangent, axis=1)
        bad = dist >= L
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        r.fail(
            "geometry",
            f"leg {i + 1} cannot reach the platform: its attachment is {dist[i]:.4g} m from its base{'' if planar else ' across the base axis'} but the rod is {L[i]:.4g} m long",
        )


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
