"""`pcrjax bench CASE --gradient`: the cost of a gradient through a rollout.

For the case's first scene (RK4, ``--gradient-nodes`` nodes, ``--gradient-steps`` steps): compile
and run time of the jitted rollout (a scalar of it: the end's final z) and of its gradient with
respect to every rod's length and Young's modulus (implicit differentiation through every Newton
solve), as `jax.grad` gets it (`rollout` takes few inputs' derivatives by forward columns) and
in reverse mode (``forward_columns=0``), each against the rollout. Runs are timed after
compilation, best of ``repeats`` rounds that run the three in turn.
"""

from __future__ import annotations

import time

import equinox as eqx
import jax

from ..io.scene_file import with_solver
from ..simulation import FORWARD_COLUMNS, rollout


def _compiled(fn, *args):
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - t0


def _best_interleaved(programs, args, repeats: int):
    """Best wall time of each compiled program over ``repeats`` rounds that run each once in
    turn, so that a machine whose speed drifts during the benchmark moves them alike."""
    best = [float("inf")] * len(programs)
    for _ in range(repeats):
        for k, p in enumerate(programs):
            t = time.perf_counter()
            jax.block_until_ready(p(*args))
            best[k] = min(best[k], time.perf_counter() - t)
    return best


def gradient_cost(scene, nodes: int, steps: int, repeats: int = 5) -> dict:
    s = with_solver(scene, nodes=nodes, integrator="rk4", duration=steps * float(scene.solver.dt))
    params = (s.legs.rod.length, s.legs.rod.youngs_modulus)

    def final_z(p, forward_columns=None):
        sc = eqx.tree_at(lambda q: (q.legs.rod.length, q.legs.rod.youngs_modulus), s, p)
        return rollout(sc, forward_columns=forward_columns).position[-1, 2]

    fwd, fwd_c = _compiled(final_z, params)
    grad, grad_c = _compiled(jax.grad(final_z), params)
    rev, rev_c = _compiled(jax.grad(lambda p: final_z(p, 0)), params)
    fwd_s, grad_s, rev_s = _best_interleaved((fwd, grad, rev), (params,), repeats)
    return dict(
        case=s.name,
        nodes=nodes,
        steps=steps,
        forward_compile_s=fwd_c,
        forward_s=fwd_s,
        gradient_compile_s=grad_c,
        gradient_s=grad_s,
        ratio=grad_s / fwd_s,
        reverse_compile_s=rev_c,
        reverse_s=rev_s,
        reverse_ratio=rev_s / fwd_s,
        scalars=int(sum(a.size for a in params)),
    )


def print_gradient_cost(row: dict):
    print(
        f"\nGradient (lengths and E of every rod) of the end's final z, RK4 N = {row['nodes']}, {row['steps']} steps ({row['case']}):\n"
        f"  forward rollout: compile {row['forward_compile_s']:.1f} s, run {row['forward_s'] * 1e3:.1f} ms\n"
        f"  jax.grad:        compile {row['gradient_compile_s']:.1f} s, run {row['gradient_s'] * 1e3:.1f} ms"
        f" = {row['ratio']:.2f} forward runs ({row['scalars']} scalars: "
        f"{'forward columns' if row['scalars'] <= FORWARD_COLUMNS else 'reverse mode'}, `rollout`'s choice)\n"
        f"  reverse mode:    compile {row['reverse_compile_s']:.1f} s, run {row['reverse_s'] * 1e3:.1f} ms"
        f" = {row['reverse_ratio']:.2f} forward runs (forward_columns=0)",
        flush=True,
    )
