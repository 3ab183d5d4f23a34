"""`pcrjax-identify RECORDING.csv [MORE.csv ...] --fit tau,lengths [--scene S] [--cluster C] --out DIR`.

Writes ``DIR/fit.json`` (values, standard errors, correlation, noise estimates, final loss,
iterations, wall time, outlier frames), ``DIR/fit_time.png`` (measured vs simulated x, y, theta over time),
``DIR/fit_plane.png`` (the path in the plane, like thesis Figure 5.7), ``DIR/residuals.png`` and
``DIR/loss.png``; progress is printed while it runs and saved in ``DIR`` so that an interrupted
fit resumes where it stopped. Bad input prints one line naming the cause and exits with status 2.
Several recordings: each as alone into ``DIR/<its name>/``, here or on a Dask cluster (`batch`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
from pathlib import Path

import numpy as np

import pcrjax
from pcrjax import SceneError


def _parser():
    p = argparse.ArgumentParser(prog="pcrjax-identify", description="Fit damping and rod lengths to a recorded motion.")
    p.add_argument(
        "recording",
        nargs="+",
        help="CSV t_s,x_m,y_m,theta_rad (with its TOML sidecar, or --scene); several: each fitted into DIR/<its name>/, "
        "with a summary in DIR/fits.csv",
    )
    p.add_argument(
        "--fit",
        default="tau,lengths",
        help="parameters: tau (shared), tau_per_rod, tau_split (stretch-shear and bend-twist apart), lengths, youngs_modulus "
        "(E of all rods, the shear modulus with it), platform_mass (the inertia with it) (comma separated)",
    )
    p.add_argument("--scene", help="scene name or TOML path (default: the sidecar's)")
    p.add_argument("--out", default="out/identify", help="output folder")
    p.add_argument("--max-iter", type=int, default=30, help="Levenberg-Marquardt iterations per pass")
    p.add_argument("--tau0", type=float, help="initial damping time (s; default: the scene's)")
    p.add_argument(
        "--start",
        choices=("modal", "given"),
        default="modal",
        help="modal: search the prior for the recording's modes (default); given: start from the scene's values and --tau0",
    )
    p.add_argument(
        "--refine",
        type=int,
        default=2,
        metavar="LEVELS",
        help="refinements of the grid that measure the discretisation error, at most, in space (2x nodes each) and then in time (dt/2 each) (default 2; 0: none)",
    )
    p.add_argument(
        "--profile",
        action="store_true",
        help="profile the loss along each measured value at the fit's grid: 68 %% intervals that follow a curved valley of "
        "the loss; where a profile finds a minimum the fit missed, the fit moves there (a few Levenberg-Marquardt fits "
        "per point; slow)",
    )
    p.add_argument(
        "--cluster",
        help="fit the recordings as tasks on Dask: 'local' (a worker per core), 'local:W' or a scheduler address "
        "(tcp://host:8786; every worker needs pcrjax installed); default: one after another in this process",
    )
    return p


def _scale(values, unit: str):
    """(factor, label) of the SI prefix in which ``values`` (in ``unit``) read as 1-1000."""
    factor, prefix = _prefix(float(np.max(np.abs(values))) if np.size(values) else 0.0)
    return factor, f"{prefix}{unit}"


def _import_pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401


def _plots(out: Path, rec, seen, result):
    _import_pyplot()
    import matplotlib.pyplot as plt

    t, meas = rec.t, rec.pose
    bad = np.isin(t, np.asarray(result.outliers))  # frames reported as outliers
    rel, fit_rel, res = meas - meas[0], seen - meas[0], seen - meas
    units = [_scale(rel[:, :2], "m")] * 2 + [_scale(rel[:, 2], "rad")]
    res_units = [_scale(res[~bad][:, :2], "m")] * 2 + [_scale(res[~bad][:, 2], "rad")]
    names = ("x", "y", "θ")

    def marked(ax, x, y):
        if np.any(bad):
            ax.plot(x[bad], y[bad], "x", color="red", ms=5, label=f"outliers ({int(np.sum(bad))})")

    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for k, (ax, nm, (sc, unit)) in enumerate(zip(axes, names, units)):
        ax.plot(t, rel[:, k] / sc, ".", ms=3, label="measured")
        ax.plot(t, fit_rel[:, k] / sc, "-", lw=1, label="simulated (fit)")
        marked(ax, t, rel[:, k] / sc)
        ax.set_ylabel(f"{nm} − {nm}₀ ({unit})")
    axes[0].legend()
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(out / "fit_time.png", dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 6))
    sc, unit = units[0]
    ax.plot(rel[:, 0] / sc, rel[:, 1] / sc, ".", ms=3, label="measured")
    ax.plot(fit_rel[:, 0] / sc, fit_rel[:, 1] / sc, "-", lw=1, label="simulated (fit)")
    marked(ax, rel[:, 0] / sc, rel[:, 1] / sc)
    ax.set_xlabel(f"x − x₀ ({unit})")
    ax.set_ylabel(f"y − y₀ ({unit})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fit_plane.png", dpi=120)
    plt.close(fig)
    fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True)
    for k, (ax, nm, (sc, unit)) in enumerate(zip(axes, names, res_units)):
        ax.plot(t[~bad], res[~bad, k] / sc, ".", ms=3)
        if np.any(bad):  # off the scale of the others: drawn at its edge
            lim = 5 * np.max(np.abs(res[~bad, k] / sc))
            ax.plot(t[bad], np.clip(res[bad, k] / sc, -lim, lim), "x", color="red", ms=5, label="outliers (clipped)")
            ax.legend()
        ax.set_ylabel(f"{nm} residual ({unit})")
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(out / "residuals.png", dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogy(np.arange(len(result.history)), result.history, "o-")
    ax.set_xlabel("evaluation (both passes)")
    ax.set_ylabel("0.5 Σ (residual / σ)²")
    fig.tight_layout()
    fig.savefig(out / "loss.png", dpi=120)
    plt.close(fig)


def run(args) -> dict:
    from . import robust
    from .fit import Problem, fit
    from .recording import load_recording

    if args.tau0 is not None and not args.tau0 > 0:
        raise ValueError(f"--tau0 must be positive, got {args.tau0}")
    rec = load_recording(args.recording)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    init = {} if args.tau0 is None else {"tau": args.tau0}
    print(
        f"{rec.path}: {rec.frames} frames over {rec.t[-1] - rec.t[0]:.3g} s ({100 * rec.missing_fraction():.1f} % missing); building the model ...",
        flush=True,
    )
    problem = Problem(
        rec,
        tuple(f.strip() for f in args.fit.split(",") if f.strip()),
        scene=None if args.scene is None else _scene(rec, args.scene),
        initial=init,
    )
    print(f"fitting {', '.join(problem.labels())}", flush=True)

    def progress(stage, it, cost, step):
        if cost is None:
            print(f"  {stage}", flush=True)
            return
        print(f"  {stage}: iteration {it:3d}: loss {cost:.6g}, largest step {step:.3g}", flush=True)

    if args.refine < 0:
        raise ValueError(f"--refine must be 0 or more, got {args.refine}")
    # matplotlib's import (about a second) while the fit runs, which mostly waits on compiled programs
    threading.Thread(target=_import_pyplot, daemon=True).start()
    answered = []

    def answer(result):
        """The answer on the fit's grid, shown and kept in fit.json while the refinements run."""
        _write_fit(out, rec, problem, result, final=False)
        answered.append(result)
        m = result.model
        print(
            f"the fit's answer on its own grid ({m['nodes']} nodes, dt {m['dt']:.3g} s) after {result.wall_s:.1f} s, "
            f"± statistical (noise) only, in {out / 'fit.json'}:"
        )
        _print_values(result)
        print(f"its discretisation error next: up to {args.refine} refinements in space, then in time ...", flush=True)

    try:
        result = fit(
            problem,
            max_iter=args.max_iter,
            state_dir=out,
            progress=progress,
            modal=args.start == "modal",
            refine_levels=args.refine,
            profiles=args.profile,
            answer=answer,
        )
    except KeyboardInterrupt:
        if answered:
            print(f'the fit\'s answer on its own grid stays in {out / "fit.json"} ("final": false)', file=sys.stderr)
        raise
    payload = _write_fit(out, rec, problem, result, final=True)
    seen = np.asarray(problem.seen(problem.to_theta(_as_arrays(result.values))))
    _plots(out, rec, seen, result)
    if answered:
        print("the values after the refinements:")
    _print_values(result)
    if result.model:
        m = result.model
        if "extrapolated_from_dt" in m or "extrapolated_from_nodes" in m:
            time_from = (
                f"extrapolated to dt 0 (Richardson, BDF-alpha's order 2) from the models with {m['nodes']} nodes, dt "
                f"{m['extrapolated_from_dt'][0]:.3g} and {m['extrapolated_from_dt'][1]:.3g} s"
                if "extrapolated_from_dt" in m
                else f"from the model with {m['nodes']} nodes, dt {m['dt']:.3g} s"
            )
            space = ""
            if "extrapolated_from_nodes" in m:
                n1, n2 = m["extrapolated_from_nodes"]
                space = (
                    f", plus their space error extrapolated to infinitely many nodes (Richardson, RK4's order 4) from the "
                    f"moves to {n1} and {n2} nodes"
                )
            print(
                f"values {time_from}{space}, Newton tolerance {m['tol']:.0e}; ± statistical (noise), ± discretisation (the "
                "last space and time moves or their extrapolations' uncertainties, in quadrature)"
            )
        else:
            print(
                f"values from the model with {m['nodes']} nodes, dt {m['dt']:.3g} s, Newton tolerance {m['tol']:.0e}; "
                "± statistical (noise), ± discretisation (the last space and time refinements' moves, in quadrature)"
            )
    for name, entries in result.profiles.items():
        for k, pr in enumerate(entries if isinstance(entries, list) else [entries]):
            print(_profile_line(name if not isinstance(entries, list) else f"{name}[{k}]", UNITS[name], pr))
    if result.profiles:
        print(
            "the statistical errors above of the profiled values reach their 68 % profile intervals' farther ends where "
            "those lie beyond a standard error (scaled to the reported model's noise levels)"
        )
    if result.outliers:
        shown = ", ".join(f"{t:.4g}" for t in result.outliers[:10]) + (" ..." if len(result.outliers) > 10 else "")
        print(
            f"outliers: {len(result.outliers)} frames off alone, more than {robust.OUTLIER:g} times as far from what their "
            f"neighbours predict as frames around them (t = {shown} s): weighed down by the Huber loss, listed in fit.json"
        )
    if result.message:
        print(f"note: {result.message}")
    print(
        f"loss (reduced chi-square) {result.loss:.4g}, noise {result.sigma[0]:.3g} m, {result.sigma[1]:.3g} rad; "
        f"{result.iterations} iterations, {result.wall_s:.1f} s; {'converged' if result.converged else 'NOT converged'}"
    )
    (out / "fit_state.json").unlink(missing_ok=True)  # done: a new run starts afresh
    return payload


def _write_fit(out: Path, rec, problem, result, final: bool) -> dict:
    """fit.json: the result, with ``final`` false for the fit's own grid's answer that the
    refinements will replace."""
    payload = dict(recording=str(rec.path), fit=problem.fit, units=UNITS, final=final, **result.to_json())
    if result.profiles:  # the standard errors widened where the profiles' intervals are wider
        payload["statistical_errors"] = {k: result.statistical_error(k) for k in result.standard_errors}
    (out / "fit.json").write_text(json.dumps(payload, indent=2))
    return payload


def _print_values(result):
    for name, v in result.values.items():
        stat = result.statistical_error(name)
        print(f"{name:>15} = {format_value(name, v, stat, result.discretisation_errors.get(name))}")


UNITS = dict(
    tau="s",
    tau_se="s",
    tau_bt="s",
    lengths="m",
    youngs_modulus="Pa",
    platform_mass="kg",
    push_force="N",
    push_moment="N m",
    start_position="m",
    start_angle="rad",
    time_offset="s",
    frame_offset="m",
    frame_rotation="rad",
)
PREFIXES = ((1e-9, "n"), (1e-6, "µ"), (1e-3, "m"), (1.0, ""), (1e3, "k"), (1e6, "M"), (1e9, "G"))


def _profile_line(label: str, unit: str, pr: dict) -> str:
    """One profile as a line: its 68 % interval, and the lower minimum where the fit missed one."""
    scale, prefix = _prefix(abs(pr["lowest"]))
    ends = [v for v in (pr["lower"], pr["upper"]) if v is not None]
    width = abs(ends[1] - ends[0]) / scale if len(ends) == 2 and ends[1] != ends[0] else abs(pr["lowest"]) / scale * 1e-3
    decimals = max(0, 1 - int(math.floor(math.log10(width))))  # the width to two digits
    show = lambda v: "open" if v is None else f"{v / scale:.{decimals}f}"  # noqa: E731
    line = f"{label:>15}: 68 % profile interval at the fit's grid [{show(pr['lower'])}, {show(pr['upper'])}] {prefix}{unit}"
    if pr["drop"] > 0.05:
        line += (
            f"; the loss is {pr['drop']:.3g} (reduced chi-square) lower at {show(pr['lowest'])} {prefix}{unit}: "
            "the fit stopped short of that minimum"
        )
    return line


def _prefix(size: float):
    """(factor, SI prefix) in which ``size`` reads as 1-1000 (nano at the smallest)."""
    return next(((f, p) for f, p in reversed(PREFIXES) if size >= f), PREFIXES[0])


def format_value(name, value, se, disc=None) -> str:
    """``value ± se [± disc] unit`` in the SI prefix that fits the value, to the digits its
    smallest uncertainty holds (two significant figures of it)."""
    unit = UNITS.get(name, "")
    grams = 1e3 if unit == "kg" else 1.0  # prefixes go on the gram
    unit = "g" if unit == "kg" else unit
    v = np.atleast_1d(np.asarray(value, float)) * grams
    errs = [np.atleast_1d(np.asarray(e, float)) * grams for e in (se, disc) if e is not None]
    size = float(np.max(np.abs(v))) or 1.0
    factor, prefix = _prefix(size)
    if unit == "rad" and factor < 1e-3:
        factor, prefix = (1e-6, "µ")
    smallest = min((float(np.min(e[e > 0])) for e in errs if np.any(e > 0)), default=size * 1e-6) / factor
    decimals = max(0, 1 - int(np.floor(np.log10(smallest))))

    def show(a):
        a = a / factor
        return f"{a[0]:.{decimals}f}" if a.size == 1 else "[" + ", ".join(f"{x:.{decimals}f}" for x in a) + "]"

    return " ± ".join([show(v)] + [show(e) for e in errs]) + f" {prefix}{unit}"


def _as_arrays(values):
    import jax.numpy as jnp

    return {k: jnp.asarray(v, jnp.float64) for k, v in values.items()}


def _scene(rec, name):
    from .experiment import build_scene

    return build_scene(rec, name)


def main(argv=None) -> int:
    from .fit import FitError
    from .recording import RecordingError

    args = _parser().parse_args(argv)
    pcrjax.config.configure()
    try:
        if len(args.recording) > 1 or args.cluster is not None:
            from .batch import fit_all

            rows = fit_all(vars(args), args.recording, args.cluster)
            failed = [r["recording"] for r in rows if r["status"] == "failed"]
            print(f"{len(rows) - len(failed)} of {len(rows)} fits ran; summary in {Path(args.out) / 'fits.csv'}")
            return 1 if failed else 0
        args.recording = args.recording[0]
        run(args)
    except (RecordingError, SceneError, ValueError) as e:
        print(f"pcrjax-identify: error: {e}", file=sys.stderr)
        return 2
    except FitError as e:
        print(f"pcrjax-identify: fit failed: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("pcrjax-identify: interrupted; run the same command again to resume from the last saved iteration", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
