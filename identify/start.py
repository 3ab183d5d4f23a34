r"""Start values of damping and lengths: a screen of the prior, feature matching, then a short fit.

An oscillating recording's loss has a minimum every cycle of phase error, so a fit started from
nominal rod lengths lands in a wrong minimum (on the Triskele-bot 2 % of rod length moves the
platform modes from 86-155 Hz to 19-84 Hz). A planar platform's free motion (a push released)
is screened in the time domain against its lumped modes (`platform_screen`: statics only, every
frame compared as filmed). Elsewhere, features that do not depend on the phase, the amplitude,
the push or the camera's frame and clock locate the basin first:

* **a rod's free motion** (a tip load released): the frequencies of the strongest oscillations
  the camera shows. They are compared *as the camera shows them*: the model's frequencies,
  measured on its own finely sampled motion (a short simulated release), are folded at the
  frame rate (`modes.fold`) and matched to the recorded ones, so no guess of how the recording
  aliased is needed. Nonlinear harmonics (the axial swing at twice the bending frequency) are in
  both.
* **after an actuator move**: the static response to the move (`static_shift`), smooth in the
  lengths and without a rollout.

The stages (`initial_lengths`):

1. **Screen** the prior, each length within ``prior_length`` of nominal: the nominal lengths and
   a seeded Latin hypercube (`SCREEN`: many where the features are static solves, few where each
   is a simulation), on as many threads as there are cores. Candidates are ranked by their
   features' distance to the recording's.
2. **Polish** the best ones by weighted Gauss-Newton on the features (`modes.match_frequencies`),
   inside the prior. The distinct ones that match go on to the time-domain ranking
   (`fit.modal_start`).

Where the whole prior moves the features less than their match (`MATCH`), they cannot tell
lengths apart, and the time-domain fit's first window cannot miss the basin either: a rod's
modes move by about 1 % over ±2 mm of 0.4 m, less than the damping and the push move them. The
start is then the nominal lengths.

Nothing is abandoned while a candidate remains: when no polished candidate matches the features,
the polished ones go on to the ranking, and the message says what the closest reached.

**Damping** comes from the decays: Kelvin-Voigt damping decays every mode (and its harmonics)
in proportion to tau, so tau is the simulated tau times the ratio of the strongest matched
recorded oscillation's decay to the model mode's (failing a match, the strongest one's within
`TAU_MATCH`: damping itself lowers a mode's frequency, by 5 % on the cantilever at tau 11 ms),
repeated at the new tau until it settles, and kept within a decade of nominal either way.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import identify
from pcrjax import traces
from pcrjax.robots.signals import Actuation

from . import experiment, modes, platform_screen, threads
from .platform_screen import planar_rest
from .recording import RecordingError

PRIOR_LENGTH = 2e-3  # m: each rod within this of its nominal length
TAU_RANGE = 10.0  # tau within a factor of this of nominal
# candidates screened (the nominal lengths and a Latin hypercube) and the best ones polished by
# Gauss-Newton on the features, then ranked in the time domain: many where the features are
# static solves, fewer where each is a simulation
SCREEN = {True: (512, 64), False: (24, 4)}  # actuated (static features): (screened, polished); simulated
MATCH = 0.03  # features within 3 %: a match
TAU_MATCH = 0.15  # a model mode this close to the strongest recorded one gives the damping
TAU_ITER = 3  # damping estimates, each simulated at the previous one's tau
SIMULATED = 0.4  # s of free motion simulated per candidate
WINDOW = 0.1  # s: the matrix pencil's window (at least 12 frames)
ORDER = 7  # the matrix pencil's order: three oscillations and a drift
FEATURE_STRENGTH = 0.05  # recorded oscillations matched: at least this of the strongest's strength
SHAPE_STRENGTH = 0.2  # ... and their shapes too: at least this
SHAPE_WEIGHT = 0.3  # a mode shape's relative error counts less than its frequency's
MODEL_ORDER = 13  # the matrix pencil's order on the model's motion: six oscillations and a drift


def latin_hypercube(center, half_width, n: int, seed: int = 0):
    """``n`` points (n, d): ``center`` first, then a Latin hypercube of the box ``center ±
    half_width`` (each coordinate's range cut into n - 1 strata, one point in each)."""
    center = np.atleast_1d(np.asarray(center, float))
    rng = np.random.default_rng(seed)
    m = max(n - 1, 0)
    u = (np.stack([rng.permutation(m) for _ in center], axis=1) + rng.random((m, center.size))) / max(m, 1)
    return np.concatenate([center[None], center + (2.0 * u - 1.0) * half_width])


def frame_invariant(shift):
    """(|displacement|, |rotation|) of a change ``shift`` (3,) of planar pose: the same in every
    pattern frame."""
    return jnp.stack([jnp.hypot(shift[0], shift[1]), jnp.abs(shift[2])])


def _shift(scene, t_end, log_lengths):
    """The frame_invariant of the static equilibrium of ``scene`` at ``log lengths`` after the
    actuators' moves (which end at ``t_end``) relative to the one before (m and rad); NaN where
    a static solve fails."""
    end = scene.actuation(t_end)
    held = Actuation(
        initial=end, final=end, start=jnp.zeros_like(end), duration=jnp.ones_like(end), kinds=("constant",) * end.shape[0]
    )
    after = eqx.tree_at(lambda s: s.actuation, scene, held)
    lengths = {"lengths": jnp.exp(log_lengths)}
    a, ok_a, x = planar_rest(experiment.apply(scene, lengths))
    b, ok_b, _ = planar_rest(experiment.apply(after, lengths), near=x)  # a small move: Newton from the rest before it
    return jnp.where(ok_a & ok_b, frame_invariant(b - a), jnp.nan)


def static_shift(scene):
    """``log lengths ->`` `_shift` of ``scene``, compiled (its trace kept on disk,
    `pcrjax.traces`; the scene is an argument, so scenes of one robot share it). A static solve
    whose continuation loses its path ends there, not retried (`platform_screen.for_screening`):
    the screen passes over such lengths."""
    t_end = jnp.asarray(experiment.forcing_end(scene), jnp.float64)
    return traces.jit_over(_shift, "identify-static-shift", platform_screen.for_screening(scene), (), (identify,), (t_end,))


class Features:
    """The recording's features and the model's, for lengths ``x`` (logs).

    ``recorded``: the frequencies (Hz, as filmed) of the recording's strongest oscillations after
    the forcing and the strong ones' shapes, or its static response to the move; ``weights``:
    their share of the strength; ``of(x)``: the model's features matched to them one by one, NaN
    where the model fails."""

    def __init__(self, problem, theta):
        self.problem, self.theta = problem, np.array(theta, float)
        self.t_from = experiment.forcing_end(problem.scene)
        self.actuated = self.t_from > 0.0
        self.i_len = problem.slices.get("lengths")  # None: lengths held
        rec = problem.rec
        keep = rec.t >= self.t_from
        window = max(12, int(round(WINDOW * rec.frame_rate)))
        try:
            f, d, s, shape = modes.dominant(rec.t[keep], rec.pose[keep], rec.frame_rate, ORDER, window)
        except ValueError as e:
            raise ValueError(f"{rec.path}: after t = {self.t_from:g} s: {e}") from None
        if f.size == 0:
            raise ValueError(f"{rec.path}: no decaying oscillation found after t = {self.t_from:g} s to start the fit from")
        self.freq, self.decay, self.strength, self.shape = f, d, s, shape
        if self.actuated:
            late = rec.t >= min(max(0.6, self.t_from), 0.5 * (self.t_from + rec.t[-1]))  # a short recording: its second half
            before = rec.pose[rec.t < experiment.forcing_start(problem.scene)]
            rest = modes.settled(rec.t[late], rec.pose[late], rec.frame_rate, 5)[1]
            self.recorded = np.asarray(frame_invariant(rest - np.mean(before, axis=0)))
            self.weights = np.ones(2) / 2
            self._shift = static_shift(problem.scene)
        else:
            # each oscillation's frequency as filmed, and the strong ones' shapes
            self.n_freq = int(np.sum(s >= FEATURE_STRENGTH * s[0]))
            self.n_shape = int(np.sum(s >= SHAPE_STRENGTH * s[0]))
            self.recorded = np.concatenate([f[: self.n_freq], shape[: self.n_shape]])
            w = s / np.sum(s[: self.n_freq])
            self.weights = np.concatenate([w[: self.n_freq], SHAPE_WEIGHT * w[: self.n_shape]])
        # the model's simulated modes at theta's damping (the discretised damping moves frequencies too)
        damping = [np.exp(self.theta[sl]) for sl in problem.damping]
        self.tau_sim = float(np.mean(np.concatenate(damping))) if damping else None

    def describe(self) -> str:
        if self.actuated:
            return f"static response to the move {self.recorded[0] * 1e6:.4g} um, {self.recorded[1] * 1e6:.4g} urad"
        return "strongest oscillations " + ", ".join(
            f"{f:.2f} Hz (decay {d:.3g}/s, {sh:.3g} m/rad)" for f, d, sh in zip(self.freq, self.decay, self.shape)
        )

    def _theta(self, x, tau: float | None = None):
        """The fit's parameters at log lengths ``x`` (None: theta's) and damping ``tau`` (None: theta's)."""
        th = self.theta.copy() if tau is None else _set_damping(self.problem, self.theta, tau)
        if x is not None:
            th[self.i_len] = x
        return th

    def simulated(self, x, tau: float | None = None):
        """(physical frequencies Hz, decays 1/s, strengths, shapes) of the model's free motion at
        log lengths ``x`` (None: theta's) and damping ``tau`` (None: theta's), the strongest
        first; None where the simulation fails."""
        dt = float(self.problem.scene.solver.dt)
        m = self.problem.motion(self._theta(x, tau), self.t_from + SIMULATED)[int(round(self.t_from / dt)) :]
        if not np.all(np.isfinite(m)):
            return None
        sub = max(1, int(round(1e-3 / dt)))  # about 1 kHz: modes up to a few hundred Hz
        m, rate = m[::sub], 1.0 / (dt * sub)
        try:
            return modes.dominant(
                np.arange(m.shape[0]) / rate, m, rate, MODEL_ORDER, max(12, int(round(WINDOW * rate))), keep=6, floor=0.01
            )
        except ValueError:
            return None

    def modes_at(self, x):
        """(frequencies Hz, shapes m/rad) of the oscillations of the model's simulated release at
        log lengths ``x`` (a rod: its modes are its own); NaN where the model fails."""
        sim = self.simulated(x)
        if sim is None or sim[0].size == 0:
            return np.full(1, np.nan), np.full(1, np.nan)
        return sim[0], sim[3]

    def of(self, x):
        if self.actuated:
            return np.asarray(self._shift(jnp.asarray(x)))
        f, shape = self.modes_at(x)
        if not np.all(np.isfinite(f)):
            return np.full(self.recorded.size, np.nan)
        rate = self.problem.rec.frame_rate
        physical = np.concatenate([f, 2.0 * f])  # with a nonlinear motion's second harmonics
        shown = modes.fold(physical, rate)
        r = self.freq[: self.n_freq, None]
        k = np.argmin(np.abs(shown[None, :] - r) / physical[None, :], axis=1)
        k_shape = np.argmin(np.abs(shown[None, : f.size] - r[: self.n_shape]) / f[None, :], axis=1)
        # a frequency as filmed is compared in proportion to the physical one it shows: 1 % of a
        # 94 Hz mode is 4 % of the 20 Hz it aliases to at 114 frames/s
        matched = r[:, 0] * np.exp((shown[k] - r[:, 0]) / physical[k])
        return np.concatenate([matched, shape[k_shape]])

    def trace(self, x):
        """Trace the program that `of` runs (a static shift, or a rollout), without compiling it."""
        if self.actuated:
            self._shift.trace(jnp.asarray(x))
            return
        self.problem.trace_motion(self._theta(x), self.t_from + SIMULATED)

    def of_all(self, xs, warm=None) -> list:
        """`of` each of the log lengths ``xs`` (n, rods), on as many threads as there are cores.
        ``warm()`` is called once the program is traced (the caller traces its own programs
        while this one compiles)."""
        if warm is not None and len(xs):
            self.trace(xs[0])
            warm()
        return list(threads.map_in_threads(self.of, xs))

    def distance(self, features, shapes: bool = True) -> float:
        """Weighted relative distance of model ``features`` to the recorded ones (inf: failed);
        without the mode shapes if not ``shapes``."""
        rel = np.abs(np.log(np.maximum(features, 1e-300) / self.recorded))
        w = self.weights if shapes or self.actuated else np.where(np.arange(rel.size) < self.n_freq, self.weights, 0.0)
        return float(np.sum(w * np.minimum(rel, 1.0)) / np.sum(w)) if np.all(np.isfinite(rel)) else np.inf

    def _decay_ratio(self, sim):
        """(recorded / model decay, the recorded (Hz as filmed, decay 1/s)) of the strongest
        recorded oscillation that a model mode of ``sim`` (`simulated`) shows within MATCH of its
        physical frequency, else of the strongest one within TAU_MATCH; None if none."""
        shown = modes.fold(sim[0], self.problem.rec.frame_rate)
        for within in (MATCH, TAU_MATCH):
            for f, d in zip(self.freq, self.decay):
                miss = np.abs(shown - f) / sim[0]
                k = int(np.argmin(miss))
                if miss[k] < within and sim[1][k] > 0:
                    return d / sim[1][k], (f, d)
                if within == TAU_MATCH:
                    break
        return None

    def tau(self, x, tau_nominal: float):
        """(tau, the recorded oscillation it comes from: (Hz as filmed, decay 1/s), or None: the
        nominal) at log lengths ``x``: the simulated tau times the ratio of the decay of the
        strongest recorded oscillation that a model mode matches (`_decay_ratio`) to that mode's
        (Kelvin-Voigt damping decays every mode in proportion to tau), simulated again at the
        new tau until it moves less than 5 %, kept within TAU_RANGE of nominal."""
        if self.tau_sim is None:
            return tau_nominal, None
        tau, used = self.tau_sim, None
        for _ in range(TAU_ITER):
            sim = self.simulated(x, tau)
            if sim is None or sim[0].size == 0:
                break
            found = self._decay_ratio(sim)
            if found is None:
                break
            ratio, used = found
            new = float(np.clip(tau * ratio, tau_nominal / TAU_RANGE, tau_nominal * TAU_RANGE))
            settled, tau = abs(new / tau - 1.0) < 0.05, new
            if settled:
                break
        return (tau, used) if used is not None else (tau_nominal, None)


def initial_lengths(problem, theta, progress=None, warm=None, prior_length: float = PRIOR_LENGTH, seed: int = 0):
    """(theta with damping and lengths started from the recording's features, the candidates
    (log lengths) worth ranking in the time domain, best first). See the module's text."""
    theta = np.array(theta, float)
    say = _sayer(progress)
    i_len = problem.slices["lengths"]
    L0 = np.exp(theta[i_len])
    if np.any(L0 <= prior_length):
        raise RecordingError(f"prior: lengths {L0.tolist()} m cannot vary by ±{prior_length:g} m")
    scene = problem.scene
    if experiment.forcing_end(scene) <= 0.0 and not experiment.is_rod(scene) and bool(scene.effects.planar):
        # a planar platform's free motion: its lumped modes against the frames themselves
        log_tau, found = platform_screen.screen(problem, theta, i_len, say, prior_length, TAU_RANGE, seed, warm)
        theta = _set_damping(problem, theta, float(np.exp(log_tau))) if problem.damping else theta
        theta[i_len] = found[0]
        return theta, found
    feats = Features(problem, theta)
    say(f"start: recorded {feats.describe()}")
    x0 = theta[i_len]
    n_screen, n_polish = SCREEN[feats.actuated]
    cands = np.log(latin_hypercube(L0, prior_length, n_screen, seed))
    found = feats.of_all(cands, warm)
    dist = np.array([feats.distance(f) for f in found])
    order = np.argsort(dist, kind="stable")
    ok = order[np.isfinite(dist[order])]
    say(
        f"start: screened {len(cands)} sets of lengths within ±{prior_length * 1e3:g} mm: "
        f"the model holds at {ok.size}, the closest features {np.round(found[ok[0]], 4).tolist() if ok.size else '-'}"
    )
    if ok.size == 0:
        raise RecordingError(
            f"{problem.rec.path}: the model fails at every one of {len(cands)} sets of lengths within ±{prior_length:g} m of nominal"
        )

    if not feats.actuated and _indistinct([found[i][: feats.n_freq] for i in ok]):
        say(
            f"start: over the prior the model's features move less than {MATCH:.0%}: they cannot tell lengths apart; "
            "starting from the nominal lengths"
        )
        return _with_tau(problem, feats, theta, x0, say), [x0]
    box = (np.log(L0 - prior_length), np.log(L0 + prior_length))

    def polish(x):
        return modes.match_frequencies(feats.of, x, feats.recorded, max_iter=8, tol=1e-3, weights=feats.weights, bounds=box)

    polished = list(threads.map_in_threads(polish, cands[ok[:n_polish]]))
    reached = [feats.of(x) for x, _ in polished]
    # a match is judged on the frequencies alone: a shape read off an aliased, noisy recording
    # can be a factor 10 off where the frequencies agree to 1 % (the finer-grid suite)
    dists = [feats.distance(f, shapes=False) for f in reached]
    matched = []
    for (x, _), d in zip(polished, dists):
        if (
            d < MATCH
            and np.all(np.abs(np.exp(x) - L0) <= 1.5 * prior_length)
            and not any(np.max(np.abs(x - y)) < 1e-3 for y in matched)
        ):
            matched.append(x)
    say(
        f"start: {len(polished)} closest polished: {len(matched)} distinct sets of lengths match the {'static response' if feats.actuated else 'frequencies'} to {MATCH:.0%}"
    )
    if not matched:
        closest = reached[int(np.argmin(dists))] if dists else found[ok[0]]
        say(
            f"start: no lengths within the prior match the recorded features {np.round(feats.recorded, 4).tolist()} to {MATCH:.0%}; "
            f"the closest reach {np.round(closest, 4).tolist()}: going on from the polished ones"
        )
        matched = [x for x, _ in polished] or [cands[ok[0]]]
    return _with_tau(problem, feats, theta, matched[0], say), matched


def _sayer(progress):
    """``say(message)`` through ``progress(stage, iteration, loss, step)`` (or nowhere)."""
    return (lambda msg: progress(msg, 0, None, None)) if progress is not None else (lambda msg: None)


def _set_damping(problem, theta, tau: float):
    """``theta`` (a copy) with every damping time ``tau``."""
    theta = np.array(theta, float)
    for sl in problem.damping:
        theta[sl] = np.log(tau)
    return theta


def _indistinct(features) -> bool:
    """Whether every set of ``features`` (frequencies) lies within MATCH of the first (the
    nominal lengths')."""
    ref = np.asarray(features[0])
    return all(np.max(np.abs(np.log(np.asarray(f) / ref))) < MATCH for f in features[1:])


def _with_tau(problem, feats, theta, x, say):
    """``theta`` with tau from the recorded decays at log lengths ``x`` (`Features.tau`)."""
    if not problem.damping:
        return theta
    tau, used = feats.tau(x, float(np.mean(problem.fixed["tau"])))
    theta = _set_damping(problem, theta, tau)
    say(
        f"start: tau {tau:.4g} s"
        + (f" from the decay of {used[0]:.2f} Hz" if used is not None else " (no decay matched: the scene's)")
    )
    return theta


def initial_tau(problem, theta, progress=None):
    """``theta`` with its damping started from the recording's decays at its lengths (a fit of
    the damping alone)."""
    theta = np.array(theta, float)
    if not problem.damping:
        return theta
    return _with_tau(problem, Features(problem, theta), theta, None, _sayer(progress))
