r"""Modal initialisation: the damped modes a recording shows, and model parameters that show the same.

An oscillating recording's loss has a minimum every cycle of phase error, so a fit started from
nominal rod lengths (a few percent off, which moves the Triskele's 19-85 Hz platform modes by a few Hz)
lands in a wrong minimum. The poles of the motion (frequency and decay of each mode) do not
depend on the phase, the amplitude, the push or the camera's frame and clock: they depend on
the damping and the lengths only. So the fit first moves those until the model's poles match the
recording's, and starts the time-domain fit from there (`fit.fit`).

**Poles** by the matrix-pencil method (Hua & Sarkar 1990) on the three columns together: windows
of ``L`` consecutive frames (those with a missing frame are skipped, so decoding gaps do no
harm), the row space truncated to ``order`` by an SVD, and the eigenvalues ``z = exp(s / f_s)``
of the shift between the truncated windows. Frames alias the modes (Nyquist 57.2 Hz at 114.44
frames/s), and so do the poles; model and recording are sampled alike, so they alias alike.

**Settled pose** (`settled`): after an actuator move, the constant a least-squares fit puts
beside the pencil's damped modes, the equilibrium the motion settles to.
"""

from __future__ import annotations

import itertools

import numpy as np


def poles(t, pose, frame_rate, order: int, window: int = 12):
    """Discrete poles (complex, Im >= 0, one per mode; a real pole for the drift to rest) of
    uniformly sampled frames ``pose`` (M, 3) at times ``t`` with some frames missing."""
    k = np.rint((np.asarray(t) - t[0]) * frame_rate).astype(int)
    full = np.full((k[-1] + 1, pose.shape[1]), np.nan)
    full[k] = pose
    sd = np.nanstd(full, axis=0)
    full = (full[:, sd > 0] - np.nanmean(full[:, sd > 0], axis=0)) / sd[sd > 0]  # constant columns carry no modes
    rows = []
    for c in range(full.shape[1]):
        for i in range(full.shape[0] - window + 1):
            w = full[i : i + window, c]
            if np.all(np.isfinite(w)):
                rows.append(w)
    if len(rows) <= order:
        raise ValueError(
            f"{len(rows)} windows of {window} consecutive frames, more than {order} needed to estimate the modes (a recording too short, or too many frames missing)"
        )
    Y = np.asarray(rows)
    _, _, vt = np.linalg.svd(Y, full_matrices=False)
    V = vt[:order].T  # (window, order): the signal subspace
    z = np.linalg.eigvals(np.linalg.pinv(V[:-1]) @ V[1:])
    return z[np.imag(z) >= -1e-12]


def describe(z, frame_rate):
    """(aliased frequency Hz, decay rate 1/s) of discrete poles ``z``."""
    s = np.log(z.astype(complex)) * frame_rate
    return np.abs(np.imag(s)) / (2 * np.pi), -np.real(s)


def unalias(freq, decay, frame_rate, folds: int = 4, tau_range=(0.0, np.inf)):
    """Physical frequencies (Hz, sorted) and the damping time ``tau`` that explain aliased modes.

    Each aliased frequency ``f`` could be ``k f_s + f`` or ``(k + 1) f_s - f``. Kelvin-Voigt
    damping of the rods' strain decays each mode at ``tau omega^2 / 2``, so of all the choices the
    one whose ``decay / omega^2`` is the most uniform across the modes is taken, and ``tau`` is
    their geometric mean; choices whose ``tau`` lies outside ``tau_range`` are not considered
    (decays measured over a few cycles are imprecise, and a high fold can fit them better by
    chance). (A recording filmed fast enough has ``k = 0`` for every mode.)"""
    if len(freq) == 0:
        raise ValueError("no modes to unalias")
    cands = [[c for k in range(folds) for c in (k * frame_rate + f, (k + 1) * frame_rate - f)] for f in freq]
    best, best_log_tau, spread = None, None, np.inf
    for choice in itertools.product(*cands):
        w = 2 * np.pi * np.asarray(choice)
        log_tau = np.log(2 * decay / w**2)
        if not tau_range[0] <= np.exp(np.mean(log_tau)) <= tau_range[1]:
            continue
        s = np.std(log_tau)
        if s < spread:
            best, best_log_tau, spread = w, log_tau, s
    if best is None:
        return None, None
    return np.sort(best / (2 * np.pi)), float(np.exp(np.mean(best_log_tau)))


def recorded_modes(rec, t_from: float = 0.0, n_modes: int = 3, order: int | None = None, tau_range=(0.0, np.inf)):
    """(physical frequencies Hz, tau) of the ``n_modes`` modes of lowest (aliased) frequency the
    recording shows after ``t_from`` (poles of ``order``, default ``2 n_modes + 1``; a pole at the
    Nyquist frequency is noise, not a mode)."""
    keep = rec.t >= t_from
    try:
        z = poles(rec.t[keep], rec.pose[keep], rec.frame_rate, order or 2 * n_modes + 1)
    except ValueError as e:
        raise ValueError(f"{rec.path}: after t = {t_from:g} s: {e}") from None
    f, d = describe(z, rec.frame_rate)
    osc = (f > 1e-3 * rec.frame_rate) & (f < 0.49 * rec.frame_rate) & (d > 0)
    if osc.sum() < n_modes:
        raise ValueError(
            f"{rec.path}: {osc.sum()} decaying oscillations found after t = {t_from:g} s, {n_modes} needed for the modal initialisation"
        )
    lowest = np.argsort(f[osc])[:n_modes]
    freqs, tau = unalias(f[osc][lowest], d[osc][lowest], rec.frame_rate, tau_range=tau_range)
    if freqs is None:
        raise ValueError(
            f"{rec.path}: no unaliasing of the recorded modes gives a damping time within {tau_range[0]:.3g}-{tau_range[1]:.3g} s"
        )
    return freqs, tau


def settled(t, pose, frame_rate, order: int):
    """(discrete poles, the constant pose (3,) the motion settles to) of frames ``pose`` (M, 3) at
    times ``t``: the constant of a least-squares fit of a constant plus the poles' damped
    oscillations (the mean of a few cycles is off by a fraction of their amplitude)."""
    z = poles(t, pose, frame_rate, order)
    n = np.rint((np.asarray(t) - t[0]) * frame_rate)
    cols = [np.ones_like(n)]
    for zk in z[np.abs(z - 1.0) > 1e-6]:  # the constant is fitted as such
        zn = zk**n
        cols += [zn.real] + ([zn.imag] if abs(zk.imag) > 1e-12 else [])
    coef = np.linalg.lstsq(np.stack(cols, axis=1), pose, rcond=None)[0]
    return z, coef[0]


def simulated_frequencies(motion, dt, n_modes: int, order: int = 9, rate: float | None = None, span: float | None = None):
    """The ``n_modes`` lowest frequencies (Hz) of a simulated motion (T, 3) sampled every ``dt``,
    resampled at about ``rate`` (None: every sample; no aliasing below rate/2), pencil windows of
    ``span`` s (None: 40 samples). NaN where the motion is not finite (a failed simulation)."""
    if not np.all(np.isfinite(motion)):
        return np.full(n_modes, np.nan)
    sub = 1 if rate is None else max(1, int(round(1.0 / (rate * dt))))
    x, h = motion[::sub], dt * sub
    f, d = describe(poles(np.arange(x.shape[0]) * h, x, 1.0 / h, order, 40 if span is None else int(round(span / h))), 1.0 / h)
    f = np.sort(f[(f > 1.0) & (d > -1.0)])
    return f[:n_modes] if f.size >= n_modes else np.full(n_modes, np.nan)


def match_frequencies(features_of, x0, target, max_iter: int = 20, max_step: float = 0.01, h: float = 1e-4, tol: float = 1e-4):
    """Gauss-Newton on log features: ``x`` (log lengths) such that ``features_of(x)`` (positive: sorted
    frequencies in Hz, static displacements) equals ``target`` (as many or more than ``x``: least
    squares); finite-difference Jacobian, steps bounded to ``max_step``. Returns (x, converged):
    converged when every feature matches to ``tol`` (as many as ``x``) or the steps stop."""
    x, last = np.asarray(x0, float).copy(), None
    for _ in range(max_iter):
        res = np.log(features_of(x) / target)
        if not np.all(np.isfinite(res)):
            return x, False
        if np.max(np.abs(res)) < tol:
            return x, True
        if last is not None and np.max(np.abs(last)) < 0.1 * tol:
            return x, bool(np.max(np.abs(res)) < 0.03)  # least squares: stationary, features within 3 %
        J = np.empty((target.size, x.size))
        for k in range(x.size):
            e = x.copy()
            e[k] += h
            J[:, k] = (np.log(features_of(e) / target) - res) / h
        if not np.all(np.isfinite(J)):  # a neighbour's simulation failed
            return x, False
        step = np.linalg.lstsq(J, -res, rcond=None)[0]
        last = step * min(1.0, max_step / max(np.max(np.abs(step)), 1e-300))
        x += last
    res = np.log(features_of(x) / target)
    return x, bool(np.max(np.abs(res)) < (tol if target.size == x.size else 0.03))
