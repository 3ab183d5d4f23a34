"""Static equilibrium of any robot: the end's continuation plan around one Newton solve.

The final solve at full load is the one differentiated (implicit function theorem); the
continuation stages before it only provide its start.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..numerics import newton
from . import assembly

# A continuation planned first (a platform's) that ends unconverged is tried again with this many
# times its stages: a stage's Newton can wander off the path (round-off decides; the same solve
# can converge outside `jit` and fail inside), and shorter stages follow it. A solve that stops
# where it loses its path (`NewtonSettings.stop_when_lost`: a screen of many candidates) is not
# retried: a batch iterates until its last member finishes, so one member's retry would cost them all.
STATIC_RETRY = 2


class StaticSolution(eqx.Module):
    position: jnp.ndarray  # end: platform centre or first tip
    rotation: jnp.ndarray
    nodes: jnp.ndarray  # (n, N+1, 18)
    unknowns: jnp.ndarray
    stats: newton.Stats
    actuators: jnp.ndarray  # (n_act,) actuator values
    stages: jnp.ndarray  # (n, N, stages, 18) the legs' states at their integrator's stage points


def solve_static(scene, t=0.0, near=None) -> StaticSolution:
    """Static equilibrium under the actuator values and loads at time ``t``. ``near``: the
    unknowns of a neighbouring equilibrium (another solve's `StaticSolution.unknowns`, of the
    same structure) that Newton starts from; the end's continuation then runs only if that fails."""
    s = scene.solver
    legs, end = scene.legs, scene.end
    n = legs.count
    t = jnp.asarray(t, jnp.float64)
    a = scene.actuator_values(t)
    F, M = end.load(t)
    weight = end.weight(scene.effects, scene.gravity)
    hist = assembly.zero_histories(scene)

    def problem(lam):
        cfg = end.static_config(legs, a, F, M, weight, lam)
        return assembly.Problem(
            scene, False, a, jnp.zeros_like(a), lam * scene.gravity, hist, jnp.zeros((n, 0, 3, 3)), jnp.zeros(()), cfg
        )

    prob1 = problem(jnp.asarray(1.0))
    pre, fallback_stages = end.static_plan(s)
    rod_weight = prob1.k.gravity if prob1.k.gravity is not None else jnp.zeros((n, 3))
    guess = end.static_guess(legs, a, F, M, rod_weight, prob1.sc)
    x0 = jax.lax.stop_gradient(jnp.zeros(prob1.size) if guess is None else guess)
    homotopy = (lambda x, lam: problem(lam).residual(x, True), lambda x, lam: problem(lam).jacobian(x))
    if near is not None:
        stages = newton.with_continuation(jax.lax.stop_gradient(jnp.asarray(near, x0.dtype)), max(pre, fallback_stages, 1))
    elif pre:
        stages = newton.continuation_first(x0, pre, retry=0 if s.newton.stop_when_lost else STATIC_RETRY * pre)
    elif fallback_stages:
        stages = newton.with_continuation(x0, fallback_stages)
    else:
        stages, homotopy = newton.plain(x0), None
    x, _, stats, legs_at_root = newton.solve(
        lambda x: prob1.residual(x, True),
        prob1.jacobian,
        newton.Jacobian.empty(prob1.size),
        s.newton,
        stages,
        homotopy,
        has_aux=True,
    )
    xp, xl = prob1.split(x)
    _, tips, nodes, leg_stages = prob1.recorded_legs(xl, legs_at_root)
    p, R = end.output_pose(prob1.pose(xp), tips)
    return StaticSolution(position=p, rotation=R, nodes=nodes, unknowns=x, stats=stats, actuators=a, stages=leg_stages)
