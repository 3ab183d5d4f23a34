"""Recordings of a robot's motion (DESIGN §4): a CSV of decoded camera frames plus a TOML sidecar.

CSV: header ``t_s,x_m,y_m,theta_rad``, one row per decoded frame (frames the camera failed to
decode are simply absent), times strictly increasing, every value finite. For a Triskele-bot
the columns are the platform pose seen by the encoded-pattern camera; for a cantilever, the tip
marker's position in the bending plane (x along the rod, y across) and its in-plane angle.

Sidecar ``NAME.toml`` next to ``NAME.csv`` (optional for real logs: then ``--scene`` says which
scene the recording belongs to)::

    scene = "triskele"            # shipped scene name, or a path relative to the sidecar
    experiment = "push_release"   # "push_release" | "actuator_step" | "release" (cantilever)
    frame_rate = 114.44           # frames/s (informative: the frame times are the CSV's)
    exposure = 2e-4               # s; each frame averages the motion over its exposure
    synthetic = false             # true for generated recordings, with a [truth] table
    description = "..."
    [units]                       # the CSV's units (default s, m, rad); the header names them:
    time = "s"                    #   "s" | "ms"
    position = "mm"               #   "m" | "mm" | "um" | "nm"   -> header t_s,x_mm,y_mm,theta_deg
    angle = "deg"                 #   "rad" | "mrad" | "urad" | "deg"
    [solver] [effects] [rod] [actuation] [load] [tip]   # laid over the scene's tables
    [truth]                       # synthetic only: the generating parameters and seed

Everything is validated on load: a bad file raises `RecordingError` naming the file and cause.
A `Recording` holds SI values (s, m, rad) whatever the file's units.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from pcrjax.io.scene_file import read_toml
from pcrjax.io.tables import TableError, read_table

EXPERIMENTS = ("push_release", "actuator_step", "release")
OVERRIDES = ("solver", "effects", "rod", "actuation", "load", "tip")
SIDECAR_KEYS = {
    "scene", "experiment", "frame_rate", "exposure", "synthetic", "description", "units", "truth", "provenance", *OVERRIDES
}  # fmt: skip
# the [units] a CSV may be written in: name -> SI factor
UNITS = {
    "time": {"s": 1.0, "ms": 1e-3},
    "position": {"m": 1.0, "mm": 1e-3, "um": 1e-6, "nm": 1e-9},
    "angle": {"rad": 1.0, "mrad": 1e-3, "urad": 1e-6, "deg": math.pi / 180.0},
}
SI_UNITS = {"time": "s", "position": "m", "angle": "rad"}


def columns(units: dict) -> tuple[str, ...]:
    """The CSV header for ``units`` (quantity -> unit name; missing: SI)."""
    u = {**SI_UNITS, **units}
    return (f"t_{u['time']}", f"x_{u['position']}", f"y_{u['position']}", f"theta_{u['angle']}")


COLUMNS = columns(SI_UNITS)  # t_s, x_m, y_m, theta_rad


class RecordingError(ValueError):
    """A recording that cannot be used; the message names the file and the cause."""


@dataclasses.dataclass(frozen=True)
class Recording:
    """Decoded frames ``t`` (K,) s and ``pose`` (K, 3) = x, y (m), theta (rad), plus the sidecar."""

    path: Path
    t: np.ndarray
    pose: np.ndarray
    scene: str | None = None
    experiment: str | None = None
    frame_rate: float | None = None
    exposure: float = 0.0
    synthetic: bool = False
    description: str = ""
    overrides: dict = dataclasses.field(default_factory=dict)
    truth: dict = dataclasses.field(default_factory=dict)
    provenance: dict = dataclasses.field(default_factory=dict)

    @property
    def frames(self) -> int:
        return self.t.shape[0]

    def missing_fraction(self) -> float:
        """Fraction of frames absent, judged from the frame rate (0 if unknown)."""
        if not self.frame_rate or self.frames < 2:
            return 0.0
        expected = round((self.t[-1] - self.t[0]) * self.frame_rate) + 1
        return max(0.0, 1.0 - self.frames / expected)

    def window(self, t_end: float) -> Recording:
        """The frames up to ``t_end`` (s): a shorter recording."""
        keep = self.t <= t_end
        return dataclasses.replace(self, t=self.t[keep], pose=self.pose[keep])


def sidecar_path(csv_path) -> Path:
    return Path(csv_path).with_suffix(".toml")


def _number(p, key, v, positive=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise RecordingError(f"{p}: {key} must be a {'positive ' if positive else ''}finite number, got {v!r}")
    return float(v)


def read_sidecar(path) -> dict:
    """Parse and validate a sidecar TOML (see module doc)."""
    p = Path(path)
    data = read_toml(p, RecordingError)
    unknown = sorted(set(data) - SIDECAR_KEYS)
    if unknown:
        raise RecordingError(f"{p}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(SIDECAR_KEYS))})")
    out: dict = {}
    if "scene" in data:
        if not isinstance(data["scene"], str) or not data["scene"]:
            raise RecordingError(f"{p}: scene must be a scene name or path, got {data['scene']!r}")
        out["scene"] = data["scene"]
    if "experiment" in data:
        if data["experiment"] not in EXPERIMENTS:
            raise RecordingError(f"{p}: experiment must be one of {', '.join(EXPERIMENTS)}, got {data['experiment']!r}")
        out["experiment"] = data["experiment"]
    if "frame_rate" in data:
        out["frame_rate"] = _number(p, "frame_rate", data["frame_rate"], positive=True)
    if "exposure" in data:
        out["exposure"] = _number(p, "exposure", data["exposure"])
        if out["exposure"] < 0:
            raise RecordingError(f"{p}: exposure must be >= 0 s, got {data['exposure']!r}")
    if "synthetic" in data:
        if not isinstance(data["synthetic"], bool):
            raise RecordingError(f"{p}: synthetic must be true or false, got {data['synthetic']!r}")
        out["synthetic"] = data["synthetic"]
    for key in ("description",):
        if key in data:
            out[key] = str(data[key])
    out["units"] = _units(p, data.get("units", {}))
    for key in OVERRIDES + ("truth", "provenance"):
        if key in data and not isinstance(data[key], dict):
            raise RecordingError(f"{p}: [{key}] must be a table")
    out["overrides"] = {k: data[k] for k in OVERRIDES if k in data}
    out["truth"] = data.get("truth", {})
    out["provenance"] = data.get("provenance", {})
    if out.get("synthetic") and not out["truth"]:
        raise RecordingError(f"{p}: a synthetic recording must state its generating parameters in [truth]")
    return out


def _units(p, table) -> dict:
    if not isinstance(table, dict):
        raise RecordingError(f"{p}: [units] must be a table")
    for key, name in table.items():
        if key not in UNITS:
            raise RecordingError(f"{p}: [units]: unknown key {key!r} (allowed: {', '.join(UNITS)})")
        if name not in UNITS[key]:
            raise RecordingError(f"{p}: [units] {key} must be one of {', '.join(UNITS[key])}, got {name!r}")
    return dict(table)


def load_recording(path, require_sidecar: bool = False) -> Recording:
    """Read ``path`` (CSV) and its sidecar, if any, into SI units; raise `RecordingError` on
    anything unusable."""
    p = Path(path)
    side = sidecar_path(p)
    meta = read_sidecar(side) if side.is_file() else {}
    if require_sidecar and not meta:
        raise RecordingError(f"{p}: no sidecar {side.name} (it names the scene and the experiment)")
    units = {**SI_UNITS, **meta.pop("units", {})}
    try:
        t, pose = read_table(p, columns(units))
    except TableError as e:
        hint = "" if units == SI_UNITS else f" (the sidecar's [units]: {', '.join(f'{k} {v}' for k, v in units.items())})"
        raise RecordingError(f"{e}{hint}") from None
    scale = np.array([UNITS["position"][units["position"]]] * 2 + [UNITS["angle"][units["angle"]]])
    return Recording(path=p, t=t * UNITS["time"][units["time"]], pose=pose * scale, **meta)


def write_frames(path, t, pose) -> None:
    """Write the frames' CSV ``path`` (SI columns, full float precision)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    rows = [",".join(COLUMNS)] + [
        f"{ti!r},{x!r},{y!r},{th!r}" for ti, (x, y, th) in zip(np.asarray(t, float).tolist(), np.asarray(pose, float).tolist())
    ]
    p.write_text("\n".join(rows) + "\n")


def write_recording(path, t, pose, sidecar: dict) -> None:
    """Write ``path`` (CSV, full float precision) and its sidecar TOML."""
    write_frames(path, t, pose)
    sidecar_path(path).write_text(dumps_toml(sidecar))


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in list(v)) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dumps_toml(data: dict) -> str:
    """A minimal TOML writer for sidecars: scalars and arrays first, then one level of tables."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"
