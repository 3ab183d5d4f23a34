"""`pcrjax bench batch`: throughput of batched rollouts (`jax.vmap`) against a loop of single runs.

Till's cantilever case (`cases`) with Kelvin-Voigt damping, its members differing in tau
(0.2-2 ms). The loop runs the members one after another through one compiled single-run
program; the batch runs them through one `jit(vmap(rollout))` program. Figures: compile time,
member-steps per second, the batch's throughput over the loop's, and the largest difference of
the end's positions from the loop's (relative to the largest displacement).

First, the ceiling: the legs' integration alone (the bulk of every residual, which a step
evaluates 7-10 times), timed single and batched. A batch gains by running each kernel over many
members, but where the single run's kernels are already busy with arithmetic (as they are with
16 kernels per RK4 node step) the gain is what the wider arithmetic allows, and no batched
rollout gains more than its integration does.
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..io.scene_file import scene_from_dict, with_solver
from ..simulation import rollout
from ..sweeps import batched, shard_members
from .cases import _cantilever_dicts
from .kernels import legs_integration, unknowns_shape


def _scene(nodes: int, steps: int):
    d = _cantilever_dicts()["till"]
    d["effects"]["damping"] = True
    d["rod"]["tau"] = 1e-3
    d["solver"]["duration"] = steps * d["solver"]["dt"]
    return with_solver(scene_from_dict(d, "<bench batch>"), nodes=nodes, integrator="rk4")


def _tau(scene):
    return scene.legs.rod.damping.tau


def _taus(n: int):
    """The members' tau (n, 1): 0.2-2 ms."""
    return jnp.linspace(2e-4, 2e-3, n)[:, None]


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def integration_gain(scene, sizes, calls: int = 400) -> list[tuple[int, float]]:
    """(batch size, microseconds per member) of the legs' integration of ``scene`` with members
    that differ in tau, for size 1 (unbatched) and each of ``sizes``; ``calls`` members per figure."""
    x = jnp.full(unknowns_shape(scene), 1e-3)
    one = lambda t: legs_integration(eqx.tree_at(_tau, scene, t), x)  # noqa: E731
    rows = []
    for size in (1, *sizes):
        program = jax.jit(jax.vmap(one) if size > 1 else one)
        t = _taus(size) if size > 1 else _tau(scene)
        jax.block_until_ready(program(t))
        reps = max(calls // size, 10)
        t0 = time.perf_counter()
        for _ in range(reps):
            out = program(t)
        jax.block_until_ready(out)
        rows.append((size, (time.perf_counter() - t0) / (reps * size) * 1e6))
    return rows


def bench_batch(sizes, nodes: int = 20, steps: int = 200, loop_members: int = 16) -> list[dict]:
    """Rows per batch size; the loop's throughput is measured over ``loop_members`` single runs."""
    scene = _scene(nodes, steps)

    def run(t):
        tr = rollout(eqx.tree_at(_tau, scene, t))
        return tr.position, tr.iterations

    single = jax.jit(run)
    t0 = time.perf_counter()
    single = single.lower(_taus(1)[0]).compile()
    single_compile = time.perf_counter() - t0
    loop_members = max(loop_members, 1)
    loop = [_timed(single, t) for t in _taus(loop_members)]
    loop_rate = loop_members * steps / sum(dt for _, dt in loop)
    print(
        f"Till's cantilever, RK4 N {nodes}, {steps} steps, tau 0.2-2 ms. Loop of single runs: compile {single_compile:.1f} s, "
        f"{loop_rate:.0f} member-steps/s ({1e3 / loop_rate:.3f} ms per member-step, {loop_members} runs)"
    )
    per_member = dict(integration_gain(scene, [b for b in sizes if b > 1]))
    print(
        "The legs' integration alone (the bulk of a residual), microseconds per member: "
        + ", ".join(
            f"batch {b} {us:.2f} ({per_member[1] / us:.2f}x)" if b > 1 else f"single {us:.2f}" for b, us in per_member.items()
        )
        + ": no batched rollout gains more here"
    )
    print(f"{'batch':>6}{'compile s':>11}{'run s':>9}{'member-steps/s':>16}{'vs loop':>9}{'max diff':>11}{'Newton it/step':>16}")
    rows = []
    devices = len(jax.local_devices())
    if devices > 1:
        print(f"each batch split across {devices} local devices (jax.sharding); the loop runs on one")
    for size in sizes:
        ts = _taus(size)
        if size % devices == 0:
            ts = shard_members(ts)
        t0 = time.perf_counter()
        program = jax.jit(batched(run) if size % devices == 0 else jax.vmap(run)).lower(ts).compile()
        compile_s = time.perf_counter() - t0
        (pos, its), run_s = _timed(program, ts)
        ref = [single(t)[0] for t in _taus(size)[: min(size, 8)]]
        scale = max(float(np.max(np.abs(np.asarray(r) - np.asarray(r)[0]))) for r in ref)
        diff = max(float(np.max(np.abs(np.asarray(pos[i]) - np.asarray(r)))) for i, r in enumerate(ref)) / scale
        rate = size * steps / run_s
        row = dict(
            batch=size, devices=devices if size % devices == 0 else 1, compile_s=compile_s, run_s=run_s, member_steps_per_s=rate, vs_loop=rate / loop_rate, max_rel_diff=diff,
            newton_iterations=float(np.mean(its)), single_compile_s=single_compile, loop_member_steps_per_s=loop_rate,
            integration_gain=per_member[1] / per_member[size],
        )  # fmt: skip
        print(
            f"{size:>6}{compile_s:>11.1f}{run_s:>9.2f}{rate:>16.0f}{rate / loop_rate:>9.2f}{diff:>11.1e}{row['newton_iterations']:>16.2f}"
        )
        rows.append(row)
    return rows
