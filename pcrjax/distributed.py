"""Work on a Dask cluster: each batch of a sweep's members, or each recording of a set of
identification fits, is one task on a worker process.

Dask distributed rather than Ray: it is pure Python (nothing to build, one wheel on every
platform), its `LocalCluster` starts worker processes on this machine with no setup, and a real
cluster is a scheduler address away (``dask scheduler`` on one machine, ``dask worker ADDRESS``
on each of the others, or dask-jobqueue on a batch system; every worker needs pcrjax
installed). A task carries the scene file's parsed dict and its members' rows, never compiled
code or JAX arrays: the worker builds the scenes, compiles the batch's program once per process
(or loads it from the persistent compilation cache, which workers on one machine share) and
sends back numpy arrays. A member runs the same program on the same inputs as in-process, so the
results are equal to the in-process sweep's (same batch size, same kind of machine).
"""

from __future__ import annotations

import logging
import os
import time

from .errors import SceneError


def parse(cluster: str) -> tuple[str, object]:
    """``"local"`` -> ("local", None: one worker per core); ``"local:W"`` -> ("local", W); a
    scheduler address (``tcp://host:8786``, ``host:8786``) -> ("address", it)."""
    c = str(cluster).strip()
    if c == "local":
        return "local", None
    if c.startswith("local:"):
        w = c.split(":", 1)[1]
        if not w.isdigit() or int(w) < 1:
            raise SceneError(f"--cluster {cluster!r}: 'local:W' needs a worker count W >= 1")
        return "local", int(w)
    if "://" in c or (":" in c and c.rsplit(":", 1)[1].isdigit()):
        return "address", c
    raise SceneError(f"--cluster {cluster!r}: 'local', 'local:W' or a Dask scheduler address such as tcp://host:8786")


def _task(data, source, keys, rows, size, budget):
    """On a worker: build the members' scenes and run them as one batched program (as smaller
    ones if it needs more than ``budget`` bytes; None: half of the worker's available memory)."""
    from .config import configure

    configure()  # float64 and the compilation cache, in the worker's process
    from .sweeps import _scenes, run_members

    return run_members(_scenes(data, source, keys, rows), size, budget)


def map_tasks(cluster: str, fn, tasks, collect) -> dict:
    """Run ``fn(*args)`` for each ``(key, args)`` of ``tasks`` as one task on the Dask cluster
    (``parse``); ``collect(key, result)`` as each finishes (any order). ``fn`` must be importable
    by the workers and its arguments and result picklable. Returns how it ran: kind, workers,
    wall seconds."""
    kind, arg = parse(cluster)
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise SceneError("--cluster needs Dask distributed: pip install 'pcrjax[distributed]'") from None
    t0 = time.perf_counter()
    local = None
    try:
        if kind == "local":
            workers = arg or os.cpu_count() or 1
            local = LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=logging.ERROR
            )
            client = Client(local)
        else:
            client = Client(arg, timeout="20s")
    except OSError as e:  # refused, unreachable, timed out
        if local is not None:
            local.close()
        raise SceneError(f"--cluster {cluster!r}: cannot start or reach the Dask cluster: {e}") from None
    try:
        workers = len(client.scheduler_info()["workers"])
        futures = {client.submit(fn, *args, pure=False): key for key, args in tasks}
        for fut in as_completed(futures):
            collect(futures[fut], fut.result())
    finally:
        client.close()
        if local is not None:
            local.close()
    return {"kind": kind, "address": arg if kind == "address" else None, "workers": workers, "wall_s": time.perf_counter() - t0}


def run_jobs(cluster: str, data: dict, source: str, keys, values, jobs, collect, budget: int | None = None) -> dict:
    """A sweep's jobs (members, batch size), each as one task (`map_tasks`);
    ``collect(members, result)`` as each finishes."""
    tasks = [(tuple(members), (data, source, keys, values[members], size, budget)) for members, size in jobs]
    return map_tasks(cluster, _task, tasks, lambda key, result: collect(list(key), result))
