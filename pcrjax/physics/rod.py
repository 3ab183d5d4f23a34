"""Cosserat-rod physics: material parameters, effects and the spatial ODE (thesis eq. 3.37-3.38).

State along arclength $s$ (global frame for $p, n, m$; local frame for $q, \\omega$):

* statics: ``y = [p(3), R(9, row-major), n(3), m(3)]`` (18 numbers);
* dynamics: ``y = [p, R, n, m, q(3), w(3)]`` (24 numbers).

Time enters only through the BDF-alpha coefficient $c_0$ and the per-node history
``h = [v^h, u^h, q^h, w^h]`` (12 numbers) so that $f_t = c_0 f + f^h$ (see `bdf_alpha.py`).
Every effect (inertia, gravity, damping, drag, shear/extension, precurvature) is switched by a
Python-level flag or an ``X | None`` field, so a scene compiles only what it turns on.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .rotations import cross, matvec, rmatvec

STATIC_DIM = 18
DYNAMIC_DIM = 24
HISTORY_DIM = 12

_E3 = (0.0, 0.0, 1.0)


class Effects(eqx.Module):
    """Which physical effects a scene compiles (static structure, not differentiable)."""

    inertia: bool = eqx.field(static=True, default=True)
    gravity: bool = eqx.field(static=True, default=False)
    damping: bool = eqx.field(static=True, default=False)
    drag: bool = eqx.field(static=True, default=False)
    shear_extension: bool = eqx.field(static=True, default=True)
    planar: bool = eqx.field(static=True, default=False)  # parallel robots: platform on a planar bearing


class TauDamping(eqx.Module):
    """Kelvin-Voigt damping proportional to stiffness, $B = \\tau K$ (thesis eq. 3.6); tau in s."""

    tau: Float[Array, ""]

    def diagonals(self, kse, kbt):
        return self.tau * kse, self.tau * kbt


class SplitTauDamping(eqx.Module):
    """Kelvin-Voigt damping with one time for stretch and shear, another for bending and twist:
    ``bse = tau_se * Kse``, ``bbt = tau_bt * Kbt`` (s each)."""

    tau_se: Float[Array, ""]
    tau_bt: Float[Array, ""]

    def diagonals(self, kse, kbt):
        return self.tau_se * kse, self.tau_bt * kbt


class DiagonalDamping(eqx.Module):
    """Kelvin-Voigt damping with explicit diagonals: ``bse`` (N s), ``bbt`` (N m^2 s)."""

    bse: Float[Array, 3]
    bbt: Float[Array, 3]

    def diagonals(self, kse, kbt):
        return self.bse, self.bbt


class Rod(eqx.Module):
    """One rod's material and geometry (SI units). Every field is a differentiable leaf.

    **Fields:** ``length`` L (m), ``radius`` r (m), ``youngs_modulus`` E (Pa), ``shear_modulus``
    G (Pa), ``density`` rho (kg/m^3), ``damping`` (`TauDamping` | `SplitTauDamping` | `DiagonalDamping` | None),
    ``drag`` diagonal of C (kg/m^2, or None), ``precurvature`` u* (1/m, or None).
    """

    length: Float[Array, ""]
    radius: Float[Array, ""]
    youngs_modulus: Float[Array, ""]
    shear_modulus: Float[Array, ""]
    density: Float[Array, ""]
    damping: TauDamping | SplitTauDamping | DiagonalDamping | None = None
    drag: Float[Array, 3] | None = None
    precurvature: Float[Array, 3] | None = None

    @property
    def area(self):
        return jnp.pi * self.radius**2

    @property
    def second_moment(self):
        """Area moment $I = \\pi r^4/4$ (m^4); polar $J = 2I$."""
        return 0.25 * jnp.pi * self.radius**4

    @property
    def kse(self):
        """Diagonal of $K_{se}$ = (GA, GA, EA) in N."""
        A = self.area
        return jnp.stack([self.shear_modulus * A, self.shear_modulus * A, self.youngs_modulus * A])

    @property
    def kbt(self):
        """Diagonal of $K_{bt}$ = (EI, EI, GJ) in N m^2, with J = 2I (circular section)."""
        I = self.second_moment
        return jnp.stack([self.youngs_modulus * I, self.youngs_modulus * I, 2.0 * self.shear_modulus * I])

    @property
    def bending_stiffness(self):
        return self.youngs_modulus * self.second_moment


class RodCoefficients(eqx.Module):
    """Per-rod constants of the spatial ODE at one time step (built by `coefficients`)."""

    kse: Array
    kbt: Array
    bse: Array | None
    bbt: Array | None
    rho_a: Array
    rho_j: Array  # rho * diag(I, I, 2I)
    c0: Array
    gravity: Array | None  # distributed weight rho*A*g (N/m)
    drag: Array | None
    ustar: Array | None


def coefficients(rod: Rod, effects: Effects, c0, gravity) -> RodCoefficients:
    """Evaluate the constant factors of the rod ODE once per step, honouring the effect switches."""
    I = rod.second_moment
    bse = bbt = None
    if effects.damping and effects.inertia:
        if rod.damping is None:
            raise ValueError("effects.damping is on but the rod has no damping parameters")
        with jax.named_scope("damping"):
            bse, bbt = rod.damping.diagonals(rod.kse, rod.kbt)
    g = None
    if effects.gravity:
        with jax.named_scope("gravity"):
            g = rod.density * rod.area * gravity
    drag = None
    if effects.drag and effects.inertia:
        if rod.drag is None:
            raise ValueError("effects.drag is on but the rod has no drag coefficients")
        drag = rod.drag
    return RodCoefficients(
        kse=rod.kse,
        kbt=rod.kbt,
        bse=bse,
        bbt=bbt,
        rho_a=rod.density * rod.area,
        rho_j=rod.density * jnp.stack([I, I, 2.0 * I]),
        c0=c0,
        gravity=g,
        drag=drag,
        ustar=rod.precurvature,
    )


@jax.custom_jvp
def _frame(y):
    """Columns and rows of the rotation in a state vector (row-major at [3:12]), read by (strided)
    slices of the state: a reshaped copy of it is a kernel of its own on XLA:CPU."""
    return tuple(y[3 + j : 12 : 3] for j in range(3)), tuple(y[3 + 3 * i : 6 + 3 * i] for i in range(3))


@_frame.defjvp
def _frame_jvp(primals, tangents):
    # The tangents through a reshape: reverse mode transposes this rule, and the transpose of a
    # strided slice (an interior-padded pad) made the gradient of a rollout twice as slow.
    (y,), (dy,) = primals, tangents
    dR = dy[3:12].reshape(3, 3)
    return _frame(y), (tuple(dR[:, j] for j in range(3)), tuple(dR[i, :] for i in range(3)))


class _Frame:
    """The rotation of a state vector, read as ``R[:, j]`` (columns), ``R[i, :]`` (rows) or ``R[i, j]``."""

    def __init__(self, y):
        self.cols, self.rows = _frame(y)

    def __getitem__(self, idx):
        i, j = idx
        if isinstance(i, slice):
            return self.cols[j]
        return self.rows[i] if isinstance(j, slice) else self.rows[i][j]


def unpack(y):
    """Split a state vector into (p, R, n, m[, q, w]); R is read by index (`_Frame`)."""
    p, R, n, m = y[0:3], _Frame(y), y[12:15], y[15:18]
    if y.shape[0] == DYNAMIC_DIM:
        return p, R, n, m, y[18:21], y[21:24]
    return p, R, n, m


def strains(y, h, k: RodCoefficients, effects: Effects):
    """Local strains $(v, u)$ from the internal loads by the constitutive law (eq. 3.38)."""
    _, R, n, m = unpack(y)[:4]
    rn = rmatvec(R, n)
    rm = rmatvec(R, m)
    ustar_term = 0.0 if k.ustar is None else k.kbt * k.ustar
    # Products with reciprocals, not divisions: XLA:CPU computes a division once, in a kernel of its
    # own, where a product fuses into every consumer of the strains.
    if k.bse is not None:
        with jax.named_scope("damping"):
            if effects.shear_extension:
                v = (rn + k.kse * jnp.asarray(_E3) - k.bse * h[0:3]) * (1.0 / (k.kse + k.c0 * k.bse))
            u = (rm + ustar_term - k.bbt * h[3:6]) * (1.0 / (k.kbt + k.c0 * k.bbt))
    else:
        if effects.shear_extension:
            v = rn * (1.0 / k.kse) + jnp.asarray(_E3)
        u = rm * (1.0 / k.kbt) + (0.0 if k.ustar is None else k.ustar)
    if not effects.shear_extension:
        v = jnp.asarray(_E3, dtype=y.dtype)
    return v, u


def _rotate_cross_plus(R, a, b, c):
    """$R (a \\times b + c)$ with the cross product's components kept apart: on XLA:CPU a stacked
    3-vector that a product with R reads componentwise is a kernel of its own."""
    axb = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
    return R[:, 0] * (axb[0] + c[0]) + R[:, 1] * (axb[1] + c[1]) + R[:, 2] * (axb[2] + c[2])


def rhs(y, h, k: RodCoefficients, effects: Effects):
    """$dy/ds$ of the Cosserat rod at one point, given its history ``h`` (ignored in statics). It
    does not depend on the position y[0:3] (`spatial.integrate_tangents` carries a tangent that
    moves the position alone without integrating it)."""
    v, u = strains(y, h, k, effects)
    if effects.inertia:
        p, R, n, m, q, w = unpack(y)
    else:
        p, R, n, m = unpack(y)
    p_s = matvec(R, v)
    omega = matvec(R, u)  # R u: global curvature vector; R_s = R u^ has columns omega x R e_i
    R_s = jnp.stack([cross(omega, R[:, j]) for j in range(3)], axis=1)
    f = jnp.zeros(3, y.dtype)
    if k.gravity is not None:
        with jax.named_scope("gravity"):
            f = f + k.gravity
    if not effects.inertia:
        n_s = -f
        m_s = -cross(p_s, n)
        return jnp.concatenate([p_s, R_s.reshape(9), n_s, m_s])
    if k.drag is not None:
        with jax.named_scope("drag"):
            # |q| as a sign flip, not `abs`: analytic for the complex step of `spatial.integrate_tangents`
            f = f - matvec(R, k.drag * q * jnp.where(jnp.real(q) < 0, -q, q))
    c0 = k.c0
    q_t = c0 * q + h[6:9]
    w_t = c0 * w + h[9:12]
    u_t = c0 * u + h[3:6]
    n_s = k.rho_a * _rotate_cross_plus(R, w, q, q_t) - f
    m_s = _rotate_cross_plus(R, w, k.rho_j * w, k.rho_j * w_t) - cross(p_s, n)
    if effects.shear_extension:
        v_t = c0 * v + h[0:3]
        q_s = v_t - cross(u, q) + cross(w, v)
    else:
        q_s = -cross(u, q) + cross(w, v)
    w_s = u_t - cross(u, w)
    return jnp.concatenate([p_s, R_s.reshape(9), n_s, m_s, q_s, w_s])


def kinematic_state(y, h, k: RodCoefficients, effects: Effects):
    """The quantities BDF-alpha differentiates in time at a node: ``z = [v, u, q, w]``."""
    v, u = strains(y, h, k, effects)
    return jnp.concatenate([v, u, y[18:21], y[21:24]])


def energy(k: RodCoefficients, effects: Effects, nodes, z, ds):
    """Elastic, kinetic and (with gravity) potential energy of one rod (J), trapezoidal rule over
    its ``nodes`` (N+1, 24) with kinematic states ``z`` (N+1, 12) = [v, u, q, w]."""
    v, u, q, w = z[:, 0:3], z[:, 3:6], nodes[:, 18:21], nodes[:, 21:24]
    e = 0.5 * jnp.sum(k.kbt * (u - (0.0 if k.ustar is None else k.ustar)) ** 2, axis=1)
    if effects.shear_extension:
        e = e + 0.5 * jnp.sum(k.kse * (v - jnp.asarray(_E3)) ** 2, axis=1)
    e = e + 0.5 * k.rho_a * jnp.sum(q * q, axis=1) + 0.5 * jnp.sum(k.rho_j * w * w, axis=1)
    if k.gravity is not None:
        e = e - nodes[:, 0:3] @ k.gravity
    return ds * (jnp.sum(e) - 0.5 * (e[0] + e[-1]))
