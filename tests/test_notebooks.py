"""Every notebook in notebooks/ runs top to bottom (small settings) and carries no outputs in git.

The notebooks assert their key numbers against oracles themselves, so a notebook that drifts
into showing something wrong fails here. ``PCRJAX_NOTEBOOKS=full`` runs them at the settings
their text describes; ``PCRJAX_NOTEBOOKS_OUT=DIR`` keeps the executed copies (with outputs).
"""

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

FOLDER = Path(__file__).resolve().parent.parent / "notebooks"
NOTEBOOKS = sorted(FOLDER.glob("*.ipynb"))


def test_notebooks_exist():
    names = {p.stem for p in NOTEBOOKS}
    assert {
        "quickstart",
        "cantilever",
        "stewart_gough",
        "triskele",
        "identification",
        "inverse_and_design",
        "sweeps_and_accuracy",
    } <= names, names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_stripped(path):
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert not cell.outputs and cell.execution_count is None, f"{path.name}: outputs committed (strip them)"


@pytest.mark.notebooks
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, monkeypatch):
    mode = os.environ.get("PCRJAX_NOTEBOOKS", "quick")
    monkeypatch.setenv("PCRJAX_NOTEBOOKS", mode)  # the kernel inherits this process's environment
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(nb, timeout=3600, kernel_name="python3", resources={"metadata": {"path": str(FOLDER)}})
    try:
        client.execute()
    finally:
        out = os.environ.get("PCRJAX_NOTEBOOKS_OUT")
        if out:
            Path(out).mkdir(parents=True, exist_ok=True)
            nbformat.write(nb, Path(out) / path.name)
