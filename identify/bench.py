"""Identification figures (printed, never asserted): ``python -m identify.bench accuracy|correlation|optimizers``.

``accuracy RECORDING``: how well damping, rod lengths and the pattern frame are determined by a
recording of length T with a fraction of its frames missing. One Problem (one compiled residual and
Jacobian) serves every cell: shorter recordings are windows of the shipped one, missing frames are
frames dropped at random (seeded) on top of those already missing. Each cell is fitted by
Levenberg-Marquardt from the optimum of the whole recording, with the true noise levels; the
table gives the error against the generating values and the reported standard error.
This measures what the data determine, given that the fit is in the right basin (the full fit
from nominal values, `fit.fit`, is what gets it there).

``correlation RECORDING``: the correlation matrix of the fitted unknowns at the whole recording's
optimum (true noise levels): how much damping, lengths and nuisances trade off.

``optimizers RECORDING``: Levenberg-Marquardt against optax Adam from the same start (truth with
damping x1.5 and lengths +0.3 %, in the basin of the true minimum) on the first ``--window``
seconds: iterations until the loss is within 1 % of the best either reached.
"""

from __future__ import annotations

import argparse
import math
import time

import jax.numpy as jnp
import numpy as np

import pcrjax

from .least_squares import adam, levenberg_marquardt
from .problem import Problem
from .recording import load_recording
from .result import summarize


def _truth_theta(pb: Problem, scale_tau=1.0, scale_lengths=1.0):
    """theta at the generating values (camera start pose from the first frame; LM fits it)."""
    tr = pb.rec.truth
    vals = dict(pb.initial_values)
    for k in ("tau", "lengths", "push_force", "push_moment", "time_offset"):
        if k in tr and k in pb.slices:
            vals[k] = jnp.asarray(tr[k], jnp.float64)
    vals["tau"] = vals["tau"] * scale_tau
    vals["lengths"] = vals["lengths"] * scale_lengths
    return np.asarray(pb.to_theta(vals))


def _lm(pb, theta, t_end, max_iter=30):
    return levenberg_marquardt(
        lambda th: pb.residual(th, t_end),
        lambda th: pb.residual_and_jacobian(th, t_end),
        theta,
        max_iter,
        max_step=pb.max_step,
    )


def _problem(path) -> Problem:
    """The fit of damping and lengths to a synthetic recording, with its true noise levels."""
    rec = load_recording(path)
    return Problem(rec, ("tau", "lengths")).with_noise([rec.truth["noise_position"]] * 2 + [rec.truth["noise_angle"]])


def _optimum(path):
    """(Problem, LM's result from the generating values on the whole recording)."""
    pb = _problem(path)
    t0 = time.perf_counter()
    out = _lm(pb, _truth_theta(pb), None)
    print(f"{pb.rec.path}: optimum of the whole recording in {time.perf_counter() - t0:.0f} s (compilation included)", flush=True)
    return pb, out


def correlation(path):
    """The correlation matrix of the fitted unknowns at the optimum (what `fit.json` reports)."""
    pb, (theta, J, r, *_) = _optimum(path)
    res = summarize(pb, theta, J, r)
    labels = [s.replace("start_", "s_").replace("lengths", "L").replace("push_", "p_") for s in res.labels]
    print(" " * 14 + "".join(f"{s:>14}" for s in labels))
    for s, row in zip(labels, np.asarray(res.correlation)):
        print(f"{s:>14}" + "".join(f"{c:14.2f}" for c in row))
    return res


def accuracy(path, fractions=(0.125, 0.25, 0.5, 1.0), missing=(0.0, 0.2, 0.5), seed=0):
    """Cells: the first ``fractions`` of the recording x ``missing`` extra frames dropped."""
    whole, (best, *_) = _optimum(path)
    rec, tr = whole.rec, whole.rec.truth
    lengths = [f * float(rec.t[-1]) for f in fractions]
    rng = np.random.default_rng(seed)
    u = rng.random(rec.t.size)
    print(
        f"{'T s':>5} {'extra missing':>13} {'frames':>6} | {'tau err %':>9} {'SE %':>7} | {'max |dL| um':>11} {'max SE um':>9} | "
        f"{'frame err um':>12} {'SE um':>7} | {'rot err urad':>12} {'SE':>6} | {'within 3 SE':>11} {'chi2':>5} {'it':>3} {'s':>4}"
    )
    rows = []
    for T in lengths:
        for miss in missing:
            pb = whole.with_frames((u >= miss) | (np.arange(u.size) == 0))
            t_end = None if T >= rec.t[-1] - 1e-9 else T
            t1 = time.perf_counter()
            theta, J, r, it, conv, _ = _lm(pb, best, t_end)
            res = summarize(pb, theta, J, r, t_end=t_end)
            v, se = res.values, res.standard_errors
            e_tau = v["tau"] / tr["tau"] - 1
            dL = np.abs(np.atleast_1d(v["lengths"]) - tr["lengths"])
            dF = np.abs(np.asarray(v["frame_offset"]) - tr["frame_offset"])
            dR = abs(v["frame_rotation"] - tr["frame_rotation"])
            ok = (
                abs(v["tau"] - tr["tau"]) < 3 * se["tau"]
                and np.all(dL < 3 * np.asarray(se["lengths"]))
                and np.all(dF < 3 * np.asarray(se["frame_offset"]))
                and dR < 3 * se["frame_rotation"]
            )
            row = dict(
                T=T,
                missing=miss,
                frames=int(pb.counted(t_end) / 3),
                tau_err=e_tau,
                tau_se=se["tau"] / tr["tau"],
                dL=dL.max(),
                L_se=np.max(se["lengths"]),
                dF=dF.max(),
                F_se=np.max(se["frame_offset"]),
                dR=dR,
                R_se=se["frame_rotation"],
                ok=ok,
                chi2=res.loss,
                it=it,
                s=time.perf_counter() - t1,
            )
            rows.append(row)
            print(
                f"{T:5.2f} {100 * miss:12.0f}% {row['frames']:6d} | {100 * e_tau:9.3f} {100 * row['tau_se']:7.3f} | {1e6 * row['dL']:11.4f} {1e6 * row['L_se']:9.4f} | "
                f"{1e6 * row['dF']:12.4f} {1e6 * row['F_se']:7.4f} | {1e6 * dR:12.3f} {1e6 * row['R_se']:6.3f} | {str(ok):>11} {res.loss:5.2f} {it:3d} {row['s']:4.0f}",
                flush=True,
            )
    return rows


def optimizers(path, window=0.2, adam_steps=200, learning_rates=(1e-2, 1e-1)):
    pb = _problem(path)
    start = _truth_theta(pb, 1.5, 1.003)
    t0 = time.perf_counter()
    _, _, _, it_lm, conv, hist_lm = _lm(pb, start, window, 50)
    print(
        f"Levenberg-Marquardt: {it_lm} iterations ({'converged' if conv else 'not converged'}), loss {hist_lm[0]:.4g} -> {hist_lm[-1]:.6g}, {time.perf_counter() - t0:.0f} s",
        flush=True,
    )
    noise, (mask, active) = pb._noise(), pb.window(window)
    runs = {"levenberg-marquardt": hist_lm}
    for lr in learning_rates:
        t0 = time.perf_counter()
        report = lambda k, loss, step: print(f"  Adam lr={lr:g} step {k}: loss {loss:.6g}", flush=True) if k % 25 == 0 else None  # noqa: E731
        _, hist = adam(lambda th: pb._residual_fn(th, noise, mask, active)[0], start, adam_steps, lr, progress=report)
        runs[f"adam lr={lr:g}"] = hist
        fate = (
            f"stopped at step {len(hist)}: the simulation failed there (NaN loss)"
            if not np.isfinite(hist[-1])
            else f"{adam_steps} steps"
        )
        finite = [c for c in hist if np.isfinite(c)] or [math.nan]
        print(
            f"Adam (learning rate {lr:g}): {fate}, loss {hist[0]:.4g} -> best {min(finite):.6g}, last finite {finite[-1]:.6g}, "
            f"{time.perf_counter() - t0:.0f} s",
            flush=True,
        )
    target = 1.01 * min(np.nanmin(h) for h in runs.values())
    for name, h in runs.items():
        hit = next((k for k, c in enumerate(h) if c <= target), None)
        print(f"{name:>22}: iterations to within 1 % of the best loss: {hit if hit is not None else f'not within {len(h) - 1}'}")
    return runs


def main(argv=None):
    pcrjax.config.configure()
    p = argparse.ArgumentParser(prog="python -m identify.bench", description=__doc__.splitlines()[0])
    p.add_argument("what", choices=("accuracy", "correlation", "optimizers"))
    p.add_argument("recording", nargs="?", default="experiments_data/triskele_push_release.csv")
    p.add_argument("--window", type=float, default=0.2, help="optimizers: seconds of the recording fitted")
    p.add_argument("--adam-steps", type=int, default=200, help="optimizers: Adam steps per learning rate")
    p.add_argument("--learning-rates", default="0.01,0.1", help="optimizers: Adam learning rates, comma-separated")
    args = p.parse_args(argv)
    if args.what == "accuracy":
        accuracy(args.recording)
    elif args.what == "correlation":
        correlation(args.recording)
    else:
        optimizers(args.recording, args.window, args.adam_steps, tuple(float(v) for v in args.learning_rates.split(",")))


if __name__ == "__main__":
    main()
