"""Parameter sweeps: variants of one scene file, run as batched programs (`jax.vmap`).

A sweep varies keys of the scene file (``rod.tau``, ``solver.dt``, ``platform.mass``,
``tip.force[2]``, ``rods[1].length``) over a grid or a Latin hypercube. Every member is built and
validated as its own scene; members whose compiled structure agrees (the same node counts,
shooting segments, step count...) run together, ``batch`` at a time, as one `jit(vmap(...))`
program (the Newton solves keep their economy under `vmap`: `pcrjax.numerics.newton.solve`).
A member that does not converge is marked (``converged`` 0, ``failed_at_s``) and never stops the
others; its outputs are what its run reached.

Outputs per member (dynamic scenes): the end's final position and rotation vector, the peak
displacement from the start, the settling time (last time the end is further than 2 % of its
largest excursion from its mean over the last tenth of the run; NaN if it has not settled), the
dominant frequency of its motion (Hann-windowed spectrum of the displacement along its principal
axis, peak refined by a parabola), mean Newton iterations per step, Jacobians evaluated, the
largest scaled residual. Static scenes: the equilibrium pose and the solve's statistics.
"""

from __future__ import annotations

import copy
import itertools
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from . import executables
from .errors import SceneError
from .io.scene_file import read_toml, scene_from_dict, scene_path
from .memory import default_budget, parse_size, program_bytes
from .numerics import results
from .robots import statics
from .simulation import _signature, rollout, static_result

_PART = re.compile(r"^([A-Za-z_]\w*)(?:\[(\d+)\])?$")
SETTLE_BAND = 0.02  # settled: within this fraction of the largest excursion
DYNAMIC_OUTPUTS = (
    "x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad", "peak_m", "settling_s", "frequency_hz",
    "newton_iterations", "jacobians", "max_residual", "converged", "failed_at_s",
)  # fmt: skip
STATIC_OUTPUTS = ("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad", "newton_iterations", "max_residual", "converged")


def _parts(key: str):
    parts = [_PART.match(p) for p in key.split(".")]
    if not key or not all(parts):
        raise SceneError(f"sweep key {key!r}: write it as table.key, table.key[i] or rods[i].key")
    return [(m.group(1), None if m.group(2) is None else int(m.group(2))) for m in parts]


def _typed(old, value: float):
    """``value`` as an integer where the file holds an integer there (``solver.nodes``)."""
    if isinstance(old, int) and not isinstance(old, bool):
        if value != int(value):
            raise SceneError(f"{value:g}: the scene holds an integer here")
        return int(value)
    return float(value)


def _set(data: dict, key: str, value: float):
    """Set ``key`` (dotted, with optional [i]) of the parsed scene ``data`` to ``value``."""
    parts = _parts(key)
    node = data
    for i, (name, idx) in enumerate(parts):
        last = i == len(parts) - 1
        if not isinstance(node, dict):
            raise SceneError(f"sweep key {key!r}: {name!r} is not inside a table")
        if last and idx is None:
            node[name] = _typed(node.get(name), value)
            return
        if name not in node:
            if idx is not None:
                raise SceneError(f"sweep key {key!r}: the scene has no {name!r} to index")
            node[name] = {}
        if idx is None:
            node = node[name]
            continue
        seq = node[name]
        if not isinstance(seq, list) or idx >= len(seq):
            raise SceneError(f"sweep key {key!r}: {name!r} has no entry {idx}")
        if last:
            seq[idx] = _typed(seq[idx], value)
            return
        node = seq[idx]


def values_from_spec(spec: str) -> np.ndarray:
    """``a:b:n`` (n values from a to b), ``a:b:n:log`` (geometric), or ``v1,v2,...``."""
    f = spec.split(":")
    try:
        if len(f) == 1:
            vals = np.array([float(v) for v in spec.split(",") if v.strip()])
        elif len(f) in (3, 4) and f[3:] in ([], ["log"]):
            a, b, n = float(f[0]), float(f[1]), int(f[2])
        else:
            raise ValueError
    except ValueError:
        raise SceneError(f"{spec!r}: not a range a:b:n[:log] or a list of numbers v1,v2,...") from None
    if len(f) > 1:
        if n < 1:
            raise SceneError(f"{spec!r}: empty range (n must be at least 1)")
        if len(f) == 4 and (a <= 0 or b <= 0):
            raise SceneError(f"{spec!r}: a log range needs positive ends")
        vals = np.geomspace(a, b, n) if len(f) == 4 else np.linspace(a, b, n)
    if vals.size == 0:
        raise SceneError(f"{spec!r}: no values")
    return vals


def latin_hypercube(ranges: dict, samples: int, seed: int = 0) -> np.ndarray:
    """(samples, keys) points, one per stratum of each key's range (log-uniform where the range
    is given as log), in a random order per key."""
    rng = np.random.default_rng(seed)
    cols = []
    for lo, hi, log in ranges.values():
        u = (rng.permutation(samples) + rng.random(samples)) / samples
        cols.append(np.exp(np.log(lo) + u * np.log(hi / lo)) if log else lo + u * (hi - lo))
    return np.stack(cols, axis=1)


def _sample_range(key: str, v):
    """(lo, hi, log) of a key sampled by the Latin hypercube: a spec ``a:b[:n][:log]`` or values
    whose smallest and largest are the range."""
    try:
        f = v.split(":") if isinstance(v, str) else np.asarray(v, float)
        if isinstance(v, str):
            lo, hi, log = float(f[0]), float(f[1]), f[-1] == "log"
        elif f.ndim == 1 and f.size >= 2:
            lo, hi, log = float(f.min()), float(f.max()), False
        else:
            raise IndexError
    except (ValueError, IndexError, TypeError):
        raise SceneError(f"{key}={v!r}: --samples needs a range a:b[:n][:log] or at least two values") from None
    if log and (lo <= 0 or hi <= 0):
        raise SceneError(f"{key}={v!r}: a log range needs positive ends")
    if not lo < hi:
        raise SceneError(f"{key}={v!r}: empty range")
    return lo, hi, log


@dataclass
class Sweep:
    """Members' varied ``values`` (M, K) under ``keys``, per-member ``outputs`` (name -> (M,)),
    and, for dynamic scenes, each member's times ``t[m]`` (T,) and end ``position[m]`` (T, 3)."""

    scene: str
    keys: list
    values: np.ndarray
    outputs: dict
    t: list | None = None
    position: list | None = None
    grid_shape: tuple | None = None  # per key, when the members are a full grid
    timings: dict = field(default_factory=dict)

    @property
    def converged(self) -> np.ndarray:
        return self.outputs["converged"].astype(bool)

    def table(self):
        """(header, rows): the member index, the varied values, then the outputs."""
        header = ["member"] + list(self.keys) + list(self.outputs)
        cols = [np.arange(len(self.values))[:, None], self.values] + [
            np.asarray(v, float)[:, None] for v in self.outputs.values()
        ]
        return header, np.concatenate(cols, axis=1)


def _members(vary: dict, samples: int | None, seed: int):
    keys = list(vary)
    if not keys:
        raise SceneError("a sweep needs at least one key to vary")
    for k in keys:
        _parts(k)
    if samples is not None:
        if samples < 1:
            raise SceneError("--samples must be at least 1")
        ranges = {k: _sample_range(k, v) for k, v in vary.items()}
        return keys, latin_hypercube(ranges, samples, seed), None
    axes = []
    for k, v in vary.items():
        try:
            axes.append(values_from_spec(v) if isinstance(v, str) else np.atleast_1d(np.asarray(v, float)))
        except SceneError as e:
            raise SceneError(f"{k}={e}") from None
        except (TypeError, ValueError):
            raise SceneError(f"{k}: values must be numbers") from None
    for k, a in zip(keys, axes, strict=True):
        if a.size == 0:
            raise SceneError(f"{k}: no values")
        if not np.all(np.isfinite(a)):
            raise SceneError(f"{k}: values must be finite numbers")
    return keys, np.array(list(itertools.product(*axes)), float).reshape(-1, len(keys)), tuple(a.size for a in axes)


def _scenes(data: dict, source: str, keys, values):
    """One validated scene per member; a value the scene cannot take names the member."""
    scenes = []
    for m, row in enumerate(values):
        d = copy.deepcopy(data)
        try:
            for k, v in zip(keys, row, strict=True):
                _set(d, k, v)
            scenes.append(scene_from_dict(d, source))
        except SceneError as e:
            raise SceneError(
                f"sweep member {m} ({', '.join(f'{k}={v:g}' for k, v in zip(keys, row, strict=True))}): {e}"
            ) from None
    for j, k in enumerate(keys):  # a key the scene ignores (e.g. damping switched off) is a mistake
        differ = [i for i in range(1, len(scenes)) if values[i, j] != values[0, j]]
        if differ and _same(scenes[0], scenes[differ[0]]):
            raise SceneError(f"sweep key {k!r} changes nothing in the scene {source} (is its effect switched on?)")
    return scenes


def _same(a, b) -> bool:
    la, ta = jax.tree.flatten(a)
    lb, tb = jax.tree.flatten(b)
    return ta == tb and all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb, strict=True))


def _run_dynamic(scene):
    tr = rollout(scene)
    return dict(
        t=tr.t, position=tr.position, rotation_vector=tr.rotation_vector[-1], iterations=tr.iterations, jacobians=tr.jacobians,
        residual=tr.residual, result=tr.result,
    )  # fmt: skip


def _run_static(scene):
    res = static_result(scene, statics.solve_static(scene))
    return dict(
        position=res.position, rotation_vector=res.rotation_vector, iterations=res.newton_iterations, residual=res.residual_norm,
        result=res.result,
    )  # fmt: skip


_PROGRAMS: dict = {}  # (structure signature, batch size) -> compiled jit(vmap(run)), per process


def _mesh():
    devices = jax.local_devices()
    return None if len(devices) == 1 else jax.sharding.Mesh(np.array(devices), ("members",))


def shard_members(tree):
    """``tree``'s leading (members) axis split across the local devices (unchanged with one); the
    members must be a multiple of the devices."""
    mesh = _mesh()
    if mesh is None:
        return tree
    return jax.device_put(tree, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("members")))


def batched(fn):
    """``jax.vmap(fn)`` over a leading members axis; with several local devices each device runs
    it on its own share of the members (`jax.shard_map`). Each device's Newton loops then stop
    when its own members have converged: a program partitioned from a global `vmap` would
    agree on every loop's stopping test across the devices at every pass."""
    mesh = _mesh()
    if mesh is None:
        return jax.vmap(fn)
    spec = jax.sharding.PartitionSpec("members")
    return jax.shard_map(jax.vmap(fn), mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)


def _program(stacked, size: int, ndev: int, dynamic: bool):
    """The compiled batched program for ``stacked`` members (compiled once per process for each
    structure and size) and the seconds spent compiling it now."""
    key = (_signature(stacked), size, ndev)
    if key in _PROGRAMS:
        return _PROGRAMS[key], 0.0
    executables.make_room()
    t0 = time.perf_counter()
    _PROGRAMS[key] = jax.jit(batched(_run_dynamic if dynamic else _run_static)).lower(stacked).compile()
    return _PROGRAMS[key], time.perf_counter() - t0


def run_members(scenes: list, size: int, budget: int | None = None) -> tuple[list, float, float, dict]:
    """Run ``scenes`` (one compiled structure, at most ``size``) as one batched program padded to
    ``size`` members: (per-member outputs as numpy dicts, compile s, run s, {size: bytes} of the
    programs run).

    With several local devices (GPUs, or CPU devices from
    ``XLA_FLAGS=--xla_force_host_platform_device_count=K``) the members axis is sharded across
    them (`jax.sharding`; the batch is padded to a multiple of their count). ``budget`` (bytes;
    None: `pcrjax.memory.default_budget`): a program that needs more
    (`pcrjax.memory.program_bytes`) runs as smaller batches instead, sized by its need per
    member; a single member over the budget raises `SceneError`.
    """
    budget = default_budget() if budget is None else budget
    ndev = len(jax.local_devices())
    size = -(-size // ndev) * ndev
    padded = scenes + [scenes[-1]] * (size - len(scenes))
    stacked = shard_members(jax.tree.map(lambda *a: jnp.stack(a), *padded))
    prog, compile_s = _program(stacked, size, ndev, scenes[0].effects.inertia)
    need = program_bytes(prog)
    if budget is not None and need > budget:  # still None where the system does not say
        if size <= ndev:
            raise SceneError(
                f"{scenes[0].name}: one batch of {size} member(s) needs {need / 1e6:.0f} MB, more than the memory budget "
                f"of {budget / 1e6:.0f} MB: allow more memory or shorten the run"
            )
        smaller = min(size - ndev, max(ndev, (size * budget // need) // ndev * ndev))
        outs, run_s, sizes = [], 0.0, {}
        for i in range(0, len(scenes), smaller):
            o, c, r, z = run_members(scenes[i : i + smaller], smaller, budget)
            outs, compile_s, run_s, sizes = outs + o, compile_s + c, run_s + r, sizes | z
        return outs, compile_s, run_s, sizes
    t0 = time.perf_counter()
    res = jax.tree.map(np.asarray, jax.block_until_ready(prog(stacked)))
    return [{k: v[j] for k, v in res.items()} for j in range(len(scenes))], compile_s, time.perf_counter() - t0, {size: need}


def batches(scenes: list, batch: int) -> list[tuple[list, int]]:
    """(member indices, program size) per batch: members of one compiled structure together,
    ``batch`` at a time (a structure's last batch is padded to its size)."""
    groups: dict = {}
    for m, s in enumerate(scenes):
        groups.setdefault(_signature(s), []).append(m)
    jobs = []
    for members in groups.values():
        size = min(int(batch), len(members))
        jobs += [(members[i : i + size], size) for i in range(0, len(members), size)]
    return jobs


def release_compiled():
    """Forget the compiled sweep programs (see `executables.make_room`)."""
    _PROGRAMS.clear()


def sweep(
    scene,
    vary: dict,
    *,
    samples: int | None = None,
    seed: int = 0,
    batch: int = 64,
    progress: bool | Callable = False,
    source: str = "<scene>",
    cluster: str | None = None,
    memory: int | str | None = None,
) -> Sweep:
    """Run variants of ``scene`` (a scene file, a shipped scene's name, or a parsed scene dict).

    ``vary``: key -> values (a sequence, or a spec string ``a:b:n``, ``a:b:n:log``,
    ``v1,v2,...``); the members are the grid of all combinations, or with ``samples`` a Latin
    hypercube of that many points over each key's range (``seed`` fixes it). ``batch``: members
    per compiled program (memory grows with it). ``progress``: True prints a line per batch to
    stderr, or a callable ``f(done_members, total_members)``. ``source``: the file a scene dict
    came from (names it in errors; relative files in it are read from its folder). ``cluster``:
    None runs the batches in this process; ``"local"`` or ``"local:W"`` on a Dask cluster of W
    worker processes on this machine (default: one per core); an address
    (``"tcp://host:8786"``) on that Dask scheduler's workers (`pcrjax.distributed`). ``memory``:
    the most one batched program may hold, in bytes or as ``"500MB"``, ``"2GiB"`` (default: half
    of the memory available when each batch runs, where it runs); a batch that needs
    more runs as smaller ones (``timings["batch_sizes"]``; ``timings["batch_bytes"]``: what each
    size's program needs).
    """
    if isinstance(scene, dict):
        data = scene
    elif isinstance(scene, str | Path):
        p = scene_path(scene)
        data, source = read_toml(p), str(p)
    else:
        raise SceneError(
            "sweep takes a scene file, a shipped scene's name or a parsed scene dict (the keys it varies are the file's)"
        )
    if int(batch) < 1:
        raise SceneError("batch must be at least 1")
    budget = None if memory is None else parse_size(memory)
    if cluster is not None:
        from . import distributed

        distributed.parse(cluster)  # a malformed --cluster is reported before any work
    keys, values, grid_shape = _members(vary, samples, seed)
    scenes = _scenes(data, source, keys, values)
    dynamic = scenes[0].effects.inertia
    jobs = batches(scenes, batch)
    timings = {
        "compile_s": 0.0,
        "run_s": 0.0,
        "programs": len({_signature(scenes[ms[0]]) for ms, _ in jobs}),
        "batch": int(batch),
        "batch_bytes": {},
    }
    outs: list = [None] * len(scenes)
    done = 0

    def collect(members, result):
        nonlocal done
        member_outs, compile_s, run_s, sizes = result
        timings["compile_s"] += compile_s
        timings["run_s"] += run_s
        timings["batch_bytes"] |= sizes
        for m, o in zip(members, member_outs, strict=True):
            outs[m] = o
        done += len(members)
        if progress is True:
            print(f"sweep: {done}/{len(scenes)} members ({compile_s + run_s:.1f} s for this batch)", file=sys.stderr)
        elif callable(progress):
            progress(done, len(scenes))

    timings["memory_budget_bytes"] = budget  # None: half the memory available where each batch runs
    if cluster is None:
        for members, size in jobs:
            collect(members, run_members([scenes[m] for m in members], size, budget))
    else:
        timings["cluster"] = distributed.run_jobs(cluster, data, source, keys, values, jobs, collect, budget)
    timings["batch_sizes"] = sorted(timings["batch_bytes"])
    name = scenes[0].name
    if not dynamic:
        return Sweep(name, keys, values, _static_outputs(outs), grid_shape=grid_shape, timings=timings)
    t = [o["t"] for o in outs]
    timings["member_steps_per_s"] = sum(len(x) - 1 for x in t) / max(timings["run_s"], 1e-12)
    return Sweep(name, keys, values, _dynamic_outputs(outs), t, [o["position"] for o in outs], grid_shape, timings)


def _static_outputs(outs) -> dict:
    p = np.stack([o["position"] for o in outs])
    rv = np.stack([o["rotation_vector"] for o in outs])
    codes = np.array([int(o["result"]) for o in outs])
    vals = [
        *p.T,
        *rv.T,
        [float(o["iterations"]) for o in outs],
        [float(o["residual"]) for o in outs],
        codes == results.SUCCESSFUL,
    ]
    return {k: np.asarray(v, float) for k, v in zip(STATIC_OUTPUTS, vals, strict=True)}


def settling_time(t, p) -> float:
    """Last time ``p`` (T, 3) lies further than `SETTLE_BAND` of its largest excursion from its
    mean over the last tenth of the run; NaN if that last tenth is not itself inside the band."""
    tail = max(2, len(t) // 10)
    rest = p[-tail:].mean(axis=0)
    dev = np.linalg.norm(p - rest, axis=1)
    band = SETTLE_BAND * dev.max()
    if dev.max() == 0:
        return 0.0
    if np.any(dev[-tail:] > band):
        return float("nan")
    out = np.flatnonzero(dev > band)
    return float(t[out[-1] + 1]) if out.size else 0.0


def dominant_frequency(t, p) -> float:
    """Frequency (Hz) of the strongest peak of the displacement along its principal axis."""
    d = p - p.mean(axis=0)
    if len(t) < 8 or not np.any(d):
        return float("nan")
    axis = np.linalg.svd(d, full_matrices=False)[2][0]
    x = d @ axis
    x = x - np.polyval(np.polyfit(t, x, 1), t)
    spec = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    k = 1 + int(np.argmax(spec[1:]))
    shift = 0.0
    if 1 <= k < len(spec) - 1:
        a, b, c = np.log(spec[k - 1 : k + 2] + 1e-300)
        shift = 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c < 0 else 0.0
    return float((k + shift) / (len(t) * (t[1] - t[0])))


def _dynamic_outputs(outs) -> dict:
    rows = []
    for o in outs:
        t, p = o["t"], o["position"]
        ok = np.all(np.isfinite(p))
        codes = o["result"]
        bad = np.flatnonzero(codes != results.SUCCESSFUL)
        rows.append(
            [*p[-1], *o["rotation_vector"], float(np.max(np.linalg.norm(p - p[0], axis=1))),
             settling_time(t, p) if ok else np.nan, dominant_frequency(t, p) if ok else np.nan,
             float(np.mean(o["iterations"])), float(np.sum(o["jacobians"])), float(np.max(o["residual"])),
             float(bad.size == 0), float(t[bad[0] + 1]) if bad.size else np.nan]
        )  # fmt: skip
    table = np.array(rows, float)
    return {k: table[:, i] for i, k in enumerate(DYNAMIC_OUTPUTS)}


def write(out: Path, sw: Sweep):
    """``sweep.csv`` (one row per member), ``summary.json`` and ``sweep.png``."""
    from .io import outputs

    out.mkdir(parents=True, exist_ok=True)
    header, rows = sw.table()
    outputs.write_columns(out / "sweep.csv", header, rows)
    failed = [int(i) for i in np.flatnonzero(~sw.converged)]
    outputs.write_json(
        out / "summary.json",
        {
            "scene": sw.scene,
            "keys": sw.keys,
            "members": len(sw.values),
            "failed_members": failed,
            "grid": sw.grid_shape,
            **sw.timings,
        },
    )
    outputs.plot_sweep(out / "sweep.png", sw)
    return failed
