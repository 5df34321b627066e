"""Compiling the whole-mesh programs of every mesh size before any mesh is seen.

The whole-mesh path pads a mesh to a rung of `dmd_jax.shape_ladder`, so the programs
that meshes of any size need are known in advance. `warm_up` compiles each rung's
network program for a model (or loads it, when the on-disk cache of
`dmd_jax.compile_cache` has it) and the memory plan's measurement of the network
(`memory_plan.network_bytes_per_vertex`), so that a later process, on a mesh of any
size in the range, loads its program instead of compiling it. `dmd-jax warmup` runs it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from dmd_jax import shape_ladder

# The default range of `dmd-jax warmup`: 1k to 1M faces (55 rungs).
DEFAULT_MIN_FACES = 1_000
DEFAULT_MAX_FACES = 1_000_000
# Bytes one stored whole-mesh program of the bundled network takes in the cache (2.0 MB
# measured at 41k and 45k padded vertices; the size hardly depends on the rung), with room.
PROGRAM_BYTES = int(2.5 * 2**20)


class Warmed(NamedTuple):
    """One program `warm_up` made ready.

    Attributes:
      rung: padded vertices.
      widths: `(vertex, face)` neighbour-table widths (None: no table).
      seconds: wall time to compile or load it.
      compiled: True if compiled here, False if loaded from the cache (or already in
        this process).
      update: the vertex update the program runs.
    """

    rung: int
    widths: tuple
    seconds: float
    compiled: bool
    update: str = ""


def warm_up(
    bundle=None,
    *,
    min_faces: int = DEFAULT_MIN_FACES,
    max_faces: int = DEFAULT_MAX_FACES,
    layouts=(shape_ladder.STANDARD_WIDTHS,),
    jobs: int = 1,
    report: Callable[[Warmed], None] | None = None,
) -> list[Warmed]:
    """Compiles (or loads) the whole-mesh program of every rung from `min_faces` to
    `max_faces` faces, for each table layout of `layouts` and each vertex update a
    default call may run (`ModelBundle.vertex_updates`: two when the weights carry a
    smoothing controller whose options use both).

    Args:
      bundle: a `ModelBundle` (default: the bundled weights).
      min_faces, max_faces: the face counts to cover (`shape_ladder.rungs_between`).
      layouts: `(vertex, face)` table widths to compile each rung for
        (`shape_ladder.LAYOUTS` adds the high-valence one).
      jobs: programs compiled at once (threads; XLA compiles outside the GIL).
      report: called with each `Warmed` as it finishes.

    Returns:
      A `Warmed` per program, in ladder order (for each rung and layout, one per update).

    Raises:
      ValueError: a bad range or `jobs`, a cache that is off or refused, or more
        programs than its bound holds.
    """
    import jax

    from dmd_jax import compile_cache
    from dmd_jax.checkpoints import as_bundle
    from dmd_jax.forward import predictor
    from dmd_jax.memory_plan import network_bytes_per_vertex

    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    rungs = shape_ladder.rungs_between(int(min_faces), int(max_faces))
    settings = compile_cache.settings()
    if compile_cache.store() is None:
        raise ValueError(
            "the compilation cache is off or refused (see the warning above, "
            f"{compile_cache.ENV}): a warm-up would compile programs no later process "
            "can load"
        )
    bundle = as_bundle(bundle)
    # One program per vertex update a default call may run (a controller's options may
    # run another update than the config's: each is its own program).
    updates = bundle.vertex_updates()
    n_programs = len(rungs) * len(layouts) * len(updates)
    need = n_programs * PROGRAM_BYTES
    if need > settings.max_bytes:
        raise ValueError(
            f"{n_programs} programs take about {need / 2**20:.0f} MiB, more "
            f"than the cache holds ({settings.max_bytes / 2**20:.0f} MiB): the first would "
            f"be evicted by the last; raise {compile_cache.ENV_MAX_MB} or narrow the range"
        )
    programs = [(u, predictor(bundle.with_vertex_update(u).config)) for u in updates]
    # The memory plan's measurement (a small compile of its own), kept on disk too.
    network_bytes_per_vertex(bundle.config.model)

    def one(task) -> Warmed:
        rung, widths, (update, program) = task
        # As `inference` passes them: float32 positions, the padded graph's arrays.
        noisy = jax.ShapeDtypeStruct((rung, 3), np.float32)
        graph = shape_ladder.abstract_graph(rung, widths)
        start = time.perf_counter()
        how = program.prepare(bundle.params, noisy, graph)
        seconds = time.perf_counter() - start
        out = Warmed(rung, tuple(widths), seconds, how == "compiled", update)
        if report is not None:
            report(out)
        return out

    tasks = [(r, tuple(w), p) for r in rungs for w in layouts for p in programs]
    if jobs == 1:
        return [one(t) for t in tasks]
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(one, tasks))
