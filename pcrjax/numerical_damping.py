"""The numerical damping of BDF-alpha on a free oscillation (thesis 4.1.2, Fig. 4.3), with the
scheme's alpha: -0.5 is the trapezoidal rule (no damping), 0 is BDF2 (the most; DESIGN §1).

Members: every (dt, alpha) pair at the scene's N, and every N at one (dt, alpha). Each member runs
the same number of steps, so all members of one N share a compiled program and run as one batch
(`sweeps.run_members`): the whole (dt, alpha) plane is one program. A member's damping ratio is
the thesis's: the log decrement over the peaks of its end's displacement (delta = ln(X0/Xn)/n;
here peak to trough, the slope fitted over all peaks), xi = delta / sqrt(4 pi^2 + delta^2)
(eq. 4.1-4.2). Beside it, the scheme's own prediction (`bdf_alpha.amplification`) for a linear
oscillator at the first frequency, and the simulated first mode's own per-step factor by Prony's
method, which the higher modes beating on the peaks do not bias (they bias the log decrement by
~5e-4 to 1e-3 in xi over a few periods). A large release is nonlinear: there the theory holds
only roughly.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from .errors import SceneError
from .io.scene_file import with_solver
from .numerics import results
from .numerics.bdf_alpha import amplification
from .sweeps import batches, dominant_frequency, run_members


def _displacement(p) -> np.ndarray:
    """The end's displacement along its principal axis, about its mean."""
    d = p - p.mean(axis=0)
    return d @ np.linalg.svd(d, full_matrices=False)[2][0]


def _peak_height(x, k: int) -> float:
    """A sampled peak refined by the parabola through it and its neighbours (sampling at h = omega
    dt = 0.5 misses the true peak by up to 3 %)."""
    if k == 0 or k == len(x) - 1:
        return float(x[k])
    a, b, c = x[k - 1], x[k], x[k + 1]
    curv = a - 2 * b + c
    return float(b - (a - c) ** 2 / (8 * curv)) if curv < 0 else float(b)


def damping_ratio(t, p, floor: float = 1e-6) -> float:
    """Thesis eq. 4.1-4.2 from the peaks of the displacement, each measured from the trough
    after it (peak to trough: an offset of the equilibrium cancels, where the mean of a decaying
    run is not the equilibrium), the decrement fitted over all of them (heights below ``floor``
    of the first are left out: numerical noise); NaN with fewer than two."""
    x = _displacement(np.asarray(p))
    x = x * np.sign(x[0]) if x[0] != 0 else x
    inner = x[1:-1]
    peaks = np.flatnonzero((inner > x[:-2]) & (inner >= x[2:])) + 1
    troughs = np.flatnonzero((inner < x[:-2]) & (inner <= x[2:])) + 1
    if x[0] > 0:
        peaks = np.concatenate([[0], peaks])  # a release starts at its largest excursion
    heights = []
    for k in peaks:
        after = troughs[troughs > k]
        if after.size:
            heights.append(_peak_height(x, k) + _peak_height(-x, after[0]))
    heights = np.array(heights)
    if heights.size < 2:
        return float("nan")
    heights = heights[heights > floor * heights[0]]
    if heights.size < 2:
        return float("nan")
    # The decrement per period: the slope of log height against peak number, fitted over all
    # peaks (the thesis takes the first and the last; a higher mode beating on the peaks biases
    # two points more than the fit).
    return float(_ratio(-np.polyfit(np.arange(heights.size), np.log(heights), 1)[0]))


def _ratio(delta: float) -> float:
    return delta / math.sqrt(4 * math.pi**2 + delta**2)


def root_ratio(z) -> float:
    """The damping ratio of a mode whose amplitude changes by |z| and phase by arg z per step."""
    return _ratio(-2 * math.pi * math.log(abs(z)) / abs(np.angle(z)))


def theory_ratio(frequency_hz: float, dt: float, alpha: float) -> float:
    """The damping ratio BDF-alpha gives a linear oscillator of this frequency
    (`bdf_alpha.amplification`, pure scheme theory)."""
    return root_ratio(amplification(2 * math.pi * frequency_hz * dt, alpha))


def prony_root(x, near, order: int = 8) -> complex:
    """The root nearest ``near`` of the order-``order`` linear recurrence fitted to the samples
    ``x`` (Prony's method): a linear motion's samples obey one whose roots are its modes'
    per-sample factors, so this separates the first mode from the others and from the offset."""
    x = np.asarray(x, float)
    rows = np.stack([x[order - j - 1 : len(x) - j - 1] for j in range(order)], axis=1)
    coef, *_ = np.linalg.lstsq(rows, x[order:], rcond=None)
    roots = np.roots(np.concatenate([[1.0], -coef]))
    return complex(roots[np.argmin(np.abs(roots - near))])


def step_root(t, p, frequency_hz: float, dt: float, alpha: float) -> complex:
    """The simulated first mode's per-step factor: Prony's method on the end's displacement from
    the first step on (the start's rest history is no oscillation), the samples decimated to about
    40 a period (a recurrence on hundreds of samples a period is ill-conditioned) and the root
    taken to the power 1/k (its principal root: |arg| < pi / k)."""
    near = amplification(2 * math.pi * frequency_hz * dt, alpha)
    k = max(1, round(2 * math.pi / (40 * abs(np.angle(near)))))
    zk = prony_root(_displacement(np.asarray(p)[1:])[::k], near**k)
    return zk ** (1 / k)


def _member_figures(out, dt: float, alpha: float, frequency_hz: float | None) -> dict:
    """One member's damping figures (NaN where its run did not converge)."""
    if not bool(np.all(out["result"] == results.SUCCESSFUL)):
        nan = float("nan")
        return dict(dt=dt, alpha=alpha, frequency_hz=nan, damping_ratio=nan, prony_ratio=nan, theory_ratio=nan,
                    step_decay=nan, theory_step_decay=nan, converged=False)  # fmt: skip
    t, p = out["t"], out["position"]
    root = step_root(t, p, dominant_frequency(t, p), dt, alpha)
    # the theory at the true frequency when given, else at the first mode's own (from its root)
    f = float(frequency_hz) if frequency_hz is not None else abs(np.angle(root)) / (2 * math.pi * dt)
    theory = amplification(2 * math.pi * f * dt, alpha)
    return dict(
        dt=dt, alpha=alpha, frequency_hz=f, damping_ratio=damping_ratio(t, p), prony_ratio=root_ratio(root),
        theory_ratio=root_ratio(theory), step_decay=abs(root), theory_step_decay=abs(theory), converged=True,
    )  # fmt: skip


def study(
    scene,
    dts,
    alphas,
    nodes=(),
    *,
    at: tuple[float, float] | None = None,
    steps: int | None = None,
    periods: float = 3.0,
    frequency_hz: float | None = None,
    batch: int = 64,
    progress: Callable | None = None,
) -> list[dict]:
    """Damping ratio for every (dt, alpha) at the scene's N, and for every N in ``nodes`` at
    ``at`` = (dt, alpha) (default: the scene's). ``steps`` per member (default: enough for
    ``periods`` periods of the scene's own frequency at the smallest dt, from a first run). The
    theory is taken at ``frequency_hz`` (the true first frequency, e.g. a closed form), or at the
    simulated one (which differs from it by the scheme's period error, O(dt^2)).
    Rows: nodes, dt, alpha, duration_s, frequency_hz, damping_ratio (the thesis's log decrement),
    prony_ratio (from the first mode's per-step factor, `step_root`), theory_ratio, step_decay and
    theory_step_decay (|z| per step, simulated and the scheme's), converged, wall_s (of its batch,
    per member)."""
    dts, alphas = [float(d) for d in dts], [float(a) for a in alphas]
    if not dts or not alphas:
        raise SceneError("the numerical-damping study needs at least one dt and one alpha")
    if any(not (d > 0) for d in dts) or any(not (-0.5 <= a <= 0.0) for a in alphas):
        raise SceneError("dt must be positive and alpha in [-0.5, 0]")
    if not scene.effects.inertia:
        raise SceneError("the numerical-damping study needs a dynamic scene (effects.inertia)")
    s = scene.solver
    at = (float(s.dt), float(s.alpha)) if at is None else (float(at[0]), float(at[1]))
    if steps is None:
        probe = with_solver(scene, dt=min(dts), alpha=-0.5, duration=min(dts) * 400)
        out, *_ = run_members([probe], 1)
        f = dominant_frequency(out[0]["t"], out[0]["position"])
        if not math.isfinite(f) or f <= 0:
            raise SceneError("the scene does not oscillate: no frequency to measure damping against")
        steps = int(math.ceil(periods / (f * min(dts))))
    members = [(int(s.nodes), d, a) for d in dts for a in alphas]
    members += [(int(n), at[0], at[1]) for n in nodes if (int(n), at[0], at[1]) not in members]
    scenes = [with_solver(scene, nodes=n, dt=d, alpha=a, duration=steps * d) for n, d, a in members]
    rows: list = [None] * len(members)
    done = 0
    for chunk, size in batches(scenes, batch):
        t0 = time.perf_counter()
        outs, *_ = run_members([scenes[m] for m in chunk], size)
        wall = (time.perf_counter() - t0) / len(chunk)
        for m, o in zip(chunk, outs, strict=True):
            n, d, a = members[m]
            rows[m] = dict(nodes=n, duration_s=steps * d, wall_s=wall, **_member_figures(o, d, a, frequency_hz))
        done += len(chunk)
        if progress is not None:
            progress(done, len(members))
    return rows
