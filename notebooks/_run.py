"""Builds and executes the exploration notebooks from their percent scripts (`make notebooks`).

Each notebook has one source, `notebooks/NN_name.py`, a Python script in jupytext's
percent format: `# %%` starts a code cell, `# %% [markdown]` a markdown cell whose lines
are comments (`# text`). The scripts are linted like the rest of the code, run as plain
Python, and open as notebooks in Jupyter with jupytext. This runner turns each into a
notebook (`notebook`), executes it with nbclient in a fresh `python3` kernel and writes
the executed copy, outputs included, to `notebooks/executed/` (git-ignored).

Notebooks 05 and 06 need trained weights: the bundled
`dmd_jax/weights/dmd_small.msgpack`, or a weights file named by the environment variable
`DMD_JAX_WEIGHTS`; without either they are skipped with a message.

Usage:
  python notebooks/_run.py [--only 03_geometry_and_features] [--out DIR] [--timeout S]
  python notebooks/_run.py --no-execute   # write the stripped .ipynb files only
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parent
NEEDS_WEIGHTS = ("05_feature_guided_transformer", "06_denoise_walkthrough")
# Notebooks that read real meshes from the project's shared/meshes folder (beside the
# repository, or DMD_JAX_SHARED_MESHES); users without it skip them.
NEEDS_SHARED = ("07_bundled_model_layer_by_layer",)
CODE_MARK = "# %%"
MARKDOWN_MARK = "# %% [markdown]"


def notebooks() -> list[Path]:
    """The numbered notebook scripts, in order."""
    return sorted(HERE.glob("[0-9][0-9]_*.py"))


def cells_of(text: str) -> list[tuple[str, str]]:
    """`(kind, source)` of every cell of a percent script, `kind` `"code"` or `"markdown"`.

    Blank lines around a cell are dropped; a markdown line `# text` becomes `text` and
    a bare `#` an empty line. Text before the first marker is not a cell.
    """
    cells: list[tuple[str, list[str]]] = []
    for line in text.splitlines():
        if line.strip() == MARKDOWN_MARK:
            cells.append(("markdown", []))
        elif line.strip() == CODE_MARK:
            cells.append(("code", []))
        elif cells:
            kind, lines = cells[-1]
            if kind == "markdown" and line.strip():
                if not line.startswith("#"):
                    raise ValueError(f"markdown cell line is not a comment: {line!r}")
                line = line[2:] if line.startswith("# ") else line[1:]
            lines.append(line)
    return [(kind, "\n".join(lines).strip("\n")) for kind, lines in cells]


def notebook(path: Path):
    """The notebook of a percent script: cell ids `NN-ii`, a `python3` kernelspec."""
    out = []
    for i, (kind, source) in enumerate(cells_of(Path(path).read_text())):
        cell = new_markdown_cell(source) if kind == "markdown" else new_code_cell(source)
        cell["id"] = f"{Path(path).stem[:2]}-{i:02d}"
        out.append(cell)
    nb = new_notebook(
        cells=out,
        metadata={
            "kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"},
            "language_info": {"name": "python"},
        },
    )
    nbformat.validate(nb)
    return nb


def weights_available() -> str | None:
    """Why notebooks 05/06 cannot run (None when weights are there)."""
    env = os.environ.get("DMD_JAX_WEIGHTS")
    if env:
        return None if Path(env).is_file() else f"DMD_JAX_WEIGHTS={env} is not a file"
    from dmd_jax.checkpoints import pretrained_path

    path = pretrained_path()
    if path.is_file():
        return None
    return f"{path} does not exist yet and DMD_JAX_WEIGHTS is not set (see notebooks/README.md)"


def shared_meshes_available() -> str | None:
    """Why notebook 07 cannot run (None when shared/meshes is there)."""
    from dmd_jax.protocol import shared_meshes_dir

    folder = shared_meshes_dir()
    if (folder / "fandisk.off").is_file():
        return None
    return f"{folder} holds no fandisk.off (set DMD_JAX_SHARED_MESHES=DIR)"


def execute(path: Path, *, timeout: int = 600, cwd: Path | None = None):
    """Runs every cell of the notebook of `path` in a fresh `python3` kernel.

    Raises:
      nbclient.exceptions.CellExecutionError: naming the cell, on any cell error.
    """
    nb = notebook(path)
    client = NotebookClient(
        nb,
        timeout=timeout,
        kernel_name="python3",
        resources={"metadata": {"path": str(cwd or Path(path).parent)}},
    )
    client.execute()
    return nb


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="notebook names (with or without .py)")
    parser.add_argument("--out", type=Path, default=HERE / "executed")
    parser.add_argument("--timeout", type=int, default=600, help="seconds per cell")
    parser.add_argument(
        "--no-execute", action="store_true", help="write the notebooks without running them"
    )
    args = parser.parse_args(argv)

    paths = notebooks()
    if args.only:
        wanted = {Path(name).stem for name in args.only}
        paths = [p for p in paths if p.stem in wanted]
        missing = wanted - {p.stem for p in paths}
        if missing:
            parser.error(f"no such notebook: {', '.join(sorted(missing))}")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.no_execute:
        for path in paths:
            nbformat.write(notebook(path), args.out / f"{path.stem}.ipynb")
            print(f"wrote {args.out / path.stem}.ipynb")
        return 0

    failed = []
    for path in paths:
        if path.stem in NEEDS_WEIGHTS and (reason := weights_available()):
            print(f"SKIP {path.name}: {reason}")
            continue
        if path.stem in NEEDS_SHARED and (reason := shared_meshes_available()):
            print(f"SKIP {path.name}: {reason}")
            continue
        start = time.perf_counter()
        try:
            nb = execute(path, timeout=args.timeout, cwd=args.out)
        except Exception as exc:  # report every notebook, then fail
            print(f"FAIL {path.name} ({time.perf_counter() - start:.1f} s): {exc}")
            failed.append(path.name)
            continue
        nbformat.write(nb, args.out / f"{path.stem}.ipynb")
        print(f"ok   {path.name} ({time.perf_counter() - start:.1f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
