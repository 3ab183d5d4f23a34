"""TOML form of the parallel robots (DESIGN §2-§3): Stewart-Gough and Triskele-bot geometry.

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
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .platform import Platform
from .robot import Legs, ParallelScene
from .rod import Effects
from .scene import _SCHEMA, SceneError, _f, _Reader, make_rod, make_solver, read_effects, read_gravity, read_solver, rod_values
from .signals import KINDS, LOAD_COLUMNS, Actuation, PlatformLoad, TableError, read_table

SG_DEFAULTS = dict(
    base_radius=0.087,
    platform_radius=0.087,
    base_angles=[-10.0, 10.0, 110.0, 130.0, 230.0, 250.0],
    platform_angles=[-50.0, 50.0, 70.0, 170.0, 190.0, 290.0],
)
TRISKELE_DEFAULTS = dict(actuator_radius=0.080, gamma=[-30.0, 210.0, 90.0], phi=[140.0, 20.0, -100.0], clamp_angles=[130.0, 10.0, -110.0])


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
    )


def _per_leg(r, t, key, n, default):
    v = t.get(key, default)
    if isinstance(v, list):
        return r.numbers(t, "actuation", key, n)
    return np.full(n, r.number(t, "actuation", key, default))


def _load(r: _Reader, base_dir: Path) -> PlatformLoad:
    t = r.table("load")
    table_t = table_w = None
    if "file" in t:
        if not isinstance(t["file"], str):
            r.fail("[load] file", "must be a path string")
        try:
            table_t, table_w = read_table(base_dir / t["file"], LOAD_COLUMNS)
        except TableError as e:
            raise SceneError(f"{r.source}: [load] file: {e}") from None
    return PlatformLoad(
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


def parallel_scene(r: _Reader, robot: str, name: str) -> ParallelScene:
    effects = read_effects(r, planar=robot == "triskele")
    if "rod" not in r.data:
        r.fail("[rod]", "missing required table")
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
            ok = isinstance(att, list) and len(att) == n and all(
                isinstance(p, list) and len(p) == 2 and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in p) for p in att
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
    legs = Legs(rod=rod, base_position=_f(base_pos), base_rotation=_f(base_R), attachment=_f(attach), clamp=_f(clamp), kind=kind)
    a0 = np.asarray(actuation(jnp.zeros(())))
    if kind == "length" and np.any(a0 <= 0):
        r.fail("[actuation] initial", f"leg lengths must be > 0, got {list(a0)}")
    _check_closure(r, legs, a0, p_ref, R_ref, effects.planar)
    solver_args = read_solver(r)
    sized = rod if kind == "prismatic" else _with_lengths(rod, a0)
    solver = make_solver(sized, **solver_args)
    return ParallelScene(
        legs=legs,
        platform=platform,
        reference_position=_f(p_ref),
        reference_rotation=_f(R_ref),
        actuation=actuation,
        load=load,
        gravity=read_gravity(r),
        effects=effects,
        solver=solver,
        name=name,
        robot=robot,
    )


def _with_lengths(rod, lengths):
    return dataclasses.replace(rod, length=_f(lengths))


def _check_closure(r: _Reader, legs: Legs, a0, p_ref, R_ref, planar: bool):
    """Reject geometries whose legs cannot reach the platform at its reference pose.

    Planar: the in-plane distance from base to attachment may exceed the rod length by at most
    1 % (a stretch no elastic rod takes). Otherwise the distance across the base tangent (the
    platform may still move along the legs) must be less than the length.
    """
    base = np.asarray(legs.base_positions(jnp.asarray(a0)))
    L = np.asarray(legs.lengths(jnp.asarray(a0))) * np.ones(len(a0))
    tips = p_ref + np.asarray(legs.attachment) @ R_ref.T
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
        r.fail("geometry", f"leg {i + 1} cannot reach the platform: its attachment is {dist[i]:.4g} m from its base{'' if planar else ' across the base axis'} but the rod is {L[i]:.4g} m long")
