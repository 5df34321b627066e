"""Timing, environment, test-mesh and report helpers shared by the benchmark scripts.

A library module, not a script: every script of `benchmarks/` (speed) and
`benchmarks/quality/` imports its shared helpers from here and never from another
script. Every report goes through `write_report`, whose header names the git commit
and the weights file (SHA-256) it was made with (`provenance`).

The machine these run on is shared and noisy, so the helpers favour robust statistics:
every case is warmed up (compiled) first, cases are timed round-robin (A, B, C, A, B,
C, ...) so that a burst of load hits all of them alike, and results are medians with the
interquartile range. Ratios between cases are only meaningful within one process.

Typical use::

    cases = {"mine": lambda: f(x), "reference": lambda: g(x)}
    timings = time_interleaved(cases, repeat=5)
    timings["mine"].median  # seconds
"""

from __future__ import annotations

import csv
import datetime as _dt
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"
REPO = Path(__file__).resolve().parents[1]
# `write_report(..., weights=BUNDLED)`: the report used the bundled weights.
BUNDLED = "bundled"


def block(value):
    """Waits for every JAX array in `value` (any pytree) and returns it; other leaves
    (NumPy arrays, floats) pass through."""
    import jax

    return jax.block_until_ready(value)


@dataclass(frozen=True)
class Timing:
    """The wall-clock times of the timed (not warm-up) calls of one case, in seconds."""

    times: tuple[float, ...]

    @property
    def n(self) -> int:
        return len(self.times)

    @property
    def median(self) -> float:
        return float(np.median(self.times))

    @property
    def q1(self) -> float:
        return float(np.percentile(self.times, 25))

    @property
    def q3(self) -> float:
        return float(np.percentile(self.times, 75))

    @property
    def iqr(self) -> float:
        return self.q3 - self.q1

    @property
    def min(self) -> float:
        return float(np.min(self.times))


def time_interleaved(
    cases: Mapping[str, Callable[[], object]],
    *,
    repeat: int = 5,
    warmup: int = 1,
    min_total_s: float = 0.0,
    max_repeat: int | None = None,
) -> dict[str, Timing]:
    """Times zero-argument callables round-robin and returns a `Timing` per case.

    Each call's result goes through `block` (so asynchronous JAX work is included);
    NumPy and SciPy calls are timed as they are.

    Args:
      cases: name -> callable; the order is the order inside a round.
      repeat: timed rounds (at least).
      warmup: untimed calls of each case first (compilation, caches, page faults).
      min_total_s: keep adding rounds while the timed rounds took less than this in
        total, so fast cases get more samples...
      max_repeat: ...up to this many rounds (default `repeat`, i.e. no extra rounds).

    Returns:
      name -> `Timing`, in the order of `cases`.
    """
    if repeat < 1 or warmup < 0:
        raise ValueError(f"need repeat >= 1 and warmup >= 0, got {repeat}, {warmup}")
    max_repeat = repeat if max_repeat is None else max(max_repeat, repeat)
    for fn in cases.values():
        for _ in range(warmup):
            block(fn())
    times: dict[str, list[float]] = {name: [] for name in cases}
    spent = 0.0
    rounds = 0
    while rounds < repeat or (spent < min_total_s and rounds < max_repeat):
        for name, fn in cases.items():
            start = time.perf_counter()
            block(fn())
            elapsed = time.perf_counter() - start
            times[name].append(elapsed)
            spent += elapsed
        rounds += 1
    return {name: Timing(tuple(t)) for name, t in times.items()}


def time_call(fn: Callable[[], object], *, repeat: int = 5, warmup: int = 1) -> Timing:
    """`time_interleaved` for a single case."""
    return time_interleaved({"case": fn}, repeat=repeat, warmup=warmup)["case"]


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _memory_gib() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                return f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except OSError:
        pass
    return "unknown"


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "not installed"


def _git(*args: str) -> str | None:
    try:
        return subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def _git_commit() -> str:
    return _git("rev-parse", "--short", "HEAD") or "unknown"


def _weights_file(weights) -> Path | None:
    """The weights file a report used: the bundled one for `BUNDLED`, else `weights`."""
    if weights == BUNDLED:
        from dmd_jax.checkpoints import pretrained_path

        return pretrained_path()
    return Path(weights)


def file_sha256(path, length: int = 12) -> str:
    """The first `length` hex digits of a file's SHA-256."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()[:length]


def provenance(weights=BUNDLED) -> str:
    """The line that says what a report was made with: commit and weights file.

    Args:
      weights: `BUNDLED` (the bundled weights), a weights file or checkpoint directory,
        or None for a report that used no trained weights.

    Returns:
      e.g. ``Made at commit `abc1234` with weights `dmd_small.msgpack` (SHA-256
      `0123456789ab`).``, with "(plus uncommitted changes)" after the commit when
      tracked files differed from it.
    """
    commit = f"`{_git_commit()}`"
    if _git("status", "--porcelain", "--untracked-files=no"):
        commit += " (plus uncommitted changes)"
    if weights is None:
        return f"Made at commit {commit}, with no trained weights."
    path = _weights_file(weights)
    name = ("bundled " if weights == BUNDLED else "") + f"`{path.name}`"
    if path.is_file():
        what = f"{name} (SHA-256 `{file_sha256(path)}`)"
    elif path.is_dir():
        what = f"{name} (a checkpoint directory)"
    else:
        what = f"{name} (missing)"
    return f"Made at commit {commit} with weights {what}."


def environment(packages: Sequence[str] = ("jax", "jaxlib", "numpy", "scipy")) -> dict[str, str]:
    """What a reader needs to compare two result files: hardware, load, versions, flags."""
    import jax

    env = {
        "date (UTC)": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M"),
        "git commit": _git_commit(),
        "nproc": str(
            len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        ),
        "CPU": _cpu_model(),
        "memory": _memory_gib(),
        "load average (1 min) at start": f"{os.getloadavg()[0]:.2f}",
        "python": platform.python_version(),
    }
    env.update({package: _version(package) for package in packages})
    env["JAX backend"] = f"{jax.default_backend()} ({', '.join(str(d) for d in jax.devices())})"
    env["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") or "(unset)"
    env["GLIBC_TUNABLES"] = os.environ.get("GLIBC_TUNABLES", "") or "(unset)"
    return env


def command_line() -> str:
    """The command that produced this run, for the report header."""
    script = Path(sys.argv[0])
    try:
        script = script.resolve().relative_to(REPO)
    except ValueError:
        pass
    return " ".join(["python", str(script), *sys.argv[1:]])


def format_ms(seconds: float | None) -> str:
    """Milliseconds with three significant digits; `—` for a missing value."""
    if seconds is None or not np.isfinite(seconds):
        return "—"
    ms = seconds * 1e3
    return f"{ms:.3g}" if ms < 1000 else f"{ms:.0f}"


def median(times: Sequence[float]) -> float:
    """The median of raw times (seconds), as `Timing.median`."""
    return float(np.median(times))


def format_timing(times: Timing | Sequence[float] | None) -> str:
    """`median (IQR)` in milliseconds of a `Timing` or of raw times; `—` for None."""
    if times is None:
        return "—"
    t = times if isinstance(times, Timing) else Timing(tuple(times))
    return f"{format_ms(t.median)} ({format_ms(t.iqr)})"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured markdown table; numeric-looking columns are right-aligned."""

    def numeric(col: int) -> bool:
        values = [str(r[col]) for r in rows if str(r[col]) not in ("", "—")]
        try:
            [float(v.rstrip("×")) for v in values]
        except ValueError:
            return False
        return bool(values)

    align = ["---:" if numeric(i) else "---" for i in range(len(headers))]
    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def write_text(path: Path, text: str) -> Path:
    """Writes `text` to `path` atomically (a finished file or none)."""
    from dmd_jax.io import write_text_atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, text)


def write_report(
    path: Path,
    *,
    title: str,
    env: Mapping[str, str],
    sections: Sequence[tuple[str, str]],
    intro: str = "",
    command: str | None = None,
    weights=BUNDLED,
) -> Path:
    """Writes a markdown report: title, provenance, intro, command, environment, sections.

    Args:
      path: the `.md` file.
      title: top-level heading.
      env: from `environment()` (plus anything benchmark-specific).
      sections: `(heading, markdown body)` pairs, in order.
      intro: a paragraph under the title.
      command: the command line (default: this process's).
      weights: the weights the report used, for its provenance line (`provenance`):
        `BUNDLED`, a path, or None for none.
    """
    parts = [f"# {title}", "", provenance(weights), ""]
    if intro:
        parts += [intro.strip(), ""]
    parts += ["```bash", command or command_line(), "```", ""]
    parts += [markdown_table(["", ""], [(k, v) for k, v in env.items()]), ""]
    for heading, body in sections:
        parts += [f"## {heading}", "", body.strip(), ""]
    return write_text(path, "\n".join(parts))


def write_csv(path: Path, headers: Sequence[str], rows: Sequence[Sequence[object]]) -> Path:
    """Writes raw results as CSV next to the report, for re-plotting without re-running."""
    from dmd_jax.io import atomic_write

    def write(tmp):
        with open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(headers)
            writer.writerows(rows)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, write, overwrite=True)


def plot_loglog(
    path: Path,
    panels: Sequence[tuple[str, Mapping[str, tuple[Sequence[float], Sequence[float]]]]],
    *,
    xlabel: str,
    ylabel: str,
    suptitle: str = "",
    reference_slope: float | None = 1.0,
    ncols: int | None = None,
) -> Path:
    """Log-log line plots, one panel per `(title, {label: (x, y)})`, written as PNG.

    Args:
      reference_slope: draw a dashed `y ∝ x^slope` guide through each panel's data (1 =
        linear scaling); None for no guide.
      ncols: panels per row (default: all in one row).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = len(panels) if ncols is None else ncols
    nrows = -(-len(panels) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 4.2 * nrows), squeeze=False)
    for ax in axes.ravel()[len(panels) :]:
        ax.set_visible(False)
    for ax, (title, series) in zip(axes.ravel(), panels, strict=False):
        all_x, all_y = [], []
        for label, (x, y) in series.items():
            keep = [(a, b) for a, b in zip(x, y, strict=True) if b is not None and np.isfinite(b)]
            if not keep:
                continue
            xs, ys = zip(*keep, strict=True)
            ax.plot(xs, ys, marker="o", label=label)
            all_x += xs
            all_y += ys
        if reference_slope is not None and all_x:
            x0, x1 = min(all_x), max(all_x)
            y0 = float(np.exp(np.median(np.log(all_y)))) / (np.sqrt(x0 * x1) ** reference_slope)
            ax.plot(
                [x0, x1],
                [y0 * x0**reference_slope, y0 * x1**reference_slope],
                "k--",
                lw=0.8,
                label=f"∝ n^{reference_slope:g}",
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout()
    from dmd_jax.io import atomic_write

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"), overwrite=True)
    plt.close(fig)
    return path


def available_gib() -> float:
    """`MemAvailable` of /proc/meminfo in GiB (inf where unknown)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable"):
                return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return float("inf")


def peak_rss_gib() -> float:
    """Peak resident memory of this process so far (Linux `ru_maxrss`), in GiB."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


# --------------------------------------------------------------------------------------
# Synthetic meshes and graphs of any size
# --------------------------------------------------------------------------------------


def grid_faces(n_target: int) -> tuple[np.ndarray, int]:
    """A `side × side` triangulated grid with `side = round(sqrt(n_target))`.

    Every quad is split along the same diagonal, so interior vertices have valence 6
    (the regular-mesh average) and vertices are numbered row by row, as a scanned or
    remeshed surface usually is.

    Returns:
      `([n_face, 3] int64 faces, n_vertex)`.
    """
    side = max(int(round(np.sqrt(n_target))), 2)
    idx = np.arange(side * side, dtype=np.int64).reshape(side, side)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return faces, side * side


def gcn_edges(faces: np.ndarray, n_vertex: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The primal graph of `build_mesh_graph`: senders, receivers (sorted) and weights.

    The same edges and weights as `build_mesh_graph(faces, n_vertex).vertex_*` (the smoke
    test checks), without the dual graph and with a sort-based deduplication: NumPy 2.4's
    `np.unique` took 24 s for 6M keys here, `np.sort` under 1 s.

    Returns:
      `(senders [e] int32, receivers [e] int32, weights [e] float32)`, self loops included.
    """
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    loops = np.arange(n_vertex, dtype=np.int64)
    r = np.concatenate([e[:, 0], e[:, 1], loops])
    s = np.concatenate([e[:, 1], e[:, 0], loops])
    key = np.sort(r * n_vertex + s)
    key = key[np.concatenate([[True], key[1:] != key[:-1]])]
    r, s = np.divmod(key, n_vertex)
    degree = np.bincount(r, minlength=n_vertex).astype(np.float64)
    weight = 1.0 / np.sqrt(degree[s] * degree[r])
    return s.astype(np.int32), r.astype(np.int32), weight.astype(np.float32)


def noisy_grid(n_face: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A noisy wavy height field of about `n_face` faces.

    Returns:
      `(vertices float64 [n, 3], faces int32 [f, 3])`, `f = 2 (side - 1)²`.
    """
    side = max(int(round(np.sqrt(n_face / 2.0))) + 1, 2)
    faces, n_vertex = grid_faces(side * side)
    t = np.linspace(0.0, 1.0, side)
    x, y = (a.ravel() for a in np.meshgrid(t, t, indexing="ij"))
    z = 0.1 * np.sin(3 * np.pi * x) * np.sin(2 * np.pi * y)
    v = np.stack([x, y, z], axis=1)
    spacing = 1.0 / (side - 1)
    v += np.random.default_rng(seed).normal(scale=0.2 * spacing, size=v.shape)
    assert v.shape[0] == n_vertex
    return v, faces.astype(np.int32)
