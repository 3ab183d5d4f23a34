"""`pcrjax bench cantilever|stewart_gough|triskele|inverse|design`: the cost of accuracy (figures, never assertions).

For each case, dt and (integrator, N): wall time per step after compilation, real-time factor
(simulated over wall seconds), compile time (cold, or a load from the persistent cache), Newton
iterations and Jacobians per step, the end's position error against a converged reference (max
over time; ``rel err``: over the reference's largest displacement), the internal grid
(nodes x shooting segments) and the XLA:CPU kernels one RK4/Euler node step runs
(`kernels.node_step_kernels`) and one residual runs (that times the scan's length: N, or N/M for
M equal segments side by side): on this backend each kernel costs a fixed overhead, so this count
is the lever on per-step time. ``--noise`` (Stewart-Gough) adds thesis Tables 4.3-4.4; ``--gradient`` the cost of a reverse-mode
gradient through a rollout (`gradient.py`); ``inverse`` times inverse dynamics (`inverse.py`), ``design`` trajectory design (`design.py`),
``batch`` batched rollouts against a loop of single runs (`batch.py`).
"""

from __future__ import annotations

import json
import math

import numpy as np

from ..errors import SceneError
from ..io.scene_file import load_scene, with_solver
from ..simulation import simulate
from .cases import cases
from .gradient import gradient_cost, print_gradient_cost
from .kernels import node_step_kernels

HEADER = (
    f"{'case':<15}{'int':<6}{'N':>5}{'dt s':>10}{'us/step':>11}{'RTF':>8}{'compile s':>11}{'Newton it':>11}{'Jac/step':>10}"
    f"{'pos err m':>12}{'rel err':>10}{'rot err rad':>13}{'grid':>9}{'kern/node':>11}{'kern/resid':>11}"
)


def scan_steps(solver) -> int:
    """Node steps of one residual's scan: the internal grid, or one segment of it where the
    segments are equal (they run side by side)."""
    n, m = solver.grid_nodes, solver.segments
    return n // m if n % m == 0 else n


def noise(position) -> float:
    p = np.asarray(position)
    rmse = np.sqrt(np.mean((p - p.mean(axis=0)) ** 2, axis=0))
    with np.errstate(divide="ignore"):
        return float(np.mean(np.log10(rmse)))


def _row(label, scene, tr, tm, compile_s, ref, kernels):
    per_step = tm["run_s"] / tm["steps"]
    pos = np.asarray(tr.position)
    ref_pos = np.asarray(ref.position)
    err = float(np.max(np.linalg.norm(pos - ref_pos, axis=1)))
    amplitude = float(np.max(np.linalg.norm(ref_pos - ref_pos[0], axis=1)))
    rot = float(np.max(np.abs(np.asarray(tr.rotation_vector) - np.asarray(ref.rotation_vector))))
    s = scene.solver
    return dict(
        case=label,
        integrator=s.integrator,
        nodes=s.nodes,
        dt=float(s.dt),
        alpha=float(s.alpha),
        us_per_step=per_step * 1e6,
        realtime_factor=float(s.dt) / per_step,
        compile_s=compile_s,
        newton_iterations=float(np.mean(tr.iterations)),
        jacobians_per_step=float(np.mean(tr.jacobians)),
        position_error_m=err,
        relative_error=err / amplitude if amplitude > 0 else math.nan,
        rotation_error_rad=rot,
        internal_nodes=s.grid_nodes,
        segments=s.segments,
        kernels_per_node_step=kernels,
        kernels_per_residual=kernels * scan_steps(s),
        tol=float(s.newton.tol),
    )


def _print(row):
    grid = f"{row['internal_nodes']}x{row['segments']}"
    print(
        f"{row['case']:<15}{row['integrator']:<6}{row['nodes']:>5}{row['dt']:>10.3g}{row['us_per_step']:>11.1f}{row['realtime_factor']:>8.2f}"
        f"{row['compile_s']:>11.2f}{row['newton_iterations']:>11.2f}{row['jacobians_per_step']:>10.2f}{row['position_error_m']:>12.3e}"
        f"{row['relative_error']:>10.2e}{row['rotation_error_rad']:>13.3e}{grid:>9}{row['kernels_per_node_step']:>11}"
        f"{row['kernels_per_residual']:>11}",
        flush=True,
    )


def _sweep(case, duration, tol):
    rows = []
    for dt in case.dts:
        ref = simulate(with_solver(case.scene, nodes=case.reference_nodes, integrator="rk4", dt=dt, duration=duration, tol=1e-12))
        for integ, n in case.grid:
            scene = with_solver(case.scene, nodes=n, integrator=integ, dt=dt, duration=duration, tol=tol)
            cold: dict = {}
            simulate(scene, timings=cold)  # compiles (or loads from the persistent cache)
            tm: dict = {}
            tr = simulate(scene, timings=tm)  # measured
            row = _row(case.label, scene, tr, tm, cold["compile_s"], ref, node_step_kernels(scene))
            rows.append(row)
            _print(row)
    if case.note:
        print(case.note)
    return rows


def _noise_table(nodes, duration):
    base = load_scene("stewart_gough")
    table = {}
    print(
        "\nThesis noise (eq. 4.15-4.17) of the unperturbed Stewart-Gough equilibrium; thesis Tables 4.3-4.4: -3.5 .. -8.5; target <= -11."
        " '-inf': the platform did not move at all (RMS 0)."
    )
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
            print(
                f"{dt:>8.3g}{alpha:>7.2g}"
                + "".join(f"{c:>10.2f}" if math.isfinite(c) else f"{'-inf':>10}" for c in cells)
                + f"{its:>16}",
                flush=True,
            )
    return table


def run_bench(args) -> dict:
    """Print (and with ``--json`` write) the benchmark of ``args.case``."""
    out: dict = {"case": args.case, "rows": []}
    if args.case in ("inverse", "design", "batch"):
        if args.case == "batch":
            from .batch import bench_batch

            try:
                sizes = [int(b) for b in args.batches.split(",")]
                nodes = int(args.nodes or 20)
            except ValueError:
                raise SceneError("bench batch: --batches takes integers (1,8,64) and --nodes one integer") from None
            out["rows"] = bench_batch(sizes, nodes, args.gradient_steps)
        elif args.case == "inverse":
            from .inverse import bench_inverse

            out["rows"] = bench_inverse(args.nodes, args.duration)
        else:
            from .design import bench_design

            out.update(bench_design(horizons=[int(h) for h in args.horizons.split(",")]))
        if args.json:
            with open(args.json, "w") as f:
                json.dump(out, f, indent=2)
        return out
    todo = cases(args.case, args.nodes, args.euler_nodes, args.reference_nodes)
    if not args.gradient_only:
        print(HEADER, flush=True)
        for case in todo:
            out["rows"] += _sweep(case, args.duration, args.tol)
        print(
            f"Newton tol {args.tol:g} (scaled max-norm); reference: finest RK4, tol 1e-12, same dt; 'grid': nodes x shooting segments."
        )
    if args.gradient or args.gradient_only:
        out["gradient"] = gradient_cost(todo[-1].scene, args.gradient_nodes, args.gradient_steps)
        print_gradient_cost(out["gradient"])
    if args.noise and args.case == "stewart_gough":
        out["noise"] = _noise_table([int(n) for n in str(args.noise_nodes).split(",")], args.duration)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return out
