"""The small recordings the end-to-end tests fit, made once and committed to ``experiments_data/tests/``:
``python experiments_data/test_recordings.py [NAME ...]``.

Each is a synthetic recording of `generate.py` (its sidecar holds every generating number and the
seed) whose truth is simulated on a grid finer than the fit's, so that a test fits data its model
did not make on its own grid. `specs` holds the specifications (as the tests once simulated them
before each fit); the tests read the truths from the sidecars. Rerun this script when the model
or the generator changes what a recording holds.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import jax

HERE = Path(__file__).resolve().parent
FOLDER = HERE / "tests"


def _generator():
    spec = importlib.util.spec_from_file_location("generate", HERE / "generate.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    return gen


def _small_release(gen, seconds, truth_solver, start_tau_factor=3.0, **truth):
    """The cantilever release at the fit's grid N 6, dt 2 ms, its truth on ``truth_solver``, fitted
    from tau ``start_tau_factor`` times the truth's (None: the shipped sidecar's)."""
    spec = dict(gen.RECORDINGS["cantilever_release"], seconds=seconds)
    spec["solver"] = dict(spec["solver"], nodes=6, dt=2e-3)
    spec["truth_solver"] = dict(spec["solver"], **truth_solver)
    spec["truth"] = dict(spec["truth"], **truth)
    if start_tau_factor is not None:
        spec["rod"] = dict(tau=start_tau_factor * spec["truth"]["tau"])
    return spec


def specs() -> dict:
    """Name -> generator specification of every test recording."""
    import numpy as np

    from pcrjax.io.scene_file import read_toml, scene_path

    gen = _generator()
    out = {
        # 0.2 s at 1 kHz, truth 3x finer in space and 40x in time
        "small_release": _small_release(gen, 0.2, dict(nodes=18, dt=5e-5)),
        # 0.1 s, two other damping times, truth 3x finer in space and 5x in time
        "small_a": _small_release(gen, 0.1, dict(nodes=18, dt=4e-4), None, tau=1.5e-3),
        "small_b": _small_release(gen, 0.1, dict(nodes=18, dt=4e-4), None, tau=3e-3),
    }
    # E drawn within 10 % of the scene's (the length known), truth 3x finer in space, 5x in time
    nominal_E = float(read_toml(scene_path("cantilever"))["rod"]["youngs_modulus"])
    E = nominal_E * np.random.default_rng(29).uniform(0.9, 1.1)
    out["small_release_E"] = _small_release(gen, 0.2, dict(nodes=18, dt=4e-4), lengths=0.4, youngs_modulus=E)
    # the Triskele push-release of the random suite's generator at a seed no fit was developed on,
    # 0.4 s, truth 3x finer in space and extrapolated to dt 0 from 2.5x and 5x finer in time
    push = dict(gen.random_suite(seed=7)["triskele_push_release_r1"], seconds=0.4)
    push["truth_solver"] = dict(push["solver"], nodes=30, dt=1e-4)
    out["short_push_release"] = push
    for name, spec in out.items():
        spec["description"] = f"Test recording {name} (experiments_data/test_recordings.py): {spec['description']}"
    return out


def make(name: str, folder: Path = FOLDER) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return _generator().generate(name, specs()[name], folder)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("names", nargs="*", help="recordings to make (default: all)")
    p.add_argument("--out", default=str(FOLDER), help="output folder (default: experiments_data/tests/)")
    args = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    for name in args.names or list(specs()):
        make(name, Path(args.out))


if __name__ == "__main__":
    main()
