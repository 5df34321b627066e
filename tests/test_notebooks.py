"""The exploration notebooks: one percent script each, and each runs top to bottom.

Each script (`notebooks/NN_name.py`) becomes a notebook through `notebooks/_run.py`, as
`make notebooks` builds it, and executes in a fresh `python3` kernel (nbclient), with a
temporary working directory; any cell error fails its test. Notebooks 05 and 06 need
trained weights, the bundled `dmd_jax/weights/dmd_small.msgpack` or a file named by
`DMD_JAX_WEIGHTS`, and are skipped when neither exists.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
from conftest import NEEDS_SHARED

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
    "07_bundled_model_layer_by_layer",
]
# Per cell; a whole notebook takes well under a minute on two idle cores.
CELL_TIMEOUT_S = 300


def _path(name: str) -> Path:
    return NOTEBOOK_DIR / f"{name}.py"


def test_notebook_set_is_complete():
    assert [p.stem for p in runner.notebooks()] == NOTEBOOKS
    assert not list(NOTEBOOK_DIR.glob("*.ipynb")), "the scripts are the only source"


def test_percent_cells_round_trip():
    text = "# %% [markdown]\n# # Title\n#\n# text\n\n# %%\nx = 1\n\n\nx\n\n# %%\ny = 2\n"
    assert runner.cells_of(text) == [
        ("markdown", "# Title\n\ntext"),
        ("code", "x = 1\n\n\nx"),
        ("code", "y = 2"),
    ]
    with pytest.raises(ValueError, match="not a comment"):
        runner.cells_of("# %% [markdown]\ntext\n")


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_script_builds_a_valid_notebook(name):
    nb = runner.notebook(_path(name))
    nbformat.validate(nb)
    assert nb.metadata["kernelspec"]["name"] == "python3"
    assert [c.id for c in nb.cells] == [f"{name[:2]}-{i:02d}" for i in range(len(nb.cells))]
    assert nb.cells[0].cell_type == "markdown" and nb.cells[0].source.startswith("# ")
    assert any(c.cell_type == "code" and c.source for c in nb.cells)


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_needs_no_shared_data(name):
    """Users do not have the project's ../shared folder: notebooks make their meshes,
    except those that say they need it (`_run.NEEDS_SHARED`, skipped without it)."""
    if name in runner.NEEDS_SHARED:
        pytest.skip("reads shared/meshes by design; skipped where it is absent")
    source = "\n".join(
        c.source for c in runner.notebook(_path(name)).cells if c.cell_type == "code"
    )
    assert not re.search(r"shared/|SHARED_MESHES|shared_mesh", source)


# The five heaviest notebooks (15-40 s each on 2 idle cores) run with `make test-slow`
# and `make notebooks`; the default suite executes the other two.
HEAVY_NOTEBOOKS = {
    "03_geometry_and_features",
    "06_denoise_walkthrough",
    "04_noise_models",
    "05_feature_guided_transformer",
    "07_bundled_model_layer_by_layer",
}


@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=pytest.mark.slow) if n in HEAVY_NOTEBOOKS else n for n in NOTEBOOKS],
)
def test_notebook_executes(name, tmp_path):
    if name in runner.NEEDS_WEIGHTS and (reason := runner.weights_available()):
        pytest.skip(f"{NEEDS_SHARED}: {reason}")
    if name in runner.NEEDS_SHARED and (reason := runner.shared_meshes_available()):
        pytest.skip(f"{NEEDS_SHARED}: {reason}")
    # Raises CellExecutionError, naming the cell, on any error.
    nb = runner.execute(_path(name), timeout=CELL_TIMEOUT_S, cwd=tmp_path)
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"
    ]
    assert not errors
