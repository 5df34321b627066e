"""Executes the exploration notebooks with nbclient (`make notebooks`).

Executed copies, outputs included, go to `notebooks/executed/` (git-ignored); the
notebooks in `notebooks/` stay stripped. Notebooks 05 and 06 need trained weights: the
bundled `dmd_jax/weights/dmd_small.msgpack`, or a weights file named by the environment
variable `DMD_JAX_WEIGHTS`; without either they are skipped with a message.

Usage:
  python notebooks/_run.py [--only 03_geometry_and_features] [--out DIR] [--timeout S]
  python notebooks/_run.py --strip    # remove outputs from the notebooks in place
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).resolve().parent
NEEDS_WEIGHTS = ("05_feature_guided_transformer", "06_denoise_walkthrough")


def notebooks() -> list[Path]:
    """The numbered notebooks, in order."""
    return sorted(HERE.glob("[0-9][0-9]_*.ipynb"))


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


def execute(path: Path, *, timeout: int = 600, cwd: Path | None = None):
    """Runs every cell of `path` in a fresh `python3` kernel; raises on any cell error."""
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(
        nb,
        timeout=timeout,
        kernel_name="python3",
        resources={"metadata": {"path": str(cwd or path.parent)}},
    )
    client.execute()
    return nb


def strip(nb) -> bool:
    """Removes outputs and execution counts in place; True when something changed."""
    changed = False
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        if cell.outputs or cell.execution_count is not None:
            changed = True
        cell.outputs = []
        cell.execution_count = None
    return changed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="notebook names (with or without .ipynb)")
    parser.add_argument("--out", type=Path, default=HERE / "executed")
    parser.add_argument("--timeout", type=int, default=600, help="seconds per cell")
    parser.add_argument("--strip", action="store_true", help="strip outputs in place, run nothing")
    args = parser.parse_args(argv)

    paths = notebooks()
    if args.only:
        wanted = {name.removesuffix(".ipynb") for name in args.only}
        paths = [p for p in paths if p.stem in wanted]
        missing = wanted - {p.stem for p in paths}
        if missing:
            parser.error(f"no such notebook: {', '.join(sorted(missing))}")
    if args.strip:
        for path in paths:
            nb = nbformat.read(path, as_version=4)
            if strip(nb):
                nbformat.write(nb, path)
                print(f"stripped {path.name}")
        return 0

    args.out.mkdir(parents=True, exist_ok=True)
    failed = []
    for path in paths:
        if path.stem in NEEDS_WEIGHTS and (reason := weights_available()):
            print(f"SKIP {path.name}: {reason}")
            continue
        start = time.perf_counter()
        try:
            nb = execute(path, timeout=args.timeout, cwd=args.out)
        except Exception as exc:  # report every notebook, then fail
            print(f"FAIL {path.name} ({time.perf_counter() - start:.1f} s): {exc}")
            failed.append(path.name)
            continue
        nbformat.write(nb, args.out / path.name)
        print(f"ok   {path.name} ({time.perf_counter() - start:.1f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
