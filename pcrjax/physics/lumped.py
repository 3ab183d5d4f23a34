"""The lumped rod (thesis 3.1): N rigid nodes joined by springs and dampers.

A rod of length L becomes N + 1 nodes, 0 clamped at the base, spaced l = L/N along it. Node i
carries a position $p_i$ and an orientation (unit quaternion $q_i$); the segment between nodes
i and i + 1 is a spring whose strains are the discrete Cosserat strains

* $v = R_m^T (p_{i+1} - p_i)/l$ (shear and stretch, in the midpoint frame $R_m$ halfway between
  $R_i$ and $R_{i+1}$, so the chain is symmetric and second-order accurate), and
* $u = \\log(R_i^T R_{i+1})/l$ (bending and twist),

with energy $l\\,[\\tfrac12 (v - e_3)^T K_{se} (v - e_3) + \\tfrac12 (u - u^*)^T K_{bt} (u - u^*)]$.
Per segment that is the thesis's axial spring $k = EA/l$ (eq. 3.4) and torsion spring
$k_T = GJ/l$ (eq. 3.5), with bending springs $EI/l$ and shear springs $GA/l$ alongside. Damping is
Kelvin-Voigt on the strain rates, $b = \\tau k$ (eq. 3.6) through the rod's damping model.
Masses $\\rho A l$ and the rotational inertias of rigid segments,
$\\rho l\\,\\mathrm{diag}(I + A l^2/12, I + A l^2/12, 2I)$, sit on the nodes (half at the free end);
the segment's own $m l^2/12$ keeps the shear-rotation modes near the axial ones ($\\sim c/l$) instead of
$\\sim c/r$, so that an explicit integrator can take steps of the axial wave's time scale. Forces are gradients of the energy with respect to a displacement of each
node and a small rotation of its frame (body axes); damping forces are gradients of the
dissipation function with respect to the node velocities.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .rod import Effects, Rod
from .rotations import cross

_E3 = jnp.array([0.0, 0.0, 1.0])


def qmul(a, b):
    """Quaternion product $a \\otimes b$, ``(w, x, y, z)``."""
    w = a[0] * b[0] - jnp.dot(a[1:], b[1:])
    return jnp.concatenate([w[None], a[0] * b[1:] + b[0] * a[1:] + cross(a[1:], b[1:])])


def qrotate(q, x):
    """$R(q) x$ for a unit quaternion."""
    t = 2.0 * cross(q[1:], x)
    return x + q[0] * t + cross(q[1:], t)


def qrotate_inverse(q, x):
    """$R(q)^T x$ for a unit quaternion."""
    return qrotate(q * jnp.array([1.0, -1.0, -1.0, -1.0]), x)


def qexp(a):
    """Unit quaternion of the rotation vector ``a``, smooth at ``a = 0``."""
    t2 = jnp.dot(a, a)
    small = t2 < 1e-12
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    c = jnp.where(small, 1.0 - t2 / 8.0, jnp.cos(0.5 * t))
    s = jnp.where(small, 0.5 - t2 / 48.0, jnp.sin(0.5 * t) / t)
    return jnp.concatenate([c[None], s * a])


def qlog(q):
    """Rotation vector of a unit quaternion with ``w >= 0``, smooth at the identity (to every order)."""
    n2 = jnp.dot(q[1:], q[1:])
    small = n2 < 1e-12
    s = jnp.sqrt(jnp.where(small, 1.0, n2))
    scale = jnp.where(small, (2.0 - 2.0 * n2 / (3.0 * q[0] ** 2)) / q[0], 2.0 * jnp.arctan2(s, q[0]) / s)
    return scale * q[1:]


def normalised(q):
    """Quaternions (..., 4) scaled to unit length."""
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def displaced(p, q, d):
    """Node positions (N, 3) moved by ``d[:, :3]`` and quaternions (N, 4) turned by the small
    body-axis rotations ``d[:, 3:]``: the coordinates forces, Jacobians and modes are taken in."""
    return p + d[:, :3], normalised(jax.vmap(qmul)(q, jax.vmap(qexp)(d[:, 3:])))


def _segment_strains(pa, qa, pb, qb, l):
    qa = qa / jnp.linalg.norm(qa)
    qb = qb / jnp.linalg.norm(qb)
    sign = jnp.where(jnp.dot(qa, qb) < 0, -1.0, 1.0)
    qb = sign * qb
    qrel = qmul(qa * jnp.array([1.0, -1.0, -1.0, -1.0]), qb)
    u = qlog(qrel) / l
    qm = qa + qb
    qm = qm / jnp.linalg.norm(qm)
    v = qrotate_inverse(qm, (pb - pa) / l)
    return v, u


class Chain(eqx.Module):
    """A rod as ``segments`` rigid segments: spring and damper diagonals, node masses and
    inertias (nodes 1..N), and the clamped base node's position and quaternion."""

    l: jnp.ndarray
    kse: jnp.ndarray
    kbt: jnp.ndarray
    bse: jnp.ndarray | None
    bbt: jnp.ndarray | None
    ustar: jnp.ndarray | None
    mass: jnp.ndarray  # (N,)
    inertia: jnp.ndarray  # (N, 3) body-axis diagonal
    base_position: jnp.ndarray
    base_quaternion: jnp.ndarray

    @classmethod
    def of_rod(cls, rod: Rod, effects: Effects, segments: int, base_position, base_quaternion):
        l = rod.length / segments
        w = jnp.ones(segments).at[-1].set(0.5)
        I = rod.second_moment
        bse = bbt = None
        if effects.damping and rod.damping is not None:
            bse, bbt = rod.damping.diagonals(rod.kse, rod.kbt)
        return cls(
            l=l,
            kse=rod.kse,
            kbt=rod.kbt,
            bse=bse,
            bbt=bbt,
            ustar=rod.precurvature,
            mass=rod.density * rod.area * l * w,
            # A node stands for a rigid segment: its section's inertia plus the segment's own m l^2/12.
            inertia=rod.density * l * w[:, None] * jnp.stack([I + rod.area * l**2 / 12, I + rod.area * l**2 / 12, 2.0 * I]),
            base_position=base_position,
            base_quaternion=base_quaternion,
        )

    @property
    def segments(self) -> int:
        return self.mass.shape[0]

    def straight(self):
        """Positions (N, 3) and quaternions (N, 4) of the unstrained straight rod."""
        s = self.l * jnp.arange(1, self.segments + 1)
        d = qrotate(self.base_quaternion, _E3)
        return self.base_position + s[:, None] * d, jnp.tile(self.base_quaternion, (self.segments, 1))

    def strains(self, p, q):
        """Segment strains ``v`` (N, 3) and ``u`` (N, 3) of node positions (N, 3) and quaternions (N, 4)."""
        P = jnp.concatenate([self.base_position[None], p])
        Q = jnp.concatenate([self.base_quaternion[None], q])
        return jax.vmap(_segment_strains, in_axes=(0, 0, 0, 0, None))(P[:-1], Q[:-1], P[1:], Q[1:], self.l)

    def energy(self, p, q):
        """Elastic energy (J)."""
        v, u = self.strains(p, q)
        dv = v - _E3
        du = u if self.ustar is None else u - self.ustar
        return 0.5 * self.l * (jnp.sum(dv * dv * self.kse) + jnp.sum(du * du * self.kbt))

    def kinetic(self, v, w):
        """Kinetic energy (J) of node velocities (N, 3) and body angular velocities (N, 3)."""
        return 0.5 * (jnp.sum(self.mass[:, None] * v * v) + jnp.sum(self.inertia * w * w))

    def elastic_forces(self, p, q):
        """$\\partial E/\\partial p_i$ (N, 3) and $\\partial E/\\partial \\theta_i$ (N, 3, body axes)."""
        g = jax.grad(lambda d: self.energy(*displaced(p, q, d)))(jnp.zeros((p.shape[0], 6)))
        return g[:, :3], g[:, 3:]

    def damping_forces(self, p, q, v, w):
        """$\\partial D/\\partial v_i$ and $\\partial D/\\partial \\omega_i$ of the dissipation
        $D = \\tfrac l2 \\sum (\\dot v^T B_{se} \\dot v + \\dot u^T B_{bt} \\dot u)$."""

        def dissipation(rates):
            _, (vd, ud) = jax.jvp(lambda d: self.strains(*displaced(p, q, d)), (jnp.zeros_like(rates),), (rates,))
            return 0.5 * self.l * (jnp.sum(vd * vd * self.bse) + jnp.sum(ud * ud * self.bbt))

        g = jax.grad(dissipation)(jnp.concatenate([v, w], axis=1))
        return g[:, :3], g[:, 3:]

    def accelerations(self, p, q, v, w, force, moment_body):
        """Node accelerations (N, 3) and body angular accelerations (N, 3) under the external
        node forces ``force`` (N, 3) and body-axis moments ``moment_body`` (N, 3)."""
        fp, ft = self.elastic_forces(p, q)
        if self.bse is not None:
            dp, dt = self.damping_forces(p, q, v, w)
            fp, ft = fp + dp, ft + dt
        a = (force - fp) / self.mass[:, None]
        Jw = self.inertia * w
        alpha = (moment_body - ft - jax.vmap(cross)(w, Jw)) / self.inertia
        return a, alpha
