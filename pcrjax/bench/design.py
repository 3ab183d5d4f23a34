"""`pcrjax bench design`: what trajectory design costs (figures, never assertions).

* The Triskele point-to-point move of the design tests (5 um in 10 ms, 20 ms settling window,
  undamped, 4 corrections per actuator): Levenberg-Marquardt (forward-mode Jacobian) against
  Adam (the gradient: reverse mode for its 12 coefficients): iterations, wall and compile
  time to reach 1e-4 of the plain move's sum of squares, and the residual vibration on the finer
  independent grid.
* The gradient of a scalar of the rollout against one forward rollout (cost ratio), as `jax.grad`
  gets it (forward columns for one scalar, `numerics.few_inputs`) and in reverse mode.
* Memory and time of that gradient against the horizon: forward columns, and reverse mode with
  and without checkpointed chunks of about sqrt(steps) steps (temporary memory as XLA:CPU plans
  it for the compiled program).
"""

from __future__ import annotations

import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import design
from ..io.scene_file import load_scene, with_solver
from ..simulation import rollout


def _triskele(nodes, dt):
    sc = with_solver(load_scene("triskele"), nodes=nodes, dt=dt)
    zero = jnp.zeros(3)
    return eqx.tree_at(lambda s: (s.load.force, s.load.moment), sc, (zero, zero))


def _optimisers(dt: float, iterations: int) -> list[dict]:
    sc = _triskele(10, dt)
    move, scene = design.plan_move(sc, [5e-6, 0.0, 0.0], [0.0, 0.0, 0.0], 0.01, 0.02, count=4)
    rows = []
    for method, its in (("lm", iterations), ("adam", 10 * iterations)):
        res = design.design_move(scene, move, method=method, iterations=its, log=lambda *_: None)
        obj = res["objective"]
        goal = 1e-4 * obj[0]
        reached = next((k for k, v in enumerate(obj) if v <= goal), None)
        plain = design.settling(design.verify(scene, move, jnp.zeros_like(res["coefficients"])), move)
        fine = design.settling(design.verify(scene, move, res["coefficients"]), move)
        row = dict(
            method=method, iterations=len(obj) - 1, reached_1e4_at=reached, final_ratio=obj[-1] / obj[0],
            compile_s=res["compile_s"], optimise_s=res["optimise_s"],
            plain_vibration_m=plain["residual_vibration_m"], designed_vibration_m=fine["residual_vibration_m"],
        )  # fmt: skip
        rows.append(row)
        print(
            f"{method:<6}{row['iterations']:>6}{str(reached):>10}{row['final_ratio']:>12.2e}{row['compile_s']:>11.1f}"
            f"{row['optimise_s']:>12.1f}{row['plain_vibration_m']:>13.3e}{row['designed_vibration_m']:>13.3e}",
            flush=True,
        )
    return rows


def _objective(scene, checkpoint, forward_columns=None):
    def f(mass):
        tr = rollout(eqx.tree_at(lambda s: s.end.body.mass, scene, mass), checkpoint=checkpoint, forward_columns=forward_columns)
        return jnp.sum((tr.position[:, :2] - tr.position[0, :2]) ** 2) * 1e12

    return f


def _horizons(horizons, nodes: int, dt: float) -> list[dict]:
    rows = []
    for steps in horizons:
        scene = with_solver(load_scene("triskele"), nodes=nodes, dt=dt, duration=steps * dt)
        m = scene.end.body.mass
        fwd = jax.jit(lambda mass: _objective(scene, None)(mass))
        fwd(m).block_until_ready()
        t0 = time.perf_counter()
        fwd(m).block_until_ready()
        t_fwd = time.perf_counter() - t0
        # the default (one scalar: forward columns), then reverse mode, plain and checkpointed
        for mode, ck, cols in (
            ("forward", None, None),
            ("reverse", None, 0),
            ("reverse", max(1, int(round(math.sqrt(steps)))), 0),
        ):
            t0 = time.perf_counter()
            comp = jax.jit(jax.grad(_objective(scene, ck, cols))).lower(m).compile()
            t_c = time.perf_counter() - t0
            comp(m).block_until_ready()
            t0 = time.perf_counter()
            comp(m).block_until_ready()
            t_g = time.perf_counter() - t0
            mem = comp.memory_analysis().temp_size_in_bytes / 1e6
            row = dict(
                steps=steps, mode=mode, checkpoint=ck, compile_s=t_c, gradient_s=t_g, forward_s=t_fwd, ratio=t_g / t_fwd, temp_MB=mem
            )  # fmt: skip
            rows.append(row)
            print(
                f"{steps:>7}{mode:>9}{str(ck):>12}{t_c:>11.1f}{t_fwd:>11.3f}{t_g:>12.3f}{row['ratio']:>9.2f}{mem:>11.1f}",
                flush=True,
            )
    return rows


def bench_design(dt: float = 5e-5, iterations: int = 6, horizons=(100, 1000, 10000), nodes: int = 5) -> dict:
    print(f"Design of a 5 um, 10 ms Triskele move (N 10, dt {dt:.3g} s): LM (forward-mode Jacobian) vs Adam (gradient)")
    print(
        f"{'method':<6}{'iters':>6}{'to 1e-4':>10}{'final/plain':>12}{'compile s':>11}{'optimise s':>12}{'plain vib m':>13}{'designed m':>13}"
    )
    out = {"optimisers": _optimisers(dt, iterations)}
    print("'designed m': largest residual vibration of the designed move rerun at 2N nodes and dt/2.")
    print(f"\nGradient of a rollout scalar (platform mass) vs the forward rollout (Triskele N {nodes}, dt 5e-4 s)")
    print("forward: jax.grad as rollout gives it for one scalar (forward columns); reverse: forward_columns=0")
    print(
        f"{'steps':>7}{'mode':>9}{'checkpoint':>12}{'compile s':>11}{'forward s':>11}{'gradient s':>12}{'ratio':>9}{'temp MB':>11}"
    )
    out["horizons"] = _horizons(horizons, nodes, 5e-4)
    return out
