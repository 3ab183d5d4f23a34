r"""Inverse problems: the end's pose is prescribed and the actuator values are unknowns.

Direct inverse dynamics solves the same equations as forward dynamics (same rods, BDF-alpha,
platform inertia and loads) with the roles of the unknowns swapped: the platform pose of each
step is given (`signals.PosePath`) and each leg's actuator value $a_i$ takes its place. The
counts match when the robot has as many actuators as pose unknowns (6 for the Stewart-Gough
platform, 3 for the planar Triskele-bot). The actuator rate the legs' bases move with comes from
BDF-alpha on the actuator values, $\dot a = c_0 a + a^h$, as in forward dynamics, so replaying
the solved actuator values forward at the same step and grid reproduces the path to solver
tolerance.

**Jacobian.** Leg $i$ depends on its own unknowns and on $a_i$ only, so the leg blocks of the
forward Jacobian gain one column each, the derivative of the leg's [junctions, tip state] with
respect to its actuator; all n of these come from one forward-mode JVP along $(1, \dots, 1)$.
The pose columns drop out. Actuator unknowns are scaled by the rod length and taken relative
to a reference value (the last step's, or the forward static solve's), which keeps their
round-off at the level of the motion.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..errors import SceneError
from ..numerics import newton, results
from ..physics.rotations import exp_map, matmul, rotation_vector, transpose_matmul
from . import assembly
from .statics import STATIC_RETRY, StaticSolution, solve_static


def check_square(scene):
    """Raise `SceneError` unless the robot has as many actuators as pose unknowns."""
    P = scene.end.pose_size(scene.effects)
    n = scene.actuator_values(jnp.zeros(())).shape[0]
    if not scene.legs.actuated or P == 0:
        raise SceneError(
            f"{scene.name}: inverse dynamics needs a platform moved by actuated legs; robot '{scene.robot}' has none"
        )
    if P != n:
        raise SceneError(
            f"{scene.name}: inverse dynamics needs as many actuators as platform pose unknowns ({n} actuators, {P} pose unknowns)"
        )


class InverseProblem:
    """Residual and Jacobian of one shooting problem whose end pose (p, R) is prescribed.

    Unknowns, per leg: its scaled leg unknowns (`assembly.Problem`), then its scaled actuator
    value $(a_i - a^{ref}_i)/L$. ``ah``: the actuator history ($\\dot a = c_0 a + a^h$; None in
    statics). The other arguments are those of `assembly.Problem`.
    """

    def __init__(self, scene, inertia: bool, a_ref, ah, gravity, history, leg_R_ref, c0, cfg, p, R):
        self.scene, self.inertia, self.a_ref, self.ah = scene, inertia, a_ref, ah
        self.gravity, self.history, self.leg_R_ref, self.c0, self.cfg = gravity, history, leg_R_ref, c0, cfg
        self.sc = assembly.scales(scene, inertia)
        base = self.problem(jnp.zeros_like(a_ref))
        self.n, self.S = base.n, base.S
        self.xp = scene.end.pose_unknowns(p, R, cfg.p_prev, cfg.R_prev, scene.effects.planar, base.sc)

    def actuators(self, xa):
        return self.a_ref + self.sc.length * xa

    def problem(self, xa) -> assembly.Problem:
        a = self.actuators(xa)
        adot = self.c0 * a + self.ah if self.inertia else jnp.zeros_like(a)
        return assembly.Problem(self.scene, self.inertia, a, adot, self.gravity, self.history, self.leg_R_ref, self.c0, self.cfg)

    @property
    def size(self) -> int:
        return self.n * (self.S + 1)

    def split(self, x):
        """(actuator unknowns (n,), leg unknowns (n, S))."""
        X = x.reshape(self.n, self.S + 1)
        return X[:, self.S], X[:, : self.S]

    def join(self, xa, xl):
        return join(xa, xl)

    def residual(self, x, record=False):
        """As `assembly.Problem.residual`, of the problem at the actuator unknowns in ``x``."""
        xa, xl = self.split(x)
        return self.problem(xa).residual(jnp.concatenate([self.xp, xl.reshape(-1)]), record)

    def jacobian(self, x):
        xa, xl = self.split(x)
        prob = self.problem(xa)
        tips, Jl = prob.leg_jacobians(xl)
        legs = lambda z: self.problem(z).legs(xl, all_nodes=False)[:2]  # noqa: E731
        _, (junc_a, tips_a) = jax.jvp(legs, (xa,), (jnp.ones_like(xa),))  # leg i depends on a_i only
        Ja = jnp.concatenate([junc_a, tips_a], axis=1)[:, :, None]
        return prob.assemble(self.xp, tips, jnp.concatenate([Jl, Ja], axis=2), pose_columns=False)


def join(xa, xl):
    """The inverse unknown vector from actuator unknowns ``xa`` (n,) and leg unknowns ``xl`` (n, S)."""
    return jnp.concatenate([xl, xa[:, None]], axis=1).reshape(-1)


def _geodesic(p0, R0, p1, R1, s):
    """The pose a fraction ``s`` of the way from (p0, R0) to (p1, R1) (straight line, geodesic)."""
    return p0 + s * (p1 - p0), matmul(R0, exp_map(s * rotation_vector(transpose_matmul(R0, R1))))


def solve_static_inverse(scene, p, R, stages: int | None = None, t=0.0) -> StaticSolution:
    """Actuator values and legs that hold the end at pose (p, R) in static equilibrium under the
    loads at time ``t``. Starts from the forward static solution at the scene's actuator values and
    moves the prescribed pose from there to (p, R) in ``stages`` continuation steps (default
    ``solver.continuation``), each a Newton solve from the last."""
    check_square(scene)
    s = scene.solver
    legs, end = scene.legs, scene.end
    n = legs.count
    t = jnp.asarray(t, jnp.float64)
    fwd = solve_static(scene, t)
    a0 = fwd.actuators
    F, M = end.load(t)
    cfg = end.static_config(legs, a0, F, M, end.weight(scene.effects, scene.gravity), jnp.asarray(1.0))
    hist = assembly.zero_histories(scene)

    def problem(lam):
        pl, Rl = _geodesic(fwd.position, fwd.rotation, p, R, lam)
        return InverseProblem(scene, False, a0, None, scene.gravity, hist, jnp.zeros((n, 0, 3, 3)), jnp.zeros(()), cfg, pl, Rl)

    prob1 = problem(jnp.asarray(1.0))
    _, xl0 = prob1.problem(jnp.zeros(n)).split(fwd.unknowns)
    x0 = jax.lax.stop_gradient(prob1.join(jnp.zeros(n), xl0))
    k = max(1, s.continuation if stages is None else stages)
    homotopy = (lambda x, lam: problem(lam).residual(x, True), lambda x, lam: problem(lam).jacobian(x))
    x, _, stats, legs_at_root = newton.solve(
        lambda x: prob1.residual(x, True),
        prob1.jacobian,
        newton.Jacobian.empty(prob1.size),
        s.newton,
        newton.continuation_first(x0, k, retry=STATIC_RETRY * k),
        homotopy,
        has_aux=True,
    )
    stats = newton.Stats(
        iterations=stats.iterations + fwd.stats.iterations,
        residual=stats.residual,
        jacobians=stats.jacobians + fwd.stats.jacobians,
        evaluations=stats.evaluations + fwd.stats.evaluations,
        result=results.worst(fwd.stats.result, stats.result),
    )
    xa, xl = prob1.split(x)
    _, _, nodes, stages = prob1.problem(xa).recorded_legs(xl, legs_at_root)
    return StaticSolution(
        position=p, rotation=R, nodes=nodes, unknowns=x, stats=stats, actuators=prob1.actuators(xa), stages=stages
    )
