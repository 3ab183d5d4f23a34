"""`pcrjax bench stewart_gough|triskele`: cost and accuracy of the parallel robots (figures only).

For each (integrator, N, dt): wall time per step after compilation, real-time factor, compile time,
Newton iterations and Jacobians per step, and the platform error against a converged reference
(finest RK4 grid at tol 1e-12, same dt).

* Stewart-Gough, Till's settings (dt = 1/120 s, alpha = -0.2): legs 1-3 lengthen by 10 mm in a
  0.25 s smooth step, 1 s of motion. Till's C++ (6 x 200 Euler nodes): 80 ms/step on this
  machine (real-time factor 0.06); his paper reports 7-8 with three threads. Target: RTF >= 10 at
  accuracy no worse than 200 Euler nodes. ``--noise`` adds thesis Tables 4.3-4.4: the noise
  (eq. 4.15-4.17) of the unperturbed equilibrium over alpha x N x dt.
* Triskele: the shipped push-and-release scene (alpha = -0.2; the platform moves about 0.2 um,
  so the rods stay nearly straight), then an actuator move (``triskele_move``: bases slide by
  +1, -0.5, +0.25 mm in a 0.2 s smooth step, slow enough that no fibre is pushed near its 32 mN
  buckling load), which bends the rods; target real time at N = 50, dt = 1 ms.
  ``rel err`` is the position error over the reference's largest displacement.
"""

from __future__ import annotations

import dataclasses
import json
import math

import jax.numpy as jnp
import numpy as np

from .scene import load_scene, with_solver
from .simulation import simulate


def noise(position) -> float:
    p = np.asarray(position)
    rmse = np.sqrt(np.mean((p - p.mean(axis=0)) ** 2, axis=0))
    with np.errstate(divide="ignore"):
        return float(np.mean(np.log10(rmse)))


def _sg_motion(scene):
    act = scene.actuation
    final = act.initial.at[:3].add(0.01)
    moved = dataclasses.replace(act, final=final, start=jnp.full(6, 0.05), duration=jnp.full(6, 0.25), kinds=("smooth_step",) * 6)
    return dataclasses.replace(scene, actuation=moved)


def _triskele_move(scene):
    act = scene.actuation
    moved = dataclasses.replace(
        act, final=act.initial + jnp.array([1e-3, -0.5e-3, 0.25e-3]), start=jnp.full(3, 0.05), duration=jnp.full(3, 0.2), kinds=("smooth_step",) * 3
    )
    zero = jnp.zeros(3)
    return dataclasses.replace(scene, actuation=moved, load=dataclasses.replace(scene.load, force=zero, moment=zero))


def _row(label, scene, tr, tm, compile_s, ref):
    per_step = tm["run_s"] / tm["steps"]
    pos = np.asarray(tr.position)
    ref_pos = np.asarray(ref.position)
    err = float(np.max(np.linalg.norm(pos - ref_pos, axis=1)))
    amplitude = float(np.max(np.linalg.norm(ref_pos - ref_pos[0], axis=1)))
    rot = float(np.max(np.abs(np.asarray(tr.rotation_vector) - np.asarray(ref.rotation_vector))))
    return dict(
        case=label,
        integrator=scene.solver.integrator,
        nodes=scene.solver.nodes,
        dt=float(scene.solver.dt),
        alpha=float(scene.solver.alpha),
        us_per_step=per_step * 1e6,
        realtime_factor=float(scene.solver.dt) / per_step,
        compile_s=compile_s,
        newton_iterations=float(np.mean(tr.iterations)),
        jacobians_per_step=float(np.mean(tr.jacobians)),
        position_error_m=err,
        relative_error=err / amplitude if amplitude > 0 else math.nan,
        rotation_error_rad=rot,
    )


HEADER = f"{'case':<15}{'int':<6}{'N':>5}{'dt s':>10}{'us/step':>11}{'RTF':>8}{'compile s':>11}{'Newton it':>11}{'Jac/step':>10}{'pos err m':>12}{'rel err':>10}{'rot err rad':>13}"


def _print(row):
    print(
        f"{row['case']:<15}{row['integrator']:<6}{row['nodes']:>5}{row['dt']:>10.3g}{row['us_per_step']:>11.1f}{row['realtime_factor']:>8.2f}"
        f"{row['compile_s']:>11.2f}{row['newton_iterations']:>11.2f}{row['jacobians_per_step']:>10.2f}{row['position_error_m']:>12.3e}{row['relative_error']:>10.2e}{row['rotation_error_rad']:>13.3e}",
        flush=True,
    )


def _sweep(label, base, grid, dts, reference_nodes, duration):
    rows = []
    for dt in dts:
        ref = simulate(with_solver(base, nodes=reference_nodes, integrator="rk4", dt=dt, duration=duration, tol=1e-12))
        for integ, n in grid:
            scene = with_solver(base, nodes=n, integrator=integ, dt=dt, duration=duration)
            cold: dict = {}
            simulate(scene, timings=cold)  # compiles (or loads from the persistent cache)
            tm: dict = {}
            tr = simulate(scene, timings=tm)  # measured
            row = _row(label, scene, tr, tm, cold["compile_s"], ref)
            rows.append(row)
            _print(row)
    return rows


def _noise_table(nodes, duration):
    base = load_scene("stewart_gough")
    table = {}
    print("\nThesis noise (eq. 4.15-4.17) of the unperturbed Stewart-Gough equilibrium; thesis Tables 4.3-4.4: -3.5 .. -8.5; target <= -11."
          " '-inf': the platform did not move at all (RMS 0).")
    print(f"{'dt s':>8}{'alpha':>7}" + "".join(f"{'N=' + str(n):>10}" for n in nodes) + f"{'  max Newton it':>16}")
    for dt in (5e-3, 1e-2):
        for alpha in (0.0, -0.2, -0.4, -0.5):
            cells, its = [], 0
            for n in nodes:
                tr = simulate(with_solver(base, nodes=n, dt=dt, alpha=alpha, duration=duration))
                v = noise(tr.position)
                cells.append(v)
                its = max(its, int(np.max(tr.iterations)))
                table[f"dt={dt},alpha={alpha},N={n}"] = v
            print(f"{dt:>8.3g}{alpha:>7.2g}" + "".join(f"{c:>10.2f}" if math.isfinite(c) else f"{'-inf':>10}" for c in cells) + f"{its:>16}", flush=True)
    return table


def run_parallel_bench(args) -> dict:
    out: dict = {"case": args.case}
    print(HEADER, flush=True)
    if args.case == "stewart_gough":
        base = _sg_motion(load_scene("stewart_gough"))
        base = with_solver(base, alpha=-0.2)
        grid = [("rk4", int(n)) for n in str(args.nodes or "10,20,40").split(",")] + [("euler", int(n)) for n in str(args.euler_nodes or "50,100,200").split(",")]
        out["rows"] = _sweep("stewart_gough", base, grid, [1.0 / 120.0], args.reference_nodes or 80, args.duration)
        print("Till's C++ (6 x 200 Euler, dt 1/120 s, alpha -0.2): 80 ms/step, RTF 0.06 on this machine; target RTF >= 10 at the accuracy of 200 Euler nodes.")
        if args.noise:
            out["noise"] = _noise_table([int(n) for n in str(args.noise_nodes).split(",")], args.duration)
    else:
        base = load_scene("triskele")
        grid = [("rk4", int(n)) for n in str(args.nodes or "10,20,50").split(",")] + [("euler", int(n)) for n in str(args.euler_nodes or "50,200").split(",")]
        out["rows"] = _sweep("triskele", base, grid, [1e-3, 5e-4], args.reference_nodes or 100, args.duration)
        out["rows"] += _sweep("triskele_move", _triskele_move(base), grid, [1e-3], args.reference_nodes or 100, args.duration)
        print("Target: real time (RTF >= 1) at N = 50 RK4, dt = 1 ms (thesis section 4.3.2).")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return out
