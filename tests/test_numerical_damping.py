"""The numerical-damping study (thesis Fig. 4.3) against BDF-alpha's own theory."""

import math

import numpy as np
import pytest
from helpers import rod_scene
from oracles import first_frequency_hz

from pcrjax.errors import SceneError
from pcrjax.numerical_damping import damping_ratio, study, theory_ratio

F1 = first_frequency_hz(0.4, 207e9, 1e-3, 8000.0)
W1 = 2 * math.pi * F1


def test_log_decrement_of_a_sampled_decaying_cosine():
    # xi = 0.02 exactly, sampled at h = 0.5 (12.6 samples a period): the parabola finds the peaks.
    xi = 0.02
    t = np.arange(0, 8 / F1, 0.5 / W1)
    x = np.exp(-xi * W1 * t) * np.cos(W1 * math.sqrt(1 - xi**2) * t)
    p = np.stack([x, 0 * x, 0 * x], axis=1)
    assert damping_ratio(t, p) == pytest.approx(xi, rel=2e-2)
    assert theory_ratio(F1, 0.5 / W1, -0.5) == pytest.approx(0.0, abs=1e-12)


def test_damping_grows_with_dt_and_alpha_as_the_scheme_predicts_and_not_with_n():
    """Small load (linear cantilever), (dt, alpha) on one batched program, plus N 6 at one
    setting: the trapezoid does not damp, the others damp as the scheme's amplification factor
    says, more with dt and with alpha, and N does not change it."""
    scene = rod_scene(force=(0, 0, -1e-3), nodes=8, dt=5e-3, alpha=-0.2)
    dts = [0.25 / W1, 0.5 / W1]
    rows = study(scene, dts, [-0.5, -0.2, 0.0], nodes=[6], at=(0.5 / W1, -0.2), steps=160, frequency_hz=F1)
    assert len(rows) == 7 and all(r["converged"] for r in rows)
    xi = {(r["nodes"], r["dt"], r["alpha"]): r["prony_ratio"] for r in rows}
    for r in rows:
        print(
            r["nodes"],
            f"{r['dt'] * W1:.2f}",
            r["alpha"],
            *(f"{r[k]:.6f}" for k in ("damping_ratio", "prony_ratio", "theory_ratio")),
        )
        # the first mode's damping (Prony) is the scheme's
        assert abs(r["prony_ratio"] - r["theory_ratio"]) < max(1e-4, 0.05 * r["theory_ratio"]), r
        # the thesis's log decrement, biased by the second mode's beating on the peaks
        assert abs(r["damping_ratio"] - r["theory_ratio"]) < 2e-3, r
    for a in (-0.2, 0.0):
        assert xi[(8, dts[1], a)] > xi[(8, dts[0], a)]
    assert xi[(8, dts[1], 0.0)] > xi[(8, dts[1], -0.2)]
    assert xi[(6, dts[1], -0.2)] == pytest.approx(xi[(8, dts[1], -0.2)], rel=0.05)


def test_study_rejects_bad_settings():
    scene = rod_scene(force=(0, 0, -1e-3), nodes=6)
    with pytest.raises(SceneError, match="alpha"):
        study(scene, [1e-3], [0.3], steps=10)
    with pytest.raises(SceneError, match="dt"):
        study(scene, [], [-0.2], steps=10)
