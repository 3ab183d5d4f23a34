r"""Feasibility of an actuator trajectory: actuator range, speed and acceleration against the
scene's limits (`signals.ActuatorLimits`), and each leg's axial compression against its buckling
load.

Speeds and accelerations are central differences of the values at the step times (one-sided at
the ends). The buckling load is Euler's for a rod clamped at both ends, $4\pi^2 EI/L^2$ (the
actuator clamps the base, the platform the tip); a platform free to sway sideways lowers it to
a quarter of that, so compressions near a quarter are reported as a warning.
"""

from __future__ import annotations

import numpy as np


def _exceeded(name: str, t, values, limit, unit: str) -> dict | None:
    """The worst excess of ``values`` (T, n) over ``limit`` (n,) with the steps where it happens."""
    over = np.abs(values) > limit[None, :]
    if not over.any():
        return None
    rows = np.flatnonzero(over.any(axis=1))
    i, j = np.unravel_index(np.argmax(np.abs(values) - limit[None, :]), values.shape)
    return {
        "what": name,
        "unit": unit,
        "worst": float(values[i, j]),
        "limit": float(limit[j]),
        "actuator": int(j) + 1,
        "time_s": float(t[i]),
        "first_time_s": float(t[rows[0]]),
        "last_time_s": float(t[rows[-1]]),
        "steps": int(rows.size),
    }


def rates(t, a):
    """(speed, acceleration) (T, n) of the values ``a`` (T, n) at times ``t`` (T,)."""
    t, a = np.asarray(t), np.asarray(a)
    if t.shape[0] < 3:
        z = np.zeros_like(a)
        return (np.gradient(a, t, axis=0) if t.shape[0] > 1 else z), z
    v = np.gradient(a, t, axis=0, edge_order=2)
    return v, np.gradient(v, t, axis=0, edge_order=2)


def buckling_loads(scene, a) -> np.ndarray:
    """Euler buckling load (legs,) of each leg clamped at both ends at actuator values ``a``."""
    rod = scene.legs.rod
    L = np.asarray(scene.legs.lengths(a))
    return 4.0 * np.pi**2 * np.asarray(rod.youngs_modulus) * np.asarray(rod.second_moment) / L**2


def feasibility(scene, t, actuators, base_wrenches) -> dict:
    """Report on a trajectory: ``t`` (T,), ``actuators`` (T, n), ``base_wrenches`` (T, legs, 2, 3).

    Returns a JSON-ready dict: the range, peak speed and acceleration used per actuator, each leg's
    peak axial compression and buckling load, and ``violations``: a list of the limits exceeded
    (what, worst value, limit, which actuator or leg, when, for how many steps). ``feasible`` is
    True when that list is empty.
    """
    t, a, w = np.asarray(t), np.asarray(actuators), np.asarray(base_wrenches)
    speed, accel = rates(t, a)
    d = np.asarray(scene.legs.base_rotation)[:, :, 2]  # leg tangents at the base
    compression = -np.einsum("tlk,lk->tl", w[:, :, 0, :], d)  # axial force pushing each leg (N)
    p_cr = np.stack([buckling_loads(scene, a_i) for a_i in a]) if a.shape[1] else np.zeros_like(compression)
    report = {
        "actuator_min": a.min(axis=0).tolist(),
        "actuator_max": a.max(axis=0).tolist(),
        "peak_speed": np.abs(speed).max(axis=0).tolist(),
        "peak_acceleration": np.abs(accel).max(axis=0).tolist(),
        "peak_compression_N": compression.max(axis=0).tolist(),
        "buckling_load_N": p_cr.min(axis=0).tolist(),
    }
    violations = []
    lim = scene.actuation.limits if scene.actuation is not None else None
    if lim is not None:
        low, high = np.asarray(lim.low), np.asarray(lim.high)
        centre = np.where(np.isfinite(low + high), 0.5 * (low + high), 0.0)
        half = 0.5 * (high - low)
        out = _exceeded("range", t, a - centre[None, :], half, "m from the range's centre")
        if out is not None:
            j = out["actuator"] - 1
            out.update(worst=out["worst"] + float(centre[j]), limit=[float(low[j]), float(high[j])], unit="m")
            violations.append(out)
        for name, vals, limit, unit in (
            ("speed", speed, np.asarray(lim.max_speed), "m/s"),
            ("acceleration", accel, np.asarray(lim.max_acceleration), "m/s^2"),
        ):
            out = _exceeded(name, t, vals, limit, unit)
            if out is not None:
                violations.append(out)
    ratio = compression / p_cr
    for name, bound in (("buckling (clamped-clamped)", 1.0), ("buckling if the platform sways (a quarter)", 0.25)):
        out = _exceeded(name, t, np.maximum(ratio, 0.0), np.full(ratio.shape[1], bound), "compression / buckling load")
        if out is not None:
            out["leg"] = out.pop("actuator")
            out["severity"] = "error" if bound == 1.0 else "warning"
            violations.append(out)
    report["violations"] = violations
    report["feasible"] = not any(v.get("severity", "error") == "error" for v in violations)
    return report
