"""`pcrjax pareto`: what accuracy costs in time, for one scene.

Every setting (node count N, time step dt, BDF-alpha's alpha, Newton tolerance, RK4 or explicit
Euler in space, Cosserat or Kirchhoff rods, and for single-rod scenes the lumped model of thesis
3.1 at several segment counts) is run over the same duration; its error is the largest distance
of the end's position from a converged reference over the run, divided by the reference's largest
displacement; its cost is wall seconds per simulated second after compilation (compile time is
reported apart).

**The reference** is a Richardson extrapolation in time of the finest runs: RK4 at
``reference_nodes`` (spatial error of RK4 falls as N^-4, so it is below the temporal one; the
report gives the change from N/2 to N as a bound), the scene's alpha, Newton tolerance 1e-12, at
h, h/2, h/4 and h/8 with h the smallest dt of the grid, sampled at h, all four on the grid and
shooting segments of h/8 (`with_step`: the runs differ in time only, and share one program).
BDF-alpha is second-order for every alpha, but its first step is backward Euler (it starts the
rates from rest, DESIGN/README), whose O(h) error in the rates stays in the motion after a
release; the runs then carry both an O(h) and an O(h^2) term (observed orders 0.4-1.3 on the released cantilever at h =
2.5 ms), and the extrapolation (8 x(k/4) - 6 x(k/2) + x(k))/3 of three runs removes both (error
O(k^3)). That of h/2, h/4 and h/8 is the reference where its remainder, its difference from that
of h, h/2 and h/4 (the O(k^3) terms left, or more where the chain is not yet asymptotic), is
below the last halving's change |x(h/4) - x(h/8)|; else the finest run is, and that change
bounds its error (for a chain of order 1 or more). The observed order log2(|x(h/2) - x(h/4)| /
|x(h/4) - x(h/8)|) and the change the extrapolation made are reported. On the thesis cantilever
(released at dt 5 ms, alpha -0.4, h 1.25 ms) the order was 1.4 and the remainder 2.5e-2 of the
swing against a last change of 5.1e-3: the extrapolation from so coarse a chain is no better
than its finest run.

**The reference's floor**: errors below it are not resolved. It is the larger of RK4's spatial
error at the reference's N (the change from N/2 over 15, N^-4) and the reference's own error in
time (the remainder, or the last halving's change). The front and `cheapest` count an error
below the floor as the floor, so that settings the reference cannot tell apart are ranked by
cost alone.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import numpy as np

from .errors import ConvergenceError, SceneError
from .io.scene_file import with_solver, with_step
from .simulation import simulate

# The families `--families` names, and how tables and plots call them.
FAMILIES = {
    "N": "N (RK4)",
    "dt": "dt",
    "alpha": "alpha",
    "tol": "Newton tol",
    "euler": "Euler",
    "kirchhoff": "Kirchhoff",
    "lumped": "lumped",
}
THESIS = "thesis"  # the scene's own setting


@dataclasses.dataclass
class Setting:
    family: str
    label: str
    solver: dict  # with_solver overrides
    kirchhoff: bool = False
    lumped_segments: int | None = None

    @property
    def thesis(self) -> bool:
        return self.family == THESIS


def _nodes_ladder(n0: int) -> list[int]:
    return sorted({max(4, int(round(n0 / f))) for f in (16, 8, 4, 2, 1)})


def settings(scene, quick: bool = False) -> list[Setting]:
    """The settings compared for ``scene``: one family per knob, each around the scene's own
    (thesis) setting, plus that setting itself."""
    s = scene.solver
    n0, dt0, a0, tol0 = s.nodes, float(s.dt), float(s.alpha), float(s.newton.tol)
    nm = min(n0, 20)  # the families other than N run at a moderate N
    F = FAMILIES
    out = [Setting(THESIS, f"scene's own: N {n0}, dt {dt0:g}, alpha {a0:g}", {})]
    nodes = _nodes_ladder(n0)[:2] if quick else _nodes_ladder(n0)
    out += [Setting(F["N"], f"N {n}", {"nodes": n}) for n in nodes if n != n0]
    for f in (2.0, 0.5) if quick else (2.0, 0.5, 0.25):
        out.append(Setting(F["dt"], f"dt {dt0 * f:g}", {"nodes": nm, "dt": dt0 * f}))
    for a in (-0.5, 0.0) if quick else (-0.5, -0.3, -0.2, 0.0):
        if a != a0:
            out.append(Setting(F["alpha"], f"alpha {a:g}", {"nodes": nm, "alpha": a}))
    for tol in (1e-6,) if quick else (1e-6, 1e-8, 1e-12):
        if tol != tol0:
            out.append(Setting(F["tol"], f"tol {tol:g}", {"nodes": nm, "tol": tol}))
    for n in (nm,) if quick else (nm, 2 * nm, 4 * nm):
        out.append(Setting(F["euler"], f"Euler N {n}", {"nodes": n, "integrator": "euler"}))
    out.append(Setting(F["kirchhoff"], f"Kirchhoff N {nm}", {"nodes": nm}, kirchhoff=True))
    if scene.robot == "rod":
        for m in (4, 8) if quick else (4, 8, 16, 32):
            out.append(Setting(F["lumped"], f"lumped {m} segments", {}, lumped_segments=m))
    return out


def _kirchhoff(scene):
    return dataclasses.replace(scene, effects=dataclasses.replace(scene.effects, shear_extension=False))


@dataclasses.dataclass
class Reference:
    t: np.ndarray
    position: np.ndarray
    dt: float
    nodes: int
    observed_order: float
    extrapolation_change: float  # max |the extrapolation - x(h/8)| / displacement
    spatial_change: float  # max |x(N) - x(N/2)| / displacement at h
    seconds: float
    last_change: float = 0.0  # max |x(h/4) - x(h/8)| / displacement
    remainder: float = 0.0  # max |the extrapolations of h/2, h/4, h/8 and of h, h/2, h/4| / displacement

    @property
    def extrapolated(self) -> bool:
        """Whether the reference is the extrapolation (else the finest run; module doc)."""
        return self.remainder < self.last_change

    @property
    def floor(self) -> float:
        """The smallest error this reference resolves (module doc)."""
        return max(self.spatial_change / 15.0, self.remainder if self.extrapolated else self.last_change)


def reference(scene, dts, reference_nodes: int, progress=print) -> Reference:
    """The Richardson reference of ``scene`` on the grid h = min(dts) (see the module doc)."""
    t_start = time.perf_counter()
    h = min(dts)
    runs = []
    # Every step on the finest step's grid and segments: the runs differ in time only (what the
    # extrapolation assumes), and share one compiled program.
    finest = with_solver(scene, nodes=reference_nodes, integrator="rk4", dt=h / 8, tol=1e-12)
    for k in (1, 2, 4, 8):
        progress(f"reference: RK4 N {reference_nodes}, dt {h / k:g}")
        tr = simulate(with_step(finest, h / k))
        runs.append(np.asarray(tr.position)[::k])
    half = with_solver(scene, nodes=max(4, reference_nodes // 2), integrator="rk4", dt=h / 8, tol=1e-12)
    coarse = simulate(with_step(half, h))
    x1, x2, x4, x8 = runs
    fine = _extrapolated(x2, x4, x8)
    amp = _amplitude(fine)
    change = lambda a, b: float(np.max(np.linalg.norm(a - b, axis=1)))  # noqa: E731
    d24, d48 = change(x2, x4), change(x4, x8)
    out = Reference(
        t=np.arange(len(fine)) * h,
        position=fine,
        dt=h,
        nodes=reference_nodes,
        observed_order=float(np.log2(d24 / d48)) if d48 > 0 else math.nan,
        extrapolation_change=change(fine, x8) / amp,
        spatial_change=change(np.asarray(coarse.position), x1) / amp,
        seconds=time.perf_counter() - t_start,
        last_change=d48 / amp,
        remainder=change(fine, _extrapolated(x1, x2, x4)) / amp,
    )
    return out if out.extrapolated else dataclasses.replace(out, position=x8)


def _extrapolated(x1, x2, x4):
    """Richardson's extrapolation of runs at k, k/2, k/4 (sampled alike) that removes their O(k)
    and O(k^2) terms."""
    return (8.0 * x4 - 6.0 * x2 + x1) / 3.0


def _amplitude(p) -> float:
    a = float(np.max(np.linalg.norm(p - p[0], axis=1)))
    if a == 0:
        raise SceneError("the reference does not move: nothing to measure an error against")
    return a


def relative_error(ref: Reference, dt: float, position) -> float:
    """Largest distance from the reference at the run's steps, over the reference's largest displacement."""
    k = dt / ref.dt
    if abs(k - round(k)) > 1e-9:
        raise SceneError(f"dt {dt:g} is not a multiple of the reference step {ref.dt:g}")
    r = ref.position[:: int(round(k))]
    p = np.asarray(position)[: len(r)]
    return float(np.max(np.linalg.norm(p - r[: len(p)], axis=1)) / _amplitude(ref.position))


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    jax.block_until_ready(out)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = fn()
    jax.block_until_ready(out)
    run = time.perf_counter() - t0
    return out, max(first - run, 0.0), run


def run_setting(scene, st: Setting, ref: Reference) -> dict:
    """One row: the setting, its error against ``ref``, wall seconds per simulated second and compile seconds."""
    duration = float(scene.solver.duration)
    if st.lumped_segments is not None:
        from .lumped import simulate_lumped

        tr, compile_s, run_s = _timed(lambda: simulate_lumped(scene, st.lumped_segments))
        dt, nodes, its = float(scene.solver.dt), st.lumped_segments, math.nan
    else:
        sc = with_solver(scene, **st.solver)
        if st.kirchhoff:
            sc = _kirchhoff(sc)
        timings: dict = {}
        simulate(sc, timings=timings)
        compile_s = timings["compile_s"]
        tm: dict = {}
        tr = simulate(sc, timings=tm)
        run_s = tm["run_s"]
        dt, nodes, its = float(sc.solver.dt), sc.solver.nodes, float(np.mean(tr.iterations))
    return _row(
        st,
        nodes=nodes,
        dt_s=dt,
        alpha=float(st.solver.get("alpha", scene.solver.alpha)) if st.lumped_segments is None else math.nan,
        error=relative_error(ref, dt, tr.position),
        wall_per_sim_s=run_s / duration,
        compile_s=compile_s,
        newton_iterations=its,
    )


def _row(st: Setting, **figures) -> dict:
    return dict(family=st.family, label=st.label, thesis=st.thesis, **figures)


def pareto_front(rows, floor: float = 0.0) -> np.ndarray:
    """Mask of the rows no other row beats in both error and cost (errors below ``floor`` count as ``floor``)."""
    e = np.maximum(np.array([r["error"] for r in rows]), floor)
    c = np.array([r["wall_per_sim_s"] for r in rows])
    out = np.ones(len(rows), bool)
    for i in range(len(rows)):
        better = (e <= e[i]) & (c <= c[i]) & ((e < e[i]) | (c < c[i]))
        out[i] = not np.any(better)
    return out


def cheapest(rows, target: float, floor: float = 0.0) -> dict | None:
    """The row of least wall time per simulated second whose error is at most ``target``; none
    where ``target`` is below the reference's ``floor`` (no error that small is resolved)."""
    if target < floor:
        return None
    ok = [r for r in rows if r["error"] <= target]
    return min(ok, key=lambda r: r["wall_per_sim_s"]) if ok else None


def run_pareto(
    scene, *, quick: bool = False, families=None, reference_nodes: int | None = None, progress=print
) -> tuple[list, Reference]:
    """The settings of ``scene`` (all families, or those named in ``families``, keys of `FAMILIES`;
    the scene's own setting always) against its Richardson reference: (rows, reference)."""
    todo = settings(scene, quick)
    if families is not None:
        unknown = set(families) - set(FAMILIES)
        if unknown:
            raise SceneError(
                f"unknown famil{'ies' if len(unknown) > 1 else 'y'} {', '.join(sorted(unknown))}; choose from {', '.join(FAMILIES)}"
            )
        keep = {FAMILIES[f] for f in families}
        todo = [s for s in todo if s.thesis or s.family in keep]
    dts = [s.solver.get("dt", float(scene.solver.dt)) for s in todo if s.lumped_segments is None]
    n_ref = reference_nodes or 2 * max(s.solver.get("nodes", scene.solver.nodes) for s in todo if s.lumped_segments is None)
    ref = reference(scene, dts, n_ref, progress)
    rows = []
    for st in todo:
        progress(f"{st.family}: {st.label}")
        try:
            rows.append(run_setting(scene, st, ref))
        except ConvergenceError as e:  # kept in the table: a setting that fails is a finding
            progress(f"  did not converge: {e}")
            rows.append(_row(st, nodes=st.solver.get("nodes", math.nan), dt_s=math.nan, alpha=math.nan, error=math.inf,
                             wall_per_sim_s=math.inf, compile_s=math.nan, newton_iterations=math.nan))  # fmt: skip
    for r, f in zip(rows, pareto_front(rows, ref.floor), strict=True):
        r["pareto"] = bool(f)
        r["resolved"] = bool(r["error"] > ref.floor)
    return rows, ref


COLUMNS = (
    "family",
    "label",
    "nodes",
    "dt_s",
    "alpha",
    "error",
    "wall_per_sim_s",
    "compile_s",
    "newton_iterations",
    "resolved",
    "pareto",
    "thesis",
)


def write(out, scene_name: str, rows, ref: Reference, target: float | None = None) -> dict | None:
    """``pareto.csv`` (one row per setting), ``summary.json`` (the reference and how it was built,
    the front, the cheapest setting meeting ``target``) and ``pareto.png``."""
    from .io import outputs

    out.mkdir(parents=True, exist_ok=True)
    lines = [",".join(COLUMNS)] + [
        ",".join(f'"{r[c]}"' if isinstance(r[c], str) else f"{float(r[c]):.10g}" for c in COLUMNS) for r in rows
    ]
    outputs._atomic_write(out / "pareto.csv", "\n".join(lines) + "\n")
    best = cheapest(rows, target, ref.floor) if target is not None else None
    outputs.write_json(
        out / "summary.json",
        {
            "scene": scene_name,
            "reference": {
                "how": (
                    "(8 x(h/8) - 6 x(h/4) + x(h/2))/3: Richardson in dt removing O(h) and O(h^2), RK4, Newton tol 1e-12, "
                    "sampled at h; its remainder: the difference from the same of h, h/2, h/4; where that is not below "
                    "|x(h/4) - x(h/8)|, the run at h/8"
                ),
                "dt_s": ref.dt,
                "nodes": ref.nodes,
                "observed_order": ref.observed_order,
                "extrapolation_change": ref.extrapolation_change,
                "spatial_change_n_half": ref.spatial_change,
                "last_halving_change": ref.last_change,
                "remainder": ref.remainder,
                "extrapolated": ref.extrapolated,
                "floor": ref.floor,
                "seconds": ref.seconds,
            },
            "front": [r["label"] for r in rows if r["pareto"]],
            "target_error": target,
            "cheapest_meeting_target": best,
        },
    )
    outputs.plot_pareto(out / "pareto.png", rows, f"{scene_name}: error against the Richardson reference vs cost")
    return best
