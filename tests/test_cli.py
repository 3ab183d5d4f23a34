"""Command line: outputs of `simulate`/`static`, and one clear line with exit 2 for bad input."""

import csv
import json
import subprocess
import sys

import pytest

from pcrjax.cli import main

GOOD = """
name = "t"
robot = "rod"
[solver]
nodes = 6
dt = 5e-3
alpha = -0.2
duration = 0.05
[rod]
length = 0.4
radius = 1e-3
youngs_modulus = 207e9
shear_modulus = 79.61e9
density = 8000.0
[tip]
force = [0.0, 0.0, -1.0]
"""


def _write(tmp_path, text, name="scene.toml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


BAD = {
    "malformed": ("[solver\nnodes = 3", "malformed TOML"),
    "unknown_key": (GOOD.replace("[rod]", "[rod]\ncolour = 1"), "unknown key 'colour'"),
    "unknown_table_key": (GOOD + "\n[tip]\n", "malformed TOML"),
    "missing_required": (GOOD.replace("length = 0.4\n", ""), "[rod] length: missing required key"),
    "negative_length": (GOOD.replace("length = 0.4", "length = -0.4"), "[rod] length: must be > 0"),
    "zero_radius": (GOOD.replace("radius = 1e-3", "radius = 0.0"), "[rod] radius: must be > 0"),
    "nan": (GOOD.replace("density = 8000.0", "density = nan"), "[rod] density: must be finite"),
    "alpha_out_of_range": (GOOD.replace("alpha = -0.2", "alpha = 0.3"), "[solver] alpha: must lie in [-0.5, 0]"),
    "dt_zero": (GOOD.replace("dt = 5e-3", "dt = 0.0"), "[solver] dt: must be > 0"),
    "dt_negative": (GOOD.replace("dt = 5e-3", "dt = -1e-3"), "[solver] dt: must be > 0"),
    "bad_integrator": (GOOD.replace("nodes = 6", 'nodes = 6\nintegrator = "rk45"'), "integrator"),
    "text_for_number": (GOOD.replace("nodes = 6", 'nodes = "six"'), "[solver] nodes"),
}


@pytest.mark.parametrize("case", list(BAD))
@pytest.mark.parametrize("command", ["static", "simulate"])
def test_bad_input_one_line_exit_2(case, command, tmp_path, capsys):
    text, needle = BAD[case]
    path = _write(tmp_path, text)
    args = [command, path] + (["--out", str(tmp_path / "out")] if command == "simulate" else [])
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert needle in err and "Traceback" not in err
    assert path in err  # names the file


def test_missing_file(tmp_path, capsys):
    assert main(["static", str(tmp_path / "nope.toml")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_static_prints_json(tmp_path, capsys):
    assert main(["static", _write(tmp_path, GOOD)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"position", "rotation_vector", "base_wrenches", "residual_norm", "newton_iterations"}
    assert out["base_wrenches"][0][0] == pytest.approx([0.0, 0.0, -1.0], abs=1e-12)


def test_simulate_writes_outputs(tmp_path):
    out = tmp_path / "out"
    assert main(["simulate", _write(tmp_path, GOOD), "--out", str(out), "--quiet"]) == 0
    rows = list(csv.reader(open(out / "trajectory.csv")))
    assert rows[0] == ["t_s", "x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"]
    assert len(rows) == 1 + 11 and float(rows[1][0]) == 0.0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged"] and len(summary["newton_iterations"]) == 10
    assert summary["compile_s"] > 0 and summary["wall_s"] > 0
    for png in ("tip_path.png", "rod_shapes.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"


def test_non_convergence_reported_with_time_and_partial_output(tmp_path, capsys):
    # Eight Newton iterations reach 1e-14 in the statics but not in every step after release:
    # reported with the time, exit 2, and the steps before the failure are kept.
    text = GOOD.replace("dt = 5e-3", "dt = 5e-3\ntol = 1e-14\nmax_iter = 8").replace("-1.0]", "-1.0]\n")
    out = tmp_path / "out"
    assert main(["simulate", _write(tmp_path, text), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "did not converge" in err and "t = " in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged"] is False and summary["failure"]["time_s"] > 0
    rows = list(csv.reader(open(out / "trajectory.csv")))
    assert len(rows) >= 3  # header, the initial state and the steps before the failure


@pytest.mark.integration  # a fresh process: compiles its programs cold
def test_console_script_runs_shipped_scene(tmp_path):
    cmd = [sys.executable, "-m", "pcrjax.cli", "static", "cantilever", "--nodes", "10"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["newton_iterations"] > 0
    r = subprocess.run(
        [sys.executable, "-m", "pcrjax.cli", "static", str(tmp_path / "x.toml")], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.integration  # the whole benchmark command: minutes of compiling (the gradients' programs)
def test_bench_prints_the_table_kernels_and_gradient_cost(capsys, tmp_path):
    args = ["bench", "cantilever", "--nodes", "5", "--euler-nodes", "", "--duration", "0.02", "--reference-nodes", "5"]
    args += ["--gradient", "--gradient-nodes", "5", "--gradient-steps", "3", "--json", str(tmp_path / "b.json")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "kern/node" in out and "forward runs" in out
    rows = json.loads((tmp_path / "b.json").read_text())
    assert [r["case"] for r in rows["rows"]] == ["thesis", "till"]
    # An RK4 node step is at least four right-hand sides, and a residual's scan runs whole node
    # steps, at most the internal grid's one after the other and at least its share of one of
    # the segments side by side. Timings and ratios are printed, not compared (wall-clock figures
    # are noisy on a shared machine).
    assert all(r["kernels_per_node_step"] >= 4 for r in rows["rows"])
    for r in rows["rows"]:
        scan, rest = divmod(r["kernels_per_residual"], r["kernels_per_node_step"])
        assert rest == 0 and r["internal_nodes"] / r["segments"] <= scan <= r["internal_nodes"], r
    # The reference here is the rows' own grid (RK4, N 5, same dt) solved to 1e-12: the rows
    # differ from it by their Newton tolerance only, far below a micron.
    assert all(0 <= r["position_error_m"] < 1e-6 for r in rows["rows"])
    assert rows["gradient"]["scalars"] == 2 and rows["gradient"]["steps"] == 3


@pytest.mark.integration  # the batch benchmark command: a batched program per batch size
def test_bench_batch_prints_the_integrations_ceiling_and_matches_single_runs(capsys, tmp_path):
    args = ["bench", "batch", "--batches", "1,3", "--nodes", "5", "--gradient-steps", "3", "--json", str(tmp_path / "b.json")]
    assert main(args) == 0
    assert "The legs' integration alone" in capsys.readouterr().out
    rows = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert [r["batch"] for r in rows] == [1, 3]
    # members equal their single runs (to round-off); gains are timings: printed, not compared
    assert all(r["max_rel_diff"] < 1e-10 for r in rows)
