"""The exploration notebooks: committed without outputs, and each runs top to bottom.

Each notebook executes in a fresh `python3` kernel (nbclient), with a temporary working
directory; any cell error fails its test. Notebooks 05 and 06 need trained weights, the
bundled `dmd_jax/weights/dmd_small.msgpack` or a file named by `DMD_JAX_WEIGHTS`, and
are skipped when neither exists.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
# `make notebooks`'s runner (not a package): the tests execute notebooks the same way.
_spec = importlib.util.spec_from_file_location("notebook_runner", NOTEBOOK_DIR / "_run.py")
runner = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(runner)
NOTEBOOKS = [
    "01_graph_ops",
    "02_node_feature_collision",
    "03_geometry_and_features",
    "04_noise_models",
    "05_feature_guided_transformer",
    "06_denoise_walkthrough",
]
# Per cell; a whole notebook takes well under a minute on two idle cores.
CELL_TIMEOUT_S = 300


def _path(name: str) -> Path:
    return NOTEBOOK_DIR / f"{name}.ipynb"


def test_notebook_set_is_complete():
    found = sorted(p.stem for p in NOTEBOOK_DIR.glob("[0-9][0-9]_*.ipynb"))
    assert found == NOTEBOOKS


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_committed_notebook_is_valid_and_stripped(name):
    nb = nbformat.read(_path(name), as_version=4)
    nbformat.validate(nb)
    assert nb.metadata["kernelspec"]["name"] == "python3"
    code_cells = [c for c in nb.cells if c.cell_type == "code"]
    assert code_cells and any(c.cell_type == "markdown" for c in nb.cells)
    for cell in code_cells:
        assert cell.outputs == [], f"{name}: cell {cell.id} has outputs; strip them"
        assert cell.execution_count is None, f"{name}: cell {cell.id} has an execution count"
    assert not [c.id for c in nb.cells if "execution" in c.metadata], "execution timings left in"


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_needs_no_shared_data(name):
    """Users do not have the project's ../shared folder: notebooks make their meshes."""
    nb = nbformat.read(_path(name), as_version=4)
    source = "\n".join(c.source for c in nb.cells if c.cell_type == "code")
    assert not re.search(r"shared/|SHARED_MESHES|shared_mesh", source)


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_executes(name, tmp_path):
    if name in runner.NEEDS_WEIGHTS and (reason := runner.weights_available()):
        pytest.skip(reason)
    # Raises CellExecutionError, naming the cell, on any error.
    nb = runner.execute(_path(name), timeout=CELL_TIMEOUT_S, cwd=tmp_path)
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"
    ]
    assert not errors
