"""Several recordings fitted in one command: one after another here, or one task each on a
Dask cluster (`pcrjax.distributed`: a local cluster of worker processes on this machine, or a
scheduler's address).

Each recording is fitted exactly as alone (the same `cli.run`, the same settings) into its own
folder ``DIR/<recording name>/`` (fit.json, plots, its printout in ``fit.log``, its resume
state), so a worker runs the same programs on the same inputs and its results equal this
process's. Every recording is read before any fit starts: a bad one stops the command with one
line naming it, and nothing runs. A fit that fails is marked in the summary and never stops the
others. ``DIR/fits.csv`` holds a row per recording (status, reduced chi-square, wall time, each
fitted value with its statistical and discretisation errors) and ``DIR/fits.json`` the same
with each fit's message.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import time
from pathlib import Path

import numpy as np


def _fit_one(options: dict) -> dict:
    """Fit one recording with the CLI's ``options`` (its argparse namespace as a dict), its
    printout to ``fit.log`` in its folder; returns its summary row (never raises for a fit
    that fails or a recording the model cannot fit)."""
    import pcrjax

    from . import cli
    from .fit import FitError
    from .recording import RecordingError

    pcrjax.config.configure()  # float64 and the compilation cache, in a worker's process too
    out = Path(options["out"])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    row = {"recording": options["recording"], "out": str(out)}
    with open(out / "fit.log", "w") as log, contextlib.redirect_stdout(log):
        try:
            payload = cli.run(argparse.Namespace(**options))
        except (FitError, RecordingError, pcrjax.SceneError, ValueError) as e:
            return {**row, "status": "failed", "message": str(e), "wall_s": time.perf_counter() - t0}
    return {
        **row,
        "status": "converged" if payload["converged"] else "not converged",
        "message": payload.get("message", ""),
        "wall_s": time.perf_counter() - t0,
        "reduced_chi2": payload["loss"],
        "values": payload["values"],
        "standard_errors": payload["standard_errors"],
        "discretisation_errors": payload.get("discretisation_errors", {}),
    }


def folders(paths) -> list[str]:
    """Each recording's folder name (its file name without .csv); the names must differ."""
    names = [Path(p).stem for p in paths]
    seen = {}
    for p, n in zip(paths, names, strict=True):
        if n in seen:
            from .recording import RecordingError

            raise RecordingError(f"{seen[n]} and {p} would share the output folder {n}/: rename one")
        seen[n] = p
    return names


def _columns(rows) -> list[str]:
    """A column per fitted number: ``name`` where every row's value is a scalar, else
    ``name[i]`` up to the longest (a cantilever's one length sits in ``lengths[0]`` beside a
    Triskele's three)."""
    sizes: dict[str, int] = {}
    for r in rows:
        for k, v in r.get("values", {}).items():
            sizes[k] = max(sizes.get(k, 0), int(np.size(v)))
    return [k if n == 1 else f"{k}[{i}]" for k, n in sizes.items() for i in range(n)]


def _entry(d: dict, label: str):
    """The cell of ``label`` in one row's ``d`` (values or errors); blank where that row has
    no such number."""
    name, _, index = label.partition("[")
    if name not in d:
        return ""
    v = np.atleast_1d(d[name])
    i = int(index[:-1]) if index else 0
    return repr(float(v[i])) if i < v.size else ""


def write_summary(out: Path, rows: list[dict]):
    """``fits.csv`` (a row per recording, in the order given) and ``fits.json``."""
    labels = _columns(rows)
    with open(out / "fits.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            ["recording", "status", "reduced_chi2", "wall_s"] + [c for lb in labels for c in (lb, f"{lb}_se", f"{lb}_disc")]
        )
        for r in rows:
            cells = [r["recording"], r["status"], repr(r.get("reduced_chi2", float("nan"))), f"{r['wall_s']:.1f}"]
            for lb in labels:
                cells += [_entry(r.get(k, {}), lb) for k in ("values", "standard_errors", "discretisation_errors")]
            w.writerow(cells)
    (out / "fits.json").write_text(json.dumps(rows, indent=2))


def fit_all(options: dict, recordings: list[str], cluster: str | None = None, say=print) -> list[dict]:
    """Fit each of ``recordings`` with the CLI's ``options`` into ``options["out"]/<name>/``,
    here or on ``cluster``; writes the summary and returns its rows (in the order given)."""
    from pcrjax import distributed

    from .recording import load_recording

    for p in recordings:  # every recording read (and refused) before any fit starts
        load_recording(p)
    if cluster is not None:
        distributed.parse(cluster)
    out = Path(options["out"])
    tasks = [
        (i, ({**options, "recording": str(p), "out": str(out / name)},))
        for i, (p, name) in enumerate(zip(recordings, folders(recordings), strict=True))
    ]
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[int, dict] = {}

    def collect(i, row):
        rows[i] = row
        say(f"[{len(rows)}/{len(tasks)}] {row['recording']}: {row['status']} ({row['wall_s']:.0f} s) -> {row['out']}/")

    if cluster is None:
        for i, args in tasks:
            collect(i, _fit_one(*args))
    else:
        ran = distributed.map_tasks(cluster, _fit_one, tasks, collect)
        say(f"ran on {ran['workers']} Dask worker(s) ({ran['kind']}) in {ran['wall_s']:.0f} s")
    ordered = [rows[i] for i in range(len(tasks))]
    write_summary(out, ordered)
    return ordered
