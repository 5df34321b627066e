"""`dmd-jax demo`: one noisy CAD part denoised by DMD-Net and by classic filters.

Everything the demo needs is generated here, so it runs on a fresh install with no data:
a `fastener` (chamfered nut or bolt, sharp edges) from the project's procedural
generator, the benchmark noise of `dmd_jax.protocol` at 0.2 × the mean edge length
(Gaussian, along the vertex normals), then DMD-Net with the bundled weights, pymeshlab's
Taubin smoothing and bilateral normal filtering (`bnf`). It prints the paper's three
metrics for each and writes the meshes and a colour-mapped render.

`fastener` is one of the categories the procedural training set holds out whole
(`dmd_jax.data.DEFAULT_TEST_INTER`), and the demo's dataset seed is not the training
seed, so the bundled model has never seen this shape or its category.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

DEMO_CATEGORY = "fastener"
DEMO_SEED = 2024
DEMO_INSTANCE = 2  # a flanged hex nut, 5198 vertices
NOISE_LEVEL = 0.2  # × mean edge length
NOISE_SEED = 0
# The fastest of the feature-preserving classic baselines in `dmd_jax.baselines`
# that keeps sharp edges (bilateral normal filtering, Zheng et al. 2011).
FEATURE_BASELINE = "bnf"

MESH_FILES = {
    "clean": "clean.obj",
    "noisy": "noisy.obj",
    "dmd": "denoised_dmd.obj",
    "taubin": "denoised_taubin.obj",
    FEATURE_BASELINE: f"denoised_{FEATURE_BASELINE}.obj",
}
RENDER_FILE = "before_after.png"
RENDER_ELEVATION = 30.0  # degrees; shows the top face and the bore of the nut
RENDER_PANEL_SIZE = 2.6  # inches per panel: five columns, 1430 px wide at 110 dpi
METRICS_FILE = "metrics.json"

_LABELS = {
    "noisy": "noisy input",
    "dmd": "DMD-Net",
    "taubin": "Taubin (pymeshlab)",
    FEATURE_BASELINE: "bilateral normal filter",
}


class DemoResult(NamedTuple):
    """What `run_demo` measured and wrote."""

    metrics: dict  # method -> mesh_metrics(...) keys and "seconds"
    files: dict  # name -> Path
    table: str  # the markdown table printed to the terminal
    model: str  # one line describing the weights used


def load_bundle(weights=None):
    """The model to run: the bundled weights, a weights file, or a checkpoint directory.

    Args:
      weights: None for `dmd_jax.load_pretrained()`; otherwise a path to a
        file written by `save_weights` / `dmd-jax export-weights`, or an Orbax
        checkpoint directory written by `dmd-jax train`.

    Raises:
      FileNotFoundError: the bundled weights or the given path is missing.
      ValueError: the file is not a valid weights file.
    """
    from dmd_jax.checkpoints import load_model

    try:
        return load_model(weights)
    except FileNotFoundError as exc:
        if weights is not None:
            raise
        raise FileNotFoundError(
            f"{exc}; pass --weights PATH (a file from `dmd-jax export-weights`)"
        ) from exc


def _describe(bundle, weights) -> str:
    from dmd_jax.model import param_count

    source = "bundled weights" if weights is None else f"weights {weights}"
    note = bundle.meta.get("note") or bundle.meta.get("description")
    return (
        f"DMD-Net, preset {bundle.config.name}, {param_count(bundle.config.model):,} "
        f"parameters, {source}" + (f" ({note})" if note else "")
    )


def _markdown_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A GitHub markdown table; floats printed with 3 decimals (4 significant if small)."""

    def fmt(x):
        if isinstance(x, float):
            return f"{x:.4g}" if abs(x) < 0.01 and x != 0 else f"{x:.3f}"
        return str(x)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(x) for x in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return np.asarray(out, np.float64), time.perf_counter() - start


def run_demo(
    out_dir,
    *,
    weights=None,
    overwrite: bool = False,
    render: bool = True,
    echo=print,
) -> DemoResult:
    """Generates, corrupts and denoises the demo mesh; writes meshes, metrics and a PNG.

    Args:
      out_dir: output directory (created if missing).
      weights: None for the bundled model, or a weights file / checkpoint directory
        (see `load_bundle`).
      overwrite: replace existing output files; without it any existing output is an
        error raised before any work is done.
      render: write `before_after.png` (matplotlib; a few seconds).
      echo: where progress lines and the table go (`print`, or a no-op).

    Returns:
      A `DemoResult`.

    Every file is written into a hidden folder inside `out_dir` and moved into place at
    the end: an error (a full disk, Ctrl-C) leaves no partial output, and with
    `overwrite` the old outputs stay until the new ones are complete.

    Raises:
      FileExistsError: an output file exists and `overwrite` is False.
      FileNotFoundError, ValueError: the weights cannot be loaded, or are one of the
        demo's outputs (`check_demo_outputs`).
    """

    out = Path(out_dir)
    check_demo_outputs(out, weights, overwrite, render=render)
    bundle = load_bundle(weights)
    model = _describe(bundle, weights)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    # Every file is written into a hidden folder inside `out` first and moved into place
    # at the end, so a failure (a full disk) leaves none of them, old outputs intact.
    stage = out / ".dmd-jax-demo.unused"
    try:
        stage = Path(tempfile.mkdtemp(prefix=".dmd-jax-demo.", dir=out))
        result = _run(out, stage, bundle, model, render, echo)
        for path in result.files.values():
            os.replace(stage / path.name, out / path.name)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    shutil.rmtree(stage, ignore_errors=True)
    files = {k: out / p.name for k, p in result.files.items()}
    return result._replace(files=files)


def check_demo_outputs(out_dir, weights, overwrite: bool, *, render: bool = True) -> None:
    """What would make `run_demo` fail to write or overwrite an input, before any work:
    `out_dir` a file, an existing output without `overwrite`, the weights among the
    outputs (with or without `overwrite`).

    Raises:
      FileExistsError: `out_dir` is a file, or an output exists and `overwrite` is False.
      ValueError: `weights` is one of the files the demo writes.
    """
    from dmd_jax.io import same_file

    out = Path(out_dir)
    names = list(MESH_FILES.values()) + [METRICS_FILE] + ([RENDER_FILE] if render else [])
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a directory")
    if weights is not None and any(same_file(weights, out / n) for n in names):
        raise ValueError(f"{weights}: the weights are one of the demo's outputs in {out}")
    existing = [n for n in names if (out / n).exists()]
    if existing and not overwrite:
        raise FileExistsError(
            f"{out}: {', '.join(existing)} already exist (pass --overwrite to replace them)"
        )


def _run(out, stage, bundle, model, render, echo) -> DemoResult:
    """`run_demo`'s work, every file written into `stage`; `out` names the folder."""
    from dmd_jax import baselines, inference
    from dmd_jax.baselines.meshlab import pymeshlab_filter
    from dmd_jax.data import generate_shape
    from dmd_jax.io import save_mesh
    from dmd_jax.metrics import (
        DEFAULT_METRICS,
        NORMAL,
        face_normal_errors_deg,
        format_metric,
        mesh_metrics,
        metric_cells,
        metric_header,
        metrics_legend,
    )
    from dmd_jax.protocol import benchmark_noise

    start = time.perf_counter()
    clean, faces = generate_shape(DEMO_CATEGORY, DEMO_SEED, DEMO_INSTANCE)
    noisy = benchmark_noise(clean, faces, NOISE_LEVEL, NOISE_SEED)
    echo(
        f"demo mesh: procedural {DEMO_CATEGORY!r} (seed {DEMO_SEED}, instance "
        f"{DEMO_INSTANCE}), {len(clean)} vertices, {len(faces)} faces; Gaussian noise "
        f"σ = {NOISE_LEVEL} × mean edge length (seed {NOISE_SEED}); "
        f"{time.perf_counter() - start:.1f} s"
    )
    echo(f"model: {model}")

    results = {"noisy": (noisy, 0.0)}
    results["dmd"] = _timed(lambda: inference.denoise(noisy, faces, bundle))
    results["taubin"] = _timed(lambda: pymeshlab_filter(noisy, faces, "taubin"))
    results[FEATURE_BASELINE] = _timed(
        lambda: baselines.run_baseline(FEATURE_BASELINE, noisy, faces)
    )

    metrics = {}
    for name, (v, seconds) in results.items():
        metrics[name] = {**mesh_metrics(v, clean, faces), "seconds": seconds}
    # Names, units and scaling of dmd_jax.metrics, as in `dmd-jax evaluate`.
    rows = [
        [_LABELS[name], *metric_cells(m), "—" if name == "noisy" else f"{m['seconds']:.2f}"]
        for name, m in metrics.items()
    ]
    table = _markdown_table(
        ["method", *(metric_header(s) for s in DEFAULT_METRICS), "time (s)"], rows
    )
    echo("")
    echo(table.rstrip())
    echo(metrics_legend() + " Times include JIT compilation (first call in this process).")

    files = {}
    meshes = {"clean": clean, "noisy": noisy} | {k: results[k][0] for k in results if k != "noisy"}
    for name, filename in MESH_FILES.items():
        files[name] = save_mesh(stage / filename, meshes[name], faces)
    payload = {
        "mesh": {
            "category": DEMO_CATEGORY,
            "seed": DEMO_SEED,
            "instance": DEMO_INSTANCE,
            "n_vertex": int(len(clean)),
            "n_face": int(len(faces)),
        },
        "noise": {"kind": "gaussian", "level": NOISE_LEVEL, "units": "edge", "seed": NOISE_SEED},
        "model": model,
        "metrics": metrics,
    }

    from dmd_jax.io import atomic_write

    text = json.dumps(payload, indent=2) + "\n"
    files["metrics"] = atomic_write(stage / METRICS_FILE, lambda tmp: Path(tmp).write_text(text))
    if render:
        from dmd_jax.render import render_meshes, sharpest_face

        panels = ["clean", "noisy", "dmd", "taubin", FEATURE_BASELINE]
        values = [None] + [face_normal_errors_deg(meshes[k], clean, faces) for k in panels[1:]]
        titles = ["clean"] + [
            f"{_LABELS[k]}\n{NORMAL.name} {format_metric(NORMAL, metrics[k][NORMAL.key])}"
            f"{NORMAL.unit}"
            for k in panels[1:]
        ]
        files["render"] = render_meshes(
            [(meshes[k], faces) for k in panels],
            stage / RENDER_FILE,
            titles=titles,
            face_values=values,
            elev=RENDER_ELEVATION,
            shaded_row=True,
            crop_face=sharpest_face(clean, faces, elev=RENDER_ELEVATION),
            panel_size=RENDER_PANEL_SIZE,
        )
    echo("")
    echo(
        f"wrote {', '.join(p.name for p in files.values())} to {out} "
        f"({time.perf_counter() - start:.1f} s in all)"
    )
    return DemoResult(metrics=metrics, files=files, table=table, model=model)
