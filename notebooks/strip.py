"""Remove outputs and execution counts from notebooks: ``python notebooks/strip.py notebooks/*.ipynb``."""

import sys

import nbformat

for name in sys.argv[1:]:
    nb = nbformat.read(name, as_version=4)
    for cell in nb.cells:
        cell.metadata = {}
        if cell.cell_type == "code":
            cell.outputs = []
            cell.execution_count = None
    nbformat.write(nb, name)
