"""Files a run writes: trajectory.csv, summary.json and PNG plots (DESIGN §3)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

TRAJECTORY_HEADER = ["t_s", "x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"]


def _atomic_write(path: Path, text: str):
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_trajectory(path: Path, traj, actuators: np.ndarray | None = None):
    t = np.asarray(traj.t)
    cols = [t[:, None], np.asarray(traj.position), np.asarray(traj.rotation_vector)]
    header = list(TRAJECTORY_HEADER)
    if actuators is not None:
        cols.append(actuators)
        header += [f"a{i + 1}" for i in range(actuators.shape[1])]
    data = np.concatenate(cols, axis=1)
    lines = [",".join(header)] + [",".join(f"{v:.17g}" for v in row) for row in data]
    _atomic_write(path, "\n".join(lines) + "\n")


def write_json(path: Path, obj):
    _atomic_write(path, json.dumps(obj, indent=2) + "\n")


def _rod_dict(rod) -> dict:
    f = lambda a: np.asarray(a).tolist()  # noqa: E731  (scalars, or one value per leg)
    return {
        "length_m": f(rod.length),
        "radius_m": f(rod.radius),
        "youngs_modulus_pa": f(rod.youngs_modulus),
        "shear_modulus_pa": f(rod.shear_modulus),
        "density_kg_m3": f(rod.density),
    }


def scene_settings(scene) -> dict:
    s = scene.solver
    e = scene.effects
    out = {
        "name": scene.name,
        "robot": scene.robot,
        "nodes": s.nodes,
        "integrator": s.integrator,
        "dt_s": float(s.dt),
        "alpha": float(s.alpha),
        "steps": s.steps,
        "duration_s": float(s.steps * s.dt),
        "tol": s.newton.tol,
        "shooting_segments": s.segments,
        "internal_nodes": s.grid_nodes,
        "effects": {k: getattr(e, k) for k in ("inertia", "gravity", "damping", "drag", "shear_extension")},
    }
    if hasattr(scene, "legs"):
        out["effects"]["planar"] = e.planar
        out["rods"] = _rod_dict(scene.legs.rod)
        out["legs"] = scene.legs.count
        out["actuation_kind"] = scene.legs.kind
        out["platform"] = {"mass_kg": float(scene.platform.mass), "inertia_kg_m2": np.asarray(scene.platform.inertia).tolist()}
        out["static_continuation_stages"] = s.continuation
    else:
        out["rod"] = _rod_dict(scene.rod)
    return out


def _time_series(ax, t, values, labels, ylabel):
    for v, lab in zip(values.T, labels):
        ax.plot(t, v, label=lab)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.legend()
    ax.grid(alpha=0.3)


def _path(fig, ax, t, x, y, xlabel, ylabel, title):
    """Path in a plane, coloured by time."""
    sc = ax.scatter(x, y, c=t, s=4, cmap="viridis")
    ax.plot(x, y, lw=0.5, color="0.6")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title)
    fig.colorbar(sc, ax=ax, label="t [s]")


def _save(fig, path: Path, title: str):
    import matplotlib.pyplot as plt

    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_tip(path: Path, traj, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(traj.t)
    p = np.asarray(traj.position)
    d = (p - p[0]) * 1e3
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    _time_series(ax[0], t, d, [f"{c} − {c}(0)" for c in "xyz"], "tip displacement [mm]")
    # Path in the plane of largest motion.
    i, j = sorted(np.argsort(d.std(axis=0))[::-1][:2])
    _path(fig, ax[1], t, p[:, i] * 1e3, p[:, j] * 1e3, f"{'xyz'[i]} [mm]", f"{'xyz'[j]} [mm]", "tip path")
    _save(fig, path, title)


def plot_shapes(path: Path, traj, title: str, count: int = 12):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import cm

    t = np.asarray(traj.t)
    P = np.asarray(traj.positions)
    spread = (P.reshape(-1, 3)).std(axis=0)
    i, j = sorted(np.argsort(spread)[::-1][:2])
    idx = np.unique(np.linspace(0, len(t) - 1, count).round().astype(int))
    fig, ax = plt.subplots(figsize=(7, 5))
    for k in idx:
        ax.plot(P[k, :, i] * 1e3, P[k, :, j] * 1e3, color=cm.viridis(k / max(1, len(t) - 1)), lw=1.2)
    ax.set_xlabel(f"{'xyz'[i]} [mm]")
    ax.set_ylabel(f"{'xyz'[j]} [mm]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    sm = cm.ScalarMappable(cmap="viridis", norm=matplotlib.colors.Normalize(t[0], t[-1]))
    fig.colorbar(sm, ax=ax, label="t [s]")
    ax.set_title(f"{title}: rod shapes over time")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_platform(path: Path, traj, title: str):
    """Platform position and rotation over time, and its path in the x-y plane."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(traj.t)
    p = np.asarray(traj.position)
    rv = np.asarray(traj.rotation_vector)
    d = (p - p[0]) * 1e6
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    _time_series(ax[0], t, d, [f"{c} − {c}(0)" for c in "xyz"], "platform displacement [µm]")
    _time_series(ax[1], t, (rv - rv[0]) * 1e6, [f"r{c} − r{c}(0)" for c in "xyz"], "rotation vector change [µrad]")
    _path(fig, ax[2], t, d[:, 0], d[:, 1], "x − x(0) [µm]", "y − y(0) [µm]", "platform path")
    _save(fig, path, title)


def plot_legs(path: Path, traj, title: str):
    """Leg shapes at the first and last time: top view (x-y) and side view (x-z)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = np.asarray(traj.positions)  # (T, legs, nodes, 3)
    fig, ax = plt.subplots(1, 2, figsize=(12, 5))
    for k, (style, lab) in enumerate(((":", "t = 0"), ("-", f"t = {float(np.asarray(traj.t)[-1]):.3g} s"))):
        frame = P[0] if k == 0 else P[-1]
        for i, leg in enumerate(frame):
            for a, (u, v) in zip(ax, ((0, 1), (0, 2))):
                a.plot(leg[:, u] * 1e3, leg[:, v] * 1e3, style, color=f"C{i}", lw=1.4, label=f"leg {i + 1}, {lab}" if a is ax[0] else None)
    for a, (u, v) in zip(ax, (("x", "y"), ("x", "z"))):
        a.set_xlabel(f"{u} [mm]")
        a.set_ylabel(f"{v} [mm]")
        a.set_aspect("equal", adjustable="datalim")
        a.grid(alpha=0.3)
    ax[0].set_title("top view")
    ax[1].set_title("side view")
    ax[0].legend(fontsize=7, ncol=2)
    _save(fig, path, f"{title}: legs")
