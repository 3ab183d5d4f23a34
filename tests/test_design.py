"""Trajectory design: the correction basis, gradients against central differences, and a
designed point-to-point move against the plain one, checked on a finer independent grid."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pcrjax
from pcrjax import cli, design, load_scene, with_solver
from pcrjax.io.tables import read_path
from pcrjax.physics.rotations import rotz
from pcrjax.replay import path_errors
from pcrjax.robots.inverse import solve_static_inverse
from pcrjax.robots.limits import feasibility
from pcrjax.robots.signals import PosePath

NO_LOAD = (jnp.zeros(3), jnp.zeros(3))


def _triskele(nodes, dt, tol=1e-10):
    sc = with_solver(load_scene("triskele"), nodes=nodes, dt=dt, tol=tol)
    return eqx.tree_at(lambda s: (s.load.force, s.load.moment), sc, NO_LOAD)


def test_correction_basis_is_smooth_and_vanishes_at_the_ends():
    # The clamped quintic basis is a partition of unity (a property of B-splines, not of this
    # code); the corrections keep the move's end values, velocities and accelerations.
    u = np.linspace(0.0, 1.0, 1001)
    full = design.bspline_basis(u, 10)
    assert np.abs(full.sum(axis=1) - 1.0).max() < 1e-12
    h = 1e-4
    t = np.array([0.0, h, 2 * h, 1.0 - 2 * h, 1.0 - h, 1.0])
    B = design.correction_basis(t, 1.0, 4)
    assert np.abs(B[[0, -1]]).max() < 1e-15
    # zero value, slope and curvature at both ends: each correction grows as u^3 or faster there
    for near, twice in ((1, 2), (-2, -3)):
        nz = np.abs(B[near]) > 0
        assert nz.any() and np.all(B[twice][nz] / B[near][nz] > 8.0 * (1 - 2e-3))
    assert np.abs(design.correction_basis(np.array([-0.1, 1.1]), 1.0, 4)).max() == 0.0


# Slow (3-5 min cold): reverse mode through a rollout is checked against central differences in
# the default run by test_gradients (cantilever, checkpointed), in CI's integration set by
# test_adam_gradient_is_the_central_difference and in its notebook set by quickstart.ipynb; design's LM
# path (forward mode) there too, by test_cli_design_small_move and inverse_and_design.ipynb reaching
# their quieter moves.
@pytest.mark.slow
def test_vibration_gradient_matches_central_differences():
    sc = _triskele(nodes=5, dt=5e-4, tol=1e-13)
    move, scene = design.plan_move(sc, [3e-6, 1e-6, 0.0], [0.0, 0.0, 1e-4], 5e-3, 5e-3, count=2)
    lever = 0.05

    def f(c):  # sum of squares in um^2
        r, _ = design.vibration(scene, move, c.reshape(2, 3), lever)
        return jnp.sum((1e6 * r) ** 2)

    rng = np.random.default_rng(7)
    c = jnp.asarray(rng.normal(size=6) * 1e-7)
    vg = jax.jit(jax.value_and_grad(f))  # one program: the differences evaluate its value half
    g = np.asarray(vg(c)[1])
    h = 1e-9
    fd = np.array([(float(vg(c.at[i].add(h))[0]) - float(vg(c.at[i].add(-h))[0])) / (2 * h) for i in range(6)])
    print("gradient", g, "central differences", fd)
    assert np.abs(g - fd).max() < 1e-6 * np.abs(fd).max()


@pytest.mark.integration  # reverse mode through a Triskele rollout: minutes of compiling
def test_adam_gradient_is_the_central_difference():
    """Adam's gradient (`MovePrograms.gradient`, the path `--method adam` takes) against central
    differences of the same program's residuals."""
    sc = _triskele(nodes=5, dt=5e-4, tol=1e-13)
    move, scene = design.plan_move(sc, [3e-6, 1e-6, 0.0], [0.0, 0.0, 1e-4], 5e-3, 5e-3, count=2)
    progs = design.MovePrograms(scene, 0.05)
    tab = design.moves.move_tables(scene, move)
    c = jnp.asarray(np.random.default_rng(11).normal(size=6) * 1e-7)
    value, g = progs.gradient(c, tab)

    def ss(x):
        r, code = progs.residual(x, tab)
        assert int(code) == 0
        return float(jnp.sum(r**2))

    assert float(value) == pytest.approx(ss(c), rel=1e-12)
    h = 1e-9
    fd = np.array([(ss(c.at[i].add(h)) - ss(c.at[i].add(-h))) / (2 * h) for i in range(6)])
    assert np.abs(np.asarray(g) - fd).max() < 1e-6 * np.abs(fd).max()


@pytest.mark.integration  # the whole command: its own reverse-mode gradient program, minutes cold
def test_cli_runs_adam(tmp_path):
    """``pcrjax design --method adam`` end to end on a small move."""
    out = tmp_path / "adam"
    argv = ["design", "triskele", "--dx", "5e-6", "--time", "0.01", "--settle", "0.006", "--knots", "2", "--iterations", "3"]
    assert cli.main(argv + ["--method", "adam", "--nodes", "5", "--dt", "5e-4", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == "adam" and len(summary["objective_m2"]) == 4


@pytest.mark.integration  # the whole command: the LM design's programs, minutes cold
def test_cli_design_small_move(tmp_path):
    out = tmp_path / "d"
    argv = ["design", "triskele", "--dx", "5e-6", "--time", "0.01", "--settle", "0.006", "--knots", "2", "--iterations", "2"]
    rc = cli.main(argv + ["--nodes", "5", "--dt", "5e-4", "--out", str(out), "--quiet"])
    assert rc == 0
    for f in ("actuators.csv", "plain_actuators.csv", "summary.json", "design.png"):
        assert (out / f).is_file(), f
    s = json.loads((out / "summary.json").read_text())
    # the shipped scene's push is released at t = 0 and rings too; the design cancels it as well
    assert s["designed"]["same_grid"]["residual_vibration_m"] < 0.1 * s["plain"]["same_grid"]["residual_vibration_m"]
    assert s["objective_m2"][-1] < s["objective_m2"][0]


@pytest.mark.slow
def test_designed_move_is_100x_quieter_on_a_finer_grid():
    """A 5 um move in 10 ms (the platform's in-plane mode is near 300 Hz, undamped): the plain
    smooth step leaves about 0.4 um of ringing; the designed move, optimised at dt = 5e-5 s and
    N 10, rings at least 100x less when rerun independently at dt/2 and 2N (measured: 4.1e-7 m
    plain, 1.3e-9 m designed, 316x; optimised at dt = 1e-4 s it was 80x: the design's grid must
    resolve the mode it cancels)."""
    sc = _triskele(nodes=10, dt=5e-5)
    move, scene = design.plan_move(sc, [5e-6, 0.0, 0.0], [0.0, 0.0, 0.0], 0.01, 0.02, count=4)
    res = design.design_move(scene, move, method="lm", iterations=6)
    plain = design.settling(design.verify(scene, move, jnp.zeros((4, 3))), move)
    run = design.verify(scene, move, res["coefficients"])
    designed = design.settling(run, move)
    print(plain, designed)
    assert designed["residual_vibration_m"] * 100 <= plain["residual_vibration_m"]
    rep = feasibility(scene, run.t, run.actuators, run.base_wrenches)  # SLC-1730 stages: 2 mm/s
    assert rep["feasible"], rep["violations"]


def test_cli_design_refuses_a_move_no_trajectory_can_make(tmp_path, capsys):
    # 0.5 mm in 10 ms: the SLC-1730 stages (2 mm/s) need at least 0.25 s for the actuators' stroke
    argv = ["design", "triskele", "--dx", "5e-4", "--time", "0.01", "--nodes", "5", "--dt", "5e-4", "--out", str(tmp_path)]
    rc = cli.main(argv + ["--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "no trajectory makes the move in 0.01 s" in err and err.count("\n") == 1, err


def test_a_plain_move_that_fails_is_reported_and_the_design_kept(tmp_path, monkeypatch):
    """The plain move is only the comparison: where its run does not converge (a fast one can load
    the legs past what Newton follows), the design's outputs are still written and the plain
    run's failure is reported in summary.json, its steps up to the failure plotted. The runs are
    stand-ins (no rollout compiled): this checks the writing, not the dynamics."""
    from types import SimpleNamespace

    scene = with_solver(load_scene("triskele"), nodes=5, dt=1e-3, duration=0.004)
    a0 = scene.actuator_values(jnp.zeros(()))
    move = design.Move(a0=a0, a1=a0 + 1e-6, p1=jnp.zeros(3), R1=jnp.eye(3), duration=0.002, settle=0.002, count=2)
    coeffs = jnp.full((2, 3), 1e-7)

    def run(t, c):
        off = np.tile([1e-7, 0.0, 0.0], (t.size, 1))  # 0.1 um from the target throughout
        return SimpleNamespace(
            t=t, position=off, actuators=np.asarray(move.actuators(t, c)), base_wrenches=np.zeros((t.size, 3, 2, 3))
        )

    def verify(scene_, move_, c, finer=True):
        t = np.linspace(0.0, 0.004, 9 if finer else 5)
        if np.any(np.asarray(c)):
            return run(t, c)
        e = pcrjax.ConvergenceError("Newton did not converge at t = 0.002 s (step 2)", 0.002)
        e.partial = None if finer else run(t[:2], c)
        raise e

    monkeypatch.setattr(design, "verify", verify)
    out = tmp_path / "m"
    out.mkdir()
    s = cli._write_move(out, scene, move, coeffs, {}, 1e-6, "stand-in")
    on_disk = json.loads((out / "summary.json").read_text())
    for grid in ("same_grid", "finer_grid"):
        assert on_disk["plain"][grid] == {"converged": False, "failure": "Newton did not converge at t = 0.002 s (step 2)"}
        assert on_disk["designed"][grid] == {"converged": True, "residual_vibration_m": 1e-7, "settling_time_s": 0.0}
    assert on_disk["vibration_reduction_finer_grid"] is None and "did not converge" in cli._plain_vibration(s)
    plain = np.loadtxt(out / "plain_actuators.csv", delimiter=",", skiprows=1)
    assert plain.shape == (5, 4) and np.allclose(plain[-1, 1:], np.asarray(move.a1), rtol=0, atol=1e-15)
    assert (out / "actuators.csv").exists() and (out / "design.png").stat().st_size > 0


@pytest.mark.integration  # the whole command: a design per trial duration, minutes cold
def test_cli_design_fastest_move(tmp_path):
    """The fastest 5 um move that stays within the SLC-1730's 2 mm/s and settles into +-1 um
    (on the finer grid) by the end of the move: no faster than the stroke at top speed allows
    (an oracle independent of the design), and a trial shorter than the answer was refused."""
    out = tmp_path / "f"
    argv = ["design", "triskele", "--goal", "fastest", "--dx", "5e-6", "--time", "0.01", "--settle", "0.006", "--knots", "2"]
    rc = cli.main(argv + ["--iterations", "2", "--nodes", "5", "--dt", "5e-4", "--out", str(out), "--quiet"])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    T = s["fastest_duration_s"]
    rest_to_target = np.loadtxt(out / "actuators.csv", delimiter=",", skiprows=1)
    stroke = np.abs(rest_to_target[-1, 1:] - rest_to_target[0, 1:]).max()
    assert T >= stroke / 0.002 and s["lower_bound_s"] == pytest.approx(stroke / 0.002, rel=1e-9)
    assert s["feasibility"]["feasible"] and s["designed"]["finer_grid"]["settling_time_s"] == 0.0
    refused = [t["duration_s"] for t in s["trials"] if not t["accepted"]]
    accepted = [t["duration_s"] for t in s["trials"] if t["accepted"]]
    assert min(accepted) == T and refused and max(refused) < T
    assert T - max(r for r in refused if r < T) <= 0.05 * 0.01 + 1e-12  # bisection to 5 % of the longest move


def _lag_bound(t, a_inverse, vmax, G):
    """Least largest platform pose error of any motion whose actuators move no faster than
    ``vmax`` from the path's start, quasi-statically and to first order: actuator i cannot be
    nearer its inverse value than |a_i(t) - a_i(0)| - vmax t, and a pose error e (x, y, lever
    times the angle) moves the actuators by at most |G| |e| (G: the static inverse's derivative)."""
    lag = np.maximum(np.abs(a_inverse - a_inverse[0]) - vmax * t[:, None], 0.0).max()
    return lag / np.linalg.norm(G, 2)


@pytest.mark.integration  # the whole tracking command and a second design: the costliest programs
def test_design_tracks_a_path_within_the_speed_limit(tmp_path):
    """The shipped 1 mm move in 0.3 s needs 5.9 mm/s of the SLC-1730's 2 mm/s stages. The tracking
    design stays within the limit (by construction), lags the path no less than the speed limit
    forces (a quasi-static bound from the static inverse), does better than its start, and its
    finer-grid check agrees. With the speed unlimited, the design reproduces the direct inverse
    (the exact answer, an independent solve) to the spline's resolution."""
    out = tmp_path / "t"
    argv = ["design", "triskele", "--goal", "track", "--path", "triskele_move", "--knots", "6", "--iterations", "3"]
    rc = cli.main(argv + ["--nodes", "5", "--dt", "2e-3", "--out", str(out), "--quiet"])
    assert rc == 0
    for f in ("actuators.csv", "inverse_actuators.csv", "tracking.csv", "summary.json", "tracking.png"):
        assert (out / f).is_file(), f
    s = json.loads((out / "summary.json").read_text())
    assert not s["direct_inverse_feasibility"]["feasible"]
    assert s["feasibility"]["feasible"] and max(s["feasibility"]["peak_speed"]) <= 0.002
    assert s["objective_m2"][-1] < 0.7 * s["objective_m2"][0]
    same, finer = (s["tracking_error"][g]["max_position_error_m"] for g in ("same_grid", "finer_grid"))
    assert abs(finer - same) < 0.05 * same
    inv = np.loadtxt(out / "inverse_actuators.csv", delimiter=",", skiprows=1)
    sc = load_scene("triskele")
    rest = pcrjax.solve_static(sc)
    lever = design.default_lever(sc)

    def actuators(q):
        p = rest.position + jnp.stack([q[0], q[1], 0.0])
        return solve_static_inverse(sc, p, rotz(rest.rotation_vector[2] + q[2] / lever)).actuators

    bound = _lag_bound(inv[:, 0], inv[:, 1:], 0.002, np.asarray(jax.jacfwd(actuators)(jnp.zeros(3))))
    err = s["tracking_error"]["same_grid"]
    pose = np.hypot(err["max_position_error_m"], lever * err["max_rotation_error_rad"])
    print(f"tracking error {same:.3g} m (pose {pose:.3g} m), speed-limit bound {bound:.3g} m")
    assert 0.9 * bound <= pose

    # the speed unlimited: the direct inverse is feasible, and the design's answer
    sc = with_solver(sc, nodes=5, dt=2e-3, duration=0.4)
    lim = sc.actuation.limits
    sc = eqx.tree_at(lambda s: s.actuation.limits.max_speed, sc, jnp.full(3, jnp.inf))
    t, v = read_path("triskele_move", planar=True)
    path = PosePath.from_samples(t, v)
    tr, start, inverse = design.plan_tracking(sc, path, 6)
    res = design.design_tracking(sc, tr, start, iterations=2)
    err = path_errors(path, design.verify_tracking(sc, tr, res["coefficients"], finer=False))
    print(f"unlimited: {err['max_position_error_m']:.3g} m, {err['relative_error']:.3g} of the motion")
    assert err["relative_error"] < 1e-2 and np.isinf(np.asarray(tr.max_speed)).all() and lim is not None


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--goal", "track"], "--goal track needs --path"),
        (["--goal", "fastest", "--dx", "1e-6"], "--goal fastest needs --time"),
        (["--goal", "hover", "--time", "0.01"], "--goal hover: unknown"),
    ],
)
def test_cli_design_bad_goals(tmp_path, capsys, extra, needle):
    rc = cli.main(["design", "triskele", *extra, "--out", str(tmp_path / "x"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and err.count("\n") == 1, err
    assert not (tmp_path / "x" / "summary.json").exists()
