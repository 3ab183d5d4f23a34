"""`pcrjax bench inverse`: the cost of direct inverse dynamics (figures, never assertions).

Cases: the thesis's Triskele circle (section 4.3.2: N 50, dt 1 ms, alpha -0.2; target real-time
factor >= 1 on one core) and a Stewart-Gough circle at Till's dt = 1/120 s, on the shipped paths.
For each: compile time, wall time per step, real-time factor, Newton iterations and Jacobians per
step, and the forward replay's path error (same step and grid: the round trip's closure), beside
the forward run's time per step on the same scene (the replay).
"""

from __future__ import annotations

import numpy as np

from ..io.scene_file import load_scene, with_solver
from ..io.tables import read_path
from ..replay import path_errors, with_actuator_table
from ..robots.signals import PosePath
from ..simulation import inverse_dynamics, simulate

CASES = {
    "triskele_circle": ("triskele", dict(dt=1e-3, alpha=-0.2), "50"),
    "stewart_gough_circle": ("stewart_gough", dict(dt=1.0 / 120.0, alpha=-0.2), "10,20,40"),
}
HEADER = f"{'path':<22}{'N':>4}{'dt s':>9}{'steps':>7}{'compile s':>11}{'us/step':>10}{'RTF':>8}{'Newton it':>11}{'Jac/step':>10}{'fwd us/step':>13}{'replay err':>12}"


def bench_inverse(nodes: str | None, duration: float) -> list[dict]:
    print(HEADER, flush=True)
    rows = []
    for name, (scene_name, settings, default_nodes) in CASES.items():
        base = load_scene(scene_name)
        t, v = read_path(name, base.effects.planar)
        path = PosePath.from_samples(t, v)
        for n in (int(x) for x in (nodes or default_nodes).split(",")):
            scene = with_solver(base, nodes=n, duration=min(duration, float(t[-1])), **settings)
            cold: dict = {}
            inverse_dynamics(scene, path, timings=cold)
            tm: dict = {}
            inv = inverse_dynamics(scene, path, timings=tm)
            replay_scene = with_actuator_table(scene, inv.t, inv.actuators)
            simulate(replay_scene)
            fw: dict = {}
            fwd = simulate(replay_scene, timings=fw)
            err = path_errors(path, fwd)
            per = tm["run_s"] / tm["steps"]
            row = dict(
                path=name, nodes=n, dt=float(scene.solver.dt), steps=tm["steps"], compile_s=cold["compile_s"],
                us_per_step=per * 1e6, realtime_factor=float(scene.solver.dt) / per,
                newton_iterations=float(np.mean(inv.iterations)), jacobians_per_step=float(np.mean(inv.jacobians)),
                forward_us_per_step=fw["run_s"] / fw["steps"] * 1e6, replay_relative_error=err["relative_error"],
            )  # fmt: skip
            rows.append(row)
            print(
                f"{name:<22}{n:>4}{row['dt']:>9.3g}{row['steps']:>7}{row['compile_s']:>11.1f}{row['us_per_step']:>10.0f}"
                f"{row['realtime_factor']:>8.2f}{row['newton_iterations']:>11.2f}{row['jacobians_per_step']:>10.2f}"
                f"{row['forward_us_per_step']:>13.0f}{row['replay_relative_error']:>12.2e}",
                flush=True,
            )
    print("replay err: forward replay of the solved actuators at the same dt and N, largest position error / motion amplitude.")
    return rows
