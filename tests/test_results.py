"""Failures as data with a reason, stale compiled structure, and no global JAX setting on import."""

import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import rod_scene

import pcrjax
from pcrjax.numerics import results


def test_non_convergence_is_reported_with_its_reason():
    scene = rod_scene(force=(0, 0, -1e-3), nodes=6, duration=0.02, max_iter=1)  # statics converge, steps do not
    with pytest.raises(pcrjax.ConvergenceError) as e:
        pcrjax.simulate(scene)
    assert e.value.reason == results.MAX_ITERATIONS and "maximum number of iterations" in str(e.value)
    assert e.value.partial is not None and e.value.time > 0
    tr = pcrjax.rollout(scene)  # the pure function returns the codes instead
    assert np.any(np.asarray(tr.result) == results.MAX_ITERATIONS) and not bool(np.all(tr.converged))


def test_a_leaf_change_that_outgrows_the_structure_is_detected():
    scene = rod_scene(force=(0, 0, -1.0), nodes=6, dt=5e-3, duration=0.01)
    assert scene.solver.segments == 2 and scene.solver.refine == 1  # the least the automatic split gives (`auto_segments`)
    # dt 1e-6 needs several shooting segments and a finer grid than the scene was built with.
    small = eqx.tree_at(lambda s: s.solver.dt, scene, jnp.asarray(1e-6))
    with pytest.raises(pcrjax.SceneError, match="with_solver"):
        pcrjax.simulate(small)
    codes = jax.jit(lambda s: s.structure_result())(small)  # detected under jit too
    assert int(codes) == results.STALE_STRUCTURE
    rebuilt = pcrjax.with_solver(small)
    assert rebuilt.solver.segments > 2 and rebuilt.solver.refine > 1 and int(rebuilt.structure_result()) == results.SUCCESSFUL
    # A small change (a length 1 % longer) keeps the structure valid.
    longer = eqx.tree_at(lambda s: s.legs.rod.length, scene, scene.legs.rod.length * 1.01)
    assert int(longer.structure_result()) == results.SUCCESSFUL


def test_import_changes_no_jax_setting_and_scenes_need_float64():
    code = (
        "import jax; import pcrjax; x64 = jax.config.jax_enable_x64; cache = jax.config.jax_compilation_cache_dir\n"
        "try:\n    pcrjax.load_scene('cantilever'); print('built')\nexcept pcrjax.SceneError as e:\n    print('refused:', e)\n"
        "print(x64, cache)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env={"PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert "refused: pcrjax needs float64" in out.stdout and out.stdout.strip().endswith("False None")
