"""The fastest point-to-point move that stays within the actuators' limits and settles.

A bisection on the move's duration ``T``. Each trial designs the move (`moves.design_move`, the
limits as penalty rows) and accepts it when an independent forward run on the finer grid
(2N nodes, dt/2) is inside +-``band`` of the target from the end of the move on, and the design
grid's run is within every limit (`robots.limits.feasibility`). The lower end of the bracket is
`moves.shortest_duration` (the stroke at top speed, or at top acceleration), the upper end the
longest duration allowed, which must be accepted. All trials share one horizon (the longest move
plus its settling window), so one compiled design program serves every duration.
"""

from __future__ import annotations

import dataclasses

from ..errors import ConvergenceError, SceneError
from ..robots.limits import feasibility
from .moves import MovePrograms, default_lever, design_move, plan_move, settling, shortest_duration, verify


def fastest_move(
    scene,
    dp,
    dtheta,
    longest: float,
    settle: float,
    *,
    count: int = 4,
    band: float = 1e-6,
    iterations: int = 8,
    tolerance: float = 0.05,
    log=print,
) -> dict:
    """Shortest duration (within ``tolerance`` of it, relative) of the move by ``dp``, ``dtheta``
    (as `plan_move`) found by bisection between the limits' bound and ``longest`` s, with the
    settling window ``settle`` after the longest move. Returns a dict: ``move`` and
    ``coefficients`` of the fastest accepted design, its ``scene`` (the shared horizon),
    ``trials`` (duration, accepted, within limits, residual vibration and settling time on the
    finer grid, for each design tried), ``lower_bound_s``. Raises `SceneError` when even the
    longest move is not accepted."""
    if not 0.0 < tolerance < 1.0:
        raise SceneError(f"tolerance must be in (0, 1) (got {tolerance})")
    longest_move, horizon = plan_move(scene, dp, dtheta, longest, settle, count)
    limits = horizon.actuation.limits if horizon.actuation is not None else None
    programs = MovePrograms(horizon, default_lever(horizon))
    trials, best = [], None

    def attempt(duration: float) -> bool:
        nonlocal best
        move = dataclasses.replace(longest_move, duration=float(duration))
        try:
            res = design_move(horizon, move, iterations=iterations, log=lambda *_: None, programs=programs)
            c = res["coefficients"]
            same = verify(horizon, move, c, finer=False)
            feas = feasibility(horizon, same.t, same.actuators, same.base_wrenches)
            fine = settling(verify(horizon, move, c, finer=True), move, band)
        except ConvergenceError as e:
            trials.append({"duration_s": float(duration), "accepted": False, "failure": str(e)})
            log(f"  {duration * 1e3:.4g} ms: refused ({e})")
            return False
        ok = feas["feasible"] and fine["settling_time_s"] == 0.0
        trials.append({"duration_s": float(duration), "accepted": ok, "within_limits": feas["feasible"], **fine})
        log(
            f"  {duration * 1e3:.4g} ms: {'accepted' if ok else 'refused'} (residual vibration {fine['residual_vibration_m']:.3g} m on "
            f"the finer grid; {'within limits' if feas['feasible'] else 'limits exceeded'})"
        )
        if ok and (best is None or duration < best[0].duration):
            best = (move, c, feas)
        return ok

    if not attempt(longest):
        why = trials[-1].get("failure", f"it is not within the limits and settled into +-{band:.3g} m on the finer grid")
        raise SceneError(
            f"the longest move allowed ({longest:.4g} s) fails: {why}; allow more time (--time), more correction splines "
            f"(--knots) or iterations"
        )
    lo = max(shortest_duration(longest_move.a0, longest_move.a1, limits), 2.0 * float(horizon.solver.dt))
    hi = float(longest)
    while hi - lo > tolerance * hi:
        mid = 0.5 * (lo + hi)
        if attempt(mid):
            hi = mid
        else:
            lo = mid
    move, c, feas = best
    return {
        "move": move,
        "coefficients": c,
        "scene": horizon,
        "feasibility": feas,
        "trials": trials,
        "lower_bound_s": shortest_duration(longest_move.a0, longest_move.a1, limits),
    }
