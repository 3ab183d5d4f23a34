"""Sweeps: batched members equal single runs, failures are marked, outputs match closed forms,
and bad input gets one line with exit 2."""

import copy
import csv
import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from helpers import rod_data
from test_cli import GOOD, _write

import pcrjax
from pcrjax.cli import main
from pcrjax.sweeps import dominant_frequency, latin_hypercube, settling_time, sweep


def test_members_equal_single_runs_and_failures_are_marked():
    """Six members in batches of four (the last padded): the converged ones equal their own
    single rollouts to 1e-12, and the members whose load the solve cannot carry (50 N on a 1 mm
    rod) are marked without harming the others."""
    data = rod_data(nodes=5, duration=0.02, tol=1e-13, effects={"damping": True}, rod_extra={"tau": 1e-4})
    forces, taus = [-0.5, -2.0, -50.0], [1e-4, 3e-4]
    sw = sweep(data, {"tip.force[2]": forces, "rod.tau": taus}, batch=4)
    assert sw.values.shape == (6, 2) and sw.grid_shape == (3, 2)
    single = jax.jit(pcrjax.rollout)
    for m, (force, tau) in enumerate(sw.values):
        d = copy.deepcopy(data)
        d["tip"]["force"][2], d["rod"]["tau"] = force, tau
        tr = single(pcrjax.scene_from_dict(d))
        ok = bool(np.all(np.asarray(tr.converged)))
        assert bool(sw.converged[m]) == ok == (force != -50.0)
        if ok:
            p = np.asarray(tr.position)
            assert np.max(np.abs(sw.position[m] - p)) <= 1e-12 * np.max(np.abs(p))
            assert sw.outputs["z_m"][m] == pytest.approx(p[-1, 2], rel=1e-12)
            assert sw.outputs["peak_m"][m] == pytest.approx(np.max(np.linalg.norm(p - p[0], axis=1)), rel=1e-12)
        else:
            assert sw.outputs["failed_at_s"][m] > 0


def test_frequency_and_settling_time_against_closed_forms():
    t = np.arange(2000) * 1e-3
    p = np.zeros((t.size, 3))
    p[:, 1] = 0.01 * np.sin(2 * np.pi * 7.3 * t)
    assert dominant_frequency(t, p) == pytest.approx(7.3, rel=5e-3)
    # An exponential decay e^(-t/T) stays within 2 % of its start after T ln 50.
    p[:, 1] = 0.01 * np.exp(-t / 0.1)
    assert settling_time(t, p) == pytest.approx(0.1 * np.log(50), abs=1.5e-3)
    p[:, 1] = 0.01 * np.sin(2 * np.pi * 7.3 * t)  # never settles
    assert np.isnan(settling_time(t, p))


def test_latin_hypercube_fills_every_stratum():
    pts = latin_hypercube({"a": (1.0, 2.0, False), "b": (1e-4, 1e-2, True)}, 16, seed=3)
    assert pts.shape == (16, 2)
    for col, to_unit in ((pts[:, 0], lambda v: v - 1.0), (pts[:, 1], lambda v: np.log(v / 1e-4) / np.log(100.0))):
        assert sorted(np.floor(to_unit(col) * 16).astype(int)) == list(range(16))


def test_cli_sweep_of_a_static_scene(tmp_path):
    scene = _write(tmp_path, GOOD.replace("[solver]", "[effects]\ninertia = false\n[solver]"))
    out = tmp_path / "out"
    argv = ["sweep", scene, "--vary", "tip.force[2]=-2:-0.5:3", "--vary", "rod.length=0.3,0.4", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert len(rows) == 6 and float(rows[0]["tip.force[2]"]) == -2.0 and float(rows[1]["rod.length"]) == 0.4
    assert all(float(r["converged"]) == 1.0 for r in rows)
    # A longer, more heavily loaded rod bends further down (z of the tip, rod along x).
    z = {(float(r["tip.force[2]"]), float(r["rod.length"])): float(r["z_m"]) for r in rows}
    assert z[(-2.0, 0.4)] < z[(-0.5, 0.4)] < 0 and z[(-2.0, 0.4)] < z[(-2.0, 0.3)]
    assert json.loads((out / "summary.json").read_text())["members"] == 6
    assert (out / "sweep.png").stat().st_size > 0
    # The same ranges as a Latin hypercube of six members: one per sixth of each range.
    argv = ["sweep", scene, "--vary", "tip.force[2]=-2:-0.5", "--vary", "rod.length=0.3:0.4", "--samples", "6", "--out", str(out)]
    assert main(argv + ["--quiet"]) == 0
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    force = sorted(float(r["tip.force[2]"]) for r in rows)
    assert len(rows) == 6 and [int((f + 2.0) / 0.25) for f in force] == list(range(6))
    assert all(float(r["converged"]) == 1.0 for r in rows)


BAD_VARY = {
    "unknown_key": ("rod.colour=1,2", "unknown key 'colour'"),
    "empty_range": ("rod.length=0.3:0.4:0", "empty range"),
    "not_numbers": ("rod.length=a,b", "not a range"),
    "no_equals": ("rod.length", "KEY=a:b:n"),
    "bad_key": ("rod..length=1,2", "table.key"),
    "negative_length": ("rod.length=0.3,-0.1", "sweep member 1"),
    "ignored_key": ("rod.tau=1e-4,1e-3", "changes nothing"),
}


@pytest.mark.parametrize("case", list(BAD_VARY))
def test_cli_sweep_bad_input_one_line_exit_2(tmp_path, capsys, case):
    spec, words = BAD_VARY[case]
    out = tmp_path / "out"
    assert main(["sweep", _write(tmp_path, GOOD), "--vary", spec, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not (out / "sweep.csv").exists()


def test_a_batch_over_its_memory_budget_runs_as_smaller_batches(tmp_path):
    """Six static members in one batch, then with a budget below what that batch's program
    needs (XLA's own figure): the batch runs as smaller ones with the same results; a budget
    below one member's need is refused with the figures."""
    scene = _write(tmp_path, GOOD.replace("[solver]", "[effects]\ninertia = false\n[solver]"))
    vary = {"tip.force[2]": [-2.0, -1.0, -0.5], "rod.length": [0.3, 0.4]}
    whole = sweep(scene, vary, batch=6)
    need = whole.timings["batch_bytes"][6]
    assert whole.timings["batch_sizes"] == [6] and need > 0
    split = sweep(scene, vary, batch=6, memory=int(0.7 * need))
    assert max(split.timings["batch_sizes"]) < 6
    assert all(b <= 0.7 * need for b in split.timings["batch_bytes"].values())
    for k in ("x_m", "z_m", "rx_rad", "newton_iterations"):
        np.testing.assert_allclose(split.outputs[k], whole.outputs[k], rtol=1e-12, atol=1e-15)
    with pytest.raises(pcrjax.SceneError, match="more than the memory budget"):
        sweep(scene, vary, batch=6, memory="1KB")


@pytest.mark.parametrize("memory", ["lots", "0MB", "1KB"])
def test_cli_sweep_bad_memory_one_line_exit_2(tmp_path, capsys, memory):
    scene = _write(tmp_path, GOOD.replace("[solver]", "[effects]\ninertia = false\n[solver]"))
    argv = ["sweep", scene, "--vary", "rod.length=0.3,0.4", "--memory", memory, "--out", str(tmp_path / "o"), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "memory" in err[0], err
    assert not (tmp_path / "o" / "sweep.csv").exists()


@pytest.mark.integration  # two Dask worker processes, each compiling cold
def test_sweep_on_a_local_dask_cluster_equals_the_in_process_sweep(tmp_path):
    """Six static members in batches of three on two Dask worker processes: the same table,
    to the last digit, as in this process (the workers run the same programs on the same inputs)."""
    pytest.importorskip("dask.distributed")
    scene = _write(tmp_path, GOOD.replace("[solver]", "[effects]\ninertia = false\n[solver]"))
    argv = ["sweep", scene, "--vary", "tip.force[2]=-2:-0.5:3", "--vary", "rod.length=0.3,0.4", "--batch", "3", "--quiet"]
    assert main(argv + ["--out", str(tmp_path / "here")]) == 0
    assert main(argv + ["--cluster", "local:2", "--out", str(tmp_path / "dask")]) == 0
    here, there = ((tmp_path / d / "sweep.csv").read_text() for d in ("here", "dask"))
    assert here == there and len(here.splitlines()) == 7
    ran = json.loads((tmp_path / "dask" / "summary.json").read_text())["cluster"]
    assert ran["kind"] == "local" and ran["workers"] == 2


@pytest.mark.parametrize("cluster", ["remote", "local:0"])
def test_cli_sweep_bad_cluster_one_line_exit_2(tmp_path, capsys, cluster):
    argv = ["sweep", _write(tmp_path, GOOD), "--vary", "rod.length=0.3,0.4", "--cluster", cluster, "--out", str(tmp_path / "o")]
    assert main(argv + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cluster" in err[0], err


SHARDED = """
import json, sys
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import pcrjax
from pcrjax.sweeps import sweep
pcrjax.enable_compilation_cache()
assert len(jax.local_devices()) == 2, jax.local_devices()
sw = sweep(json.load(open(sys.argv[1])), {"tip.force[2]": [-2.0, -1.0, -0.5]}, batch=3)
np.save(sys.argv[2], np.stack([sw.outputs[k] for k in ("x_m", "z_m", "ry_rad", "converged")]))
"""


@pytest.mark.integration  # a fresh process with two forced host devices
def test_members_sharded_across_two_cpu_devices_equal_one_device(tmp_path):
    """The members axis split across two (forced host) CPU devices with `jax.sharding`, the batch
    of three padded to four: the same equilibria as on one device."""
    data = rod_data(nodes=6, tol=1e-13, effects={"inertia": False})
    (tmp_path / "scene.json").write_text(json.dumps(data))
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    cmd = [sys.executable, "-c", SHARDED, str(tmp_path / "scene.json"), str(tmp_path / "sharded.npy")]
    subprocess.run(cmd, env=env, check=True, timeout=600)
    sharded = np.load(tmp_path / "sharded.npy")
    sw = sweep(data, {"tip.force[2]": [-2.0, -1.0, -0.5]}, batch=3)
    here = np.stack([sw.outputs[k] for k in ("x_m", "z_m", "ry_rad", "converged")])
    assert np.all(here[3] == 1) and np.all(sharded[3] == 1)
    np.testing.assert_allclose(sharded, here, rtol=1e-12, atol=0)
