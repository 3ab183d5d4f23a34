r"""The rigid platform: pose parametrisation, BDF-alpha rates on rotations, and its balance.

**Pose unknowns.** A displacement $\Delta p$ (scaled by a length) and a rotation increment
$\theta$, $p = p_{ref} + \Delta p$, $R = R_{ref}\exp(\hat\theta)$, relative to the previous
step's pose (the reference pose in statics). With the planar bearing (Triskele on its air bearing) the unknowns are
$x, y, \theta_z$; $z$ and the tilt stay at the previous step's values.

**Rates.** Positions use BDF-alpha directly: $v = c_0 p + p^h$, $a = c_0 v + v^h$.
Rotations use the body angular velocity $\Omega$ (platform frame) and the rotation vectors of
the two previous poses seen from the current one, $\varphi_k = \log(R^T R_{i-k})$: since
$c_0 + c_1 + c_2 = 0$, BDF-alpha applied to a rotation expressed in the current body frame is
$$\Omega_i = c_1\varphi_1 + c_2\varphi_2 + d_1\Omega_{i-1},\qquad
\dot\Omega_i = c_0\Omega_i + \Omega^h,\ \Omega^h = c_1\Omega_{i-1} + c_2\Omega_{i-2} + d_1\dot\Omega_{i-1},$$
with $\varphi_1 = -\theta$ exactly and $\varphi_2 = \log(\exp(-\hat\theta) R_{i-1}^T R_{i-2})$.
About a fixed axis (the planar case) this is exactly BDF-alpha on the angle; in 3-D it is the
scheme in the moving body frame (past body rates are not transported, an $O(\delta t^2)$
effect like the scheme's own error). At rest every rate is exactly zero. This replaces thesis
eq. 4.14, whose rotation lines are typos.

**Balance** (thesis eq. 4.9-4.11, global frame): the rods pull on the platform with minus their
tip wrenches, so
$F + m g - \sum n_i(L) = m a$ and
$M - \sum (m_i(L) + (R r_i)\times n_i(L)) = R(J\dot\Omega + \Omega\times J\Omega)$
(eq. 4.10 prints a plus sign before the sum, inconsistent with eq. 4.9).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .rotations import cross, exp_map, matmul, matvec, rotation_vector, transpose_matmul


class Platform(eqx.Module):
    """Rigid platform: ``mass`` (kg) and principal ``inertia`` (3,) (kg m^2, platform frame)."""

    mass: jnp.ndarray
    inertia: jnp.ndarray


class PlatformMotion(eqx.Module):
    r"""BDF-alpha memory of the platform at the start of a step (values of step i-1).

    Positions enter only through the displacement $\Delta p = p - p_{i-1}$:
    $v = c_0 \Delta p + g_p$ and $a = c_0 (v - v_{i-1}) + g_v$ with the motion parts
    $g_p = -c_2 \Delta p_{i-1} + d_1 v_{i-1}$, $g_v = -c_2 (v_{i-1} - v_{i-2}) + d_1 a_{i-1}$
    (equal to BDF-alpha since $c_0 + c_1 + c_2 = 0$). Written with absolute positions,
    $a = c_0^2 p + \dots$ cancels catastrophically: at $\delta t$ = 1 ms the round-off of
    $p$ alone gave a platform force error of 3e-9 in scaled units, above Newton's tolerance.
    """

    p1: jnp.ndarray  # position at t_{i-1}
    v1: jnp.ndarray  # velocity at t_{i-1}
    gp: jnp.ndarray  # v_i = c0 (p_i - p1) + gp
    gv: jnp.ndarray  # a_i = c0 (v_i - v1) + gv
    R1: jnp.ndarray  # rotation at t_{i-1}
    R2: jnp.ndarray  # rotation at t_{i-2}
    w1: jnp.ndarray  # body angular velocity at t_{i-1}
    wh: jnp.ndarray  # body angular velocity history: dw_i = c0 w_i + wh

    @classmethod
    def rest(cls, co, p, R):
        # Zeros that depend on p: under jvp their tangents are nonzero from the start, as they are
        # after a step, so that JAX finds the tangents (and, under vmap, the batching) of a scan of
        # steps in one trace of the step instead of two.
        z = 0.0 * p
        return cls(p1=p, v1=z, gp=z, gv=z, R1=R, R2=R, w1=z, wh=z)


class Rates(eqx.Module):
    v: jnp.ndarray
    a: jnp.ndarray
    w: jnp.ndarray  # body frame
    dw: jnp.ndarray  # body frame


def pose(x, planar: bool, p_prev, R_prev, length):
    """Platform (p, R, dp, theta) from the scaled pose unknowns, relative to (p_prev, R_prev):
    6 (dp/L, theta) or 3 planar (dx/L, dy/L, theta_z)."""
    if planar:
        zero = jnp.zeros_like(x[2])
        dp = jnp.stack([x[0] * length, x[1] * length, zero])
        theta = jnp.stack([zero, zero, x[2]])
    else:
        dp = x[0:3] * length
        theta = x[3:6]
    return p_prev + dp, matmul(R_prev, exp_map(theta)), dp, theta


def pose_unknowns(p, R, p_prev, R_prev, planar: bool, length):
    """Inverse of `pose`: scaled unknowns of pose (p, R) relative to (p_prev, R_prev)."""
    dp = p - p_prev
    theta = rotation_vector(transpose_matmul(R_prev, R))
    if planar:
        return jnp.stack([dp[0] / length, dp[1] / length, theta[2]])
    return jnp.concatenate([dp / length, theta])


def rates(co, m: PlatformMotion, dp, theta) -> Rates:
    v = co.c0 * dp + m.gp
    a = co.c0 * (v - m.v1) + m.gv
    phi2 = rotation_vector(matmul(exp_map(-theta), transpose_matmul(m.R1, m.R2)))
    w = -co.c1 * theta + co.c2 * phi2 + co.d1 * m.w1
    dw = co.c0 * w + m.wh
    return Rates(v=v, a=a, w=w, dw=dw)


def advance(co, m: PlatformMotion, p, R, dp, r: Rates) -> PlatformMotion:
    """Memory for the next step after a step that moved by ``dp`` to pose (p, R) with rates ``r``."""
    return PlatformMotion(
        p1=p,
        v1=r.v,
        gp=-co.c2 * dp + co.d1 * r.v,
        gv=-co.c2 * (r.v - m.v1) + co.d1 * r.a,
        R1=R,
        R2=m.R1,
        w1=r.w,
        wh=co.c1 * r.w + co.c2 * m.w1 + co.d1 * r.dw,
    )


def balance(platform: Platform, R, attachments, tip_n, tip_m, F, M, weight, r: Rates | None):
    """Net force and moment on the platform (zero at equilibrium), global frame.

    ``attachments`` (n, 3) in the platform frame; ``tip_n``, ``tip_m`` (n, 3) the rods' internal
    force and moment at their tips; ``weight`` m g (or zeros); ``r`` None in statics.
    """
    arms = jnp.stack([matvec(R, a) for a in attachments])
    force = F + weight - jnp.sum(tip_n, axis=0)
    moment = M - jnp.sum(tip_m, axis=0) - sum(cross(arms[i], tip_n[i]) for i in range(arms.shape[0]))
    if r is not None:
        J = platform.inertia
        force = force - platform.mass * r.a
        moment = moment - matvec(R, J * r.dw + cross(r.w, J * r.w))
    return force, moment


def kinetic_energy(platform: Platform, r: Rates):
    return 0.5 * platform.mass * jnp.dot(r.v, r.v) + 0.5 * jnp.dot(r.w, platform.inertia * r.w)
