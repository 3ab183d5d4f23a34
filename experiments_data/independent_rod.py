r"""An independent planar Cosserat rod (Simo-Reissner beam), to make recordings that are not
pcrjax's own model: a different discretisation (finite volumes in space, lumped masses, the
method of lines) and a different time integrator (SciPy's variable-order BDF with error control),
sharing no code with pcrjax.

The rod moves in the x-z plane, clamped at s = 0. Node i (i = 0..M, spacing h = L/M) carries a
position $r_i$ and the angle $\varphi_i$ of its director $d_3 = (\cos\varphi, \sin\varphi)$
from +x towards +z ($d_1 = (-\sin\varphi, \cos\varphi)$). Edge j between nodes j and j+1 has the
director angle $\bar\varphi_j$ (the nodes' mean) and the strains
$$\nu_j = d^T(\bar\varphi_j)\,(r_{j+1} - r_j)/h, \qquad \kappa_j = (\varphi_{j+1} - \varphi_j)/h,$$
with the stresses of a Kelvin-Voigt material (relaxation time ``tau`` on every strain rate):
shear $n_1 = GA(\nu_1 + \tau\dot\nu_1)$, stretch $n_3 = EA(\nu_3 - 1 + \tau\dot\nu_3)$, bending
$m = EI(\kappa + \tau\dot\kappa)$. Each node carries the mass and rotary inertia of the half
edges beside it and is moved by the edges' forces and moments,
$$\rho A\,\ell_i\,\ddot r_i = n_i - n_{i-1} + \rho A \ell_i g + F\,[i = M],$$
$$\rho I\,\ell_i\,\ddot\varphi_i = m_i - m_{i-1} + \tfrac h2\big[(\nu \times n)_{i-1} + (\nu \times n)_i\big]$$
(edges that do not exist contribute nothing; $\ell_i = h$, or $h/2$ at the tip; $a \times b =
a_x b_z - a_z b_x$). The static state under a tip force is the root of the same equations at
rest (Newton from the straight rod, the load applied in steps).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import sparse
from scipy.integrate import solve_ivp
from scipy.sparse.linalg import spsolve


@dataclasses.dataclass(frozen=True)
class PlanarRod:
    length: float
    radius: float
    youngs_modulus: float
    shear_modulus: float
    density: float
    tau: float
    gravity: tuple  # (gx, gz) m/s^2
    base_angle: float  # rad, from +x towards +z
    nodes: int  # edges M

    @property
    def h(self):
        return self.length / self.nodes

    def _sections(self):
        A = np.pi * self.radius**2
        I = 0.25 * np.pi * self.radius**4
        return A, I

    def _unpack(self, q):
        M = self.nodes
        x = np.concatenate([[0.0], q[:M]])
        z = np.concatenate([[0.0], q[M : 2 * M]])
        phi = np.concatenate([[self.base_angle], q[2 * M :]])
        return x, z, phi

    def forces(self, q, v, tip_force):
        """Generalised forces (3M,) on the free nodes' (x, z, phi) at positions ``q`` and rates ``v``."""
        A, I = self._sections()
        E, G, rho, h, tau = self.youngs_modulus, self.shear_modulus, self.density, self.h, self.tau
        x, z, phi = self._unpack(q)
        vx, vz, w = self._unpack_rates(v)
        dx, dz = np.diff(x) / h, np.diff(z) / h
        dvx, dvz = np.diff(vx) / h, np.diff(vz) / h
        pb, wb = 0.5 * (phi[1:] + phi[:-1]), 0.5 * (w[1:] + w[:-1])
        c, s = np.cos(pb), np.sin(pb)
        nu1, nu3 = -s * dx + c * dz, c * dx + s * dz
        nu1_dot = -s * dvx + c * dvz - wb * nu3  # d/dt of d1 . r' with d1' = -phibar' d3
        nu3_dot = c * dvx + s * dvz + wb * nu1
        kappa, kappa_dot = np.diff(phi) / h, np.diff(w) / h
        n1 = G * A * (nu1 + tau * nu1_dot)
        n3 = E * A * (nu3 - 1.0 + tau * nu3_dot)
        m = E * I * (kappa + tau * kappa_dot)
        nx, nz = -s * n1 + c * n3, c * n1 + s * n3  # n = n1 d1 + n3 d3
        torque = dx * nz - dz * nx  # r' x n on each edge
        M = self.nodes
        fx, fz, fm = np.zeros(M + 1), np.zeros(M + 1), np.zeros(M + 1)
        fx[:-1] += nx
        fx[1:] -= nx
        fz[:-1] += nz
        fz[1:] -= nz
        fm[:-1] += m + 0.5 * h * torque
        fm[1:] += -m + 0.5 * h * torque
        ell = np.full(M + 1, h)
        ell[-1] = 0.5 * h
        fx += rho * A * ell * self.gravity[0]
        fz += rho * A * ell * self.gravity[1]
        fx[-1] += tip_force[0]
        fz[-1] += tip_force[1]
        return np.concatenate([fx[1:], fz[1:], fm[1:]])

    def _unpack_rates(self, v):
        M = self.nodes
        return (np.concatenate([[0.0], v[:M]]), np.concatenate([[0.0], v[M : 2 * M]]), np.concatenate([[0.0], v[2 * M :]]))

    def inertia(self):
        A, I = self._sections()
        ell = np.full(self.nodes, self.h)
        ell[-1] = 0.5 * self.h
        return np.concatenate([self.density * A * ell, self.density * A * ell, self.density * I * ell])

    def straight(self):
        s = np.arange(1, self.nodes + 1) * self.h
        c, sn = np.cos(self.base_angle), np.sin(self.base_angle)
        return np.concatenate([s * c, s * sn, np.full(self.nodes, self.base_angle)])

    def _derivative(self, q, v, tip_force, wrt: str):
        """d forces / d q (``wrt`` "q") or d v ("v") (3M, 3M) sparse, by central differences with
        the columns coloured (a node's forces depend on its neighbours only, so every third node
        of one unknown is perturbed at once); steps of 1e-7 (q) or 1e-4 (v) of the rod length
        and radians."""
        M = self.nodes
        size = 3 * M
        step = np.concatenate([np.full(2 * M, self.length), np.ones(M)]) * (1e-7 if wrt == "q" else 1e-4)
        rows, cols, vals = [], [], []
        node = np.arange(M)
        for b in range(3):
            for c in range(3):
                pick = node[node % 3 == c]
                e = np.zeros(size)
                e[b * M + pick] = step[b * M + pick]
                if wrt == "q":
                    d = (self.forces(q + e, v, tip_force) - self.forces(q - e, v, tip_force)) / 2.0
                else:
                    d = (self.forces(q, v + e, tip_force) - self.forces(q, v - e, tip_force)) / 2.0
                j = node + ((c - node) % 3 + 1) % 3 - 1  # the neighbour of each node (i-1, i or i+1) perturbed here
                ok = (j >= 0) & (j < M)
                for a in range(3):
                    rows.append(a * M + node[ok])
                    cols.append(b * M + j[ok])
                    vals.append(d[a * M + node[ok]] / step[b * M + j[ok]])
        return sparse.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))

    def static(self, tip_force, steps: int = 8):
        """Node unknowns (3M,) of the equilibrium under gravity and ``tip_force`` (fx, fz) N:
        Newton from the straight rod, gravity and the force applied in ``steps`` equal steps."""
        q = self.straight()
        zero = np.zeros_like(q)
        for k in range(1, steps + 1):
            f = np.asarray(tip_force, np.float64) * k / steps
            rod = dataclasses.replace(self, gravity=tuple(k / steps * np.asarray(self.gravity)))
            for _ in range(50):
                r = rod.forces(q, zero, f)
                dq = spsolve(rod._derivative(q, zero, f, "q"), -r)
                q = q + dq
                if np.abs(dq[: 2 * self.nodes]).max() < 1e-14 * self.length and np.abs(dq[2 * self.nodes :]).max() < 1e-13:
                    break
            else:
                raise RuntimeError(f"static Newton did not converge at load step {k}")
        return q

    def release(self, tip_force, seconds: float, sample_dt: float, rtol: float = 1e-9, atol: float = 1e-13):
        """Free motion after ``tip_force`` (held from the start, at equilibrium) is released at
        t = 0: tip x, z and director angle (T, 3) every ``sample_dt`` s from 0 to ``seconds``."""
        q0 = self.static(tip_force)
        inv_mass = 1.0 / self.inertia()
        n = q0.size
        zero_force = np.zeros(2)

        def rhs(t, y):
            q, v = y[:n], y[n:]
            return np.concatenate([v, inv_mass * self.forces(q, v, zero_force)])

        eye, none = sparse.identity(n, format="csc"), sparse.csc_matrix((n, n))
        scale = sparse.diags(inv_mass)

        def jac(t, y):
            q, v = y[:n], y[n:]
            dq = self._derivative(q, v, zero_force, "q")
            dv = self._derivative(q, v, zero_force, "v")
            return sparse.bmat([[none, eye], [scale @ dq, scale @ dv]], format="csc")

        t_eval = np.arange(int(round(seconds / sample_dt)) + 1) * sample_dt
        sol = solve_ivp(
            rhs, (0.0, t_eval[-1]), np.concatenate([q0, np.zeros(n)]), method="BDF", t_eval=t_eval,
            rtol=rtol, atol=atol, jac=jac,
        )  # fmt: skip
        if not sol.success:
            raise RuntimeError(f"time integration failed: {sol.message}")
        M = self.nodes
        tip = sol.y[[M - 1, 2 * M - 1, 3 * M - 1], :].T
        return t_eval, tip, sol.nfev
