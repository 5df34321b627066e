"""Training steps/s and inference time on whatever device JAX sees; writes a small report.

    python -m experiments.device_bench                 # full sizes on a GPU, tiny on CPU
    python -m experiments.device_bench --small         # tiny sizes anywhere (a smoke test)
    python -m experiments.device_bench --size full     # full sizes on CPU too (slow)

What it measures, on `jax.devices()[0]`:

* **training**: for each preset (`small`, `paper`), `train.Trainer.train_step` on
  prebuilt batches of the preset's batch size (wavy grid meshes of about the preset's
  training-mesh size: `DataConfig.target_vertices`, 2,000 for both). The first steps
  compile (one program: every batch has one shape) and are timed apart; steps/s is one
  over the median of the timed steps, each run until its outputs are ready.
* **inference**: `inference.denoise` with the bundled `small` weights (its pass policy,
  memory plan and patching, the call users make) on a wavy grid of 1M and 10M faces:
  the first call (with compilation), then the median of the timed calls.

`--size tiny` (`--small`, and the default on CPU) keeps the code paths and shrinks the
sizes: the presets' models at width 8 and depth 1 without Taubin candidates, 200-vertex
meshes, 2 timed steps, inference at 2k and 20k faces. The report (`--out`, default
`experiments/results/device_bench/`) names the device, the commit (and whether the tree
was dirty), the weights' SHA-256 (the bundled file for inference, the initial params for
training) and the load, as `<platform>[-tiny].json` and `.md`. The `gpu` sweep preset
(`experiments.studies`) is sized from steps/s like these; see `dmd_jax.config` `_gpu`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "experiments" / "results" / "device_bench"
TRAIN_PRESETS = ("small", "paper")
# Full and tiny sizes: (training-mesh vertices, model width or None for the preset's,
# compile steps, timed steps, inference face counts, timed inference calls).
SIZES = {
    "full": {
        "vertices": None,
        "width": None,
        "warmup": 2,
        "steps": 20,
        "faces": (1_000_000, 10_000_000),
        "repeat": 3,
    },
    "tiny": {
        "vertices": 200,
        "width": 8,
        "warmup": 1,
        "steps": 2,
        "faces": (2_000, 20_000),
        "repeat": 1,
    },
}


def grid_mesh(n_faces: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A wavy, slightly noisy square grid with about `n_faces` triangles.

    Returns:
      `(vertices [k*k, 3] float64, faces [2 (k-1)^2, 3] int32)`, `k = ceil(sqrt(n/2)) + 1`.
    """
    k = int(np.ceil(np.sqrt(max(n_faces, 2) / 2))) + 1
    x, y = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k), indexing="ij")
    z = 0.05 * np.sin(6 * np.pi * x) * np.cos(4 * np.pi * y)
    v = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    v = v + np.random.default_rng(seed).normal(0, 0.2 / k, v.shape)
    i = np.arange(k - 1)
    a = (i[:, None] * k + i[None, :]).reshape(-1)  # lower-left corner of each cell
    faces = np.concatenate(
        [np.stack([a, a + k, a + 1], -1), np.stack([a + 1, a + k, a + k + 1], -1)]
    ).astype(np.int32)
    return v, faces


def params_hash(params) -> str:
    """SHA-256 over every parameter's path, dtype, shape and bytes (first 16 hex)."""
    import jax

    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        a = np.asarray(leaf)
        h.update(f"{jax.tree_util.keystr(path)}|{a.dtype}|{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def file_hash(path) -> str:
    """SHA-256 of a file (first 16 hex)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def commit() -> str:
    """`git rev-parse HEAD` of the repository, `+dirty` when tracked files differ."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO,
            capture_output=True,
            text=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def _median(xs) -> float:
    return float(np.median(xs)) if len(xs) else float("nan")


def train_config(preset: str, size: dict):
    """The preset's config, cut down to `size` (width, mesh size) for tiny runs."""
    from dmd_jax.config import preset as get_preset

    cfg = get_preset(preset)
    if size["width"] is not None:
        # Tiny: the same code paths with the least to compile (one two-stream block, no
        # Taubin candidates).
        w = size["width"]
        cfg = cfg.with_edits(
            {"model": {"width": w, "stn_width": w, "depth": 1, "taubin_iterations": 0}}
        )
    return cfg


def measure_training(preset: str, size: dict) -> dict[str, Any]:
    """Steps/s of one preset's train step on this device (see module doc)."""
    import jax

    from dmd_jax.pipeline import make_examples, training_batch
    from dmd_jax.train import Trainer

    cfg = train_config(preset, size)
    t = cfg.train
    n_vertex = size["vertices"] or cfg.data.target_vertices
    # One mesh size, so every batch pads to one bucket and only the first step compiles.
    meshes = [grid_mesh(2 * n_vertex, seed=i) for i in range(max(t.batch_size, 2))]
    examples = make_examples(meshes)
    n_batches = size["warmup"] + size["steps"]

    def batch(step):
        return training_batch(
            examples,
            step,
            batch_size=t.batch_size,
            seed=t.seed,
            noise=cfg.noise,
            rotate=t.rotate,
            encoding=cfg.model.encoding,
        )

    batches = [batch(s) for s in range(n_batches)]
    trainer = Trainer(cfg)
    state = trainer.init(batches[0])
    times, cpu = [], []
    for b in batches:
        start, start_cpu = time.perf_counter(), time.process_time()
        state, out = trainer.train_step(state, b)
        jax.block_until_ready(out["loss"])
        times.append(time.perf_counter() - start)
        # Process CPU time: on a shared machine, what the step costs without the wait.
        cpu.append(time.process_time() - start_cpu)
    timed = times[size["warmup"] :]
    loss = float(out["loss"])
    return {
        "preset": preset,
        "width": cfg.model.width,
        "depth": cfg.model.depth,
        "batch_size": t.batch_size,
        "mesh_vertices": int(meshes[0][0].shape[0]),
        "padded_vertices": int(np.shape(batches[0].noisy)[-2]),
        "compiles": trainer.compiles,
        "first_steps_s": [round(x, 4) for x in times[: size["warmup"]]],
        "step_s": [round(x, 5) for x in timed],
        "median_step_s": _median(timed),
        "median_step_cpu_s": _median(cpu[size["warmup"] :]),
        "steps_per_s": 1.0 / _median(timed),
        "final_loss": loss,
        "finite": bool(np.isfinite(loss)),
        "weights_sha256": params_hash(state.params),
    }


def measure_inference(n_faces: int, size: dict, bundle) -> dict[str, Any]:
    """`denoise` on a grid of about `n_faces` faces: first call and timed calls."""
    from dmd_jax.inference import denoise

    v, f = grid_mesh(n_faces)
    start = time.perf_counter()
    out, info = denoise(v, f, bundle, return_info=True)
    first = time.perf_counter() - start
    times = []
    for _ in range(size["repeat"]):
        start = time.perf_counter()
        denoise(v, f, bundle)
        times.append(time.perf_counter() - start)
    return {
        "faces": int(f.shape[0]),
        "vertices": int(v.shape[0]),
        "passes": int(info.passes),
        "first_call_s": round(first, 3),
        "call_s": [round(x, 3) for x in times],
        "median_s": _median(times),
        "finite": bool(np.all(np.isfinite(out))),
    }


def run(
    size_name: str = "auto",
    *,
    presets=TRAIN_PRESETS,
    faces=None,
    steps: int | None = None,
    inference: bool = True,
    out_dir=DEFAULT_OUT,
) -> dict[str, Any]:
    """Measures and writes the report; returns it (see module doc).

    Args:
      size_name: `full`, `tiny`, or `auto` (full on an accelerator, tiny on CPU).
      presets: training presets to measure.
      faces: inference face counts (default: the size's).
      steps: timed training steps (default: the size's).
      inference: time `denoise` as well.
      out_dir: where `<platform>[-tiny].json` and `.md` go.
    """
    import jax

    from dmd_jax.checkpoints import load_pretrained, pretrained_path

    device = jax.devices()[0]
    if size_name == "auto":
        size_name = "tiny" if device.platform == "cpu" else "full"
    size = dict(SIZES[size_name])
    if faces is not None:
        size["faces"] = tuple(faces)
    if steps is not None:
        size["steps"] = int(steps)
    load_before = os.getloadavg()
    t0 = time.time()
    report: dict[str, Any] = {
        "device": f"{device.platform} ({device.device_kind})",
        "devices": len(jax.devices()),
        "platform": device.platform,
        "size": size_name,
        "commit": commit(),
        "jax": jax.__version__,
        "cpu_count": os.cpu_count(),
        "load_before": [round(x, 2) for x in load_before],
        "training": [measure_training(p, size) for p in presets],
        "inference": [],
    }
    if inference:
        bundle = load_pretrained()
        report["inference_weights"] = {
            "file": pretrained_path().name,
            "sha256": file_hash(pretrained_path()),
        }
        report["inference"] = [measure_inference(n, size, bundle) for n in size["faces"]]
    report["load_after"] = [round(x, 2) for x in os.getloadavg()]
    report["wall_s"] = round(time.time() - t0, 1)
    write_report(report, Path(out_dir))
    return report


def markdown(r: dict[str, Any]) -> str:
    lines = [
        f"# Device benchmark: {r['device']}",
        "",
        f"Size `{r['size']}`, commit `{r['commit']}`, jax {r['jax']}, {r['cpu_count']} CPUs, "
        f"load {r['load_before'][0]:.1f} before / {r['load_after'][0]:.1f} after, "
        f"{r['wall_s']} s in all (`python -m experiments.device_bench`).",
        "",
        "| preset | width | batch | mesh vertices (padded) | first steps s | median step s "
        "| median step CPU s | steps/s | weights sha256 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for t in r["training"]:
        lines.append(
            f"| {t['preset']} | {t['width']} | {t['batch_size']} | {t['mesh_vertices']} "
            f"({t['padded_vertices']}) | {', '.join(f'{x:.2f}' for x in t['first_steps_s'])} "
            f"| {t['median_step_s']:.4f} | {t['median_step_cpu_s']:.4f} "
            f"| {t['steps_per_s']:.2f} | `{t['weights_sha256']}` |"
        )
    if r["inference"]:
        w = r["inference_weights"]
        lines += [
            "",
            f"Inference: `denoise` with the bundled weights `{w['file']}` (sha256 "
            f"`{w['sha256']}`).",
            "",
            "| faces | vertices | passes | first call s | median call s |",
            "|---|---|---|---|---|",
        ]
        for i in r["inference"]:
            lines.append(
                f"| {i['faces']:,} | {i['vertices']:,} | {i['passes']} | "
                f"{i['first_call_s']:.2f} | {i['median_s']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def write_report(report: dict[str, Any], out_dir: Path) -> Path:
    from dmd_jax.io import write_text_atomic

    out_dir.mkdir(parents=True, exist_ok=True)
    stem = report["platform"] + ("-tiny" if report["size"] == "tiny" else "")
    write_text_atomic(out_dir / f"{stem}.json", json.dumps(report, indent=2) + "\n")
    write_text_atomic(out_dir / f"{stem}.md", markdown(report))
    return out_dir / f"{stem}.md"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.device_bench", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--size", choices=("auto", "full", "tiny"), default="auto")
    parser.add_argument("--small", action="store_true", help="same as --size tiny")
    parser.add_argument("--presets", nargs="+", default=list(TRAIN_PRESETS))
    parser.add_argument("--faces", nargs="+", type=int, help="inference face counts")
    parser.add_argument("--steps", type=int, help="timed training steps (default: the size's)")
    parser.add_argument("--no-inference", action="store_true")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    report = run(
        "tiny" if args.small else args.size,
        presets=args.presets,
        faces=args.faces,
        steps=args.steps,
        inference=not args.no_inference,
        out_dir=args.out,
    )
    sys.stdout.write(markdown(report))
    ok = all(t["finite"] for t in report["training"]) and all(
        i["finite"] for i in report["inference"]
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
