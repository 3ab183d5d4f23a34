"""Parallel-robot scene files: bad geometry, actuator tables and keys give one clear line and exit 2."""

import pytest

from pcrjax.cli import main

SG = """
name = "sg"
robot = "stewart_gough"
[solver]
nodes = 6
dt = 1e-2
duration = 0.05
[rod]
length = 0.17
radius = 1e-3
youngs_modulus = 207e9
shear_modulus = 79.61e9
density = 8000.0
[platform]
mass = 0.0921
inertia = [1.91e-4, 1.91e-4, 3.81e-4]
[actuation]
initial = [0.17, 0.17, 0.17, 0.17, 0.17, 0.17]
"""

TRISKELE = """
name = "tk"
robot = "triskele"
[solver]
nodes = 6
dt = 1e-3
duration = 0.01
[rod]
length = 0.032
radius = 62.5e-6
youngs_modulus = 69.2e9
shear_modulus = 29.58e9
density = 2203.0
[platform]
mass = 0.04
inertia = [2.58e-5, 2.58e-5, 5.16e-5]
angle = 10.0
[actuation]
initial = [0.0, 0.0, 0.0]
"""

CSV_OK = "t_s,a1,a2,a3\n0,0,0,0\n0.01,1e-6,0,0\n"

BAD = {
    "legs_too_short": (
        SG.replace("initial = [0.17, 0.17, 0.17, 0.17, 0.17, 0.17]", "initial = [0.05, 0.17, 0.17, 0.17, 0.17, 0.17]"),
        None,
        "leg 1 cannot reach the platform",
    ),
    "attachment_out_of_reach": (
        TRISKELE.replace("[platform]", "[geometry]\nattachment = [[0.0, 0.3], [0.0, 0.0], [0.01, 0.0]]\n[platform]"),
        None,
        "cannot reach the platform",
    ),
    "actuator_count": (
        SG.replace("initial = [0.17, 0.17, 0.17, 0.17, 0.17, 0.17]", "initial = [0.17, 0.17, 0.17, 0.17, 0.17]"),
        None,
        "must have 6 entries",
    ),
    "negative_leg_length": (
        SG.replace("initial = [0.17, 0.17, 0.17, 0.17, 0.17, 0.17]", "initial = [-0.17, 0.17, 0.17, 0.17, 0.17, 0.17]"),
        None,
        "leg lengths must be > 0",
    ),
    "csv_columns": (TRISKELE + 'file = "a.csv"\n', "t_s,a1,a2\n0,0,0\n0.01,0,0\n", "header must be t_s,a1,a2,a3"),
    "csv_gap": (TRISKELE + 'file = "a.csv"\n', "t_s,a1,a2,a3\n0,0,0,0\n0.01,,0,0\n", "column a1 is empty (gap"),
    "csv_unsorted": (
        TRISKELE + 'file = "a.csv"\n',
        "t_s,a1,a2,a3\n0,0,0,0\n0.02,0,0,0\n0.01,0,0,0\n",
        "times must strictly increase",
    ),
    "csv_nan": (TRISKELE + 'file = "a.csv"\n', "t_s,a1,a2,a3\n0,0,0,0\n0.01,nan,0,0\n", "not finite"),
    "csv_text": (TRISKELE + 'file = "a.csv"\n', "t_s,a1,a2,a3\n0,0,0,0\n0.01,abc,0,0\n", "not a number"),
    "csv_missing": (TRISKELE + 'file = "nowhere.csv"\n', None, "no such file"),
    "csv_and_kind": (TRISKELE + 'file = "a.csv"\nkind = "step"\n', CSV_OK, "cannot be combined with file"),
    "ramp_without_duration": (TRISKELE + 'kind = "ramp"\nfinal = [1e-6, 0.0, 0.0]\n', None, "duration: must be > 0"),
    "step_without_final": (TRISKELE + 'kind = "step"\n', None, "final: missing"),
    "unknown_kind": (TRISKELE + 'kind = "jump"\n', None, "[actuation] kind"),
    "unknown_geometry_key": (
        TRISKELE.replace("[platform]", "[geometry]\nradius = 1.0\n[platform]"),
        None,
        "unknown key 'radius'",
    ),
    "sg_key_on_triskele": (
        TRISKELE.replace("[platform]", "[geometry]\nbase_radius = 0.08\n[platform]"),
        None,
        "applies to the stewart_gough robot",
    ),
    "rods_count": (TRISKELE + "[[rods]]\nlength = 0.03\n", None, "has 1 entries but the robot has 3 legs"),
    "missing_mass": (TRISKELE.replace("mass = 0.04\n", ""), None, "[platform] mass: missing required key"),
    "unknown_top_level": (TRISKELE + "[base]\nposition = [0.0, 0.0, 0.0]\n", None, "unknown key 'base'"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_parallel_scene_one_line_exit_2(case, tmp_path, capsys):
    text, csv_text, needle = BAD[case]
    (tmp_path / "scene.toml").write_text(text)
    if csv_text is not None:
        (tmp_path / "a.csv").write_text(csv_text)
    assert main(["static", str(tmp_path / "scene.toml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    assert needle in err, err
    assert "Traceback" not in err


def test_static_stewart_gough_json(capsys):
    import json

    assert main(["static", "stewart_gough", "--nodes", "10"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["base_wrenches"]) == 6 and all(len(w) == 2 and len(w[0]) == 3 for w in out["base_wrenches"])
    assert out["residual_norm"] <= 1e-10 and 0.1 < out["position"][2] < 0.17


def test_simulate_triskele_writes_outputs(tmp_path):
    import csv
    import json

    out = tmp_path / "tk"
    assert main(["simulate", "triskele", "--nodes", "10", "--duration", "0.02", "--out", str(out), "--quiet"]) == 0
    rows = list(csv.reader((out / "trajectory.csv").open()))
    assert rows[0] == ["t_s", "x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad", "a1", "a2", "a3"]
    assert len(rows) == 1 + 21
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged"] and summary["settings"]["legs"] == 3 and summary["steps_done"] == 20
    assert (out / "platform_path.png").stat().st_size > 0 and (out / "legs.png").stat().st_size > 0
