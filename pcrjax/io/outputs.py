"""Files a run writes: trajectory.csv, summary.json and PNG plots."""

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


def write_trajectory(path: Path, traj):
    """``t_s``, the end's position and rotation vector, then one column per actuator (``a1``...)."""
    t = np.asarray(traj.t)
    actuators = np.asarray(traj.actuators)
    cols = [t[:, None], np.asarray(traj.position), np.asarray(traj.rotation_vector), actuators]
    header = list(TRAJECTORY_HEADER) + [f"a{i + 1}" for i in range(actuators.shape[1])]
    write_columns(path, header, np.concatenate(cols, axis=1))


def write_columns(path: Path, header, data):
    """A CSV file: ``header`` names, then the rows of ``data`` at full precision."""
    lines = [",".join(header)] + [",".join(f"{v:.17g}" for v in row) for row in np.asarray(data)]
    _atomic_write(path, "\n".join(lines) + "\n")


def write_inverse(out: Path, traj, actuator_forces):
    """``actuators.csv`` (``t_s,a1..an``: usable as ``[actuation] file``) and ``wrenches.csv``
    (``t_s``, per leg i its base force ``n{i}_x_N..`` and moment ``m{i}_x_Nm..``, then the
    actuator forces ``f1_N..``: the base force along each leg's axis, positive pulling)."""
    t = np.asarray(traj.t)[:, None]
    a = np.asarray(traj.actuators)
    write_columns(out / "actuators.csv", ["t_s"] + [f"a{i + 1}" for i in range(a.shape[1])], np.concatenate([t, a], axis=1))
    w = np.asarray(traj.base_wrenches)  # (T, legs, 2, 3)
    header = ["t_s"]
    for i in range(w.shape[1]):
        header += [f"n{i + 1}_{c}_N" for c in "xyz"] + [f"m{i + 1}_{c}_Nm" for c in "xyz"]
    header += [f"f{i + 1}_N" for i in range(w.shape[1])]
    write_columns(out / "wrenches.csv", header, np.concatenate([t, w.reshape(len(t), -1), np.asarray(actuator_forces)], axis=1))


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
        "tol": float(s.newton.tol),
        "shooting_segments": s.segments,
        "internal_nodes": s.grid_nodes,
        "effects": {k: getattr(e, k) for k in ("inertia", "gravity", "damping", "drag", "shear_extension", "planar")},
        "rods": _rod_dict(scene.legs.rod),
        "legs": scene.legs.count,
        "base_kind": scene.legs.kind,
        "end": scene.end.describe(),
        "static_continuation_stages": s.continuation,
    }
    return out


def _scale(values) -> tuple[float, str]:
    """Factor and unit (m, mm or um) that show ``values`` (m) with a few significant digits."""
    span = float(np.max(np.abs(values))) if np.size(values) else 0.0
    for factor, unit in ((1.0, "m"), (1e3, "mm"), (1e6, "µm")):
        if span * factor >= 0.5:
            return factor, unit
    return 1e9, "nm"


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


def plot_end(path: Path, traj, title: str, label: str):
    """Position and rotation of the end (``label``: tip or platform) over time, and its path in the
    plane of largest motion, in units that fit the motion."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(traj.t)
    p = np.asarray(traj.position)
    rv = np.asarray(traj.rotation_vector)
    d = p - p[0]
    f, unit = _scale(d)
    fr, runit = _scale(rv - rv[0])
    runit = {"m": "rad", "mm": "mrad", "µm": "µrad", "nm": "nrad"}[runit]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    _time_series(ax[0], t, d * f, [f"{c} − {c}(0)" for c in "xyz"], f"{label} displacement [{unit}]")
    _time_series(ax[1], t, (rv - rv[0]) * fr, [f"r{c} − r{c}(0)" for c in "xyz"], f"rotation vector change [{runit}]")
    i, j = sorted(np.argsort(d.std(axis=0))[::-1][:2])
    _path(
        fig,
        ax[2],
        t,
        d[:, i] * f,
        d[:, j] * f,
        f"{'xyz'[i]} − {'xyz'[i]}(0) [{unit}]",
        f"{'xyz'[j]} − {'xyz'[j]}(0) [{unit}]",
        f"{label} path",
    )
    _save(fig, path, title)


def plot_shapes(path: Path, traj, title: str, count: int = 12):
    """Every leg's shape at ``count`` times (coloured by time) in the plane of largest extent."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import cm

    t = np.asarray(traj.t)
    P = np.asarray(traj.positions)  # (T, legs, nodes, 3)
    i, j = sorted(np.argsort(P.reshape(-1, 3).std(axis=0))[::-1][:2])
    f, unit = _scale(P)
    idx = np.unique(np.linspace(0, len(t) - 1, count).round().astype(int))
    fig, ax = plt.subplots(figsize=(7, 5))
    for k in idx:
        for leg in P[k]:
            ax.plot(leg[:, i] * f, leg[:, j] * f, color=cm.viridis(k / max(1, len(t) - 1)), lw=1.2)
    ax.set_xlabel(f"{'xyz'[i]} [{unit}]")
    ax.set_ylabel(f"{'xyz'[j]} [{unit}]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    sm = cm.ScalarMappable(cmap="viridis", norm=matplotlib.colors.Normalize(t[0], t[-1]))
    fig.colorbar(sm, ax=ax, label="t [s]")
    ax.set_title(f"{title}: rod shapes over time")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_inverse(path: Path, t, wanted, replayed, actuators, error, title: str, got: str = "forward replay"):
    """Inverse dynamics at a glance (as thesis Fig. 4.10-4.11): the prescribed path and its
    forward replay (or the run named ``got``) in the plane of largest motion; the actuator
    values; each coordinate prescribed and replayed over time with the replay's position error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, wanted, replayed, actuators, error = map(np.asarray, (t, wanted, replayed, actuators, error))
    d = wanted - wanted[0]
    f, unit = _scale(d)
    i, j = sorted(np.argsort(d.std(axis=0))[::-1][:2])
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.5))
    ax[0].plot(d[:, i] * f, d[:, j] * f, lw=2.5, color="tab:blue", label="prescribed (inverse)")
    r = (replayed - wanted[0]) * f
    ax[0].plot(r[:, i], r[:, j], lw=1, ls="--", color="tab:red", label=got)
    ax[0].set_xlabel(f"{'xyz'[i]} − {'xyz'[i]}(0) [{unit}]")
    ax[0].set_ylabel(f"{'xyz'[j]} − {'xyz'[j]}(0) [{unit}]")
    ax[0].set_aspect("equal", adjustable="datalim")
    ax[0].legend()
    ax[0].grid(alpha=0.3)
    ax[0].set_title("platform path")
    fa, aunit = _scale(actuators - actuators[0])
    _time_series(
        ax[1],
        t,
        (actuators - actuators[0]) * fa,
        [f"a{k + 1} − a{k + 1}(0)" for k in range(actuators.shape[1])],
        f"actuators [{aunit}]",
    )
    ax[1].set_title("actuator trajectories")
    for k, c in ((i, "tab:blue"), (j, "tab:orange")):
        ax[2].plot(t, d[:, k] * f, color=c, lw=2.5, label=f"{'xyz'[k]} prescribed")
        ax[2].plot(t, (replayed[:, k] - wanted[0, k]) * f, color="k", lw=0.8, ls="--", label=f"{'xyz'[k]}, {got}")
    ax[2].set_xlabel("t [s]")
    ax[2].set_ylabel(f"displacement [{unit}]")
    ax[2].grid(alpha=0.3)
    ax[2].legend(loc="upper left")
    tw = ax[2].twinx()  # log scale: the error is at the solver's tolerance when all is well
    tw.semilogy(t, np.maximum(error, 1e-18), color="tab:green", lw=1)
    tw.set_ylabel(f"position error of the {got} [m]", color="tab:green")
    ax[2].set_title(f"prescribed vs {got}")
    _save(fig, path, title)


def plot_design(path: Path, runs: dict, move, title: str):
    """A designed move against the plain one: the platform's distance to the target over time
    (log scale, on the design's grid and the finer check), and the actuator values."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(13, 4.5))
    styles = {"plain": "tab:red", "designed": "tab:blue"}
    for (label, grid), traj in runs.items():
        t = np.asarray(traj.t)
        err = np.linalg.norm(np.asarray(traj.position) - np.asarray(move.p1), axis=1)
        ax[0].semilogy(t * 1e3, np.maximum(err, 1e-15), color=styles[label], ls="-" if grid == "same_grid" else "--",
                       label=f"{label}, {grid.replace('_', ' ')}")  # fmt: skip
    ax[0].axvline(move.duration * 1e3, color="0.5", lw=0.8)
    ax[0].axhline(1e-6, color="0.5", lw=0.8, ls=":")
    ax[0].set_xlabel("t [ms]")
    ax[0].set_ylabel("distance to target [m]")
    ax[0].legend()
    ax[0].grid(alpha=0.3)
    ax[0].set_title("platform: residual vibration after the move (dotted: 1 µm)")
    for label in ("plain", "designed"):
        traj = runs.get((label, "same_grid"))
        if traj is None:
            continue
        a = np.asarray(traj.actuators) - np.asarray(traj.actuators)[0]
        f, unit = _scale(a)
        for i in range(a.shape[1]):
            ax[1].plot(np.asarray(traj.t) * 1e3, a[:, i] * f, color=f"C{i}", ls="-" if label == "designed" else ":",
                       label=f"a{i + 1} {label}")  # fmt: skip
    ax[1].set_xlabel("t [ms]")
    ax[1].set_ylabel(f"actuator − rest [{unit}]")
    ax[1].legend(ncol=2, fontsize=8)
    ax[1].grid(alpha=0.3)
    ax[1].set_title("actuator trajectories")
    _save(fig, path, title)


def _axis_label(name: str, values) -> tuple[float, str]:
    """Scale and label of a sweep column: lengths in a unit that fits them, others as named."""
    if name.endswith("_m"):
        f, unit = _scale(values[np.isfinite(values)] if np.any(np.isfinite(values)) else np.zeros(1))
        return f, f"{name[:-2]} [{unit}]"
    for suffix, unit in (("_s", "s"), ("_hz", "Hz"), ("_rad", "rad")):
        if name.endswith(suffix):
            return 1.0, f"{name[: -len(suffix)]} [{unit}]"
    return 1.0, name


def _log_axis(values) -> bool:
    v = np.asarray(values, float)
    return bool(np.all(v > 0) and v.max() / v.min() > 20)


def plot_sweep(path: Path, sw):
    """Each chosen output against each varied key (failed members as red crosses), or, for a
    full grid of two keys, a map of each output over the grid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wanted = ("peak_m", "settling_s", "frequency_hz", "newton_iterations")
    shown = [k for k in wanted if k in sw.outputs] or ["x_m", "y_m", "z_m", "newton_iterations"]
    bad = ~sw.converged
    keys = list(sw.keys)
    if sw.grid_shape is not None and len(keys) == 2 and min(sw.grid_shape) > 1:
        fig, axes = plt.subplots(1, len(shown), figsize=(4.2 * len(shown), 3.6), squeeze=False)
        x = sw.values[:, 0].reshape(sw.grid_shape)[:, 0]
        y = sw.values[:, 1].reshape(sw.grid_shape)[0, :]
        for ax, name in zip(axes[0], shown, strict=True):
            f, label = _axis_label(name, sw.outputs[name])
            z = (sw.outputs[name] * f).reshape(sw.grid_shape)
            mesh = ax.pcolormesh(x, y, z.T, shading="nearest", cmap="viridis")
            fig.colorbar(mesh, ax=ax, label=label)
            ax.plot(sw.values[bad, 0], sw.values[bad, 1], "rx", label="not converged")
            ax.set_xlabel(keys[0])
            ax.set_ylabel(keys[1])
            ax.set_xscale("log" if _log_axis(x) else "linear")
            ax.set_yscale("log" if _log_axis(y) else "linear")
    else:
        fig, axes = plt.subplots(len(shown), len(keys), figsize=(4.2 * len(keys), 2.6 * len(shown)), squeeze=False)
        for i, name in enumerate(shown):
            f, label = _axis_label(name, sw.outputs[name])
            for j, key in enumerate(keys):
                ax = axes[i, j]
                order = np.argsort(sw.values[:, j], kind="stable")
                v, out, b = sw.values[order, j], sw.outputs[name][order] * f, bad[order]
                ax.plot(v[~b], out[~b], "o-" if len(keys) == 1 else "o", ms=3, lw=0.8)
                ax.plot(v[b], np.where(np.isfinite(out[b]), out[b], np.nanmin(out) if np.any(np.isfinite(out)) else 0.0), "rx")
                ax.set_xscale("log" if _log_axis(v) else "linear")
                ax.set_xlabel(key)
                ax.set_ylabel(label)
                ax.grid(alpha=0.3)
    _save(fig, path, f"{sw.scene}: sweep of {len(sw.values)} members ({int(bad.sum())} not converged)")


def plot_pareto(path: Path, rows, title: str):
    """Relative error against wall seconds per simulated second, one marker per family, the
    Pareto front as a line and the scene's own (thesis) setting as a star."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    families = list(dict.fromkeys(r["family"] for r in rows))
    marks = "osD^v<>ph"
    for i, fam in enumerate(families):
        rs = [r for r in rows if r["family"] == fam and not r["thesis"]]
        if rs:
            ax.plot(
                [r["wall_per_sim_s"] for r in rs], [r["error"] for r in rs], marks[i % len(marks)], ms=6, alpha=0.8, label=fam
            )
            for r in rs:
                ax.annotate(r["label"], (r["wall_per_sim_s"], r["error"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    front = sorted((r for r in rows if r["pareto"]), key=lambda r: r["wall_per_sim_s"])
    ax.plot([r["wall_per_sim_s"] for r in front], [r["error"] for r in front], "k-", lw=1, label="Pareto front")
    for r in rows:
        if r["thesis"]:
            ax.plot(r["wall_per_sim_s"], r["error"], "r*", ms=14, label=r["label"])
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per simulated second [s] (after compilation)")
    ax.set_ylabel("max position error / largest displacement")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    _save(fig, path, title)
