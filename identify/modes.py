r"""The damped oscillations a recording (or a simulated motion) shows: poles, strengths, shapes.

The poles of a motion (frequency and decay of each mode) and its mode shapes do not depend on
the phase, the amplitude, the push or the camera's frame and clock: they depend on the damping
and the lengths only, which is what the fit's start (`start`) matches.

**Poles** by the matrix-pencil method (Hua & Sarkar 1990) on the three columns together: windows
of ``L`` consecutive frames (those with a missing frame are skipped, so decoding gaps do no
harm), the row space truncated to ``order`` by an SVD, and the eigenvalues ``z = exp(s / f_s)``
of the shift between the truncated windows. Frames alias the modes (Nyquist 57.2 Hz at 114.44
frames/s), and so do the poles (`fold`).

**Strengths and shapes** (`dominant`): each pole's amplitude in each column by least squares;
its strength is its energy over the frames, its shape the ratio of planar to angular amplitude.

**Settled pose** (`settled`): after an actuator move, the constant a least-squares fit puts
beside the pencil's damped modes, the equilibrium the motion settles to.
"""

from __future__ import annotations

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


def amplitudes(t, pose, frame_rate, z):
    """Complex amplitudes (len(z), 3) of the poles ``z`` (from `poles`) in each column of
    ``pose``, in its units: a least-squares fit of a constant and the poles' damped oscillations
    (each with its conjugate) to the frames."""
    k = np.rint((np.asarray(t) - t[0]) * frame_rate).astype(int)
    basis = [np.ones(k.size, complex)] + [zk**k for zk in z] + [np.conj(zk) ** k for zk in z if abs(zk.imag) > 1e-12]
    coef = np.linalg.lstsq(np.stack(basis, axis=1), np.asarray(pose).astype(complex), rcond=None)[0]
    return coef[1 : 1 + len(z)]


def strengths(pose, z, amps):
    """How much of the motion each pole ``z`` carries, from its amplitudes ``amps`` (`amplitudes`)
    in the columns of ``pose``: the root of its energy summed over the frames, |c|^2 / (1 - |z|^2)
    for its amplitude c in columns scaled to unit spread (a mode that dies within a few frames
    counts little, however large it starts)."""
    sd = np.std(pose, axis=0)
    c = amps / np.where(sd > 0, sd, np.inf)
    return np.sqrt(np.sum(np.abs(c) ** 2, axis=1) / np.maximum(1.0 - np.abs(z) ** 2, 1e-12))


def describe(z, frame_rate):
    """(aliased frequency Hz, decay rate 1/s) of discrete poles ``z``."""
    s = np.log(z.astype(complex)) * frame_rate
    return np.abs(np.imag(s)) / (2 * np.pi), -np.real(s)


def dominant(t, pose, frame_rate, order: int, window: int, keep: int = 3, floor: float = 0.05):
    """(frequency Hz, decay 1/s, strength, shape) of the ``keep`` strongest decaying oscillations
    in frames ``pose`` at ``frame_rate`` (strongest first; none weaker than ``floor`` of the
    strongest; the real poles of drifts and the Nyquist pole of noise are left out). ``shape``:
    the ratio of each oscillation's planar to its angular amplitude (columns x, y, angle), the
    same in every frame the plane is seen in."""
    z = poles(t, pose, frame_rate, order, window)
    f, d = describe(z, frame_rate)
    amps = amplitudes(t, pose, frame_rate, z)
    s = strengths(pose, z, amps)
    a = np.abs(amps)
    shape = np.hypot(a[:, 0], a[:, 1]) / np.maximum(a[:, 2], 1e-300)
    osc = (f > 1e-3 * frame_rate) & (f < 0.49 * frame_rate) & (d > 0)
    if not osc.any():
        return tuple(np.zeros(0) for _ in range(4))
    f, d, s, shape = f[osc], d[osc], s[osc], shape[osc]
    order_ = np.argsort(-s)
    order_ = order_[s[order_] >= floor * s[order_[0]]][:keep]
    return f[order_], d[order_], s[order_], shape[order_]


def fold(f, frame_rate):
    """The frequency (Hz) at which frames taken at ``frame_rate`` show an oscillation of ``f``."""
    f = np.asarray(f, float)
    return np.abs(f - frame_rate * np.round(f / frame_rate))


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


def match_frequencies(
    features_of,
    x0,
    target,
    max_iter: int = 20,
    max_step: float = 0.01,
    h: float = 1e-4,
    tol: float = 1e-4,
    weights=None,
    bounds=None,
):
    """Gauss-Newton on log features: ``x`` (log lengths) such that ``features_of(x)`` (positive: sorted
    frequencies in Hz, static displacements) equals ``target`` (as many or more than ``x``: least
    squares, each log ratio weighted by ``weights``); finite-difference Jacobian, steps bounded to
    ``max_step`` and ``x`` to the box ``bounds`` = (lower, upper) if given. Returns (x, converged):
    converged when every feature matches to ``tol`` (as many as ``x``) or the steps stop."""
    w = np.ones(np.size(target)) if weights is None else np.asarray(weights, float)
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
        step = np.linalg.lstsq(J * w[:, None], -res * w, rcond=None)[0]
        last = step * min(1.0, max_step / max(np.max(np.abs(step)), 1e-300))
        if bounds is not None:
            last = np.clip(x + last, *bounds) - x
        x += last
    res = np.log(features_of(x) / target)
    return x, bool(np.max(np.abs(res)) < (tol if target.size == x.size else 0.03))
