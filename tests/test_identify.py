"""Identification on the shipped recordings: the fit must recover the generating values.

The recordings are synthetic (their sidecars hold the truth), so the oracle is the truth itself:
damping within 2 %, rod lengths within 0.1 %, the pattern frame's offset within 1 um and its
rotation within 10 urad, and every truth within 3 reported standard errors (issue 4). The fits
take minutes: marked slow (`pytest -m slow tests/test_identify.py`).
"""

from __future__ import annotations

import dataclasses
import json
import re
import types
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import committed_recording, recording_generator, shared_triskele

import pcrjax
from identify import experiment, modes, platform_screen, start
from identify.fit import FitError, Problem, fit
from identify.least_squares import decrement, levenberg_marquardt
from identify.problem import CLOCK_STARTS, LINEAR
from identify.recording import load_recording, write_frames
from identify.result import summarize
from identify.start import latin_hypercube
from identify.valley import FACTOR

DATA = "experiments_data"


def test_matrix_pencil_finds_damped_modes_through_missing_frames():
    fs = 114.44
    t = np.arange(230) / fs
    rng = np.random.default_rng(0)
    keep = rng.random(t.size) > 0.05
    sig = np.stack(
        [
            np.exp(-0.9 * t) * np.cos(2 * np.pi * 46.9 * t + 0.3),
            np.exp(-0.13 * t) * np.cos(2 * np.pi * 18.9 * t),
            np.exp(-3.0 * t) * np.sin(2 * np.pi * 30.1 * t) + 0.5 * np.exp(-0.9 * t) * np.cos(2 * np.pi * 46.9 * t),
        ],
        axis=1,
    )
    f, d = modes.describe(modes.poles(t[keep], sig[keep], fs, 7), fs)  # 3 modes and the constant
    osc = f > 1.0
    order = np.argsort(f[osc])
    np.testing.assert_allclose(f[osc][order], [18.9, 30.1, 46.9], rtol=1e-9)
    np.testing.assert_allclose(d[osc][order], [0.13, 3.0, 0.9], rtol=1e-7)


def test_dominant_oscillations_come_strongest_first_with_their_shapes():
    """Two damped modes with known planar/angular amplitude ratios, 2 s at 114.44 frames/s, the
    faster one aliased (84.7 Hz is filmed at 114.44 - 84.7 = 29.74 Hz), 5 % of frames missing:
    `dominant` returns the filmed frequencies, decays and shapes, the stronger first."""
    fs = 114.44
    t = np.arange(229) / fs
    keep = np.random.default_rng(1).random(t.size) > 0.05
    slow = np.exp(-2.8 * t) * np.cos(2 * np.pi * 18.9 * t)
    fast = np.exp(-9.0 * t) * np.cos(2 * np.pi * 84.7 * t + 0.4)
    shape_slow, shape_fast = np.array([3e-6, -4e-6, 2e-4]), np.array([1e-6, 0.0, 4e-4])  # m, m, rad
    pose = 1e-3 + slow[:, None] * shape_slow + fast[:, None] * shape_fast
    f, d, s, shape = modes.dominant(t[keep], pose[keep], fs, 5, 12)
    np.testing.assert_allclose(f, [18.9, modes.fold(84.7, fs)], rtol=1e-8)
    np.testing.assert_allclose(d, [2.8, 9.0], rtol=1e-6)
    np.testing.assert_allclose(shape, [5e-6 / 2e-4, 1e-6 / 4e-4], rtol=1e-6)
    assert s[0] > s[1]
    assert modes.fold(84.7, fs) == pytest.approx(29.74, abs=1e-9)
    assert modes.fold(126.5, fs) == pytest.approx(12.06, abs=1e-9)


def test_latin_hypercube_starts_at_the_centre_and_fills_each_stratum_once():
    pts = latin_hypercube(np.array([0.032, 0.030]), 2e-3, 9, seed=3)
    np.testing.assert_array_equal(pts[0], [0.032, 0.030])
    for k, c in enumerate([0.032, 0.030]):
        strata = np.floor((pts[1:, k] - (c - 2e-3)) / 4e-3 * 8).astype(int)
        assert sorted(strata) == list(range(8))


def _damped_triskele():
    """The shipped Triskele with Kelvin-Voigt rods (tau 0.2 ms), N 10, dt 0.1 ms, 0.15 s, on the
    shared Triskele's structure (`helpers.shared_triskele`)."""
    return shared_triskele(tau=2e-4, dt=1e-4, alpha=-0.45, duration=0.15)


def test_lumped_platform_modes_are_the_simulated_ones():
    """The Triskele's rods weigh 1e-5 of its platform, so its free motion's modes are those of
    the platform on the rods' static stiffness (`platform_screen.platform_modes`, statics and an
    eigenproblem). Oracle: the frequency of a simulated release (undamped, N 10, dt 0.25 ms) at
    lengths other than nominal, measured by the matrix pencil. Measured: the simulation is 0.55 %
    higher on both modes it shows, the same at a tenth of the push and at half the dt (neither
    nonlinearity nor time discretisation); the start needs 1 %, which the time-domain fit closes.
    Run on the damped test's structure below, its tau set to zero."""
    sc = pcrjax.with_step(_damped_triskele(), 2.5e-4, alpha=-0.45, duration=0.3)
    lengths = jnp.array([0.0315, 0.0327, 0.0309])
    f_lumped, shape = (np.asarray(a) for a in platform_screen.platform_modes(sc)(jnp.log(lengths)))
    traj = pcrjax.simulate(experiment.apply(sc, {"lengths": lengths, "tau": 0.0}))
    m = np.asarray(experiment.planar_pose(sc, traj))[::4]  # 1 kHz
    f, d, s, sh = modes.dominant(np.arange(m.shape[0]) * 1e-3, m, 1e3, 9, 100)
    k = int(np.argmin(np.abs(f_lumped - f[0])))
    assert f[0] == pytest.approx(f_lumped[k], rel=1e-2)
    assert sh[0] == pytest.approx(shape[k], rel=2e-2)


def test_lumped_damping_is_tau_times_the_stiffness():
    """The screen's damping (`platform_screen`): Kelvin-Voigt rods on a platform they barely
    weigh damp it by tau K, so each mode decays at tau w^2 / 2 and rings at w sqrt(1 - zeta^2).
    Oracle: a simulated damped release (N 10, dt 0.1 ms, tau 0.2 ms: zeta 0.04-0.1), its modes
    read by the matrix pencil. Measured: decays within 3 % (the integrator's own damping adds
    1-2 %), frequencies within 0.6 % (the undamped test's offset)."""
    sc = _damped_triskele()
    lengths, tau = jnp.array([0.0315, 0.0327, 0.0309]), 2e-4
    _, w, _, ok = platform_screen.lumped_modes(sc)(jnp.log(lengths))
    assert bool(ok)
    w = np.asarray(w)
    traj = pcrjax.simulate(experiment.apply(sc, {"lengths": lengths, "tau": tau}))
    m = np.asarray(experiment.planar_pose(sc, traj))[::5]  # 2 kHz
    f, d, _, _ = modes.dominant(np.arange(m.shape[0]) * 5e-4, m, 2e3, 9, 100)
    zeta = tau * w / 2
    for fk, dk in zip(f[:2], d[:2]):
        k = int(np.argmin(np.abs(w * np.sqrt(1 - zeta**2) / (2 * np.pi) - fk)))
        assert fk == pytest.approx(w[k] * np.sqrt(1 - zeta[k] ** 2) / (2 * np.pi), rel=1e-2)
        assert dk == pytest.approx(tau * w[k] ** 2 / 2, rel=5e-2)


def test_lumped_modes_from_the_push_hold_where_the_straight_rod_continuation_is_lost():
    """Near `triskele_push_release_r2`'s truth the static solve's continuation from straight rods
    loses its path at about a third of the lengths (the polish crawled there: about half its
    trial steps were rejected). The rest reached from the pushed equilibrium
    (`platform_screen.lumped_modes(from_push=True)`, the polish's fallback) holds at every one.
    Oracle: the same rest solved by a continuation four times finer without the screen's early
    stop (which holds there), and the plain path's modes where it holds (1e-9)."""
    import jax

    rec = load_recording(f"{DATA}/triskele_push_release_r2.csv")
    scene = Problem(rec, ("tau", "lengths")).scene
    rng = np.random.default_rng(0)
    xs = np.log([31.892e-3, 31.339e-3, 31.03e-3]) + rng.uniform(-2e-3, 2e-3, (8, 3))
    plain, pushed = platform_screen.lumped_modes(scene), platform_screen.lumped_modes(scene, from_push=True)
    fine = dataclasses.replace(scene, solver=dataclasses.replace(scene.solver, continuation=4 * scene.solver.continuation))

    @jax.jit
    def oracle(x):
        s = experiment.apply(fine, {"lengths": jnp.exp(x)})
        s = eqx.tree_at(lambda s: (s.load.force, s.load.moment), s, (jnp.zeros(3), jnp.zeros(3)))
        return platform_screen.planar_rest(s)[:2]

    lost = 0
    for x in xs:
        rest, w, _, ok = (np.asarray(a) for a in pushed(jnp.asarray(x)))
        want, want_ok = (np.asarray(a) for a in oracle(jnp.asarray(x)))
        assert bool(ok) and bool(want_ok)
        np.testing.assert_allclose(rest, want, rtol=0, atol=1e-10)
        rest_p, w_p, _, ok_p = (np.asarray(a) for a in plain(jnp.asarray(x)))
        if bool(ok_p):
            np.testing.assert_allclose(rest_p, rest, rtol=0, atol=1e-10)
            np.testing.assert_allclose(w_p, w, rtol=1e-9)
        lost += not bool(ok_p)
    assert lost >= 1  # the case this path is for (measured: 3 of 8)


def _batched_lapack_calls(lowered_text: str) -> list[str]:
    """The LAPACK custom calls of a lowered program whose operands carry a batch dimension."""
    calls = re.findall(r"custom_call @(lapack_\w+)\(.*?\) .*?: \(([^)]*)\)", lowered_text)
    return [name for name, types in calls if any(t.count("x") > 2 for t in re.findall(r"tensor<([^>]*)>", types))]


def test_programs_the_screen_runs_in_threads_hold_no_batched_lapack_call():
    """JAX 0.10's LAPACK kernels split a batch of matrices over XLA's intra-op threads and wait
    for the parts on that pool; the screen ran its tau grid as a batch of least-squares solves, and
    two chunks of it in two threads on a 2-core machine waited for each other for ever (native
    stacks: both pool threads in `ParallelBatchMap` under `lapack_dgesdd_ffi`). The programs the
    screen and the polish run side by side must hold none. Checked on the lowered programs; the
    check itself finds the batch of a `vmap`ped least-squares solve."""
    import jax

    rec = load_recording(f"{DATA}/triskele_push_release_r2.csv")
    scene = Problem(rec, ("tau", "lengths")).scene
    motion = platform_screen.FreeMotion(rec, experiment.forcing_end(scene))
    free = motion.arrays(motion.t.size)
    x = jnp.log(jnp.array([31.9e-3, 31.3e-3, 31.0e-3]))
    for from_push in (False, True):
        modes = jax.jit(platform_screen.modes_program(from_push)).lower(scene, x).as_text()
        assert _batched_lapack_calls(modes) == []
    modes = (jnp.zeros(3), jnp.ones(3), jnp.eye(3), True)  # rest, angular frequencies, shapes, converged
    taus = jax.jit(platform_screen.tau_residuals).lower(free, *modes, jnp.zeros(platform_screen.TAUS)).as_text()
    assert _batched_lapack_calls(taus) == []
    batched = jax.jit(jax.vmap(lambda a: jnp.linalg.lstsq(a, jnp.ones(6))[0])).lower(jnp.ones((5, 6, 2))).as_text()
    assert _batched_lapack_calls(batched) == ["lapack_dgesdd_ffi"]


def test_programs_of_the_threaded_ranking_and_screening_hold_no_batched_lapack_call():
    """The modal start ranks its candidates by push-and-camera fits, and screens the best two by
    short fits of every unknown, on one thread per core (`identify.threads`), and the fit's
    passes take the Jacobian at a trial point beside its residual (``speculate``): the rollout's
    residual and Jacobian, the push-and-camera residual and Jacobian and the clock scan then run
    side by side, and must hold no batched LAPACK call. The clock scan's 41 starts as a `vmap`
    made its solve a batched LU (41 x 6 x 6)."""
    import jax

    rec = load_recording(f"{DATA}/triskele_push_release_r2.csv")
    pb = Problem(rec, ("tau", "lengths"))
    theta = pb.to_theta(pb.initial_values)
    noise, (mask, active) = pb._noise(), pb.window(0.1)
    motion = jax.eval_shape(lambda th: Problem._residual_fn(pb, th, noise, mask, active), theta)[1]
    m0 = jnp.zeros(motion.shape)
    push = jnp.arange(pb.n_physical)[pb.slices["push_force"].start : pb.slices["push_moment"].stop]
    dm = jnp.zeros((*motion.shape, push.size))
    x = jnp.zeros(push.size + theta.size - pb.n_physical)
    linear = (m0, dm, theta, push, noise, mask)
    programs = {
        "residual": (Problem._residual_fn, theta, noise, mask, active),
        "jacobian": (Problem._residual_and_jacobian_fn, theta, noise, mask, active),
        "linear residual": (Problem._linear_residual_fn, x, *linear),
        "linear jacobian": (jax.jacfwd(Problem._linear_residual_fn, argnums=1), x, *linear),
        "clock scan": (Problem._clock_scan_fn, jnp.tile(x, (len(CLOCK_STARTS), 1)), *linear),
    }
    for name, (method, *args) in programs.items():
        text = jax.jit(lambda *a, method=method: method(pb, *a)).lower(*args).as_text()
        assert "lapack" in text or name.startswith("linear"), name  # the checker sees the solves
        assert _batched_lapack_calls(text) == [], name


def test_free_motion_screen_is_blind_to_aliasing_push_camera_and_clock():
    """`platform_screen.FreeMotion`: three damped modes filmed at 114.44 frames/s (all three
    alias), through a rotated, offset camera with a clock offset, missing frames and noise: at
    the true modes and tau the residual is the noise alone, whatever the amplitudes and phases
    (they are solved for); tau 50 % off or the slowest mode 2 % off leaves twice the noise's
    (the fast modes ring for a few frames only)."""
    rng = np.random.default_rng(11)
    w = 2 * np.pi * np.array([71.0, 133.0, 154.0])
    phi = np.linalg.qr(rng.standard_normal((3, 3)))[0] * np.array([[1e-2], [1e-2], [1.0]])
    tau, beta, rest = 1.5e-4, 0.02, np.array([1e-3, 2e-3, 0.19])
    t = np.arange(230) / 114.44
    t = t[rng.random(t.size) > 0.04]
    zeta = tau * w / 2
    tt = t[:, None] + 2.1e-3  # the camera's clock offset
    waves = np.exp(-zeta * w * tt) * np.cos(w * np.sqrt(1 - zeta**2) * tt + rng.uniform(0, 6, 3)) * rng.uniform(1, 3, 3)
    moved = waves @ phi.T * 1e-5  # (frames, 3): 0.1-0.6 um, 10-30 urad, as on the Triskele
    c, s = np.cos(beta), np.sin(beta)
    seen = np.stack([c * moved[:, 0] - s * moved[:, 1], s * moved[:, 0] + c * moved[:, 1], moved[:, 2]], axis=1)
    settled = np.array([1.3e-3, 1.1e-3, rest[2] + beta])
    sigma = np.array([2e-9, 2e-9, 2e-6])
    pose = settled + seen + rng.standard_normal(seen.shape) * sigma
    rec = types.SimpleNamespace(t=t, pose=pose, path="synthetic")
    motion = platform_screen.FreeMotion(rec, 0.0)
    assert np.allclose(motion.sigma, sigma, rtol=0.25)

    def chi2(w_, tau_):
        r = motion.residual(jnp.asarray(rest), jnp.asarray(w_), jnp.asarray(phi), jnp.log(tau_))
        return float(jnp.sum(r**2)) / motion.rows

    # measured: 0.91 at the truth, 3.0 at tau 1.5x, 2.5 with the slowest mode 2 % off
    at_truth = chi2(w, tau)
    assert at_truth < 1.3
    assert chi2(w, 1.5 * tau) > 2 * at_truth and chi2(w * np.array([1.02, 1.0, 1.0]), tau) > 2 * at_truth


def test_platform_screen_finds_a_finer_grid_recordings_lengths():
    """The push-release start on `triskele_push_release_r1` (truth drawn inside the prior,
    simulated 9x finer in space and extrapolated to dt 0 in time): the frequency features left
    30 % of the prior matching and none of the polished candidates near the truth; the
    time-domain screen of the lumped modes puts its best within 50 um of the truth on every rod
    (the prior is +-2 mm) and tau within 20 %, from tau a factor 3 off. Measured: 15 um, 1 %."""
    rec = load_recording(f"{DATA}/triskele_push_release_r1.csv")
    pb = Problem(rec, ("tau", "lengths"), initial={"tau": rec.truth["tau"] * 3})
    theta = np.asarray(pb.to_theta(pb.initial_values))
    said = []
    theta, found = start.initial_lengths(pb, theta, progress=lambda msg, *a: said.append(msg))
    assert any("polished" in m for m in said)
    lengths = np.exp(theta[pb.slices["lengths"]])
    assert np.all(np.abs(lengths - np.asarray(rec.truth["lengths"])) < 50e-6), lengths
    assert float(np.exp(theta[pb.damping[0]][0])) == pytest.approx(rec.truth["tau"], rel=0.2)
    assert np.allclose(found[0], theta[pb.slices["lengths"]])


def test_static_response_screen_matches_continuation_solves_and_the_recording():
    """The actuator-step start's screen (`start.Features.of_all`: the rest after the move solved
    by Newton from the rest before it, a lost continuation passed over) on
    `triskele_actuator_step_r1` (truth drawn inside the prior, simulated 9x finer in space and
    extrapolated to dt 0): at the true lengths and at seven others of the prior, the shift of the
    rest equals that of two static solves by continuation from straight legs (1e-10 m and rad;
    NaN at the same lengths), and at the truth it is the recorded one within the start's match
    (3 %)."""
    import jax

    rec = load_recording(f"{DATA}/triskele_actuator_step_r1.csv")
    pb = Problem(rec, ("tau", "lengths"))
    theta = np.asarray(pb.to_theta(pb.initial_values))
    feats = start.Features(pb, theta)
    truth = np.log(np.asarray(rec.truth["lengths"]))
    xs = np.concatenate([truth[None], np.log(latin_hypercube(np.exp(theta[pb.slices["lengths"]]), 2e-3, 8, seed=3))[1:]])
    got = np.asarray(feats.of_all(xs))
    scene = pb.scene
    end = scene.actuation(jnp.asarray(experiment.forcing_end(scene)))
    after = eqx.tree_at(lambda s: s.actuation.initial, scene, end)

    @jax.jit
    def rest(sc, x):
        r = pcrjax.solve_static(experiment.apply(sc, {"lengths": jnp.exp(x)}), throw=False)
        pose = jnp.concatenate([r.position[:2], r.rotation_vector[2:]])
        return jnp.where(r.converged, pose, jnp.nan)

    want = np.asarray([start.frame_invariant(rest(after, x) - rest(scene, x)) for x in xs])
    assert np.array_equal(np.isnan(got), np.isnan(want)) and np.all(np.isfinite(got[0]))
    ok = np.all(np.isfinite(want), axis=1)
    # both rests meet the Newton tolerance from other starts; the shift is their difference
    # (measured: 1.1e-11 apart at most, on shifts of 0.2-2.4 um and 0.3-0.6 mrad)
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-10)
    assert feats.distance(got[0]) < start.MATCH, (got[0], feats.recorded)


def test_push_and_camera_fit_scans_the_clock_for_the_recorded_push():
    """`Problem.fit_linear` on `triskele_push_release_r1` at the true lengths and tau (the
    candidates' ranking of the modal start): its clock offset, 2.06 ms, is a third of a period of
    the platform's modes, and a push-and-camera fit from a clock of 0 alone found the opposite
    push, a third as large, seen 1.25 ms early (measured: push [5.9, -6.7] mN against the truth's
    [-13.6, 17.6], cost 10 720), and whole fits of this truth filmed with other noise ended in
    that basin. Started from every clock in `CLOCK_STARTS` it finds the truth's push and clock
    (measured: force 4.7 % and moment 3 % off, clock 0.19 ms; cost 1 584; the fit's own grid
    is not the truth's)."""
    rec = load_recording(f"{DATA}/triskele_push_release_r1.csv")
    pb = Problem(rec, ("tau", "lengths"))
    truth = rec.truth
    theta = np.asarray(pb.to_theta(dict(pb.initial_values, tau=jnp.asarray(truth["tau"]), lengths=jnp.asarray(truth["lengths"]))))
    th, cost = pb.fit_linear(theta, 0.1, clocks=CLOCK_STARTS)
    got = pb.to_values(jnp.asarray(th))
    push = np.linalg.norm(np.asarray(got["push_force"]) - truth["push_force"]) / np.linalg.norm(truth["push_force"])
    assert push < 0.1
    assert float(got["push_moment"]) == pytest.approx(truth["push_moment"], rel=0.1)
    assert abs(float(got["time_offset"]) - truth["time_offset"]) < 0.5e-3
    assert cost < pb.fit_linear(theta, 0.1)[1]  # a lower minimum than one clock's


def test_settled_pose_is_the_constant_beside_damped_oscillations():
    """An aliased 19 Hz oscillation plus a faster decaying 47 Hz one around a constant, 0.5 s at
    114.44 frames/s with frames missing: the mean is off by a fraction of the amplitude, the
    least-squares constant is exact."""
    fs = 114.44
    t = np.delete(np.arange(58) / fs, [5, 17, 30])
    end = np.array([3e-6, -2e-6, 2.8e-4])
    osc = np.cos(2 * np.pi * 19.2 * t) * np.exp(-0.3 * t)
    fast = np.sin(2 * np.pi * 47.4 * t) * np.exp(-2.0 * t)
    pose = end + osc[:, None] * np.array([1e-6, 2e-6, 1e-4]) + fast[:, None] * np.array([5e-7, -3e-7, 4e-5])
    z, got = modes.settled(t, pose, fs, 5)
    np.testing.assert_allclose(got, end, rtol=1e-9)
    assert abs(np.mean(pose[:, 2]) - end[2]) > 1e-7  # what a plain mean would have said


def test_frequency_matching_stops_where_the_model_fails():
    """Lengths where the model fails (NaN features) stop the matching there, unconverged,
    instead of crashing or stepping on garbage; where it holds, the match is found."""
    features = lambda x: np.exp(-0.5 * x)  # noqa: E731
    x, ok = modes.match_frequencies(features, np.array([0.0]), np.array([0.95]))
    assert ok and np.exp(-0.5 * x[0]) == pytest.approx(0.95, rel=1e-4)
    for fails_above in (-1.0, 1e-5):  # at the start, at its finite-difference neighbour
        failing = lambda x: np.where(x[0] < fails_above, features(x), np.nan)  # noqa: E731
        x, ok = modes.match_frequencies(failing, np.array([0.0]), np.array([0.95]))
        assert not ok and x[0] == 0.0


def test_recording_too_short_for_the_modal_start_is_reported_before_compiling():
    """40 ms of the push-release (5 frames) hold no window of 12 consecutive frames: the fit
    stops at once with a message that says so (no simulation is compiled first)."""
    rec = load_recording(f"{DATA}/triskele_push_release.csv").window(0.04)
    with pytest.raises(ValueError, match="too short"):
        fit(Problem(rec, ("tau", "lengths")))


def test_levenberg_marquardt_refuses_a_start_where_the_model_fails():
    """A residual that is NaN at the start (a rollout whose Newton solves failed) is reported,
    not returned as a converged fit."""
    with pytest.raises(FitError, match="not finite"):
        levenberg_marquardt(lambda th: np.full(3, np.nan), lambda th: (np.full(3, np.nan), np.ones((3, 1))), np.zeros(1))
    # nor a Jacobian that turns non-finite after a step (its tangents failed)
    rf = lambda th: np.array([th[0] - 1.0, th[0] + 1.0])  # noqa: E731
    for bad in (np.nan, np.inf):
        rj = lambda th, bad=bad: (rf(th), np.full((2, 1), 1.0 if th[0] == 0.5 else bad))  # noqa: E731
        with pytest.raises(FitError, match="not finite"):
            levenberg_marquardt(rf, rj, np.array([0.5]), 10, max_step=np.inf)


def _large_residual_problem(curvature=(-0.9, -0.5), angle=0.6):
    """Dennis and Schnabel's example 10.2.5 in two coordinates, turned by ``angle``: residuals
    ``y_i + 1`` and ``c_i y_i^2 + y_i - 1`` with ``y = R(-angle) x``. The optimum is x = 0 (gradient
    zero there, Hessian diag(2 - 2 c_i) > 0), where the residuals are (1, -1) per coordinate, not
    zero: Gauss-Newton, which drops their curvature ``-2 c_i``, converges only linearly there,
    by a factor |c_i| per iteration."""
    c = np.asarray(curvature)
    ca, sa = np.cos(angle), np.sin(angle)
    R = np.array([[ca, sa], [-sa, ca]])

    def rf(x):
        y = R @ np.asarray(x)
        return np.concatenate([y + 1.0, c * y**2 + y - 1.0])

    def rj(x):
        y = R @ np.asarray(x)
        return rf(x), np.concatenate([R, (2.0 * c * y + 1.0)[:, None] * R])

    return rf, rj


def test_levenberg_marquardt_converges_where_the_residuals_do_not_vanish():
    """At an optimum with residuals that do not vanish (a fit's are the noise), Gauss-Newton alone
    crawls (here by 0.9 per iteration: 40 iterations from 1 to 1e-2): the fit's model of the
    Hessian adds their curvature by secant updates, and its convergence test is the gradient's,
    not a step's gain. The oracle is the closed-form optimum x = 0."""
    rf, rj = _large_residual_problem()
    x, _, r, it, converged, hist = levenberg_marquardt(rf, rj, np.array([0.3, -0.2]), 40, ftol=1e-14, max_step=np.inf)
    assert converged and it < 20, (it, hist)
    assert np.max(np.abs(x)) < 1e-6, x
    assert np.isclose(0.5 * r @ r, 2.0)  # the residuals at the optimum: (1, -1) per coordinate
    # a start at the optimum is converged with no step taken
    x0, *_, it0, converged0, _ = levenberg_marquardt(rf, rj, np.zeros(2), 40, ftol=1e-14, max_step=np.inf)
    assert converged0 and it0 == 0 and np.all(x0 == 0.0)


def _exponential_decay_problem():
    """``a exp(-b t) + c`` sampled at 50 times against data made with (2, 1.3, 0.5): a
    zero-residual problem whose closed-form optimum is those values."""
    t = np.linspace(0.0, 2.0, 50)
    y = 2.0 * np.exp(-1.3 * t) + 0.5

    def rf(p):
        return p[0] * np.exp(-p[1] * t) + p[2] - y

    def rj(p):
        e = np.exp(-p[1] * t)
        return rf(p), np.stack([e, -p[0] * t * e, np.ones_like(t)], axis=1)

    return rf, rj, np.array([2.0, 1.3, 0.5])


def _counting(rj):
    """(``rj`` that counts its calls, the count: a list of one)."""
    calls = [0]

    def counted(x):
        calls[0] += 1
        return rj(x)

    return counted, calls


@pytest.mark.parametrize("case", ["large residual", "exponential decay"])
def test_levenberg_marquardt_with_secant_jacobians_reaches_the_optimum_with_the_exact_jacobian(case):
    """Broyden's secant Jacobian between exact ones (``secant_jacobian``, for a rollout's
    Jacobian that costs many residuals) reaches the closed-form optimum, declares convergence
    only on the exact Jacobian's test, and returns that Jacobian; on the zero-residual problem
    it takes fewer exact Jacobians than a step each."""
    if case == "large residual":
        rf, rj = _large_residual_problem()
        start, optimum = np.array([0.3, -0.2]), np.zeros(2)
    else:
        rf, rj, optimum = _exponential_decay_problem()
        start = np.array([1.0, 0.5, 0.0])
    runs = {}
    for secant in (False, True):
        counted, calls = _counting(rj)
        x, J, r, it, converged, _ = levenberg_marquardt(
            rf, counted, start, 60, ftol=1e-16, max_step=np.inf, secant_jacobian=secant
        )
        assert converged, (case, secant, it)
        assert np.max(np.abs(x - optimum)) < 1e-6, (case, secant, x)
        np.testing.assert_array_equal(J, rj(x)[1])  # the exact Jacobian at the answer
        runs[secant] = calls[0], it
    if case == "exponential decay":
        assert runs[True][0] < runs[False][0] / 2, runs


def test_a_pass_stopped_on_its_secant_jacobian_starts_the_next_from_it():
    """The fit's least-squares pass over the whole recording only starts the noise-weighted one:
    it stops on its secant Jacobian's test (``exact_test=False``) and the next pass starts from
    that Jacobian (``initial_exact=False``), taking the exact one where it would stop. Oracle:
    the exponential decay's closed-form optimum, the exact Jacobian returned there, and fewer
    exact Jacobians than the same two passes with exact tests. The first pass stops after 20
    iterations (it takes 30 to its own test), so that the second has steps to take."""
    rf, rj, optimum = _exponential_decay_problem()
    counts = {}
    for exact in (True, False):
        counted, calls = _counting(rj)
        x, J, r, *_ = levenberg_marquardt(
            rf, counted, np.array([1.0, 0.5, 0.0]), 20, ftol=1e-2, max_step=np.inf, secant_jacobian=True, exact_test=exact
        )
        x, J, r, it, converged, _ = levenberg_marquardt(
            rf, counted, x, 60, ftol=1e-16, max_step=np.inf, initial=(r, J), secant_jacobian=True, initial_exact=exact
        )
        assert converged and np.max(np.abs(x - optimum)) < 1e-6, (exact, x)
        np.testing.assert_array_equal(J, rj(x)[1])
        counts[exact] = calls[0]
    assert counts[False] < counts[True], counts


def _rosenbrock():
    """Rosenbrock's valley as least squares, r = (100 (y - x^2), 1 - x): a curved valley whose
    closed-form optimum is (1, 1)."""

    def rf(p):
        return np.array([100.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])

    def rj(p):
        return rf(p), np.array([[-200.0 * p[0], 100.0], [-1.0, 0.0]])

    return rf, rj


def test_geodesic_acceleration_follows_a_curved_valley_in_fewer_jacobians():
    """On Rosenbrock's valley from (-1.2, 1) the Gauss-Newton step leaves the curved valley floor
    and the damping cuts it short (118 iterations on the exact Jacobian; on Broyden's secant
    the fit stalls). With geodesic acceleration (``geodesic``: the step corrected by the
    residuals' second derivative along it, one more residual each), from the exact Jacobian or
    from the secant (exact ones once a secant step fails), the fit reaches the closed-form
    optimum (1, 1) with under half the Jacobians of the exact plain steps, and returns the exact
    Jacobian there."""
    rf, rj = _rosenbrock()
    jacobians = {}
    for geodesic, secant in ((False, False), (True, False), (True, True)):
        counted, calls = _counting(rj)
        x, J, *_, converged, _ = levenberg_marquardt(
            rf, counted, np.array([-1.2, 1.0]), 300, ftol=1e-16, max_step=np.inf, geodesic=geodesic, secant_jacobian=secant
        )
        assert converged and np.max(np.abs(x - 1.0)) < 1e-6, (geodesic, secant, x)
        np.testing.assert_array_equal(J, rj(x)[1])
        jacobians[geodesic, secant] = calls[0]
    assert max(jacobians[True, False], jacobians[True, True]) < jacobians[False, False] / 2, jacobians


def test_a_window_stops_on_the_broyden_test_where_the_exact_jacobian_would_stop_it_too():
    """A window's answer only starts the next window, which takes its own Jacobian there: with
    ``secant_test`` the convergence test after an accepted step is made on the Broyden update
    of the Jacobian, and the exact one is taken only where that fails. Oracle: on the
    large-residual problem, at each tolerance, the pass stops at the point where the exact
    tests stop it (the closed-form test: the decrement of the exact Jacobian there below the
    tolerance), with one exact Jacobian fewer."""
    rf, rj = _large_residual_problem()
    for ftol in (1e-1, 1e-2, 1e-3):
        runs = {}
        for secant_test in (False, True):
            counted, calls = _counting(rj)
            x, _, _, it, converged, _ = levenberg_marquardt(
                rf,
                counted,
                np.array([0.3, -0.2]),
                40,
                ftol=ftol,
                max_step=np.inf,
                secant_test=secant_test,
                exact_test=not secant_test,
            )
            r, J = rj(x)
            assert converged and decrement(J, r) < ftol * 0.5 * float(r @ r), (ftol, secant_test, x)
            runs[secant_test] = x, calls[0]
        np.testing.assert_array_equal(runs[True][0], runs[False][0])
        assert runs[True][1] == runs[False][1] - 1, (ftol, runs)


def test_jacobians_speculated_beside_the_trial_residual_change_no_iterate():
    """``speculate``: the Jacobian at each trial point starts in another thread beside the trial's
    residual, so an accepted step has it sooner. It changes no number: on Rosenbrock's valley
    with geodesic steps (an exact Jacobian after every accepted step) the iterates, the losses
    and the Jacobian returned equal those of the plain run, and the optimum is the closed-form
    (1, 1); the Jacobians were taken off the caller's thread."""
    import threading

    rf, rj = _rosenbrock()
    runs = {}
    for speculate in (False, True):
        where = []

        def traced(x, where=where):
            where.append(threading.current_thread() is threading.main_thread())
            return rj(x)

        x, J, _, it, converged, hist = levenberg_marquardt(
            rf, traced, np.array([-1.2, 1.0]), 300, ftol=1e-16, max_step=np.inf, geodesic=True, speculate=speculate
        )
        assert converged and np.max(np.abs(x - 1.0)) < 1e-6, (speculate, x)
        runs[speculate] = x, J, it, hist, where
    for a, b in zip(runs[False][:4], runs[True][:4], strict=True):
        np.testing.assert_array_equal(a, b)
    assert all(runs[False][4]) and not all(runs[True][4])


def test_geodesic_correction_is_half_the_acceleration_where_it_is_small_beside_the_step():
    """Residuals quadratic along every line, ``r = A theta - b + 0.5 c |theta|^2 u``, have the
    closed-form second directional derivative ``r_vv = c |v|^2 u`` (the finite difference of
    `least_squares._accelerated` is exact for them). The step is corrected to ``v + a / 2``,
    ``a = -damped^{-1} J^T r_vv``, where twice the acceleration is at most ``GEODESIC_RATIO``
    of the step in the damping's metric, and left ``v`` where it is larger or the corrected
    step leaves the trust region."""
    from identify import least_squares as ls

    rng = np.random.default_rng(11)
    A, u = rng.standard_normal((12, 3)), rng.standard_normal(12)
    b, theta = rng.standard_normal(12), np.array([0.3, -0.2, 0.5])
    for c, v, corrected in ((-0.05, np.array([0.1, 0.05, -0.08]), True), (5.0, np.array([0.2, 0.1, -0.16]), False)):

        def rf(x, c=c):
            return A @ x - b + 0.5 * c * float(x @ x) * u

        J = A + c * np.outer(u, theta)
        scale = np.diag(np.diag(J.T @ J))
        damped = J.T @ J + 1e-3 * scale
        a = -np.linalg.solve(damped, J.T @ (c * float(v @ v) * u))
        ratio = 2 * np.sqrt(a @ scale @ a) / np.sqrt(v @ scale @ v)
        assert (ratio <= ls.GEODESIC_RATIO) == corrected, ratio  # one case on each side of the bound
        step = ls._accelerated(rf, theta, rf(theta), J, v, damped, scale, np.inf)
        np.testing.assert_allclose(step, v + 0.5 * a if corrected else v, rtol=1e-7, atol=1e-12)
        if corrected:  # a trust region that holds the plain step but not the corrected one, longer here
            bound = 0.5 * (np.max(np.abs(v)) + np.max(np.abs(v + 0.5 * a)))
            assert np.max(np.abs(v)) < bound < np.max(np.abs(v + 0.5 * a))
            np.testing.assert_array_equal(ls._accelerated(rf, theta, rf(theta), J, v, damped, scale, bound), v)


def test_a_resumed_pass_keeps_the_exact_jacobians_it_had_switched_to():
    """A pass on the secant with geodesic steps that switched to exact Jacobians, interrupted and
    resumed from its saved state, goes on with exact ones: it ends at the same point as the
    uninterrupted run, the closed-form optimum (1, 1) of Rosenbrock's valley, with the same
    residual evaluations after that state (a secant step taken again would cost a failed trial
    more)."""
    rf, rj = _rosenbrock()
    kw = dict(ftol=1e-16, max_step=np.inf, geodesic=True, secant_jacobian=True)
    counted, count = _counting(rf)
    states = []  # (saved state, residuals evaluated by then)
    x, *_ = levenberg_marquardt(counted, rj, np.array([-1.2, 1.0]), 300, save=lambda st: states.append((st, count[0])), **kw)
    assert np.max(np.abs(x - 1.0)) < 1e-6, x
    state, evaluated = states[len(states) // 2]
    assert not state["secant_steps"]  # switched by then
    after = count[0] - evaluated
    count[0] = 0
    y, *_, converged, _ = levenberg_marquardt(counted, rj, np.array([-1.2, 1.0]), 300, start=state, **kw)
    assert converged
    np.testing.assert_array_equal(y, x)
    assert count[0] == after, (count[0], after)


def _check_recovery(res, truth, names):
    """Every truth within 3 reported uncertainties: statistical and discretisation combined."""
    v = res.values
    se = {k: res.uncertainty(k) for k in res.standard_errors}
    if "tau" in names:
        assert abs(v["tau"] / truth["tau"] - 1) < 0.02
        assert abs(v["tau"] - truth["tau"]) < 3 * se["tau"]
    if "lengths" in names:
        L, Lt, Ls = np.atleast_1d(v["lengths"]), np.atleast_1d(truth["lengths"]), np.atleast_1d(se["lengths"])
        assert np.all(np.abs(L / Lt - 1) < 1e-3)
        assert np.all(np.abs(L - Lt) < 3 * Ls)
    # The camera's frame: within 3 uncertainties, and within a thousandth of the robot's size,
    # the accuracy asked of the lengths. Its uncertainty follows the lengths' (the frame is the
    # start pose seen minus the model's rest pose, which the lengths move), and on a recording
    # that pins the lengths to 25-80 um (triskele_push_release_r1) that is more than 1e-3 of
    # the size: a precision the data do not hold is not asked.
    size = float(np.max(np.atleast_1d(truth["lengths"])))
    off, off_t = np.asarray(v["frame_offset"]), np.asarray(truth["frame_offset"])
    assert np.all(np.abs(off - off_t) < 3 * np.asarray(se["frame_offset"]))
    assert np.all(np.abs(off - off_t) < 1e-3 * size)
    assert abs(v["frame_rotation"] - truth["frame_rotation"]) < 3 * se["frame_rotation"]
    assert se["frame_rotation"] < 1e-3


@pytest.fixture(scope="module")
def problems():
    """One Problem (two compiled programs) per recording, shared by the slow tests."""
    cache = {}

    def get(name, fitted=("tau", "lengths")):
        if (name, fitted) not in cache:
            rec = load_recording(f"{DATA}/{name}.csv")
            # issue 4's start: nominal lengths, damping a factor 3 off the truth
            cache[name, fitted] = Problem(rec, fitted, initial={"tau": rec.truth["tau"] / 3})
        return cache[name, fitted]

    return get


def _check_fit(res, rec):
    """A fit of a shipped recording, made by the fit's own model on its own grid: there the
    truth is the coarse model's, so the fit is checked unrefined (a refinement walks away from
    it by the discretisation error: the suite's recordings, made finer, test that)."""
    assert res.converged and not res.refinements
    _check_recovery(res, rec.truth, ("tau", "lengths"))
    assert res.loss < 1.5  # reduced chi-square at the noise level
    assert np.allclose(res.sigma, [rec.truth["noise_position"], rec.truth["noise_angle"]], rtol=0.2)


SUITE = [f"{kind}_r{k}" for kind in ("triskele_push_release", "triskele_actuator_step", "cantilever_release") for k in (1, 2)]
SUITE.append("cantilever_independent")  # made by experiments_data/independent_rod.py, not by pcrjax


@pytest.mark.slow
@pytest.mark.parametrize("name", SUITE)
def test_fit_recovers_random_truths_simulated_finer(name, tmp_path):
    """The random-truth suite (truths drawn inside the prior, simulated on a grid converged at the
    noise: the Triskele's 9x finer in space and extrapolated to dt 0, the cantilever's 3x in space
    and 100x in time), fitted from the nominal lengths and the sidecar's tau (a factor 3 off): every
    physical truth within 3 combined uncertainties (statistical and discretisation)."""
    rec = load_recording(f"{DATA}/{name}.csv")
    res = fit(Problem(rec, ("tau", "lengths")), state_dir=tmp_path)
    assert res.converged
    _check_recovery(res, rec.truth, ("tau", "lengths"))


@pytest.mark.slow
def test_wild_frames_are_reported_and_change_nothing(problems, tmp_path):
    """1 % of the Triskele's frames thrown 100 noise levels off (decoding errors): the fit finds
    the same values as without them, to a third of a standard error, and reports those frames."""
    pb = problems("triskele_actuator_step")
    clean = fit(pb, refine_levels=0)
    rec = pb.rec
    wild = np.random.default_rng(7).choice(rec.frames, size=rec.frames // 100, replace=False)
    noise = np.array([rec.truth["noise_position"]] * 2 + [rec.truth["noise_angle"]])
    pose = rec.pose.copy()
    pose[wild] += 100 * noise * np.random.default_rng(8).choice([-1.0, 1.0], size=(wild.size, 3))
    res = fit(Problem(dataclasses.replace(rec, pose=pose), pb.fit, initial={"tau": rec.truth["tau"] / 3}), refine_levels=0)
    assert np.allclose(sorted(res.outliers), np.sort(rec.t[wild]))
    for key in ("tau", "lengths"):
        moved = np.abs(np.asarray(res.values[key]) - np.asarray(clean.values[key]))
        assert np.all(moved < np.asarray(clean.standard_errors[key]) / 3), (key, moved, clean.standard_errors[key])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["triskele_push_release", "triskele_actuator_step"])
def test_fit_recovers_truth(problems, name, tmp_path):
    pb = problems(name)
    _check_fit(fit(pb, state_dir=tmp_path, refine_levels=0), pb.rec)


class _Stop(Exception):
    pass


@pytest.mark.slow
def test_interrupted_cantilever_fit_resumes_and_recovers_truth(problems, tmp_path):
    pb = problems("cantilever_release")

    first = []

    def interrupt(stage, it, loss, step):
        if stage.startswith("window") and it == 1:  # the first window after the start's screening
            first.append(stage)
            raise _Stop

    with pytest.raises(_Stop):
        fit(pb, state_dir=tmp_path, progress=interrupt, refine_levels=0)
    assert (tmp_path / "fit_state.json").is_file()
    seen = []
    res = fit(pb, state_dir=tmp_path, progress=lambda stage, *a: seen.append(stage), refine_levels=0)
    assert not any(s.startswith(("start", "candidate")) for s in seen)  # no work redone
    assert seen[0] == first[0]
    _check_fit(res, pb.rec)


@pytest.mark.slow
def test_short_noisy_recording_reports_large_uncertainty():
    """50 ms of the released cantilever filmed with 1000 times the noise (2 mm, 20 mrad) barely
    shows the damping: the reported error must say so and still cover the truth. (With the
    shipped noise, even 10 ms determine tau to 1.3 %: the tip moves centimetres.)"""
    rec = load_recording(f"{DATA}/cantilever_release.csv").window(0.05)
    tr = rec.truth
    sigma = 1000 * np.array([tr["noise_position"]] * 2 + [tr["noise_angle"]])
    noisy = dataclasses.replace(rec, pose=rec.pose + np.random.default_rng(5).standard_normal(rec.pose.shape) * sigma)
    pb = Problem(noisy, ("tau", "lengths")).with_noise(sigma)
    vals = dict(pb.initial_values, **{k: np.asarray(tr[k], float) for k in ("tau", "lengths", "push_force", "time_offset")})
    th, J, r, *_ = levenberg_marquardt(
        pb.residual, pb.residual_and_jacobian, np.asarray(pb.to_theta(vals)), 30, max_step=pb.max_step
    )
    res = summarize(pb, th, J, r)
    se, err = res.standard_errors["tau"], res.values["tau"] - tr["tau"]
    # large: more than the 2 % the issue asks of a fit (measured 7 %, against 2e-6 from the whole
    # shipped recording), so the fit does not claim an accuracy the data do not hold
    assert se > 0.02 * tr["tau"], (se, err)
    assert abs(err) < 3 * se


@pytest.mark.slow
def test_recording_with_the_scenes_own_values_fits_back_unchanged(tmp_path):
    """A recording generated with the scene's own damping, length and push (the cantilever's
    sidecar values) fitted from those values: the fit must return them (no drift away from a
    start that is already the truth) with the loss at the noise level."""
    gen = recording_generator()
    spec = dict(gen.RECORDINGS["cantilever_release"])
    truth = dict(
        spec["truth"], tau=spec["rod"]["tau"], lengths=0.4, push_force=[spec["tip"]["force"][0], spec["tip"]["force"][2]]
    )
    spec.update(seconds=0.5, truth=truth)
    rec = load_recording(gen.generate("cantilever_release", spec, tmp_path))
    pb = Problem(rec, ("tau", "lengths"))
    start = pb.initial_values
    assert float(start["tau"]) == truth["tau"] and float(start["lengths"]) == truth["lengths"]  # the scene's own values
    res = fit(pb, state_dir=tmp_path, refine_levels=0)
    _check_fit(res, rec)
    assert abs(res.values["push_force"][1] - truth["push_force"][1]) < 3 * res.standard_errors["push_force"][1]


def test_rod_tip_angle_is_the_tangent_angle_in_the_bending_plane():
    """A tip marker's angle (issue 17): `planar_pose`'s theta of a rod is its tip tangent's angle
    in the x-z plane. Oracle: the one-sided second-order difference of the last three nodes'
    positions (independent of the rotations; its error h^2 |p'''| / 3 = h^2 F / (3 EI) is 2.6e-5
    rad at 2 N and N = 160; shear tilts d3 off p' by 9e-6 rad), on the shipped cantilever bent
    by its 2 N tip load and by 20 mN (nearly straight)."""
    base = pcrjax.with_solver(pcrjax.load_scene("cantilever"), nodes=160)
    for force in (-2.0, -0.02):
        st = pcrjax.solve_static(eqx.tree_at(lambda s: s.load.force, base, jnp.array([0.0, 0.0, force])))
        traj = types.SimpleNamespace(position=st.position[None], rotation_vector=st.rotation_vector[None])
        theta = float(experiment.planar_pose(base, traj)[0, 2])
        p = np.asarray(st.positions)[0]
        d = 3 * p[-1] - 4 * p[-2] + p[-3]
        expected = np.arctan2(d[2], d[0])
        print(f"tip load {force} N: theta {theta:.6f} rad, from the nodes {expected:.6f} rad")
        assert abs(theta - expected) < 1e-4 and abs(theta) > 1e-3


@pytest.mark.integration  # the whole command: fit, profiles, three refinements
def test_cli_fits_a_small_recording_from_a_finer_grid_end_to_end(tmp_path, capsys, monkeypatch):
    """The whole `pcrjax-identify` path on a small case (the integration set): a cantilever
    recording (0.2 s at 1 kHz) whose truth is simulated on a grid 3x finer in space and 40x in
    time than the fit's (N 6, dt 2 ms), fitted from tau a factor 3 off and the length 1.6 mm off
    (residuals, Jacobians, Levenberg-Marquardt over the windows, the noise re-estimated, the
    profiles, one space and two time refinements, the extrapolation to dt 0, fit.json and the
    plots), with 2 % of its frames thrown off by decoding errors: every truth within 3 combined
    uncertainties, and the wild frames reported."""
    from identify import cli

    path, truth = committed_recording("small_release", tmp_path)
    # a decoding error now and then: 2 % of the frames thrown 5 mm off (the noise is 2 um)
    rec = load_recording(path)
    wild = np.random.default_rng(3).choice(rec.frames, size=rec.frames // 50, replace=False)
    pose = rec.pose.copy()
    pose[wild, :2] += 5e-3 * np.array([1.0, -1.0])
    write_frames(path, rec.t, pose)
    out = tmp_path / "fit"
    # what fit.json holds when the refinements start: the fit's own answer
    from identify import discretisation

    kept, report = [], discretisation.report

    def reading_first(*a, **k):
        kept.append(json.loads((out / "fit.json").read_text()))
        return report(*a, **k)

    monkeypatch.setattr(discretisation, "report", reading_first)
    assert cli.main([str(path), "--out", str(out), "--start", "given", "--refine", "2", "--profile"]) == 0
    printed = capsys.readouterr().out
    print(printed)
    assert "± statistical (noise), ± discretisation" in printed
    res = json.loads((out / "fit.json").read_text())
    # that answer is the fit grid's: the tolerance refit (the same grid, a tenth of the Newton
    # tolerance) moves its values by the tolerance errors alone; no discretisation error yet
    (first,) = kept
    assert res["final"] and not first["final"] and first["discretisation_errors"] == {}
    assert first["model"] == dict(nodes=6, dt=pytest.approx(2e-3), tol=pytest.approx(1e-10)) and first["wall_s"] < res["wall_s"]
    assert "the fit's answer on its own grid (6 nodes, dt 0.002 s)" in printed
    for name in ("tau", "lengths", "time_offset"):
        moved = np.abs(np.asarray(first["values"][name]) - np.asarray(res["refinements"][0]["values"][name]))
        assert np.all(moved <= 1.01 * np.asarray(res["tolerance_errors"][name]) + 1e-15), (
            name,
            moved,
            res["tolerance_errors"][name],
        )
    # the profiles at the fit's grid: this small problem's loss is nearly quadratic, so each
    # 68 % interval is about the fit's value ± its standard error, and the fit is at its minimum
    assert set(res["profiles"]) == {"tau", "lengths"} and "68 % profile interval" in printed
    for name, pr in res["profiles"].items():
        fitted = res["refinements"][0]["values"][name]  # the tolerance refit: the fit's grid
        se = pr["standard_error"]  # the fit's grid's, whose noise levels the profile's loss has
        assert abs(pr["drop"]) < 0.05 and pr["lower"] < fitted < pr["upper"], (name, pr, fitted)
        assert abs(0.5 * (pr["upper"] - pr["lower"]) / se - 1) < 0.2, (name, pr, se)
        # the statistical error reported reaches the interval's farther end: here within 20 % of the SE
        ratio = np.asarray(res["statistical_errors"][name]) / np.asarray(res["standard_errors"][name])
        assert np.all((ratio >= 1) & (ratio < 1.2)), (name, ratio)
    assert np.allclose(sorted(res["outliers"]), np.sort(rec.t[wild])), (res["outliers"], np.sort(rec.t[wild]))
    for name in ("tau", "lengths", "time_offset"):
        stat = res["statistical_errors"][name]
        err = np.hypot(stat, res["discretisation_errors"][name])
        assert abs(res["values"][name] - truth[name]) < 3 * err, (name, res["values"][name], truth[name], err)
    # one space refinement (2N at the fit's dt), then two time refinements (dt / 2, dt / 4); the
    # space move is small, so it is the fit's grid's space error and time refines at the fit's N 6
    tol, space, step, step2 = res["refinements"]
    assert [r["refit"] for r in res["refinements"]] == ["tolerance", "space", "time", "time"]
    assert space["largest_move_se"] < 1 / 3
    assert (space["nodes"], step["nodes"], step["dt"], step2["dt"]) == (12, 6, pytest.approx(1e-3), pytest.approx(5e-4))
    # the time moves shrink at BDF-alpha's order 2 (measured: 305 and 148 SE), so the values are
    # extrapolated to dt 0 from the two time refits', v2 + m2/3, and their time error is
    # |4 m2 - m1| / 3, each move from the fit's own values (the tolerance refit's, up to the
    # tolerance error: here within it); the space error is the space refit's move. Where pcrjax refined a time
    # refit's internal grid, each value is taken on the finest one first: the space move,
    # 16/15 of it the fit grid's space error, scaled at RK4's order to each internal grid
    assert res["model"] == dict(
        nodes=6, dt=pytest.approx(5e-4), tol=step2["tol"], extrapolated_from_dt=[pytest.approx(1e-3), pytest.approx(5e-4)]
    )
    assert "values extrapolated to dt 0" in printed
    v0, v1, v2 = (r["values"]["lengths"] for r in (tol, step, step2))
    g0, g1, g2 = (r["internal_nodes"] for r in (tol, step, step2))
    space_error = 16 / 15 * (space["values"]["lengths"] - v0)
    v0, v1 = ((v + ((g0 / g) ** 4 - (g0 / g2) ** 4) * space_error) for v, g in ((v0, g0), (v1, g1)))
    assert res["values"]["lengths"] == pytest.approx(v2 + (v2 - v1) / 3, rel=1e-12, abs=res["tolerance_errors"]["lengths"])
    # each widened by what the refits' distances from their optima leave uncertain, in standard errors
    off = [r["distance_to_optimum_se"] or 0.0 for r in (space, step, step2)]
    se = res["standard_errors"]["lengths"]
    moves = (
        abs(space["values"]["lengths"] - tol["values"]["lengths"]) + off[0] * se,
        abs(4 * (v2 - v1) - (v1 - v0)) / 3 + (4 * off[2] + off[1]) / 3 * se,
    )
    assert abs(np.hypot(*moves) - res["discretisation_errors"]["lengths"]) <= 1.5 * res["tolerance_errors"]["lengths"] + 1e-15
    assert all((out / f).is_file() for f in ("fit_time.png", "fit_plane.png", "residuals.png", "loss.png"))
    assert not (out / "fit_state.json").exists()


def test_cli_keeps_the_fits_own_answer_when_the_refinements_are_interrupted(tmp_path, capsys, monkeypatch):
    """Interrupted (Ctrl-C) during the refinements, `pcrjax-identify` exits 130 and fit.json keeps
    the answer on the fit's grid that it showed when the fit converged ("final": false), and
    says so beside the resume hint (the fit itself is stood in for: the end-to-end test above
    checks the answer it hands over)."""
    import identify.fit as fit_module
    from identify import cli
    from identify.result import Result

    def interrupted(problem, answer=None, **_):
        shown = Result(problem.labels(), {"tau": 1.25e-3}, {"tau": 2e-5}, [[1.0]], [2e-6, 1e-3], 1.02, [2e-6, 2e-6, 1e-3])
        answer(dataclasses.replace(shown, wall_s=12.5, model=dict(nodes=20, dt=1e-3, tol=1e-10)))
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_module, "fit", interrupted)
    for suffix in (".csv", ".toml"):
        (tmp_path / f"rec{suffix}").write_bytes((Path(DATA) / f"cantilever_release{suffix}").read_bytes())
    out = tmp_path / "fit"
    assert cli.main([str(tmp_path / "rec.csv"), "--out", str(out), "--fit", "tau"]) == 130
    printed = capsys.readouterr()
    kept = json.loads((out / "fit.json").read_text())
    assert kept["final"] is False and kept["values"] == {"tau": 1.25e-3} and kept["wall_s"] == 12.5
    assert "the fit's answer on its own grid (20 nodes, dt 0.001 s) after 12.5 s" in printed.out
    assert "1.250 ± 0.020 ms" in printed.out
    assert "stays in" in printed.err and "resume" in printed.err


@pytest.mark.integration  # the whole command on a Triskele: screen, ranking, fit
def test_cli_fits_a_short_triskele_push_release_from_a_finer_grid_end_to_end(tmp_path, capsys):
    """The Triskele-bot's whole `pcrjax-identify` path (the integration set): a push-release
    recording of 0.4 s whose truth is drawn at random inside the prior (the random suite's
    generator with a seed no fit was developed on), simulated 3x finer in space and extrapolated
    to dt 0 from 2.5x and 5x finer in time, fitted from the nominal lengths and the sidecar's tau
    (a factor 3 off) at the shipped grid (N 10, dt 0.5 ms): the lumped-mode screen and its polish,
    the ranking with the clock scan, the windows, the noise re-estimated under the Huber loss,
    fit.json and the plots. At the fit's own grid the values carry its discretisation error
    (`--refine` measures it; not here, for time), so they are checked against what the start
    must reach: the lengths within 20 um of the truth (the prior is +-2 mm) and tau within 5 %."""
    from identify import cli

    path, truth = committed_recording("short_push_release", tmp_path)
    out = tmp_path / "fit"
    assert cli.main([str(path), "--out", str(out), "--refine", "0"]) == 0
    printed = capsys.readouterr().out
    print(printed)
    res = json.loads((out / "fit.json").read_text())
    assert res["converged"] and 0.5 < res["loss"] < 2.0
    assert np.all(np.abs(np.asarray(res["values"]["lengths"]) - truth["lengths"]) < 20e-6), (res["values"]["lengths"], truth)
    assert res["values"]["tau"] == pytest.approx(truth["tau"], rel=0.05)
    assert "screened 1024 sets of lengths" in printed and "whole recording, noise re-estimated" in printed
    # the loss's rise along its least determined direction (`identify.valley`) is measured and
    # named in unknowns of the fit, and noted where the standard errors misstate it
    valley = res["valley"]
    assert valley["rise"] > 0 and set(valley["direction"]) <= set(res["labels"]), valley
    assert ("along the least determined combination" in printed) == (not 1 / FACTOR <= valley["rise"] <= FACTOR), valley
    assert all((out / f).is_file() for f in ("fit_time.png", "fit_plane.png", "residuals.png", "loss.png"))
    assert not (out / "fit_state.json").exists()


def test_recordings_of_one_robot_share_the_fits_programs(tmp_path, monkeypatch):
    """A second recording of the same robot and experiment, with other frames (three lost), other
    poses and other sidecar values (the recorded push, the damping to start from), runs the first
    one's residual program: one program on disk, no new compilation. And that program reads the
    second recording's own frames: where its poses are the first's moved by ``d``, at the same
    unknowns its residuals are the first's less ``d / sigma``, frame by frame."""
    from pcrjax import config

    monkeypatch.setattr(config, "_traces", tmp_path)
    a = load_recording(f"{DATA}/cantilever_release.csv").window(0.03)
    keep = np.ones(a.t.size, bool)
    keep[[5, 11, 17]] = False
    d = np.array([3e-6, -2e-6, 1e-5])
    overrides = dict(a.overrides, tip=dict(a.overrides["tip"], force=[0.0, 0.0, -2.2]), rod=dict(tau=0.0012))
    b = dataclasses.replace(a, t=a.t[keep], pose=a.pose[keep] + d, overrides=overrides)
    pa, pb = Problem(a, ("tau", "lengths")), Problem(b, ("tau", "lengths"))
    assert float(pb.initial_values["tau"]) == 0.0012 and float(pa.initial_values["tau"]) == 0.001
    th = np.asarray(pa.to_theta(pa.initial_values))
    ra = np.asarray(pa.residual(th)).reshape(-1, 3)
    rb = np.asarray(pb.residual(th)).reshape(-1, 3)
    assert len(list(tmp_path.glob("identify-residual-*"))) == 1
    assert rb.shape == (a.t.size - 3, 3)
    np.testing.assert_allclose(rb, ra[keep] - d / pa.sigma, rtol=1e-10, atol=1e-6)


def test_split_damping_with_equal_times_is_the_shared_damping():
    """``--fit tau_split`` (stretch-shear and bend-twist damping apart): with both times equal the
    residuals are the shared tau's, and the two derivatives add up to the shared one's (the chain
    rule: Kelvin-Voigt damping is the sum of the two groups')."""
    rec = load_recording(f"{DATA}/cantilever_release.csv").window(0.03)
    shared = Problem(rec, ("tau", "lengths"))
    split = Problem(rec, ("tau_split", "lengths"))
    assert split.labels()[:2] == ["tau_se", "tau_bt"]
    th = np.asarray(shared.to_theta(shared.initial_values))
    th_split = np.concatenate([th[:1], th])
    r = np.asarray(shared.residual(th))
    assert np.allclose(np.asarray(split.residual(th_split)), r, rtol=1e-12, atol=1e-9 * np.max(np.abs(r)))
    h = 1e-4

    def dr(pb, theta, i):
        e = np.zeros(theta.size)
        e[i] = h
        return (np.asarray(pb.residual(theta + e)) - np.asarray(pb.residual(theta - e))) / (2 * h)

    both = dr(split, th_split, 0) + dr(split, th_split, 1)
    assert np.max(np.abs(both - dr(shared, th, 0))) < 1e-6 * np.max(np.abs(dr(shared, th, 0)))
    assert np.max(np.abs(dr(split, th_split, 1))) > 10 * np.max(np.abs(dr(split, th_split, 0)))  # bending dominates


def test_a_push_far_from_the_recorded_one_is_reported_as_a_likely_wrong_minimum():
    from identify.fit import _implausible_push

    pb = Problem(load_recording(f"{DATA}/triskele_push_release.csv"), ("tau", "lengths"))
    theta = np.array(pb.to_theta(pb.initial_values))
    assert _implausible_push(pb, theta) == ""
    theta[pb.slices["push_force"]] *= 1.3  # a push mis-recorded by 30 %: plausible
    assert _implausible_push(pb, theta) == ""
    theta[pb.slices["push_force"]] *= 4.0
    assert "wrong minimum" in _implausible_push(pb, theta)


def test_youngs_modulus_scales_the_small_deflection_inversely():
    """``--fit youngs_modulus``: E (and the shear modulus with it) of the rods. Oracle: linear
    elasticity, where every stiffness scales with E: a cantilever's small static deflection
    (2 mN at the tip, gravity off) is inversely proportional to E."""
    rec = load_recording(f"{DATA}/cantilever_release.csv")
    pb = Problem(rec, ("tau", "youngs_modulus"))
    assert pb.labels()[:2] == ["tau", "youngs_modulus"]
    E0 = float(pb.initial_values["youngs_modulus"])
    sc = experiment.apply(pb.scene, {"push_force": jnp.array([0.0, -2e-3])})

    def deflection(factor):
        s = experiment.apply(sc, {"youngs_modulus": jnp.asarray(factor * E0)})
        return float(pcrjax.solve_static(s).position[2])

    d0, d1 = deflection(1.0), deflection(1.25)
    assert d0 < 0 and d1 / d0 == pytest.approx(0.8, rel=1e-4)
    G = experiment.apply(sc, {"youngs_modulus": jnp.asarray(1.25 * E0)}).legs.rod.shear_modulus
    assert np.allclose(np.asarray(G), 1.25 * np.asarray(sc.legs.rod.shear_modulus), rtol=1e-14)


def test_platform_mass_scales_the_platform_modes_by_its_square_root():
    """``--fit platform_mass``: the platform's mass, its inertia with it. Oracle: a mass on
    springs: the Triskele's rods weigh 1e-5 of the platform, so doubling the platform's mass
    and inertia divides the frequencies of a simulated release by sqrt 2 (N 10, dt 0.1 ms, modes
    read by the matrix pencil of order 16: order 9 resolves only one of the two modes the push
    excites, 86.8 and 158.6 Hz). The rods carry a trace of damping (tau 10 us: damping ratio
    5e-3, which moves the ratio of the damped frequencies by 6e-6): undamped, the 158.6 Hz mode's
    decay is the scheme's own, near zero, and round-off decided whether the pencil kept it. A rod
    scene has no platform mass to fit."""
    rec = load_recording(f"{DATA}/triskele_push_release.csv")
    pb = Problem(rec, ("tau", "lengths", "platform_mass"))
    m0 = float(pb.initial_values["platform_mass"])
    sc = shared_triskele(dt=1e-4, alpha=-0.45, duration=0.15, tau=1e-5)

    def frequencies(mass):
        traj = pcrjax.simulate(experiment.apply(sc, {"platform_mass": jnp.asarray(mass)}))
        m = np.asarray(experiment.planar_pose(sc, traj))[::5]  # 2 kHz
        return modes.dominant(np.arange(m.shape[0]) * 5e-4, m, 2e3, 16, 100)[0][:2]

    f1, f2 = frequencies(m0), frequencies(2 * m0)
    assert f1.size == 2
    for f in f1:  # the modes the push excites
        assert f2[np.argmin(np.abs(f2 - f / np.sqrt(2)))] == pytest.approx(f / np.sqrt(2), rel=2e-3)
    with pytest.raises(Exception, match="no platform"):
        Problem(load_recording(f"{DATA}/cantilever_release.csv"), ("tau", "platform_mass"))


def _central_difference(pb, th, i, h):
    """Central difference of ``pb``'s residuals along unknown ``i`` with step ``h``."""
    e = np.zeros(th.size)
    e[i] = h
    return (np.asarray(pb.residual(th + e)) - np.asarray(pb.residual(th - e))) / (2 * h)


def _assert_column_is(J, fd, i, name):
    """Jacobian column ``i`` equals the differences ``fd`` to 1e-5 of their largest, which the recording sees."""
    assert np.max(np.abs(fd)) > 1.0, name  # the recording sees it
    print(name, np.max(np.abs(J[:, i] - fd)) / np.max(np.abs(fd)))
    assert np.max(np.abs(J[:, i] - fd)) < 1e-5 * np.max(np.abs(fd)), name


def test_physical_jacobian_columns_are_the_finite_differences():
    """Every physical unknown's Jacobian column (forward tangents through the rollout, each
    Newton solve differentiated implicitly), E, the platform mass and the released push among
    them, against central differences of the residuals. The motion is nearly linear in the
    push, so its differences take a step 100 times longer, where their round-off (the solves'
    tolerance over the step) is 100 times smaller: measured 1e-7 against 7e-6 to 1.4e-5."""
    rec = load_recording(f"{DATA}/triskele_push_release.csv").window(0.05)
    pb = Problem(rec, ("tau", "youngs_modulus", "platform_mass")).refined(tol=1e-13)  # differences need a tight solve
    th = np.asarray(pb.to_theta(pb.initial_values))
    _, J = pb.residual_and_jacobian(th)
    J = np.asarray(J)
    assert J.shape == (3 * rec.frames, th.size)
    for i, name in enumerate(pb.labels()[: pb.n_physical]):
        h = 1e-2 if name.split("[")[0] in LINEAR else 1e-4  # the push: the unknowns the motion is nearly linear in
        _assert_column_is(J, _central_difference(pb, th, i, h), i, name)


def test_jacobian_holding_step_jacobians_at_rest_is_the_finite_differences():
    """The fit's Jacobian holds each step's tangent Jacobian while the unknowns barely move
    (`newton.HOLD_MOVE`): on an actuator step that rests, moves and settles (0.05 s at rest, the
    step, 0.19 s after it), the physical columns against central differences of the residuals,
    Richardson-extrapolated from steps 1e-4 and 5e-5: the lengths' plain differences carry an
    error of 1.5e-3 to 4e-3 at 1e-4 that falls as the step squared; extrapolated, 2e-6 to 4e-6
    (measured). A Jacobian held across a change of the step's scheme (the first step's backward
    Euler) made these columns wrong by orders of magnitude."""
    rec = load_recording(f"{DATA}/triskele_actuator_step.csv").window(0.25)
    pb = Problem(rec, ("tau", "lengths")).refined(tol=1e-13)
    th = np.asarray(pb.to_theta(pb.initial_values))
    J = np.asarray(pb.residual_and_jacobian(th)[1])
    for i, name in enumerate(pb.labels()[: pb.n_physical]):
        fd = (4.0 * _central_difference(pb, th, i, 5e-5) - _central_difference(pb, th, i, 1e-4)) / 3.0
        _assert_column_is(J, fd, i, name)


@pytest.mark.integration  # the whole command with a refinement
def test_cli_fits_youngs_modulus_from_a_finer_grid(tmp_path, capsys):
    """``pcrjax-identify --fit tau,youngs_modulus`` end to end on a small case (the integration set):
    a 0.2 s cantilever recording at 1 kHz, its E drawn at random within 10 % of the scene's and
    simulated on a grid 3x finer in space and 5x in time than the fit's (N 6, dt 2 ms), fitted
    from the scene's E and tau a factor 3 off, with one refinement: E and tau within 3 combined
    uncertainties, and E printed in GPa."""
    from identify import cli

    path, truth = committed_recording("small_release_E", tmp_path)  # the length is known: E alone sets the stiffness
    out = tmp_path / "fit"
    assert cli.main([str(path), "--out", str(out), "--fit", "tau,youngs_modulus", "--start", "given", "--refine", "1"]) == 0
    printed = capsys.readouterr().out
    print(printed)
    assert "GPa" in printed
    res = json.loads((out / "fit.json").read_text())
    for name in ("tau", "youngs_modulus"):
        err = np.hypot(res["standard_errors"][name], res["discretisation_errors"][name])
        assert abs(res["values"][name] - truth[name]) < 3 * err, (name, res["values"][name], truth[name], err)
        assert err < 0.01 * truth[name]  # and pinned: E was 1-10 % off at the start


def test_summary_of_a_cantilever_and_a_triskele_fit_gives_each_number_its_column(tmp_path):
    """fits.csv of a cantilever (one length, a scalar) beside a Triskele (three lengths): the
    cantilever's length sits in lengths[0], its lengths[1] and [2] are blank, and a failed
    fit's row is blank in every value column."""
    from identify.batch import write_summary

    def row(name, values, status="converged"):
        se = {k: (0.01 * np.asarray(v)).tolist() for k, v in values.items()}
        return {"recording": name, "status": status, "wall_s": 1.0, "values": values, "standard_errors": se}

    rows = [
        row("c.csv", {"tau": 2e-3, "lengths": 0.5}),
        row("t.csv", {"tau": 4e-4, "lengths": [0.0312, 0.0329, 0.0308], "time_offset": 3e-3}),
        {"recording": "x.csv", "status": "failed", "wall_s": 0.5},
    ]
    write_summary(tmp_path, rows)
    lines = (tmp_path / "fits.csv").read_text().splitlines()
    head = lines[0].split(",")
    cells = [dict(zip(head, r.split(","), strict=True)) for r in lines[1:]]
    assert head[4:] == [
        c for lb in ("tau", "lengths[0]", "lengths[1]", "lengths[2]", "time_offset") for c in (lb, f"{lb}_se", f"{lb}_disc")
    ]
    assert float(cells[0]["lengths[0]"]) == 0.5 and cells[0]["lengths[1]"] == cells[0]["time_offset"] == ""
    assert float(cells[1]["lengths[2]"]) == 0.0308 and float(cells[1]["lengths[2]_se"]) == 0.01 * 0.0308
    assert cells[2]["status"] == "failed" and all(cells[2][c] == "" for c in head[4:])


@pytest.mark.integration  # Dask worker processes, each compiling cold
def test_several_recordings_fitted_here_and_on_a_local_dask_cluster_agree(tmp_path, capsys):
    """``pcrjax-identify A.csv B.csv --out DIR [--cluster local:2]``: two small cantilever
    recordings (0.1 s, other truths, simulated 3x finer in space and 5x in time than the fit's
    grid), each fitted into its own folder with a summary row in fits.csv; on two Dask worker
    processes the values equal this process's to the last digit (the same programs on the same
    inputs). A recording whose fit fails is marked and the others run (exit 1); a recording that
    cannot be read stops the command before any fit, with one line."""
    pytest.importorskip("dask.distributed")
    from identify import cli

    paths = [str(committed_recording(name, tmp_path)[0]) for name in ("small_a", "small_b")]
    # a recording whose sidecar the scene refuses (a negative radius): read fine, its fit fails
    broken = tmp_path / "broken.csv"
    broken.write_text(Path(paths[0]).read_text())
    side = Path(paths[0]).with_suffix(".toml").read_text()
    broken.with_suffix(".toml").write_text(side.replace("[rod]\n", "[rod]\nradius = -0.001\n", 1))
    argv = ["--start", "given", "--refine", "0"]
    assert cli.main([*paths, str(broken), *argv, "--out", str(tmp_path / "here")]) == 1  # one failed
    assert cli.main([*paths, *argv, "--out", str(tmp_path / "dask"), "--cluster", "local:2"]) == 0
    here, there = (json.loads((tmp_path / d / "fits.json").read_text()) for d in ("here", "dask"))
    assert here[2]["status"] == "failed" and "radius" in here[2]["message"]  # marked, and the others ran
    here = here[:2]
    assert [r["recording"] for r in here] == paths == [r["recording"] for r in there]
    for a, b in zip(here, there, strict=True):
        assert a["status"] == b["status"] == "converged"
        assert a["values"] == b["values"] and a["standard_errors"] == b["standard_errors"]
        assert (tmp_path / "dask" / Path(a["recording"]).stem / "fit.json").is_file()
    rows = (tmp_path / "here" / "fits.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("recording,status,reduced_chi2,wall_s,tau,tau_se,tau_disc,lengths")
    assert rows[3].split(",")[1] == "failed"
    taus = [r["values"]["tau"] for r in here]
    assert taus[1] > 1.5 * taus[0]  # each its own truth
    capsys.readouterr()
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_m,y_m,theta_rad\n0.0,0,0,0\n")
    assert cli.main([paths[0], str(bad), "--out", str(tmp_path / "bad_out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.csv" in err[0], err
    assert not (tmp_path / "bad_out" / "fits.csv").exists()


def test_levenberg_marquardt_keeps_the_damping_that_passed_and_tries_no_step_twice():
    """A chord iteration: r(x) = x with a Jacobian held at a quarter of the true one (a coarse
    model's, as the refits hold), whose Gauss-Newton step overshoots the optimum x = 0 fourfold.
    Oracle: the chord's fixed point is the optimum (J^T r = 0 only at r = 0), and a trial step
    within a tenth of the last rejected one from the same point would fail as it did. The
    damping that passed after a failed trial is kept (lowered again at once, every iteration
    alternated a failed and a passed trial, and this chord never converged); no trial repeats a
    rejected step."""
    trials = []

    def rf(x):
        trials.append(np.array(x, float))
        return np.array(x, float)

    held = np.array([[0.25]])
    x, _, _, it, converged, _ = levenberg_marquardt(
        rf, lambda x: (np.array(x, float), held), np.array([1.0]), 200, ftol=1e-20, max_step=np.inf, lam0=1e-9
    )
    assert converged and abs(float(x[0])) < 1e-6, x
    # the start, then per iteration its passed trial; failed ones: the first iteration's search
    # from Gauss-Newton (two: every damping below 1e-3 gives the same step), then at most one per
    # two iterations (a passed first trial lowers the damping again, and the next may fail)
    assert len(trials) - 1 - it <= it // 2 + 2, (len(trials), it)
    point, last_rejected = trials[0], None
    for t in trials[1:]:
        step = t - point
        if last_rejected is not None:
            assert np.max(np.abs(step - last_rejected)) >= 0.1 * np.max(np.abs(last_rejected)), (step, last_rejected)
        if abs(t[0]) < abs(point[0]):
            point, last_rejected = t, None
        else:
            last_rejected = step
