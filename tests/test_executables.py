"""Compiled code against the kernel's cap on memory mappings (`pcrjax.executables`)."""

import numpy as np
import pytest
from helpers import rod_scene, shared_rod

import pcrjax
from pcrjax import executables, simulation

pytestmark = pytest.mark.skipif(executables.map_count() is None, reason="no /proc/self/maps on this system")


def test_compiled_code_holds_memory_mappings_and_release_returns_them():
    scene = shared_rod(duration=0.02)
    pcrjax.release_compiled()
    before = executables.map_count()
    pcrjax.simulate(scene)
    held = executables.map_count() - before
    # One kernel is three mappings: a compiled rollout holds hundreds (what makes the cap reachable).
    assert held > 150
    pcrjax.release_compiled()
    assert executables.map_count() - before < held / 3


def test_make_room_releases_before_a_new_structure_near_the_cap(monkeypatch):
    a, b = shared_rod(duration=0.02), rod_scene(nodes=7, dt=5e-3, duration=0.02)
    first = pcrjax.simulate(a)
    # A cap the process is already past: the next new structure must release the old ones first.
    monkeypatch.setattr(executables, "map_limit", lambda: 100)
    with pytest.warns(RuntimeWarning, match="memory mappings"):
        pcrjax.simulate(b)
    assert len(simulation._COMPILED) == 1
    monkeypatch.undo()
    again = pcrjax.simulate(a)  # compiled again after the release: the same numbers
    np.testing.assert_array_equal(np.asarray(first.position), np.asarray(again.position))
