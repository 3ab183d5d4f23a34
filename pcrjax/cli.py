"""Command line: ``pcrjax simulate|static|inverse|design|sweep|bench|scenes``.

User errors (bad file, unknown key, non-physical value, no convergence) print one line naming
the cause and exit with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .errors import ConvergenceError, SceneError

EXIT_USER_ERROR = 2


def _solver_overrides(args) -> dict:
    """The [solver] settings given on the command line (`_add_solver_overrides`)."""
    return {
        k: getattr(args, k)
        for k in ("nodes", "integrator", "dt", "alpha", "duration", "tol")
        if getattr(args, k, None) is not None
    }


def _scene(args):
    from .io.scene_file import load_scene, with_solver

    scene = load_scene(args.scene)
    changes = _solver_overrides(args)
    return with_solver(scene, **changes) if changes else scene


def cmd_static(args) -> int:
    from .simulation import solve_static, static_failure

    scene = _scene(args)
    res = solve_static(scene, throw=False)
    out = {
        "position": np.asarray(res.position).tolist(),
        "rotation_vector": np.asarray(res.rotation_vector).tolist(),
        "base_wrenches": np.asarray(res.base_wrenches).tolist(),
        "residual_norm": float(res.residual_norm),
        "newton_iterations": int(res.newton_iterations),
    }
    print(json.dumps(out, indent=2))
    if not bool(res.converged):
        raise static_failure(scene, res)
    return 0


def cmd_simulate(args) -> int:
    from .errors import ConvergenceError
    from .io import outputs
    from .simulation import simulate

    scene = _scene(args)
    out = _out_dir(args.out)
    timings: dict = {}
    failure = None
    t0 = time.perf_counter()
    try:
        traj = simulate(scene, progress=not args.quiet and sys.stderr.isatty(), timings=timings)
    except ConvergenceError as e:
        failure = e
        traj = e.partial
    summary = {
        "settings": outputs.scene_settings(scene),
        "compile_s": timings.get("compile_s"),
        "wall_s": timings.get("run_s"),
        "total_s": time.perf_counter() - t0,
        "converged": failure is None,
    }
    if traj is not None:
        it = np.asarray(traj.iterations)
        summary.update(
            steps_done=int(len(it)),
            realtime_factor=(len(it) * float(scene.solver.dt) / timings["run_s"]) if timings.get("run_s") else None,
            wall_per_step_us=(timings["run_s"] / max(1, len(it)) * 1e6) if timings.get("run_s") else None,
            newton_iterations_mean=float(it.mean()) if len(it) else 0.0,
            newton_iterations=it.tolist(),
            residuals=np.asarray(traj.residual).tolist(),
        )
        outputs.write_trajectory(out / "trajectory.csv", traj)
        summary["energy_j"] = {"initial": float(traj.energy[0]), "final": float(traj.energy[-1])}
        if len(traj.t) > 1:
            label, path_png, shapes_png = scene.end.plots
            outputs.plot_end(out / path_png, traj, scene.name, label)
            outputs.plot_shapes(out / shapes_png, traj, scene.name)
    if failure is not None:
        summary["failure"] = {"message": str(failure), "time_s": failure.time, "residual": failure.residual}
    outputs.write_json(out / "summary.json", summary)
    if failure is not None:
        raise failure
    if not args.quiet:
        print(
            f"{scene.name}: {summary['steps_done']} steps in {summary['wall_s']:.3f} s after {summary['compile_s']:.1f} s compile "
            f"(real-time factor {summary['realtime_factor']:.2f}, {summary['newton_iterations_mean']:.2f} Newton iterations/step); wrote {out}/"
        )
    return 0


def cmd_sweep(args) -> int:
    from .io.scene_file import read_toml, scene_path
    from .sweeps import sweep, write

    path = scene_path(args.scene)
    data = read_toml(path)
    data.setdefault("solver", {}).update(_solver_overrides(args))
    vary = {}
    for item in args.vary:
        key, sep, spec = item.partition("=")
        if not sep or not key.strip() or not spec.strip():
            raise SceneError(f"--vary {item!r}: write KEY=a:b:n, KEY=a:b:n:log or KEY=v1,v2,...")
        if key.strip() in vary:
            raise SceneError(f"--vary {key.strip()}: given twice")
        vary[key.strip()] = spec.strip()
    out = _out_dir(args.out)
    sw = sweep(
        data,
        vary,
        samples=args.samples,
        seed=args.seed,
        batch=args.batch,
        progress=not args.quiet,
        source=str(path),
        cluster=args.cluster,
        memory=args.memory,
    )
    failed = write(out, sw)
    if not args.quiet:
        t = sw.timings
        which = f" (members {', '.join(map(str, failed[:10]))}{' ...' if len(failed) > 10 else ''})" if failed else ""
        print(
            f"{sw.scene}: {len(sw.values)} members in {t['run_s']:.1f} s after {t['compile_s']:.1f} s compile "
            f"({t['programs']} program(s), batch {'/'.join(map(str, t['batch_sizes']))}); {len(failed)} did not converge{which}; wrote {out}/"
        )
    return 0


def cmd_pareto(args) -> int:
    from .io.scene_file import load_scene, with_solver
    from .pareto import run_pareto, write

    scene = load_scene(args.scene)
    if args.duration is not None:
        scene = with_solver(scene, duration=args.duration)
    if args.target_error is not None and not args.target_error > 0:
        raise SceneError(f"--target-error must be > 0, got {args.target_error}")
    out = _out_dir(args.out)
    say = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    families = [f.strip() for f in args.families.split(",") if f.strip()] if args.families else None
    rows, ref = run_pareto(scene, quick=args.quick, families=families, reference_nodes=args.reference_nodes, progress=say)
    best = write(out, scene.name, rows, ref, args.target_error)
    if not args.quiet:
        print(f"{'setting':<34}{'error':>11}{'wall s/sim s':>14}{'compile s':>11}{'front':>7}")
        for r in rows:
            err = f"{r['error']:.2e}" if r["resolved"] else f"<{ref.floor:.1e}"
            print(f"{r['label']:<34}{err:>11}{r['wall_per_sim_s']:>14.3g}{r['compile_s']:>11.1f}{'*' if r['pareto'] else '':>7}")
        how = (
            f"extrapolation changed it by {ref.extrapolation_change:.1e} (remainder {ref.remainder:.1e})"
            if ref.extrapolated
            else f"the finest run (the extrapolation's remainder {ref.remainder:.1e} exceeds its last halving's change "
            f"{ref.last_change:.1e})"
        )
        print(
            f"reference: RK4 N {ref.nodes}, dt {ref.dt:g}, observed order {ref.observed_order:.2f}, {how}, N/2 differs by "
            f"{ref.spatial_change:.1e} (relative); errors below {ref.floor:.1e} are not resolved"
        )
    if args.target_error is not None:
        if best is None and args.target_error < ref.floor:
            print(f"error {args.target_error:g} is below what the reference resolves ({ref.floor:.1e}): refine the reference")
        elif best is None:
            print(f"no setting reaches error {args.target_error:g}; the finest reaches {min(r['error'] for r in rows):.2e}")
        else:
            print(
                f"cheapest setting with error <= {args.target_error:g}: {best['label']} ({best['family']}), error "
                f"{best['error']:.2e}, {best['wall_per_sim_s']:.3g} wall s per simulated s"
            )
    return 0


def cmd_scenes(args) -> int:
    from .io.scene_file import shipped_scenes

    print("\n".join(shipped_scenes()))
    return 0


def cmd_bench(args) -> int:
    from .bench.run import run_bench

    run_bench(args)
    return 0


def _path_arg(args, scene):
    """The `PosePath` of ``--path`` and the scene lasting as long as the path (or ``--duration``)."""
    from .io.scene_file import with_solver
    from .io.tables import TableError, read_path
    from .robots.signals import PosePath

    if args.path is None:
        raise SceneError(f"--goal {args.goal} needs --path PATH.csv")
    try:
        t_path, values = read_path(args.path, scene.effects.planar)
    except TableError as e:
        raise SceneError(f"--path: {e}") from None
    if t_path[0] > 0.0:
        raise SceneError(
            f"--path: {args.path}: the path starts at t = {t_path[0]} s; it must start at t = 0 (the robot's rest pose)"
        )
    if args.duration is None:
        scene = with_solver(scene, duration=float(t_path[-1]))
    elif args.duration > t_path[-1] + 1e-12:
        raise SceneError(f"--duration {args.duration} s is longer than the path ({t_path[-1]} s)")
    return scene, PosePath.from_samples(t_path, values)


def cmd_inverse(args) -> int:
    from .io import outputs
    from .replay import path_errors, replay
    from .robots.inverse import check_square
    from .robots.limits import feasibility
    from .simulation import inverse_dynamics

    scene = _scene(args)
    check_square(scene)
    scene, path = _path_arg(args, scene)
    out = _out_dir(args.out)
    progress = not args.quiet and sys.stderr.isatty()
    timings: dict = {}
    summary = {"settings": outputs.scene_settings(scene), "path_file": str(args.path)}
    try:
        traj = inverse_dynamics(scene, path, progress=progress, timings=timings)
    except ConvergenceError as e:
        summary["failure"] = {"message": f"inverse dynamics: {e}", "time_s": e.time, "residual": e.residual}
        if e.partial is not None:
            outputs.write_inverse(out, e.partial, _actuator_forces(scene, e.partial))
        outputs.write_json(out / "summary.json", summary)
        raise ConvergenceError(
            f"inverse dynamics: {e} (the path may leave the workspace there)", e.time, e.residual, e.reason
        ) from None
    forces = _actuator_forces(scene, traj)
    outputs.write_inverse(out, traj, forces)
    it = np.asarray(traj.iterations)
    summary.update(
        compile_s=timings["compile_s"],
        wall_s=timings["run_s"],
        realtime_factor=len(it) * float(scene.solver.dt) / timings["run_s"],
        newton_iterations_mean=float(it.mean()),
        feasibility=feasibility(scene, traj.t, traj.actuators, traj.base_wrenches),
    )
    fwd_timings: dict = {}
    try:
        fwd = replay(scene, traj, progress=progress, timings=fwd_timings)
        err = path_errors(path, fwd)
        summary["replay"] = {k: v for k, v in err.items() if not isinstance(v, np.ndarray)}
        planar = scene.effects.planar
        wanted = np.asarray(traj.position)
        outputs.write_trajectory(out / "replay.csv", fwd)
        outputs.plot_inverse(
            out / "inverse.png", traj.t, wanted[:, :2] if planar else wanted, np.asarray(fwd.position)[:, : 2 if planar else 3],
            traj.actuators, err["position_m"], f"{scene.name}: inverse dynamics and forward replay",
        )  # fmt: skip
    except ConvergenceError as e:
        summary["replay"] = {"failure": f"forward replay: {e}"}
    outputs.write_json(out / "summary.json", summary)
    if not args.quiet:
        rep = summary["replay"]
        check = (
            f"replay error {rep['max_position_error_m']:.3g} m ({rep['relative_error']:.2g} of the motion)"
            if "failure" not in rep
            else rep["failure"]
        )
        feas = summary["feasibility"]
        limits = (
            "within limits"
            if feas["feasible"]
            else "LIMITS EXCEEDED: "
            + "; ".join(
                f"{v['what']} ({v['worst']:.3g} vs {v['limit']})"
                for v in feas["violations"]
                if v.get("severity", "error") == "error"
            )
        )
        print(
            f"{scene.name}: {len(it)} steps in {timings['run_s']:.3f} s after {timings['compile_s']:.1f} s compile "
            f"(real-time factor {summary['realtime_factor']:.2f}, {summary['newton_iterations_mean']:.2f} Newton iterations/step); "
            f"{check}; {limits}; wrote {out}/"
        )
    return 0


def cmd_design(args) -> int:
    goals = {"move": _design_move, "fastest": _design_fastest, "track": _design_track}
    if args.goal not in goals:
        raise SceneError(f"--goal {args.goal}: unknown (available: {', '.join(goals)})")
    if args.goal != "track" and args.time is None:
        raise SceneError(
            f"--goal {args.goal} needs --time (s: the move's duration{', at most' if args.goal == 'fastest' else ''})"
        )
    log = (lambda *_: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    return goals[args.goal](args, _scene(args), log)


def _move_goal(args, scene):
    planar = scene.effects.planar
    dp = [args.dx, args.dy, 0.0 if planar else args.dz]
    dtheta = [0.0, 0.0, args.dtheta] if planar else [args.drx, args.dry, args.dtheta]
    return dp, dtheta, (args.time if args.settle is None else args.settle)


def _write_move(out, scene, move, coeffs, summary: dict, band: float, title: str) -> dict:
    """The designed and plain moves, each run on the design grid and the finer one: their
    actuator tables, settling figures and feasibility into ``summary``, summary.json and design.png."""
    import jax.numpy as jnp

    from . import design
    from .io import outputs
    from .robots.limits import feasibility

    zero = jnp.zeros_like(coeffs)
    runs = {}
    t = design.step_times(scene)
    for label, c in (("plain", zero), ("designed", coeffs)):
        for grid, finer in (("same_grid", False), ("finer_grid", True)):
            try:
                runs[(label, grid)] = design.verify(scene, move, c, finer=finer)
            except ConvergenceError as e:
                # The plain move is only the comparison: a fast one can load the legs past what
                # Newton follows (dynamic buckling). Its failure is reported, the design kept.
                if label == "designed":
                    raise
                summary.setdefault(label, {})[grid] = {"converged": False, "failure": str(e)}
                if e.partial is not None:
                    runs[(label, grid)] = e.partial
                continue
            summary.setdefault(label, {})[grid] = {"converged": True, **design.settling(runs[(label, grid)], move, band)}
        a = np.asarray(move.actuators(t, c))
        outputs.write_columns(
            out / ("actuators.csv" if label == "designed" else "plain_actuators.csv"),
            ["t_s"] + [f"a{i + 1}" for i in range(a.shape[1])],
            np.concatenate([t[:, None], a], axis=1),
        )
    d = runs[("designed", "same_grid")]
    summary["feasibility"] = feasibility(scene, d.t, d.actuators, d.base_wrenches)
    plain = summary["plain"]["finer_grid"]
    summary["vibration_reduction_finer_grid"] = (
        plain["residual_vibration_m"] / summary["designed"]["finer_grid"]["residual_vibration_m"] if plain["converged"] else None
    )
    summary["coefficients"] = np.asarray(coeffs).tolist()
    outputs.write_json(out / "summary.json", summary)
    outputs.plot_design(out / "design.png", runs, move, title)
    return summary


def _plain_vibration(summary) -> str:
    """The plain move's residual vibration on the finer grid and the design's gain, or why not."""
    plain = summary["plain"]["finer_grid"]
    if not plain["converged"]:
        return "(the plain move's run did not converge: see summary.json)"
    return f"{plain['residual_vibration_m']:.3g} m (plain, {summary['vibration_reduction_finer_grid']:.3g}x more)"


def _design_move(args, scene, log) -> int:
    from . import design
    from .io import outputs

    dp, dtheta, settle = _move_goal(args, scene)
    out = _out_dir(args.out)
    move, scene = design.plan_move(scene, dp, dtheta, args.time, settle, args.knots or 4)
    res = design.design_move(scene, move, method=args.method, iterations=args.iterations, log=log)
    summary = {
        "settings": outputs.scene_settings(scene),
        "goal": {"kind": "move", "displacement_m": dp, "rotation_rad": dtheta, "time_s": args.time, "settle_s": settle},
        "method": res["method"],
        "objective_m2": res["objective"],
        "compile_s": res["compile_s"],
        "optimise_s": res["optimise_s"],
    }
    s = _write_move(out, scene, move, res["coefficients"], summary, args.band, f"{scene.name}: designed move")
    if not args.quiet:
        print(
            f"{scene.name}: residual vibration {_plain_vibration(s)} -> "
            f"{s['designed']['finer_grid']['residual_vibration_m']:.3g} m (designed) on the finer grid; "
            f"{len(res['objective']) - 1} {res['method']} iterations in {res['optimise_s']:.1f} s after {res['compile_s']:.1f} s compile; "
            f"{'within limits' if s['feasibility']['feasible'] else 'LIMITS EXCEEDED'}; wrote {out}/"
        )
    return 0


def _design_fastest(args, scene, log) -> int:
    from . import design
    from .io import outputs

    dp, dtheta, settle = _move_goal(args, scene)
    out = _out_dir(args.out)
    t0 = time.perf_counter()
    res = design.fastest_move(
        scene, dp, dtheta, args.time, settle, count=args.knots or 4, band=args.band, iterations=args.iterations, log=log
    )
    move, scene = res["move"], res["scene"]
    summary = {
        "settings": outputs.scene_settings(scene),
        "goal": {"kind": "fastest", "displacement_m": dp, "rotation_rad": dtheta, "longest_s": args.time, "band_m": args.band},
        "fastest_duration_s": move.duration,
        "lower_bound_s": res["lower_bound_s"],
        "trials": res["trials"],
        "wall_s": time.perf_counter() - t0,
    }
    s = _write_move(out, scene, move, res["coefficients"], summary, args.band, f"{scene.name}: fastest designed move")
    if not args.quiet:
        print(
            f"{scene.name}: fastest move {move.duration * 1e3:.4g} ms (the limits allow no less than {res['lower_bound_s'] * 1e3:.4g} ms), "
            f"residual vibration {s['designed']['finer_grid']['residual_vibration_m']:.3g} m on the finer grid; "
            f"{len(res['trials'])} designs in {summary['wall_s']:.1f} s; wrote {out}/"
        )
    return 0


def _design_track(args, scene, log) -> int:
    from . import design
    from .io import outputs
    from .replay import path_errors
    from .robots.limits import feasibility

    scene, path = _path_arg(args, scene)
    out = _out_dir(args.out)
    tr, start, inverse = design.plan_tracking(scene, path, args.knots or 8)
    outputs.write_columns(
        out / "inverse_actuators.csv",
        ["t_s"] + [f"a{i + 1}" for i in range(inverse.actuators.shape[1])],
        np.concatenate([np.asarray(inverse.t)[:, None], np.asarray(inverse.actuators)], axis=1),
    )
    res = design.design_tracking(scene, tr, start, iterations=args.iterations, log=log)
    c = res["coefficients"]
    t, a = design.step_times(scene), np.asarray(tr.actuators(c))
    outputs.write_columns(
        out / "actuators.csv", ["t_s"] + [f"a{i + 1}" for i in range(a.shape[1])], np.concatenate([t[:, None], a], axis=1)
    )
    run = design.verify_tracking(scene, tr, c, finer=False)
    outputs.write_trajectory(out / "tracking.csv", run)
    errors = {"same_grid": path_errors(path, run)}
    try:
        errors["finer_grid"] = path_errors(path, design.verify_tracking(scene, tr, c, finer=True))
    except ConvergenceError as e:
        errors["finer_grid"] = {"failure": f"the finer grid's check of the design: {e}"}
    summary = {
        "settings": outputs.scene_settings(scene),
        "goal": {"kind": "track", "path_file": str(args.path), "speed_splines": tr.count},
        "direct_inverse_feasibility": feasibility(scene, inverse.t, inverse.actuators, inverse.base_wrenches),
        "tracking_error": {grid: {k: v for k, v in e.items() if not isinstance(v, np.ndarray)} for grid, e in errors.items()},
        "feasibility": feasibility(scene, run.t, run.actuators, run.base_wrenches),
        "objective_m2": res["objective"],
        "compile_s": res["compile_s"],
        "optimise_s": res["optimise_s"],
        "coefficients": np.asarray(c).tolist(),
    }
    outputs.write_json(out / "summary.json", summary)
    planar = scene.effects.planar
    wanted = np.asarray(inverse.position)[:, : 2 if planar else 3]
    outputs.plot_inverse(
        out / "tracking.png", t, wanted, np.asarray(run.position)[:, : 2 if planar else 3], a, errors["same_grid"]["position_m"],
        f"{scene.name}: path tracked within the actuator limits", got="designed motion",
    )  # fmt: skip
    e = summary["tracking_error"]
    if "failure" in e["finer_grid"]:
        raise ConvergenceError(f"{e['finer_grid']['failure']} (the design is in {out}/)", 0.0)
    if not args.quiet:
        inv_ok = summary["direct_inverse_feasibility"]["feasible"]
        print(
            f"{scene.name}: tracking error {e['same_grid']['max_position_error_m']:.3g} m ({e['same_grid']['relative_error']:.2g} of "
            f"the motion; {e['finer_grid']['max_position_error_m']:.3g} m on the finer grid); the direct inverse is "
            f"{'within' if inv_ok else 'outside'} the limits, the design "
            f"{'within' if summary['feasibility']['feasible'] else 'OUTSIDE'}; {len(res['objective']) - 1} LM iterations in "
            f"{res['optimise_s']:.1f} s after {res['compile_s']:.1f} s compile; wrote {out}/"
        )
    return 0


def _actuator_forces(scene, traj):
    """(T, legs) base force along each leg's axis (N, positive pulling the rod out)."""
    d = np.asarray(scene.legs.base_rotation)[:, :, 2]
    return np.einsum("tlk,lk->tl", np.asarray(traj.base_wrenches)[:, :, 0, :], d)


def _out_dir(path) -> Path:
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OSError(f"cannot create output folder {out}: {e.strerror}") from None
    return out


def _add_solver_overrides(p):
    p.add_argument("--nodes", type=int, help="override [solver] nodes")
    p.add_argument("--integrator", choices=["rk4", "euler"], help="override [solver] integrator")
    p.add_argument("--dt", type=float, help="override [solver] dt (s)")
    p.add_argument("--alpha", type=float, help="override [solver] alpha (-0.5 trapezoidal .. 0 BDF2)")
    p.add_argument("--duration", type=float, help="override [solver] duration (s)")
    p.add_argument("--tol", type=float, help="override [solver] tol")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="pcrjax", description="Differentiable Cosserat-rod dynamics of continuum robots.")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("simulate", help="forward dynamics; writes trajectory.csv, summary.json and plots")
    p.add_argument("scene", help="scene TOML file, or the name of a shipped scene (see `pcrjax scenes`)")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or closing line")
    _add_solver_overrides(p)
    p.set_defaults(func=cmd_simulate)
    p = sub.add_parser("static", help="static equilibrium under the initial load; prints JSON")
    p.add_argument("scene")
    _add_solver_overrides(p)
    p.set_defaults(func=cmd_static)
    p = sub.add_parser(
        "inverse",
        help="inverse dynamics: actuator trajectories that make the platform follow a path; writes actuators.csv, "
        "wrenches.csv, replay.csv (forward replay), summary.json (replay error, feasibility) and inverse.png",
    )
    p.add_argument("scene")
    p.add_argument(
        "--path", required=True, help="CSV t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad (planar robots: also t_s,x_m,y_m,theta_rad)"
    )
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or closing line")
    _add_solver_overrides(p)
    p.set_defaults(func=cmd_inverse)
    p = sub.add_parser(
        "design",
        help="trajectory design by gradient: a point-to-point platform move without residual vibration (--goal move), "
        "the fastest such move within the actuator limits (fastest), or a path tracked within them (track); writes "
        "actuators.csv, summary.json and a plot",
    )
    p.add_argument("scene")
    p.add_argument(
        "--goal",
        default="move",
        help="move (point-to-point in --time, least residual vibration), fastest (the shortest move up to --time that "
        "stays within the limits and settles into --band), track (follow --path as closely as the limits allow)",
    )
    for key, unit in (("dx", "m"), ("dy", "m"), ("dz", "m"), ("drx", "rad"), ("dry", "rad"), ("dtheta", "rad (about z)")):
        p.add_argument(f"--{key}", type=float, default=0.0, help=f"platform move {key[1:]} [{unit}]")
    p.add_argument("--time", type=float, help="move, fastest: duration of the move (fastest: the longest allowed) (s)")
    p.add_argument("--settle", type=float, help="settling window after the move (s; default: the move's duration)")
    p.add_argument("--band", type=float, default=1e-6, help="settling band around the target (m; default 1e-6)")
    p.add_argument("--path", help="track: CSV t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad (planar robots: also t_s,x_m,y_m,theta_rad)")
    p.add_argument("--knots", type=int, help="B-splines per actuator: move corrections (default 4), track speeds (default 8)")
    p.add_argument("--method", choices=["lm", "adam"], default="lm", help="move: optimiser (default lm)")
    p.add_argument("--iterations", type=int, default=8, help="optimiser iterations at most")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", action="store_true")
    _add_solver_overrides(p)
    p.set_defaults(func=cmd_design)
    p = sub.add_parser("sweep", help="run variants of a scene as batched programs; writes sweep.csv, summary.json and sweep.png")
    p.add_argument("scene")
    p.add_argument(
        "--vary",
        action="append",
        required=True,
        metavar="KEY=SPEC",
        help="a scene key (rod.tau, solver.dt, platform.mass, tip.force[2], rods[1].length) and its values: a:b:n "
        "(n values a..b), a:b:n:log (geometric), or v1,v2,...; repeat for a grid of all combinations",
    )
    p.add_argument("--samples", type=int, help="a Latin hypercube of this many members over the --vary ranges instead of a grid")
    p.add_argument("--seed", type=int, default=0, help="seed of the Latin hypercube (default 0)")
    p.add_argument("--batch", type=int, default=64, help="members per compiled program (default 64)")
    p.add_argument(
        "--memory",
        help="the most one batched program may hold, e.g. 500MB or 2GiB; a larger batch runs as smaller ones "
        "(default: half of the memory available when each batch runs)",
    )
    p.add_argument(
        "--cluster",
        help="run the batches on a Dask cluster: 'local' (worker processes on this machine, one per core), 'local:W' "
        "(W workers), or a scheduler address such as tcp://host:8786 (default: in this process)",
    )
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", action="store_true", help="no progress lines or closing line")
    _add_solver_overrides(p)
    p.set_defaults(func=cmd_sweep)
    p = sub.add_parser(
        "pareto",
        help="the cost of accuracy: error against a Richardson reference vs wall time over N, dt, alpha, tol, RK4/Euler, "
        "Cosserat/Kirchhoff and the lumped model; writes pareto.csv, summary.json and pareto.png",
    )
    p.add_argument("scene")
    p.add_argument("--target-error", type=float, help="print the cheapest setting whose relative error is at most this")
    p.add_argument("--duration", type=float, help="simulated seconds (default: the scene's)")
    p.add_argument("--reference-nodes", type=int, help="N of the reference (default: twice the largest N compared)")
    p.add_argument("--quick", action="store_true", help="fewer settings per family (a first look, or a test)")
    p.add_argument("--families", help="comma-separated subset of N,dt,alpha,tol,euler,kirchhoff,lumped (default: all)")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_pareto)
    p = sub.add_parser("bench", help="benchmark: time per step, real-time factor, compile time, iterations, error")
    p.add_argument(
        "case", choices=["cantilever", "stewart_gough", "triskele", "inverse", "design", "batch"], help="benchmark case"
    )
    p.add_argument("--nodes", help="comma-separated N values for RK4; default per case")
    p.add_argument("--euler-nodes", help="comma-separated N values for explicit Euler (empty string: none); default per case")
    p.add_argument("--duration", type=float, default=1.0, help="simulated seconds per run")
    p.add_argument(
        "--reference-nodes",
        type=int,
        help="N of the converged RK4 reference (default 320 cantilever, 80 Stewart-Gough, 100 Triskele)",
    )
    p.add_argument("--noise", action="store_true", help="stewart_gough: also print the thesis noise table (alpha x N x dt)")
    p.add_argument("--noise-nodes", default="5,10,50,85,170", help="N values of the noise table")
    p.add_argument(
        "--gradient", action="store_true", help="also time a reverse-mode gradient through a rollout against the rollout"
    )
    p.add_argument("--gradient-only", action="store_true", help="only the gradient timing")
    p.add_argument("--gradient-nodes", type=int, default=20, help="RK4 nodes of the gradient timing (default 20)")
    p.add_argument("--gradient-steps", type=int, default=200, help="steps of the gradient timing (default 200)")
    p.add_argument("--tol", type=float, default=1e-10, help="Newton tolerance of the measured runs (reference: 1e-12)")
    p.add_argument("--horizons", default="100,1000,10000", help="design: rollout lengths (steps) of the gradient memory table")
    p.add_argument(
        "--batches", default="1,8,64", help="batch: batch sizes (default 1,8,64; N from --nodes, steps from --gradient-steps)"
    )
    p.add_argument("--json", help="also write the table as JSON to this file")
    p.set_defaults(func=cmd_bench)
    p = sub.add_parser("scenes", help="list the shipped scenes")
    p.set_defaults(func=cmd_scenes)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from .config import configure

    configure()

    try:
        return args.func(args)
    except (SceneError, ConvergenceError, OSError) as e:
        print(f"pcrjax: error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("pcrjax: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
