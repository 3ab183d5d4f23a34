"""From a recording to a simulation: the scene it belongs to, its parameters, its planar pose.

**Parameters** (a flat dict of float64 arrays, the fit's vocabulary):

* ``tau`` (s): Kelvin-Voigt damping, shape () shared by all rods or (n,) per rod;
* ``tau_se``, ``tau_bt`` (s): the damping of stretch and shear and that of bending and twist
  apart (``bse = tau_se Kse``, ``bbt = tau_bt Kbt``), shared by the rods;
* ``lengths`` (m): rod lengths, (n,) (a rod scene: ());
* ``push_force`` (N, planar x, y) and ``push_moment`` (N m, about z): the load held until the
  release of a push-and-release (a rod scene: ``push_force`` is the tip force in the bending
  plane x, z);
* ``youngs_modulus`` (Pa): E of every rod, one value (the rods are cut from one wire); the shear
  modulus moves with it (Poisson's ratio held);
* ``platform_mass`` (kg): the platform's mass; its inertia moves with it (its shape held);
* ``frame_offset`` (m, 2), ``frame_rotation`` (rad), ``time_offset`` (s): the camera (`camera`).

`apply` writes the physical ones into a scene (``eqx.tree_at``; a rod length changes with the
attachment points held where they are, so the platform settles elsewhere); `planar_pose` is
what the camera (`camera.observe`) films of a trajectory.
"""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp

import pcrjax
from pcrjax import SceneError, scene_from_dict
from pcrjax.io.scene_file import read_toml, scene_path
from pcrjax.physics.rod import SplitTauDamping, TauDamping
from pcrjax.physics.rotations import exp_map

from .recording import Recording, RecordingError


def _scene_file(name_or_path: str, base_dir: Path) -> Path:
    """A path relative to the sidecar's folder, else whatever `pcrjax.io.scene_file.scene_path` finds."""
    p = Path(name_or_path)
    if not p.is_absolute() and (base_dir / p).is_file():
        return base_dir / p
    try:
        return scene_path(name_or_path)
    except SceneError as err:
        raise RecordingError(f"scene {name_or_path!r}: {err}") from None


def build_scene(rec: Recording, scene: str | None = None):
    """The scene of ``rec`` (or ``scene``, a name or path) with the sidecar's tables laid over it."""
    name = scene or rec.scene
    if name is None:
        raise RecordingError(f"{rec.path}: no scene: give --scene or a sidecar with scene = ...")
    path = _scene_file(name, rec.path.parent)
    data = read_toml(path, RecordingError)
    for table, values in rec.overrides.items():
        if table == "rod" and "rods" in data:
            data.pop("rods")
        data[table] = {**data.get(table, {}), **values}
    try:
        return scene_from_dict(data, str(path))
    except SceneError as e:
        raise RecordingError(f"{rec.path}: scene with the sidecar's settings: {e}") from None


def is_rod(scene) -> bool:
    return scene.robot == "rod"


def nominal(scene) -> dict:
    """The scene's own values of the physical parameters (damping must be switched on)."""
    rod = scene.legs.rod
    if not scene.effects.damping or not isinstance(rod.damping, TauDamping):
        raise RecordingError("identification of tau needs [effects] damping = true with a [rod] tau")
    # A rod scene's one leg: its parameters are scalars.
    one = (lambda a: a[0]) if is_rod(scene) else (lambda a: a)  # noqa: E731
    out = dict(tau=jnp.asarray(one(rod.damping.tau), jnp.float64), lengths=jnp.asarray(one(rod.length), jnp.float64))
    if is_rod(scene):
        out["push_force"] = scene.load.force[jnp.array([0, 2])]
    else:
        out["push_force"] = scene.load.force[:2]
        out["push_moment"] = scene.load.moment[2]
    return out


def material(scene, names) -> dict:
    """The scene's own ``youngs_modulus`` (the rods' mean) and ``platform_mass``, those of
    ``names`` asked for; a rod scene has no platform mass."""
    out = {}
    if "youngs_modulus" in names:
        out["youngs_modulus"] = jnp.mean(jnp.asarray(scene.legs.rod.youngs_modulus, jnp.float64))
    if "platform_mass" in names:
        if is_rod(scene):
            raise RecordingError("platform_mass: the scene is a single rod, it has no platform")
        out["platform_mass"] = jnp.asarray(scene.end.body.mass, jnp.float64)
    return out


def apply(scene, params: dict):
    """``scene`` with the physical entries of ``params`` written in (others ignored), as float64
    (a Python number would enter weakly typed: another compiled program)."""
    params = {k: jnp.asarray(v, jnp.float64) for k, v in params.items()}
    rod = scene.legs.rod
    if "tau" in params:
        tau = jnp.broadcast_to(params["tau"], jnp.shape(rod.damping.tau))
        scene = eqx.tree_at(lambda s: s.legs.rod.damping.tau, scene, tau)
    if "tau_se" in params:
        shape = jnp.shape(rod.damping.tau)
        split = SplitTauDamping(jnp.broadcast_to(params["tau_se"], shape), jnp.broadcast_to(params["tau_bt"], shape))
        scene = eqx.tree_at(lambda s: s.legs.rod.damping, scene, split)
    if "lengths" in params:
        scene = eqx.tree_at(lambda s: s.legs.rod.length, scene, jnp.broadcast_to(params["lengths"], jnp.shape(rod.length)))
    if "youngs_modulus" in params:
        E = jnp.broadcast_to(params["youngs_modulus"], jnp.shape(rod.youngs_modulus))
        G = rod.shear_modulus * (E / rod.youngs_modulus)
        scene = eqx.tree_at(lambda s: (s.legs.rod.youngs_modulus, s.legs.rod.shear_modulus), scene, (E, G))
    if "platform_mass" in params:
        body = scene.end.body
        m = params["platform_mass"]
        scene = eqx.tree_at(lambda s: (s.end.body.mass, s.end.body.inertia), scene, (m, body.inertia * (m / body.mass)))
    if "push_force" in params:
        f = params["push_force"]
        if is_rod(scene):
            scene = eqx.tree_at(lambda s: s.load.force, scene, jnp.stack([f[0], scene.load.force[1], f[1]]))
        else:
            scene = eqx.tree_at(lambda s: s.load.force, scene, jnp.stack([f[0], f[1], scene.load.force[2]]))
    if "push_moment" in params and not is_rod(scene):
        m = params["push_moment"]
        scene = eqx.tree_at(lambda s: s.load.moment, scene, jnp.stack([scene.load.moment[0], scene.load.moment[1], m]))
    return scene


def planar_pose(scene, traj):
    """(T, 3) = x, y, theta of the platform (z-rotation), or of a rod's tip in its x-z bending
    plane: y_cam = z and theta the angle of the tip's tangent d3 from +x towards +z (what a
    marker on the tip shows). The tip frame's rotation vector has no such component: a rod
    along x is the reference frame turned half a turn about an axis in the x-z plane."""
    if is_rod(scene):
        d3 = jax.vmap(exp_map)(traj.rotation_vector)[:, :, 2]
        return jnp.stack([traj.position[:, 0], traj.position[:, 2], jnp.arctan2(d3[:, 2], d3[:, 0])], axis=1)
    return jnp.stack([traj.position[:, 0], traj.position[:, 1], traj.rotation_vector[:, 2]], axis=1)


def _moves(scene) -> list:
    """(start, end) times (s) of each actuator move (a table: its time range; constants: none)."""
    if is_rod(scene):
        return []
    a = scene.actuation
    if a.table_t is not None:
        return [(float(a.table_t[0]), float(a.table_t[-1]))]
    return [
        (float(a.start[i]), float(a.start[i] + (a.duration[i] if k != "step" else 0.0)))
        for i, k in enumerate(a.kinds)
        if k != "constant"
    ]


def forcing_start(scene) -> float:
    """Time (s) the first actuator move starts (0 if none: the robot rests before it)."""
    return min((m[0] for m in _moves(scene)), default=0.0)


def forcing_end(scene) -> float:
    """Time (s) after which nothing drives the robot (free motion): the end of the actuators'
    moves (tables: their last time), else 0 (a push released at t = 0, or nothing)."""
    return max((m[1] for m in _moves(scene)), default=0.0)


def required_duration(rec: Recording, margin: float = 0.02) -> float:
    """Simulated seconds that cover every frame, allowing for a time offset of ``margin``."""
    return float(rec.t[-1]) + rec.exposure + margin


def with_duration(scene, duration: float):
    """``scene`` simulated for ``duration`` seconds (the recording's span), whatever it said."""
    return pcrjax.with_solver(scene, duration=duration)
