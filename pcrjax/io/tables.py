"""CSV time series (actuator values, loads): strict reading with one clear message per defect."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np


class TableError(ValueError):
    """A CSV time series that cannot be used; the message names the file and the cause."""


def read_table(path, columns: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Read a CSV time series with exactly the header ``columns`` (first one ``t_s``).

    Returns ``(t (K,), values (K, len(columns) - 1))``. Raises `TableError` for a missing file,
    a wrong header, empty cells (gaps), non-numeric or non-finite values, fewer than two rows,
    or times that do not strictly increase.
    """
    p = Path(path)
    if not p.is_file():
        raise TableError(f"{p}: no such file")
    try:
        with p.open(newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except UnicodeDecodeError:
        raise TableError(f"{p}: not a text file") from None
    if not rows:
        raise TableError(f"{p}: empty file")
    header = [c.strip() for c in rows[0]]
    if tuple(header) != tuple(columns):
        raise TableError(f"{p}: header must be {','.join(columns)} ({len(columns) - 1} value columns), got {','.join(header)}")
    data = []
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != len(columns):
            raise TableError(f"{p}: line {i}: expected {len(columns)} columns, got {len(r)}")
        vals = []
        for name, c in zip(columns, r):
            c = c.strip()
            if c == "":
                raise TableError(f"{p}: line {i}: column {name} is empty (gap in the series)")
            try:
                v = float(c)
            except ValueError:
                raise TableError(f"{p}: line {i}: column {name}: not a number: {c!r}") from None
            if not math.isfinite(v):
                raise TableError(f"{p}: line {i}: column {name}: not finite: {c}")
            vals.append(v)
        data.append(vals)
    if len(data) < 2:
        raise TableError(f"{p}: needs at least two rows of data, got {len(data)}")
    a = np.asarray(data)
    t = a[:, 0]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0])
        raise TableError(f"{p}: times must strictly increase: line {i + 3} has t = {t[i + 1]} after t = {t[i]}")
    return t, a[:, 1:]


SPATIAL_PATH = ("t_s", "x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad")
PLANAR_PATH = ("t_s", "x_m", "y_m", "theta_rad")


def path_file(name) -> Path:
    """A path file: ``name`` itself if it exists, else the shipped path of that name
    (``pcrjax/paths/NAME.csv``: ``triskele_circle``, ``triskele_move``, ``stewart_gough_circle``)."""
    from importlib import resources

    p = Path(name)
    if p.is_file():
        return p
    shipped = Path(str(resources.files("pcrjax") / "paths" / f"{Path(name).stem}.csv"))
    return shipped if p.suffix in ("", ".csv") and shipped.is_file() else p


def read_path(path, planar: bool) -> tuple[np.ndarray, np.ndarray]:
    """Read a platform path (a file, or a shipped path's name: `path_file`): ``t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad`` (rotation vector), or on a
    planar bearing also ``t_s,x_m,y_m,theta_rad``. Returns ``(t (K,), values (K, 6 | 3))``,
    planar values as [x, y, theta]. A planar robot's spatial path must keep its rotation about z."""
    p = path_file(path)
    head = ""
    if p.is_file():
        try:
            with p.open(newline="") as fh:
                head = next((line for line in fh if line.strip()), "")
        except UnicodeDecodeError:
            raise TableError(f"{p}: not a text file") from None
    planar_header = tuple(c.strip() for c in head.strip().split(",")) == PLANAR_PATH
    if planar_header and not planar:
        raise TableError(f"{p}: a planar path (t_s,x_m,y_m,theta_rad) needs a planar robot; give {','.join(SPATIAL_PATH)}")
    t, v = read_table(p, PLANAR_PATH if planar_header else SPATIAL_PATH)
    if planar and not planar_header:
        tilt = np.abs(v[:, 3:5]).max()
        if tilt > 1e-9:
            raise TableError(f"{p}: the robot is planar but the path tilts it (|rx|, |ry| up to {tilt:.3g} rad)")
        v = v[:, [0, 1, 5]]
    return t, v
