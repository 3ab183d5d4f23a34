"""`pcrjax pareto`: the Richardson reference against Euler-Bernoulli, the front and the cheapest
setting on hand-made rows, and the command on a small scene."""

import csv
import dataclasses
import json

import numpy as np
import pytest
from helpers import rod_scene
from oracles import euler_bernoulli_tip, first_frequency_hz, fit_sinusoids
from test_cli import GOOD, _write

from pcrjax.cli import main
from pcrjax.pareto import Reference, cheapest, pareto_front, reference

SCENE = GOOD + "release_time = 0.0\n"  # the small rod of test_cli, released at t = 0


def test_richardson_reference_oscillates_at_the_euler_bernoulli_frequency_and_bounds_its_own_error():
    # Small load (2 mN): the linear cantilever, whose first frequency is closed-form.
    scene = rod_scene(force=(0.0, 0.0, -2e-3), nodes=12, dt=5e-3, duration=0.3, alpha=-0.4)
    quiet = lambda m: None  # noqa: E731
    ref = reference(scene, [5e-3], 12, progress=quiet)
    # The floor (the extrapolation's remainder, or where that is larger the last halving's change
    # and the finest run as the reference) bounds the distance from a reference on four times
    # smaller steps, and is not vacuous. Measured: observed order 0.3 (the high modes alpha -0.4
    # damps differ at these steps), remainder 0.055 of the swing against a last change of 0.018:
    # the finest run is the reference, 0.0072 from the finer one (the extrapolation was 0.027).
    finer = reference(scene, [1.25e-3], 12, progress=quiet)
    swing = np.max(np.linalg.norm(ref.position - ref.position[0], axis=1))
    apart = np.max(np.linalg.norm(ref.position - finer.position[::4][: len(ref.position)], axis=1)) / swing
    assert apart <= ref.floor <= 20 * apart, (apart, ref.floor, ref.remainder, ref.last_change)
    f1 = first_frequency_hz(0.4, 207e9, 1e-3, 8000.0)
    # Two modes, as in test_dynamics (the second mode biases a one-mode fit over 0.3 s); one run at
    # dt 2.5e-3 alone is off by 2.6e-3.
    [(w, _), _], _ = fit_sinusoids(ref.t, ref.position[:, 2], [2 * np.pi * f1, 6.27 * 2 * np.pi * f1])
    assert abs(w / (2 * np.pi) / f1 - 1) < 1e-3
    assert abs(-ref.position[0, 2] / euler_bernoulli_tip(2e-3, 0.4, 207e9, 1e-3) - 1) < 1e-3


def test_front_and_cheapest_on_hand_made_rows():
    rows = [
        dict(label="a", error=1e-2, wall_per_sim_s=1.0),
        dict(label="b", error=1e-3, wall_per_sim_s=2.0),
        dict(label="c", error=2e-3, wall_per_sim_s=3.0),  # beaten by b in both
        dict(label="d", error=1e-4, wall_per_sim_s=10.0),
        dict(label="e", error=np.inf, wall_per_sim_s=np.inf),  # failed
    ]
    assert list(pareto_front(rows)) == [True, True, False, True, False]
    assert cheapest(rows, 5e-3)["label"] == "b"
    assert cheapest(rows, 1e-5) is None
    # A reference that resolves errors down to 2e-3 only cannot tell b, c and d apart: the
    # cheapest of them (b) is the front's end, and a target below the floor has no answer.
    assert list(pareto_front(rows, floor=2e-3)) == [True, True, False, False, False]
    assert cheapest(rows, 2.5e-3, floor=2e-3)["label"] == "b"
    assert cheapest(rows, 1e-3, floor=2e-3) is None


def test_reference_floor_is_the_extrapolations_remainder_or_the_last_halving_where_that_is_smaller():
    ref = Reference(t=np.zeros(1), position=np.zeros((1, 3)), dt=1e-3, nodes=20, observed_order=2.0,
                    extrapolation_change=1e-4, spatial_change=1.5e-6, seconds=0.0, last_change=3e-4)  # fmt: skip
    assert ref.extrapolated and ref.floor == pytest.approx(1e-7)  # RK4's N^-4: the N/2 change over 15
    assert dataclasses.replace(ref, remainder=2e-6).floor == 2e-6
    worse = dataclasses.replace(ref, remainder=5e-4)  # the extrapolation is no better than the finest run
    assert not worse.extrapolated and worse.floor == 3e-4


def test_pareto_command_on_a_small_scene(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(
        ["pareto", _write(tmp_path, SCENE), "--quick", "--families", "lumped", "--target-error", "0.05", "--out", str(out)]
    )
    assert code == 0
    rows = list(csv.DictReader(open(out / "pareto.csv")))
    assert all(r["resolved"] in ("0", "1") for r in rows)
    fams = [r["family"] for r in rows]
    # the lumped family only (sweeps_and_accuracy.ipynb runs the dt family in CI's notebook set)
    assert fams.count("thesis") == 1 and fams.count("lumped") == 2 and len(fams) == 3, fams
    err = {r["label"]: float(r["error"]) for r in rows}
    assert all(np.isfinite(e) and e > 0 for e in err.values()), err
    assert err["lumped 8 segments"] < err["lumped 4 segments"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["front"] and summary["cheapest_meeting_target"]["error"] <= 0.05
    assert (out / "pareto.png").stat().st_size > 0
    assert "cheapest setting with error <= 0.05" in capsys.readouterr().out


@pytest.mark.parametrize("args", [["--families", "dt,speed"], ["--target-error", "-1"]])
def test_pareto_bad_input(tmp_path, capsys, args):
    assert main(["pareto", _write(tmp_path, SCENE), "--out", str(tmp_path / "o"), *args]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
