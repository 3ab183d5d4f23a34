"""Command line: ``pcrjax simulate|static|bench|scenes`` (DESIGN §3).

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

EXIT_USER_ERROR = 2


def _scene(args):
    from .scene import load_scene, with_solver

    scene = load_scene(args.scene)
    changes = {k: getattr(args, k) for k in ("nodes", "integrator", "dt", "alpha", "duration", "tol") if getattr(args, k, None) is not None}
    return with_solver(scene, **changes) if changes else scene


def cmd_static(args) -> int:
    from .simulation import ConvergenceError, solve_static

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
        raise ConvergenceError(f"static solve did not converge: scaled residual {float(res.residual_norm):.3e} > tol {scene.solver.newton.tol:.1e}")
    return 0


def cmd_simulate(args) -> int:
    from . import outputs
    from .simulation import ConvergenceError, simulate

    scene = _scene(args)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OSError(f"cannot create output folder {out}: {e.strerror}") from None
    timings: dict = {}
    failure = None
    t0 = time.perf_counter()
    try:
        traj = simulate(scene, progress=not args.quiet and sys.stderr.isatty(), timings=timings)
    except ConvergenceError as e:
        failure = e
        traj = getattr(e, "partial", None)
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
        parallel = hasattr(scene, "legs")
        outputs.write_trajectory(out / "trajectory.csv", traj, np.asarray(traj.actuators) if parallel else None)
        if parallel:
            summary["energy_j"] = {"initial": float(traj.energy[0]), "final": float(traj.energy[-1])}
        if len(traj.t) > 1 and parallel:
            outputs.plot_platform(out / "platform_path.png", traj, scene.name)
            outputs.plot_legs(out / "legs.png", traj, scene.name)
        elif len(traj.t) > 1:
            outputs.plot_tip(out / "tip_path.png", traj, scene.name)
            outputs.plot_shapes(out / "rod_shapes.png", traj, scene.name)
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


def cmd_scenes(args) -> int:
    from .scene import shipped_scenes

    print("\n".join(shipped_scenes()))
    return 0


def cmd_bench(args) -> int:
    if args.case == "cantilever":
        from .bench import run_bench

        args.nodes = args.nodes or "5,10,20,40,80,160"
        args.reference_nodes = args.reference_nodes or 320
        return run_bench(args)
    from .bench_parallel import run_parallel_bench

    run_parallel_bench(args)
    return 0


def cmd_inverse(args) -> int:
    from .scene import SceneError, load_scene

    scene = load_scene(args.scene)
    if scene.robot == "rod":
        raise SceneError(f"{args.scene}: inverse dynamics needs a parallel robot; robot '{scene.robot}' has no actuators")
    raise SceneError(f"{args.scene}: inverse dynamics is not available in this version (forward dynamics and statics are: `pcrjax simulate`, `pcrjax static`)")


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
    p = sub.add_parser("inverse", help="actuator trajectories for a platform path (parallel robots)")
    p.add_argument("scene")
    p.add_argument("--path", required=True)
    p.add_argument("--out", default="out")
    p.set_defaults(func=cmd_inverse)
    p = sub.add_parser("bench", help="benchmark: time per step, real-time factor, compile time, iterations, error")
    p.add_argument("case", choices=["cantilever", "stewart_gough", "triskele"], help="benchmark case")
    p.add_argument("--nodes", help="comma-separated N values (RK4 for the parallel robots); default per case")
    p.add_argument("--euler-nodes", help="parallel robots: comma-separated N values for explicit Euler")
    p.add_argument("--integrators", default="rk4,euler", help="cantilever: integrators to run")
    p.add_argument("--duration", type=float, default=1.0, help="simulated seconds per run")
    p.add_argument("--reference-nodes", type=int, help="N of the converged RK4 reference (default 320 cantilever, 80 Stewart-Gough, 100 Triskele)")
    p.add_argument("--noise", action="store_true", help="stewart_gough: also print the thesis noise table (alpha x N x dt)")
    p.add_argument("--noise-nodes", default="5,10,50,85,170", help="N values of the noise table")
    p.add_argument("--tol", type=float, default=1e-10, help="Newton tolerance of the measured runs (reference: 1e-12)")
    p.add_argument("--json", help="also write the table as JSON to this file")
    p.set_defaults(func=cmd_bench)
    p = sub.add_parser("scenes", help="list the shipped scenes")
    p.set_defaults(func=cmd_scenes)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from .scene import SceneError
    from .simulation import ConvergenceError

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
