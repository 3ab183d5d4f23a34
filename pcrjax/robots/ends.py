r"""End conditions: what the legs' tips meet. The assembly (`assembly.py`) asks an end for

* its pose unknowns (``pose_size``: 0 for a free tip, 6 for a platform, 3 on a planar bearing)
  and the pose they give (`pose`);
* the algebraic residual rows (`rows`): the end's balance (``pose_size`` rows), then 6 rows per
  leg tip;
* the data of one solve (`static_config`, `step_config`), its static start and continuation
  plan, and what a dynamic step hands to the next (`advance`).

**Free tip** (the cantilever, thesis 4.1): no pose unknowns; each tip's internal wrench equals the
applied load, $n(L) = F$, $m(L) = M$. The static solve starts from the straight rod's exact
global balance and falls back on load continuation.

**Rigid platform** (thesis eq. 4.7-4.13, 4.18-4.22): pose unknowns (`physics.platform.pose`);
rows are the platform's force and moment balance with its inertia (planar: $F_x, F_y, M_z$),
then per leg the tip position $p_e + R_e r_i - p_i(L_i)$ and orientation
$\mathrm{vee}((R_e R_{c,i})^T R_i(L_i))$ against its clamp. Newton from straight legs diverges
(its first step asks for ~1e5 N of axial compression and buckles a rod), so the static solve is
a homotopy in $s \in [0, 1]$: at $s = 0$ each attachment point and clamp rotation sit where the
straight, unloaded leg ends when the platform is at its reference pose, and loads and weights
are off, so the root is known exactly (reference pose, zero wrenches). Attachments, clamp
rotations (along the geodesic), loads and weights then move linearly to their true values in
``solver.continuation`` stages, each a Newton solve from the last.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..physics import platform as rigid
from ..physics.rotations import cross, exp_map, matmul, matvec, rotation_vector, skew_vee, transpose_matmul
from .signals import Load


class AbstractEnd(eqx.Module):
    """What the legs' tips meet. ``cfg`` is the end's data for one solve (`static_config`,
    `step_config`); ``body_pose`` what `pose` made of the pose unknowns ``xp``; ``tips`` (n, 18)
    the legs' tip states [p, R, n, m]."""

    load: eqx.AbstractVar[Load]

    @abc.abstractmethod
    def pose_size(self, effects) -> int:
        """Number of pose unknowns (0, 3 or 6)."""

    @abc.abstractmethod
    def rows(self, cfg, tips, sc, effects, inertia, body_pose):
        """(balance rows (pose_size,), tip rows (n, 6)), scaled."""

    @abc.abstractmethod
    def static_plan(self, solver) -> tuple[int, int]:
        """(continuation stages that lead to the static solve, continuation stages as its fallback)."""

    @abc.abstractmethod
    def advance(self, cfg, memory, body_pose, tips, co):
        """(the end's memory for the next step, the end's energy)."""

    @abc.abstractmethod
    def weight(self, effects, gravity):
        """The end's own weight (3,) N (zeros without gravity or mass)."""

    @abc.abstractmethod
    def static_config(self, legs, a, F, M, weight, lam):
        """The end's data for a static solve at homotopy parameter ``lam`` (1: the true problem)."""

    @abc.abstractmethod
    def static_guess(self, legs, a, F, M, rod_weight, sc):
        """The static solve's start (scaled unknowns), or None for zeros."""

    @abc.abstractmethod
    def rest_memory(self, position, rotation, co):
        """The end's BDF-alpha memory at rest in the static pose (None if it has none)."""

    @abc.abstractmethod
    def step_config(self, memory, F, M, weight, co):
        """The end's data for one time step."""

    @abc.abstractmethod
    def pose(self, cfg, xp, sc, planar):
        """``body_pose`` from the pose unknowns (None without them)."""

    @abc.abstractmethod
    def output_pose(self, body_pose, tips):
        """(position (3,), rotation (3, 3)) reported for the end."""

    @abc.abstractmethod
    def rest_energy(self, cfg, memory, tips):
        """The end's energy at rest: potential of its weight or load."""

    @abc.abstractmethod
    def pose_unknowns(self, p, R, p_ref, R_ref, planar, sc):
        """Scaled pose unknowns of (p, R) relative to (p_ref, R_ref)."""

    @abc.abstractmethod
    def previous_pose_unknowns(self, cfg, p, R, planar, sc):
        """The last step's pose as unknowns relative to this step's pose (p, R)."""

    @abc.abstractmethod
    def describe(self) -> dict:
        """What the end is, for summary.json."""


class TipConfig(eqx.Module):
    F: jnp.ndarray
    M: jnp.ndarray


class FreeTip(AbstractEnd):
    """A free rod tip under ``load`` (force, moment: global frame)."""

    load: Load
    plots = ("tip", "tip_path.png", "rod_shapes.png")  # what the end is called, its plots' files

    def describe(self) -> dict:
        return {"kind": "free tip"}

    def pose_size(self, effects) -> int:
        return 0

    def weight(self, effects, gravity):
        return jnp.zeros(3, gravity.dtype)

    def static_config(self, legs, a, F, M, weight, lam):
        return TipConfig(F=lam * F, M=lam * M)

    def static_plan(self, solver) -> tuple[int, int]:
        return 0, solver.continuation

    def static_guess(self, legs, a, F, M, rod_weight, sc):
        """The straight rods' exact global balance: $n_0 = F + w$, $m_0 = M + L d \\times F + (L/2) d \\times w$."""
        d = legs.base_rotation[:, :, 2]
        L = legs.lengths(a)

        def one(d_i, L_i, w_i):
            w = w_i * L_i
            return jnp.concatenate([(F + w) / sc.force, (M + cross(L_i * d_i, F) + cross(0.5 * L_i * d_i, w)) / sc.moment])

        return jax.vmap(one)(d, L, rod_weight).reshape(-1)

    def rest_memory(self, position, rotation, co):
        return None

    def step_config(self, memory, F, M, weight, co):
        return TipConfig(F=F, M=M)

    def pose(self, cfg, xp, sc, planar):
        return None

    def rows(self, cfg, tips, sc, effects, inertia, body_pose):
        cons = jnp.concatenate([(tips[:, 12:15] - cfg.F) / sc.force, (tips[:, 15:18] - cfg.M) / sc.moment], axis=1)
        return jnp.zeros((0,), tips.dtype), cons

    def output_pose(self, body_pose, tips):
        return tips[0, 0:3], tips[0, 3:12].reshape(3, 3)

    def advance(self, cfg, memory, body_pose, tips, co):
        """(next memory, energy of the end): the load's potential $-F \\cdot p$ of each tip."""
        return None, self.rest_energy(cfg, memory, tips)

    def rest_energy(self, cfg, memory, tips):
        return -jnp.sum(tips[:, 0:3] @ cfg.F)

    def pose_unknowns(self, p, R, p_ref, R_ref, planar, sc):
        return jnp.zeros((0,), p.dtype)

    def previous_pose_unknowns(self, cfg, p, R, planar, sc):
        return jnp.zeros((0,), p.dtype)


class PlatformConfig(eqx.Module):
    """Everything the platform's rows need in one solve besides the unknowns."""

    attachment: jnp.ndarray
    clamp: jnp.ndarray
    F: jnp.ndarray
    M: jnp.ndarray
    weight: jnp.ndarray
    p_prev: jnp.ndarray
    R_prev: jnp.ndarray
    motion: rigid.PlatformMotion | None
    co: object | None  # bdf_alpha.Coefficients in dynamics


class RigidPlatform(AbstractEnd):
    """A rigid platform: ``body`` (mass, inertia), where the legs attach (``attachment`` (n, 3)
    and ``clamp`` (n, 3, 3): each rod's tip frame, both in the platform frame), the reference
    pose that starts the static search, and the ``load`` on its centre."""

    body: rigid.Platform
    attachment: jnp.ndarray
    clamp: jnp.ndarray
    reference_position: jnp.ndarray  # (3,); planar: z of the bearing
    reference_rotation: jnp.ndarray  # (3, 3)
    load: Load
    plots = ("platform", "platform_path.png", "legs.png")

    def describe(self) -> dict:
        return {
            "kind": "rigid platform",
            "mass_kg": float(self.body.mass),
            "inertia_kg_m2": [float(v) for v in self.body.inertia],
        }

    def pose_size(self, effects) -> int:
        return 3 if effects.planar else 6

    def weight(self, effects, gravity):
        if effects.gravity:
            return self.body.mass * gravity
        return jnp.zeros(3, gravity.dtype)

    def straight_assembly(self, legs, a):
        """Attachments and clamp rotations (platform frame) at which straight unloaded legs meet
        the platform at its reference pose: the homotopy's start."""
        R_ref, p_ref = self.reference_rotation, self.reference_position
        tips = legs.base_positions(a) + legs.lengths(a)[:, None] * legs.base_rotation[:, :, 2]
        attach0 = jax.vmap(lambda q: matvec(R_ref.T, q - p_ref))(tips)
        clamp0 = jax.vmap(lambda Rb: transpose_matmul(R_ref, Rb))(legs.base_rotation)
        return attach0, clamp0

    def static_config(self, legs, a, F, M, weight, lam):
        attach0, clamp0 = self.straight_assembly(legs, a)
        clamp_log = jax.vmap(lambda C0, C: rotation_vector(transpose_matmul(C0, C)))(clamp0, self.clamp)
        return PlatformConfig(
            attachment=(1.0 - lam) * attach0 + lam * self.attachment,
            clamp=jax.vmap(lambda C0, w: matmul(C0, exp_map(lam * w)))(clamp0, clamp_log),
            F=lam * F,
            M=lam * M,
            weight=lam * weight,
            p_prev=self.reference_position,
            R_prev=self.reference_rotation,
            motion=None,
            co=None,
        )

    def static_plan(self, solver) -> tuple[int, int]:
        return max(1, solver.continuation), 0

    def static_guess(self, legs, a, F, M, rod_weight, sc):
        return None  # the homotopy's root at s = 0: reference pose, zero wrenches

    def rest_memory(self, position, rotation, co):
        return rigid.PlatformMotion.rest(co, position, rotation)

    def step_config(self, memory, F, M, weight, co):
        return PlatformConfig(
            attachment=self.attachment,
            clamp=self.clamp,
            F=F,
            M=M,
            weight=weight,
            p_prev=memory.p1,
            R_prev=memory.R1,
            motion=memory,
            co=co,
        )

    def pose(self, cfg, xp, sc, planar):
        """(p, R, dp, theta) from the pose unknowns."""
        return rigid.pose(xp, planar, cfg.p_prev, cfg.R_prev, sc.length)

    def rows(self, cfg, tips, sc, effects, inertia, body_pose):
        p, R, dp, theta = body_pose
        r = rigid.rates(cfg.co, cfg.motion, dp, theta) if inertia else None
        force, moment = rigid.balance(self.body, R, cfg.attachment, tips[:, 12:15], tips[:, 15:18], cfg.F, cfg.M, cfg.weight, r)
        bal = jnp.concatenate([force / sc.force, moment / sc.moment])
        if effects.planar:
            bal = bal[np.array([0, 1, 5])]

        def constraint(tip, r_i, Rc):
            target = matmul(R, Rc)
            return jnp.concatenate(
                [(p + matvec(R, r_i) - tip[0:3]) / sc.length, skew_vee(transpose_matmul(target, tip[3:12].reshape(3, 3)))]
            )

        return bal, jax.vmap(constraint)(tips, cfg.attachment, cfg.clamp)

    def output_pose(self, body_pose, tips):
        return body_pose[0], body_pose[1]

    def advance(self, cfg, memory, body_pose, tips, co):
        """(next memory for the next step's scheme ``co``, energy of the platform: kinetic minus
        the weight's work); the rates are this step's (its scheme ``cfg.co``)."""
        p, R, dp, theta = body_pose
        r = rigid.rates(cfg.co, memory, dp, theta)
        return rigid.advance(co, memory, p, R, dp, r), rigid.kinetic_energy(self.body, r) - jnp.dot(cfg.weight, p)

    def rest_energy(self, cfg, memory, tips):
        return -jnp.dot(cfg.weight, memory.p1)

    def pose_unknowns(self, p, R, p_ref, R_ref, planar, sc):
        """Scaled pose unknowns of (p, R) relative to (p_ref, R_ref)."""
        return rigid.pose_unknowns(p, R, p_ref, R_ref, planar, sc.length)

    def previous_pose_unknowns(self, cfg, p, R, planar, sc):
        """The last step's pose as unknowns relative to this step's pose (p, R)."""
        return rigid.pose_unknowns(cfg.p_prev, cfg.R_prev, p, R, planar, sc.length)
