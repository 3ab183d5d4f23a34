"""Traced programs kept on disk (`pcrjax.traces`): a later process skips the trace and gets the
same numbers; anything the trace depends on names another program."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import pcrjax
from pcrjax import config, traces


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setattr(config, "_traces", tmp_path)
    return tmp_path


def _program(scale, seen):
    """A program that closes over ``scale`` and counts its traces in ``seen``; it solves a small
    system (a LAPACK call, as the Newton solves make)."""

    def f(x, n):
        seen.append(1)
        A = scale * jnp.eye(x.size) + jnp.outer(x, x)
        return jnp.linalg.solve(A, x) * n, jnp.sum(jnp.sin(x))

    return f


def test_a_second_process_loads_the_program_and_gets_the_same_numbers(folder):
    scale = np.array(2.0)
    x, n = jnp.array([0.1, 0.2, 0.3]), jnp.int32(3)
    seen = []
    first = traces.jit(_program(scale, seen), "t", (scale,))(x, n)
    assert len(seen) == 1 and len(list(folder.glob("t-*.pkl"))) == 1
    # a new process: the same program built again from nothing in memory
    again = []
    second = traces.jit(_program(scale, again), "t", (scale,))(x, n)
    assert again == []  # not traced
    plain = jax.jit(_program(scale, []))(x, n)
    for a, b, c in zip(first, second, plain, strict=True):
        assert np.array_equal(a, b) and np.array_equal(a, c)


def test_what_the_trace_depends_on_names_another_program(folder):
    x, n = jnp.array([0.1, 0.2, 0.3]), jnp.int32(3)
    seen = []
    traces.jit(_program(np.array(2.0), seen), "t", (np.array(2.0),))(x, n)
    # another closed-over value, other argument shapes, another name: each traced afresh
    out = traces.jit(_program(np.array(5.0), seen), "t", (np.array(5.0),))(x, n)
    assert len(seen) == 2
    np.testing.assert_array_equal(out[0], jax.jit(_program(5.0, []))(x, n)[0])
    traces.jit(_program(np.array(2.0), seen), "t", (np.array(2.0),))(jnp.ones(4), n)
    traces.jit(_program(np.array(2.0), seen), "u", (np.array(2.0),))(x, n)
    assert len(seen) == 4 and len(list(folder.glob("*.pkl"))) == 4


def test_an_unreadable_file_is_traced_again_and_replaced(folder):
    x, n = jnp.array([0.1, 0.2, 0.3]), jnp.int32(3)
    traces.jit(_program(np.array(2.0), []), "t", (np.array(2.0),))(x, n)
    (path,) = folder.glob("t-*.pkl")
    path.write_bytes(b"cut short")
    seen = []
    out = traces.jit(_program(np.array(2.0), seen), "t", (np.array(2.0),))(x, n)
    assert len(seen) == 1 and path.stat().st_size > 100
    np.testing.assert_array_equal(out[0], jax.jit(_program(2.0, []))(x, n)[0])


def test_a_closure_that_is_not_plain_data_is_traced_as_usual(folder):
    seen = []
    f = traces.jit(_program(np.array(2.0), seen), "t", (lambda: 0,))
    f(jnp.ones(3), jnp.int32(1))
    f(jnp.ones(3), jnp.int32(2))
    assert len(seen) == 1 and not list(folder.glob("*"))  # jax.jit's own cache, nothing on disk


def test_a_scene_is_plain_data_and_its_values_name_the_program():
    scene = pcrjax.load_scene("triskele")
    longer = pcrjax.with_solver(scene, dt=2 * float(scene.solver.dt))
    a, b = (traces.fingerprint("s", s, ()) for s in (scene, longer))
    assert a is not None and b is not None and a != b
    assert traces.fingerprint("s", scene, ()) == a


@pytest.mark.parametrize("name", ["cantilever_release", "triskele_push_release"])
def test_a_fits_programs_are_named_by_plain_data(name):
    """What a fit's programs close over (recording, unknowns, scene) can name them on disk; a
    field that is not plain data would leave every fit tracing its programs again."""
    from identify.problem import Problem
    from identify.recording import load_recording

    pb = Problem(load_recording(f"experiments_data/{name}.csv"), ("tau", "lengths"))
    assert traces.fingerprint("p", (pb.rec, pb.fit, pb.scene), ()) is not None


def test_a_program_compiled_ahead_is_kept_like_a_jitted_one(folder):
    x, n = jnp.array([0.1, 0.2, 0.3]), jnp.int32(3)
    seen = []
    first = traces.compiled(_program(np.array(2.0), seen), "c", (np.array(2.0),), (x, n))(x, n)
    again = []
    second = traces.compiled(_program(np.array(2.0), again), "c", (np.array(2.0),), (x, n))(x, n)
    assert len(seen) == 1 and again == [] and len(list(folder.glob("c-*.pkl"))) == 1
    plain = jax.jit(_program(2.0, []))(x, n)
    for a, b, c in zip(first, second, plain, strict=True):
        assert np.array_equal(a, b) and np.array_equal(a, c)


def test_a_simulations_chunk_is_kept_and_a_later_run_skips_its_trace(folder, monkeypatch):
    """`simulate` compiles its chunk of steps from the kept program once one is on disk (a later
    process: the compiled chunks forgotten), to the same trajectory as `rollout` traced afresh."""
    from pcrjax import simulation

    scene = pcrjax.load_scene("cantilever")
    scene = pcrjax.with_solver(scene, nodes=10, duration=6 * float(scene.solver.dt))
    traced = []
    scan = simulation._scan_steps
    monkeypatch.setattr(simulation, "_scan_steps", lambda *a, **k: traced.append(1) or scan(*a, **k))
    simulation.release_compiled()
    first = pcrjax.simulate(scene, chunk=4)
    assert traced and len(list(folder.glob("simulate-chunk-*.pkl"))) == 1
    traced.clear()
    simulation.release_compiled()
    second = pcrjax.simulate(scene, chunk=4)
    assert traced == []
    plain = jax.jit(pcrjax.rollout)(scene)
    for a, b, c in zip(jax.tree.leaves(first), jax.tree.leaves(second), jax.tree.leaves(plain), strict=True):
        assert np.array_equal(a, b) and np.array_equal(a, c)
