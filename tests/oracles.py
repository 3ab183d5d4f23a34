"""Independent references for the tests: closed forms and scipy solvers (no pcrjax code)."""

import math

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq, least_squares

EB_BETA1 = 1.8751040687119611  # first root of cos(b) cosh(b) = -1


def euler_bernoulli_tip(F, L, E, r):
    I = math.pi * r**4 / 4
    return F * L**3 / (3 * E * I)


def first_frequency_hz(L, E, r, rho):
    I = math.pi * r**4 / 4
    A = math.pi * r**2
    return EB_BETA1**2 / (2 * math.pi * L**2) * math.sqrt(E * I / (rho * A))


def elastica_tip(load: float):
    """Inextensible cantilever with a tip force perpendicular to its clamp tangent, load = P L^2/EI.

    Solves theta'' = -load cos(theta), theta(0) = 0, theta'(1) = 0 on s in [0, 1] by shooting
    with scipy's DOP853 (rtol 1e-13). Returns (deflection/L, shortening/L, tip angle).
    """

    def rhs(s, y):
        th, k, x, z = y
        return [k, -load * math.cos(th), math.cos(th), math.sin(th)]

    def end(k0):
        sol = solve_ivp(rhs, (0, 1), [0, k0, 0, 0], method="DOP853", rtol=1e-13, atol=1e-15)
        return sol.y[:, -1]

    k0 = brentq(lambda k: end(k)[1], 0.0, load * 1.0 + 1e-9, xtol=1e-15, rtol=1e-15)
    th, _, x, z = end(k0)
    return z, 1.0 - x, th


def fit_sinusoids(t, y, omegas, decaying=False):
    """Least-squares fit y = c + sum_k e^{sigma_k t}(a_k cos w_k t + b_k sin w_k t).

    Returns the fitted (omega, sigma) per mode (sigma = 0 unless ``decaying``).
    """
    t = np.asarray(t)
    y = np.asarray(y)
    K = len(omegas)

    def model(p):
        out = np.full_like(t, p[0])
        for k in range(K):
            w, a, b = p[1 + 4 * k : 4 + 4 * k]
            s = p[4 + 4 * k] if decaying else 0.0
            out = out + np.exp(s * t) * (a * np.cos(w * t) + b * np.sin(w * t))
        return out

    scale = np.max(np.abs(y - y.mean()))
    p0 = [y.mean()]
    for w in omegas:
        p0 += [w, scale, 0.0, 0.0]
    res = least_squares(lambda p: (model(p) - y) / scale, p0, xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=20000)
    p = res.x
    return [(p[1 + 4 * k], p[4 + 4 * k] if decaying else 0.0) for k in range(K)], np.max(np.abs(res.fun))


def window_amplitudes(t, y, omega, other_omegas=(), periods_per_window=2.0):
    """First-mode amplitude in consecutive windows by linear least squares at fixed frequencies.

    Components far from ``omega`` (e.g. under-resolved modes near the Nyquist limit) average out
    over a window. Returns (window centres, amplitudes).
    """
    t = np.asarray(t)
    y = np.asarray(y)
    T = periods_per_window * 2 * np.pi / omega
    centres, amps = [], []
    start = t[0]
    while start + T <= t[-1] + 1e-12:
        sel = (t >= start) & (t < start + T)
        cols = [np.ones(sel.sum()), np.cos(omega * t[sel]), np.sin(omega * t[sel])]
        for w in other_omegas:
            cols += [np.cos(w * t[sel]), np.sin(w * t[sel])]
        coef, *_ = np.linalg.lstsq(np.stack(cols, axis=1), y[sel], rcond=None)
        centres.append(start + T / 2)
        amps.append(math.hypot(coef[1], coef[2]))
        start += T
    return np.asarray(centres), np.asarray(amps)


def cantilever_mode1(s, L):
    """First Euler-Bernoulli cantilever mode shape, normalised to 1 at the tip."""
    b = EB_BETA1 / L
    sig = (math.cosh(EB_BETA1) + math.cos(EB_BETA1)) / (math.sinh(EB_BETA1) + math.sin(EB_BETA1))
    phi = lambda x: np.cosh(b * x) - np.cos(b * x) - sig * (np.sinh(b * x) - np.sin(b * x))  # noqa: E731
    return phi(s) / phi(L)


def tip_mass_frequency_hz(L, E, r, rho, tip_mass):
    """First bending frequency (Hz) of an Euler-Bernoulli cantilever carrying a point mass at its
    tip: the smallest root x = beta L of 1 + cos x cosh x + mu x (cos x sinh x - sin x cosh x) = 0,
    mu = tip_mass / (rho A L), omega = x^2 sqrt(EI / (rho A L^4))."""
    A = math.pi * r**2
    EI = E * math.pi * r**4 / 4
    mu = tip_mass / (rho * A * L)

    def char(x):
        return 1 + math.cos(x) * math.cosh(x) + mu * x * (math.cos(x) * math.sinh(x) - math.sin(x) * math.cosh(x))

    x = brentq(char, 0.5, 1.9)
    return x**2 * math.sqrt(EI / (rho * A * L**4)) / (2 * math.pi)
