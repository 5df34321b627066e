"""The smoothing controller's training set: generated noisy meshes and, for each, the
error of every amount of smoothing.

How much to smooth (Laplacian pre-smoothing steps, network passes, the vertex update)
is a choice per mesh that the controller (`dmd_jax.controller`) learns from examples.
Each example is a clean mesh from the training split (procedural shapes, patches of
the real training meshes, the stress shapes; never the real validation split, never
the public test meshes), one draw of one noise kind, the controller's statistics of the
noisy mesh (`controller_features.features`) and a search: the mean face-normal error
after `p` pre-smoothing steps and `k` network passes with either vertex update, for
every `p` of `PRESMOOTH_GRID` and `k` from 0 to `SEARCH_PASSES` (one run of
`SEARCH_PASSES` passes gives every pass count).

Every example is a pure function of `(seed, index)` and the sources, written as one
`.npz` (`examples/NNNNN.npz`: `features`, `features_version`, `errors [n_presmooth,
n_update, passes + 1]`, `spec` as JSON): a build resumes where it stopped, and two builds
agree file by file.

From index `TRIANGULATION_FROM` on, half the examples also re-triangulate their clean
crop (`TRIANGULATIONS`: tangentially jittered, decimated, stretched or coarse), so the
controller sees irregular triangulations clean and noisy; the examples below that index
were built before and keep their meshes' own triangulation (their specs have no
`triangulation` field and regenerate exactly).

When the statistics change (`controller_features.FEATURES_VERSION`), `--refeature`
recomputes them for every example from its regenerated noisy mesh (about 0.1 s each)
instead of redoing the search (10-15 s each); `load` refuses a set whose examples carry
statistics of another version.

The search runs every option as `denoise` runs it, holding the vertices `denoise` holds
(`held_vertices`: a CAD part's flat vertices under impulse noise, a clean part's).
Examples searched before that (`SEARCH_VERSION` 1) are refused by `load`; `--research`
redoes the search of those with held vertices (about a fifth) and stamps the others.

    python -m dmd_jax.data.smoothing_set --out data/smoothing --examples 2000
    python -m dmd_jax.data.smoothing_set --out data/smoothing --refeature
    python -m dmd_jax.data.smoothing_set --out data/smoothing --research
    python -m dmd_jax.data.smoothing_set --out data/smoothing_m --from data/smoothing \\
        --network runs/long/ft/milestones/step_030000/weights.msgpack   # another network
    python -m dmd_jax.data.smoothing_set --out data/smoothing_m --examples 2000 \\
        --network runs/long/ft/milestones/step_030000/weights.msgpack   # built for it

A set searched for another network (`search_with`: a long run's milestone) keeps every
example's statistics and spec and records the network's digest (`network`); `load`
refuses a set that mixes networks. `build` with `network` writes the same examples
searched for that network directly, when no bundled-network set is at hand.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

PRESMOOTH_GRID = (0, 3, 8, 20)
# The search's version: 2 holds the vertices `denoise` holds (`held_vertices`), as every
# option runs in `denoise`; version 1 (examples without the field) moved them, so its
# errors differ from `denoise`'s on CAD parts under impulse noise and on clean flat parts
# (`cgal_boeing` under impulse: 2 passes best at 11.38° without, 4 at 8.93° with).
SEARCH_VERSION = 2
SEARCH_PASSES = 8
UPDATES = ("jacobi", "solve")
# Noise kinds and their share of the examples.
KINDS = {
    "gaussian_normal": 0.22,
    "gaussian_iso": 0.12,
    "impulse": 0.08,
    "scanner": 0.22,
    "scan": 0.16,
    "fine": 0.12,
    "clean": 0.08,
}
# Re-triangulations of the clean crop and their share (examples from TRIANGULATION_FROM
# on; a simulated scan resamples the surface itself and keeps "given"). A real mesh's
# irregular triangulation gives the umbrella displacement a tangential part that the
# first set, all near-regular, never showed the controller (common3d_ogre in
# benchmarks/results/controller_val.md).
TRIANGULATIONS = {
    "given": 0.5,  # the source's own triangulation
    "jitter": 0.15,  # vertices moved within their tangent planes: irregular, same surface
    "decimated": 0.15,  # quadric edge collapse of a larger crop: sizes follow curvature
    "anisotropic": 0.1,  # stretched along one axis: long thin triangles
    "coarse": 0.1,  # decimated to 80-300 faces: a coarse CAD-like part
}
# Every example of the first build (indices 0-1575 written, seed 0) is below this index.
TRIANGULATION_FROM = 1576
# Patch sizes: the search runs one compiled program per padded size, so examples are
# crops of about this many faces (the controller's statistics are per-area, not totals).
PATCH_FACES = (400, 1200)


# Whole meshes: from index WHOLE_FROM on, an example is a crop of WHOLE_FACES faces (log-
# uniform), the size of a validation mesh, read by the controller as `decide` reads a
# large mesh (`crop_statistics`). The best amount of smoothing of a whole mesh is not that
# of its small pieces: on 10 real training meshes under Gaussian noise of 0.2 edges, the
# 15,000-face crop wanted one pass on 8, its 400-1200-face pieces 2-4 passes on half.
WHOLE_FROM = 10_000
WHOLE_FACES = (2_000, 15_000)

# Heavy noise: from index HEAVY_FROM on, every example carries per-coordinate noise of
# HEAVY_LEVELS mean edges (log-uniform), of one of the paper's kinds (HEAVY_KINDS), on a
# small crop. The kinds above stop at 0.6 edges of Gaussian noise; the paper's Table II
# goes to about 2.7, and there the controller trained without these chose too little
# (Block: none, 88.68 deg, where the fallback rules' 20 pre-smoothing steps give 18.38;
# docs/controller.md, "Limits").
HEAVY_FROM = 20_000
HEAVY_LEVELS = (0.6, 3.0)
HEAVY_KINDS = ("gaussian", "uniform", "gamma")


def example_spec(seed: int, index: int, sources: dict[str, int]) -> dict:
    """What example `index` is: a pure function of `(seed, index)` and the source counts.

    Args:
      seed: the set's seed.
      index: the example's number.
      sources: how many meshes each source has (`{"procedural": n, "real": n, "stress": n}`).

    Returns:
      A JSON-able dict: source, mesh, patch seed and size, noise kind and its parameters,
      and the noise seed.
    """
    rng = np.random.default_rng([seed, index])
    names = [k for k in ("procedural", "real", "stress") if sources.get(k)]
    weights = np.array([{"procedural": 0.45, "real": 0.45, "stress": 0.10}[k] for k in names])
    source = names[int(rng.choice(len(names), p=weights / weights.sum()))]
    kinds = list(KINDS)
    kind = kinds[int(rng.choice(len(kinds), p=np.array(list(KINDS.values()))))]
    spec = {
        "index": index,
        "source": source,
        "mesh": int(rng.integers(sources[source])),
        "patch_faces": int(rng.integers(*PATCH_FACES)),
        "patch_seed": int(rng.integers(2**31)),
        "kind": kind,
        "noise_seed": int(rng.integers(2**31)),
    }
    if kind in ("gaussian_normal", "gaussian_iso"):
        spec["level"] = float(np.exp(rng.uniform(np.log(0.05), np.log(0.6))))
    elif kind == "impulse":
        spec["level"] = float(rng.uniform(0.3, 1.0))
    elif kind in ("scanner", "scan", "fine"):
        # Real depth-camera noise is correlated over 4-16 rings: vary the scanner model
        # widely rather than train on its defaults alone.
        spec["level"] = float(rng.uniform(0.03, 0.15) if kind == "fine" else rng.uniform(0.2, 1.0))
        spec["correlation_length"] = float(np.exp(rng.uniform(np.log(2.0), np.log(16.0))))
        spec["white_share"] = float(rng.uniform(0.02, 0.4))
        spec["grazing_max_gain"] = float(rng.uniform(1.0, 3.0))
        spec["spike_share"] = float(rng.choice([0.0, 0.001, 0.005]))
        if kind == "scan":
            spec["resolution"] = int(rng.choice([40, 48, 64]))
    if index >= TRIANGULATION_FROM:
        # A stream of its own: the draws above stay those of the first build.
        spec["triangulation"] = triangulation_spec(np.random.default_rng([seed, index, 1]))
        if kind == "scan":
            spec["triangulation"] = {"kind": "given"}
    if index >= HEAVY_FROM:
        # A stream of its own: the mesh, crop and seeds are what the index draws anyway;
        # the drawn kind's own parameters (and any re-triangulation) do not apply.
        heavy = np.random.default_rng([seed, index, 3])
        base = ("index", "source", "mesh", "patch_faces", "patch_seed", "noise_seed")
        return {
            **{key: spec[key] for key in base},
            "kind": "heavy",
            "noise": HEAVY_KINDS[int(heavy.integers(len(HEAVY_KINDS)))],
            "level": float(np.exp(heavy.uniform(*np.log(HEAVY_LEVELS)))),
        }
    if index >= WHOLE_FROM:
        lo, hi = np.log(WHOLE_FACES[0]), np.log(WHOLE_FACES[1])
        spec["patch_faces"] = int(np.exp(np.random.default_rng([seed, index, 2]).uniform(lo, hi)))
        spec["whole"] = True
    return spec


def triangulation_spec(rng: np.random.Generator) -> dict:
    """One draw of `TRIANGULATIONS` and its parameters (JSON-able)."""
    names = list(TRIANGULATIONS)
    kind = names[int(rng.choice(len(names), p=np.array(list(TRIANGULATIONS.values()))))]
    out: dict = {"kind": kind, "seed": int(rng.integers(2**31))}
    if kind == "jitter":
        out["sigma"] = float(rng.uniform(0.1, 0.35))  # mean edges, per tangent axis
    elif kind == "decimated":
        out["keep"] = float(rng.uniform(0.2, 0.5))  # faces kept of a crop 1/keep larger
    elif kind == "anisotropic":
        out["stretch"] = float(np.exp(rng.uniform(np.log(1.5), np.log(4.0))))
        out["axis"] = [float(a) for a in rng.standard_normal(3)]
    elif kind == "coarse":
        out["faces"] = int(rng.integers(80, 300))
    return out


def retriangulate(vertices, faces, spec: dict) -> tuple[np.ndarray, np.ndarray]:
    """A clean crop re-triangulated as `spec["triangulation"]` says (the ground truth
    of the example is the result: a clean mesh with another triangulation).

    Args:
      vertices: `[m, 3]` float64 clean crop (for "decimated", a crop `1/keep` larger).
      faces: `[k, 3]`.
      spec: the example's spec.

    Returns:
      `(vertices [m', 3] float64, faces [k', 3] int32)`.
    """
    from dmd_jax.data.repair import decimate

    t = spec.get("triangulation", {"kind": "given"})
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if t["kind"] == "jitter":
        from dmd_jax.controller_features import _vertex_normals

        edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        mean_edge = float(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1).mean())
        n = _vertex_normals(v, f)
        move = np.random.default_rng(t["seed"]).standard_normal(v.shape) * t["sigma"] * mean_edge
        move -= np.sum(move * n, axis=1, keepdims=True) * n  # tangential: the surface stays
        v = v + move
    elif t["kind"] == "decimated":
        v, f = decimate(v, f, spec["patch_faces"])
    elif t["kind"] == "coarse":
        v, f = decimate(v, f, t["faces"])
    elif t["kind"] == "anisotropic":
        a = np.asarray(t["axis"], np.float64)
        a /= np.linalg.norm(a)
        v = v + (t["stretch"] - 1.0) * (v @ a)[:, None] * a
    return np.asarray(v, np.float64), np.asarray(f, np.int32)


def scanner_model(spec: dict):
    """The `ScannerModel` of a spec's scanner, scan or fine noise."""
    from dmd_jax.scanner_model import ScannerModel

    return ScannerModel(
        correlation_length=spec["correlation_length"],
        white_share=spec["white_share"],
        grazing_max_gain=spec["grazing_max_gain"],
        spike_share=spec["spike_share"],
    )


def noisy_example(spec: dict, clean: np.ndarray, faces: np.ndarray):
    """`(clean, noisy, faces)` of a spec, from its clean crop.

    A scan replaces the crop by what a simulated depth camera sees of it (its own
    clean surface points, faces and holes).
    """
    from dmd_jax import add_noise, noise
    from dmd_jax.scan import simulate_scan

    kind, seed = spec["kind"], spec["noise_seed"]
    if kind == "clean":
        return clean, clean.copy(), faces
    if kind == "gaussian_normal":
        return (
            clean,
            add_noise(
                seed, clean, faces, "gaussian", spec["level"], units="edge", direction="normal"
            ),
            faces,
        )
    if kind == "gaussian_iso":
        return clean, add_noise(seed, clean, faces, "gaussian", spec["level"], units="edge"), faces
    if kind == "impulse":
        return clean, add_noise(seed, clean, faces, "impulse", spec["level"], units="edge"), faces
    if kind == "heavy":
        return (
            clean,
            add_noise(seed, clean, faces, spec["noise"], spec["level"], units="edge"),
            faces,
        )
    model = scanner_model(spec)
    if kind == "scan":
        # A view that sees nothing (a thin part edge-on) is refused by simulate_scan:
        # the next seeds draw other views, deterministically.
        for attempt in range(8):
            try:
                scan = simulate_scan(
                    seed + attempt,
                    clean,
                    faces,
                    resolution=spec["resolution"],
                    level=spec["level"],
                    model=model,
                )
            except ValueError:
                continue
            if len(scan.faces) >= 100:
                return scan.clean, scan.noisy, scan.faces
        raise ValueError(f"example {spec['index']}: no view of its mesh gives a scan")
    import jax

    noisy = noise.scanner_noise(
        jax.random.PRNGKey(seed), clean, faces, spec["level"], units="edge", model=model
    )
    return clean, noisy, faces


class Sources:
    """The clean meshes examples are cut from: procedural training meshes, the real
    training split, the stress shapes (loaded on first use, kept)."""

    def __init__(self, dataset_dir=None, real_root=None):
        self.dataset_dir, self.real_root = dataset_dir, real_root
        self._procedural = self._real = None
        from dmd_jax.data.stress import stress_shapes

        self._stress = list(stress_shapes().values())

    def counts(self) -> dict[str, int]:
        out = {"stress": len(self._stress)}
        if self.dataset_dir is not None:
            out["procedural"] = len(self._procedural_records())
        if self.real_root is not None:
            out["real"] = len(self._real_files())
        return out

    def _procedural_records(self):
        if self._procedural is None:
            from dmd_jax.data.store import load_dataset

            self._procedural = load_dataset(self.dataset_dir).split("train")
        return self._procedural

    def _real_files(self):
        if self._real is None:
            from dmd_jax.data.real import mesh_files

            self._real = mesh_files(self.real_root, "train")
        return self._real

    def mesh(self, spec: dict) -> tuple[np.ndarray, np.ndarray]:
        """The clean crop of a spec, re-triangulated as it says (`retriangulate`):
        `(vertices [m, 3] float64, faces [k, 3] int32)`."""
        t = spec.get("triangulation", {"kind": "given"})
        if t["kind"] == "decimated":
            # A crop 1/keep larger, decimated back to the spec's size.
            larger = {**spec, "patch_faces": int(spec["patch_faces"] / t["keep"])}
            v, f = self._crop(larger)
        else:
            v, f = self._crop(spec)
        return retriangulate(v, f, spec)

    def _crop(self, spec: dict) -> tuple[np.ndarray, np.ndarray]:
        from dmd_jax.data.real import patch_mesh
        from dmd_jax.data.stress import subdivide

        source, i = spec["source"], spec["mesh"]
        if source == "stress":
            v, f = self._stress[i]
            v, f = np.asarray(v, np.float64), np.asarray(f, np.int32)
            while len(f) < spec["patch_faces"] // 2:
                v, f = subdivide(v, f, 1)
            return np.asarray(v, np.float64), np.asarray(f, np.int32)
        if source == "procedural":
            record = self._procedural_records()[i]
            v, f = record.load()
        else:
            from dmd_jax.io import load_mesh

            v, f = load_mesh(self._real_files()[i])
        v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
        if len(f) <= spec["patch_faces"]:
            return v, f.astype(np.int32)
        seed_face = spec["patch_seed"] % len(f)
        return patch_mesh(v, f, seed_face, spec["patch_faces"])


def held_vertices(noisy, faces) -> np.ndarray:
    """`[n_vertex]` bool: the vertices `denoise` holds where they are in `noisy`
    (`consistency.exact_vertices` in its pre-normalised frame, and the still vertices):
    all False on a mesh noisy everywhere; a share of a CAD part's flat vertices under
    impulse noise, which leaves most vertices exactly in their planes.

    Args:
      noisy: `[n_vertex, 3]` float64, every vertex referenced.
      faces: `[n_face, 3]`.
    """
    from dmd_jax.consistency import exact_tolerance, exact_vertices, oriented_faces, still_vertices
    from dmd_jax.inference import _prenormalised

    v, f = np.asarray(noisy, np.float64), np.asarray(faces)
    f, _ = oriented_faces(f, v.shape[0])
    x, _, _ = _prenormalised(v)
    return exact_vertices(x, f, exact_tolerance(np.float64, v, f)) | still_vertices(v, f)


def crop_statistics(noisy, faces) -> np.ndarray:
    """`[C, N_FEATURES]`: the statistics of the crops `controller.decide` reads of this
    mesh as `denoise` gives it to it (consistently wound; one crop, the whole mesh, when
    it is small), so a whole mesh's example trains the controller as it is used."""
    from dmd_jax.consistency import oriented_faces
    from dmd_jax.controller_features import crops, features

    v = np.asarray(noisy, np.float64)
    f, _ = oriented_faces(np.asarray(faces), v.shape[0])
    return np.array([features(a, b) for a, b in crops(v, f)])


def pass_errors(noisy, clean, faces, bundle, held=None) -> np.ndarray:
    """The mean face-normal error (degrees) of every setting of the search, each run as
    `denoise` runs it.

    Args:
      noisy: `[n_vertex, 3]` the noisy mesh.
      clean: `[n_vertex, 3]` its ground truth.
      faces: `[n_face, 3]`.
      bundle: the network (`ModelBundle`).
      held: `[n_vertex]` bool, the vertices `denoise` holds (`held_vertices`; None:
        computed here): put back after the pre-smoothing and after every pass.

    Returns:
      `(errors, first)`: `[len(PRESMOOTH_GRID), len(UPDATES), SEARCH_PASSES + 1]`
      float64, entry `[p, u, k]` after `PRESMOOTH_GRID[p]` Laplacian steps and `k`
      passes with update `UPDATES[u]` (`k = 0`: the pre-smoothed mesh itself); and
      `pass_change` of the first pass on the mesh as given (`[2]`).
    """
    from dmd_jax.inference import network_passes
    from dmd_jax.metrics import face_normal_errors_deg
    from dmd_jax.presmooth import laplacian_steps

    def error(x):
        return float(np.mean(face_normal_errors_deg(x, clean, faces)))

    noisy = np.asarray(noisy, np.float64)
    held = held_vertices(noisy, faces) if held is None else np.asarray(held, bool)
    out = np.empty((len(PRESMOOTH_GRID), len(UPDATES), SEARCH_PASSES + 1))
    bundles = [bundle.with_vertex_update(u) for u in UPDATES]
    x, done = noisy, 0
    first = None
    for p, steps in enumerate(PRESMOOTH_GRID):
        # Each level continues the previous one's steps; the held vertices are put back
        # only in the copy the passes start from (`denoise` smooths, then puts back).
        x = laplacian_steps(x, faces, steps - done)
        done = steps
        start = x.copy()
        start[held] = noisy[held]
        for u, b in enumerate(bundles):
            out[p, u, 0] = error(start)
            passes = network_passes(start, faces, b, SEARCH_PASSES, held=held)
            for k, y in enumerate(passes, 1):
                out[p, u, k] = error(y)
                if first is None:
                    first = pass_change(start, y, faces)
    return out, first


def pass_change(before, after, faces) -> np.ndarray:
    """How much one network pass changed a mesh: `[2]`, the mean vertex move in mean
    edges of `before` and the mean angle (degrees) between the face normals before and
    after (a statistic the controller may read: `denoise` runs that pass anyway)."""
    from dmd_jax.metrics import face_normal_errors_deg

    f = np.asarray(faces, np.int64)
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    mean_edge = float(np.linalg.norm(before[edges[:, 0]] - before[edges[:, 1]], axis=1).mean())
    move = float(np.linalg.norm(after - before, axis=1).mean()) / max(mean_edge, 1e-300)
    return np.array([move, float(np.mean(face_normal_errors_deg(after, before, faces)))])


def build(
    out,
    n_examples: int,
    *,
    seed: int = 0,
    sources: Sources,
    bundle=None,
    shard: tuple[int, int] = (0, 1),
    first: int = 0,
    network=None,
    say=print,
) -> int:
    """Writes examples `first .. n_examples-1` that `out/examples/` lacks; returns how
    many it wrote. Each is written whole or not at all (a stopped build resumes).

    `shard=(k, n)` writes only the examples whose index is `k` modulo `n` (one process
    per core, each its own shard); `first` skips the indices below it (a build that
    writes the newest examples first; a later build without it fills the gaps).
    `network` (a weights file: a long run's milestone) searches with that network
    instead of the bundled one and records its digest in the manifest and every example,
    as `search_with` does: the same examples, built without a bundled-network set first.
    """
    from dmd_jax import denoise, load_pretrained
    from dmd_jax.checkpoints import load_model
    from dmd_jax.controller_features import FEATURES_VERSION, features
    from dmd_jax.io._files import atomic_write, write_text_atomic
    from dmd_jax.metrics import face_normal_errors_deg

    out = Path(out)
    (out / "examples").mkdir(parents=True, exist_ok=True)
    if network is not None:
        bundle, digest = load_model(network), network_digest(network)
    bundle = load_pretrained() if bundle is None else bundle
    counts = sources.counts()
    manifest = {
        "seed": seed,
        "sources": counts,
        "presmooth_grid": PRESMOOTH_GRID,
        "updates": UPDATES,
        "search_passes": SEARCH_PASSES,
        "kinds": KINDS,
        "triangulations": TRIANGULATIONS,
        "triangulation_from": TRIANGULATION_FROM,
        "whole_from": WHOLE_FROM,
        "whole_faces": WHOLE_FACES,
        "heavy_from": HEAVY_FROM,
        "heavy_levels": HEAVY_LEVELS,
        "heavy_kinds": HEAVY_KINDS,
    }
    if network is not None:
        manifest["network"] = digest
    check_manifest(out, manifest)
    write_text_atomic(out / "manifest.json", json.dumps(manifest, indent=2))
    written, t0 = 0, time.time()
    start = shard[0] + max(first - shard[0] + shard[1] - 1, 0) // shard[1] * shard[1]
    for index in range(start, n_examples, shard[1]):
        path = out / "examples" / f"{index:05d}.npz"
        if path.exists():
            continue
        spec = example_spec(seed, index, counts)
        clean, faces = sources.mesh(spec)
        try:
            clean, noisy, faces = noisy_example(spec, clean, faces)
        except ValueError as err:
            say(f"skipped: {err}")
            continue
        feats = features(noisy, faces)
        crop_feats = crop_statistics(noisy, faces)
        held = held_vertices(noisy, faces)
        errors, first_pass = pass_errors(noisy, clean, faces, bundle, held)
        # Today's default call, for the controller's report (its gain over the default).
        default = float(
            np.mean(face_normal_errors_deg(denoise(noisy, faces, bundle), clean, faces))
        )

        fields = dict(
            features=feats,
            crop_features=crop_feats,
            features_version=FEATURES_VERSION,
            errors=errors,
            search_version=SEARCH_VERSION,
            held_vertices=int(held.sum()),
            first_pass=first_pass,
            default_error=default,
            spec=json.dumps(spec),
            n_faces=len(faces),
            noisy_digest=mesh_digest(noisy, faces),
        )
        if network is not None:
            fields["network"] = digest

        def write(tmp, fields=fields):
            with open(tmp, "wb") as fh:
                np.savez(fh, **fields)

        atomic_write(path, write, overwrite=False)
        written += 1
        if written % 10 == 0:
            say(
                f"{index + 1}/{n_examples} examples, {written} this run, "
                f"{(time.time() - t0) / written:.2f} s each"
            )
    return written


# Manifest fields added after the first build: a set built before them is the same set
# (its examples all lie below TRIANGULATION_FROM, where the re-triangulation is off).
_ADDED_FIELDS = (
    "triangulations",
    "triangulation_from",
    "whole_from",
    "whole_faces",
    "heavy_from",
    "heavy_levels",
    "heavy_kinds",
)


def check_manifest(out, manifest: dict) -> None:
    """Raises `ValueError` if `out` holds a set built with other settings."""
    path = Path(out) / "manifest.json"
    if not path.is_file():
        return
    old, new = json.loads(path.read_text()), json.loads(json.dumps(manifest))
    for key in _ADDED_FIELDS:
        if key not in old:
            new.pop(key, None)
    if old != new:
        raise ValueError(f"{out} holds a set built with other settings (manifest.json)")


def mesh_digest(vertices, faces) -> str:
    """SHA-1 of a mesh's float32 positions and faces: that a regenerated example is the
    one that was searched (`refeature`)."""
    h = hashlib.sha1(np.ascontiguousarray(vertices, np.float32).tobytes())
    h.update(np.ascontiguousarray(faces, np.int32).tobytes())
    return h.hexdigest()


def _example_files(out) -> list[Path]:
    # Not a build's temporary files (".NAME.xxx.npz", renamed into place when whole).
    return sorted(p for p in Path(out, "examples").glob("*.npz") if not p.name.startswith("."))


def _features_version(z) -> int:
    # Examples written before the field existed carry the first statistics.
    return int(z["features_version"]) if "features_version" in z.files else 1


def _search_version(z) -> int:
    # Examples written before the field existed were searched without held vertices.
    return int(z["search_version"]) if "search_version" in z.files else 1


def load(out) -> dict:
    """A built set as arrays: `features [n, N_FEATURES]`, `errors [n, P, U, K + 1]`,
    `first_pass [n, 2]`, `default_error [n]`, `specs` (a list of dicts), and the
    statistics of the crops the controller reads of each mesh, `crop_features [n, C,
    N_FEATURES]` with `crop_mask [n, C]` (an example stored without them, a small crop,
    is read whole: its `features`).

    Raises:
      ValueError: an example's statistics are of another `FEATURES_VERSION` than this
        dmd_jax computes (run `--refeature`), or its search of another `SEARCH_VERSION`
        (run `--research`), so stale statistics or targets are never mixed in.
    """
    from dmd_jax.controller_features import FEATURES_VERSION

    files = _example_files(out)
    out = {"features": [], "errors": [], "first_pass": [], "default_error": [], "specs": []}
    stale, unsearched, crops, networks = [], [], [], set()
    for path in files:
        with np.load(path) as z:
            networks.add(_network(z))
            if _features_version(z) != FEATURES_VERSION:
                stale.append(path.name)
            if _search_version(z) != SEARCH_VERSION:
                unsearched.append(path.name)
            for key in ("features", "errors", "first_pass", "default_error"):
                out[key].append(z[key])
            out["specs"].append(json.loads(str(z["spec"])))
            crops.append(z["crop_features"] if "crop_features" in z.files else z["features"][None])
    if stale:
        raise ValueError(
            f"{len(stale)} examples (e.g. {stale[0]}) carry statistics of another version than "
            f"{FEATURES_VERSION}: python -m dmd_jax.data.smoothing_set --out "
            f"{files[0].parents[1]} --refeature"
        )
    if unsearched:
        raise ValueError(
            f"{len(unsearched)} examples (e.g. {unsearched[0]}) were searched by another "
            f"version than {SEARCH_VERSION}: python -m dmd_jax.data.smoothing_set --out "
            f"{files[0].parents[1]} --research"
        )
    if len(networks) > 1:
        raise ValueError(
            f"{files[0].parents[1]} mixes searches of several networks: {sorted(networks)}"
        )
    out = {k: v if k == "specs" else np.array(v) for k, v in out.items()}
    out["network"] = networks.pop() if networks else BUNDLED_NETWORK
    width = max((len(c) for c in crops), default=1)
    out["crop_features"] = np.zeros((len(crops), width, out["features"].shape[-1]))
    out["crop_mask"] = np.zeros((len(crops), width), bool)
    for i, c in enumerate(crops):
        out["crop_features"][i, : len(c)] = c
        out["crop_mask"][i, : len(c)] = True
    return out


def refeature(out, *, sources: Sources, verify=None, say=print) -> dict:
    """Recomputes the statistics of every example whose `features_version` is not
    today's, from its regenerated noisy mesh (the search is kept: it does not depend on
    the statistics). Each file is rewritten whole.

    An example whose regenerated mesh is not the one that was searched (its stored
    digest, or for examples written before digests its face count, differs: a scan built
    before a fix to `noisy_example`) cannot be refeatured; it is moved to `out/rejected/`
    and a later build writes it again, consistent with today's code.

    Args:
      out: the set's folder.
      sources: its clean meshes.
      verify: optional `(noisy [m, 3], faces [k, 3], fields) -> reason or None`, a
        further check of an example without a digest (e.g. that its stored statistics
        are those of the old version on the regenerated mesh).
      say: progress lines.

    Returns:
      `{"rewritten", "digest_checked", "rejected": [names]}`.
    """
    from dmd_jax.controller_features import FEATURES_VERSION, features
    from dmd_jax.io._files import atomic_write

    counts = sources.counts()
    manifest = json.loads(Path(out, "manifest.json").read_text())
    if manifest["sources"] != counts:
        raise ValueError(f"the sources changed since {out} was built: {counts}")
    report = {"rewritten": 0, "digest_checked": 0, "rejected": []}
    for path in _example_files(out):
        with np.load(path) as z:
            if _features_version(z) == FEATURES_VERSION:
                continue
            fields = {k: z[k] for k in z.files}
        spec = json.loads(str(fields["spec"]))
        clean, faces = sources.mesh(spec)
        try:
            _, noisy, faces = noisy_example(spec, clean, faces)
        except ValueError as err:
            reason = str(err)
        else:
            digest = mesh_digest(noisy, faces)
            if "noisy_digest" in fields:
                reason = None if str(fields["noisy_digest"]) == digest else "digest differs"
                report["digest_checked"] += 1
            elif int(fields["n_faces"]) != len(faces):
                reason = f"{len(faces)} faces where {int(fields['n_faces'])} were searched"
            else:
                reason = verify(noisy, faces, fields) if verify is not None else None
        if reason is not None:
            (Path(out) / "rejected").mkdir(exist_ok=True)
            path.rename(Path(out) / "rejected" / path.name)
            report["rejected"].append(path.name)
            say(f"{path.name} moved to rejected/: {reason}")
            continue
        fields["noisy_digest"] = digest
        fields["features"] = features(noisy, faces)
        if "crop_features" in fields:
            fields["crop_features"] = crop_statistics(noisy, faces)
        fields["features_version"] = FEATURES_VERSION

        def write(tmp, fields=fields):
            with open(tmp, "wb") as fh:
                np.savez(fh, **fields)

        atomic_write(path, write, overwrite=True)
        report["rewritten"] += 1
        if report["rewritten"] % 100 == 0:
            say(f"{report['rewritten']} examples' statistics recomputed")
    return report


def research(out, *, sources: Sources, bundle=None, reverse: bool = False, say=print) -> dict:
    """Brings every example searched by an older `SEARCH_VERSION` to today's: regenerates
    its noisy mesh (checked against its digest), and where `denoise` holds vertices of it
    (`held_vertices`) redoes the search holding them; an example with none held keeps its
    errors (the search is the same) and gets the version. Each file is rewritten whole,
    so a stopped run resumes, and a second process with `reverse` (from the last
    example back) shares the work with a first one.

    Returns:
      `{"checked", "researched", "rejected": [names]}`.
    """
    from dmd_jax import load_pretrained
    from dmd_jax.io._files import atomic_write

    counts = sources.counts()
    manifest = json.loads(Path(out, "manifest.json").read_text())
    if manifest["sources"] != counts:
        raise ValueError(f"the sources changed since {out} was built: {counts}")
    bundle = load_pretrained() if bundle is None else bundle
    report = {"checked": 0, "researched": 0, "rejected": []}
    t0 = time.time()
    files = _example_files(out)
    for path in reversed(files) if reverse else files:
        if not path.exists():  # moved to rejected/ by the other process
            continue
        with np.load(path) as z:
            if _search_version(z) == SEARCH_VERSION:
                continue
            fields = {k: z[k] for k in z.files}
        spec = json.loads(str(fields["spec"]))
        clean, faces = sources.mesh(spec)
        try:
            clean, noisy, faces = noisy_example(spec, clean, faces)
        except ValueError as err:
            reason = str(err)
        else:
            reason = (
                None
                if str(fields.get("noisy_digest")) == mesh_digest(noisy, faces)
                else ("digest differs")
            )
        if reason is not None:
            (Path(out) / "rejected").mkdir(exist_ok=True)
            path.rename(Path(out) / "rejected" / path.name)
            report["rejected"].append(path.name)
            say(f"{path.name} moved to rejected/: {reason}")
            continue
        held = held_vertices(noisy, faces)
        if held.any():
            fields["errors"], fields["first_pass"] = pass_errors(noisy, clean, faces, bundle, held)
            report["researched"] += 1
        fields["search_version"] = SEARCH_VERSION
        fields["held_vertices"] = int(held.sum())

        def write(tmp, fields=fields):
            with open(tmp, "wb") as fh:
                np.savez(fh, **fields)

        atomic_write(path, write, overwrite=True)
        report["checked"] += 1
        if report["checked"] % 100 == 0:
            say(
                f"{report['checked']} examples checked, {report['researched']} searched again "
                f"({time.time() - t0:.0f} s)"
            )
    return report


def network_digest(path) -> str:
    """The first 12 hex digits of a weights file's SHA-256: which network an example's
    search ran (`search_with`); an example without the field ran the bundled one."""
    from dmd_jax.long_run import file_sha

    if not Path(path).is_file():
        raise FileNotFoundError(f"no weights file {path}")
    return file_sha(path)[:12]


def _network(z) -> str:
    return str(z["network"]) if "network" in z.files else BUNDLED_NETWORK


# `network` of the examples searched with the bundled weights (every example `build` writes).
BUNDLED_NETWORK = "bundled"


def search_with(
    src,
    out,
    weights,
    *,
    sources: Sources,
    shard: tuple[int, int] = (0, 1),
    reverse: bool = False,
    say=print,
) -> int:
    """Copies the examples of the set `src` to `out` with the search and the default
    call's error redone for the network of the weights file `weights` (a long run's
    milestone: the controller it would need). Each example's noisy mesh is regenerated
    and checked against its digest; statistics and spec are kept (they do not depend on
    the network). Resumable (an example `out` holds is skipped); `shard=(k, n)` takes
    every n-th example of `src` from the k-th (one process per core), and a second
    process with `reverse` (from the last example back: the whole meshes first) shares
    the work with a first one. Returns how many it wrote.

    Raises:
      ValueError: `src` was built from other sources, or `out` holds a set of another
        source or network.
    """
    from dmd_jax import denoise
    from dmd_jax.checkpoints import load_model
    from dmd_jax.io._files import atomic_write, write_text_atomic
    from dmd_jax.metrics import face_normal_errors_deg

    src, out = Path(src), Path(out)
    manifest = json.loads((src / "manifest.json").read_text())
    if manifest["sources"] != sources.counts():
        raise ValueError(f"the sources changed since {src} was built: {sources.counts()}")
    digest = network_digest(weights)
    manifest = {**manifest, "network": digest, "searched_from": str(src)}
    old = out / "manifest.json"
    if old.is_file() and json.loads(old.read_text()) != json.loads(json.dumps(manifest)):
        raise ValueError(f"{out} holds a set of another source or network (manifest.json)")
    (out / "examples").mkdir(parents=True, exist_ok=True)
    write_text_atomic(old, json.dumps(manifest, indent=2))
    bundle = load_model(weights)
    written, t0 = 0, time.time()
    files = _example_files(src)[shard[0] :: shard[1]]
    for path in reversed(files) if reverse else files:
        target = out / "examples" / path.name
        if target.exists():
            continue
        with np.load(path) as z:
            fields = {k: z[k] for k in z.files}
            if _search_version(z) != SEARCH_VERSION:
                raise ValueError(f"{path}: searched by an older version (run --research)")
        spec = json.loads(str(fields["spec"]))
        clean, faces = sources.mesh(spec)
        clean, noisy, faces = noisy_example(spec, clean, faces)
        if str(fields["noisy_digest"]) != mesh_digest(noisy, faces):
            say(f"{path.name} skipped: its noisy mesh no longer regenerates")
            continue
        held = held_vertices(noisy, faces)
        fields["errors"], fields["first_pass"] = pass_errors(noisy, clean, faces, bundle, held)
        fields["default_error"] = float(
            np.mean(face_normal_errors_deg(denoise(noisy, faces, bundle), clean, faces))
        )
        fields["network"] = digest

        def write(tmp, fields=fields):
            with open(tmp, "wb") as fh:
                np.savez(fh, **fields)

        try:
            atomic_write(target, write, overwrite=False)
        except FileExistsError:  # the other process (`reverse`) met this one here
            say(f"{path.name}: written by another process meanwhile")
            continue
        written += 1
        if written % 25 == 0:
            say(f"{written} examples searched again ({(time.time() - t0) / written:.2f} s each)")
    return written


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--examples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", default="data/gen_v2", help="procedural dataset")
    parser.add_argument("--real", default="../shared/meshes/train", help="real meshes")
    parser.add_argument("--shard", default="0/1", help="K/N: every N-th example from K")
    parser.add_argument("--first", type=int, default=0, help="skip the indices below this")
    parser.add_argument(
        "--refeature",
        action="store_true",
        help="recompute stale statistics of the built examples instead of building",
    )
    parser.add_argument(
        "--research",
        action="store_true",
        help="redo the search of examples of an older search version where vertices are held",
    )
    parser.add_argument(
        "--reverse",
        action="store_true",
        help="with --research or --network: from the last example back",
    )
    parser.add_argument(
        "--network",
        type=Path,
        help="search with this weights file's network instead of the bundled one: with "
        "--from, that set's examples searched again into --out; without, a build",
    )
    parser.add_argument("--from", dest="src", type=Path, help="the set --network searches again")
    args = parser.parse_args(argv)
    sources = Sources(
        args.data if Path(args.data).is_dir() else None,
        args.real if Path(args.real).is_dir() else None,
    )
    if args.refeature:
        report = refeature(args.out, sources=sources)
        print(
            f"recomputed {report['rewritten']} examples' statistics ({report['digest_checked']} "
            f"checked by digest, the others by face count); {len(report['rejected'])} moved to "
            "rejected/"
        )
        return 0
    if args.src:
        if not args.network:
            parser.error("--from needs --network")
        k, _, n = args.shard.partition("/")
        wrote = search_with(
            args.src,
            args.out,
            args.network,
            sources=sources,
            shard=(int(k), int(n)),
            reverse=args.reverse,
        )
        print(f"searched {wrote} examples of {args.src} with {args.network} into {args.out}")
        return 0
    if args.research:
        report = research(args.out, sources=sources, reverse=args.reverse)
        print(
            f"checked {report['checked']} examples, searched {report['researched']} again "
            f"(vertices held); {len(report['rejected'])} moved to rejected/"
        )
        return 0
    k, _, n = args.shard.partition("/")
    wrote = build(
        args.out,
        args.examples,
        seed=args.seed,
        sources=sources,
        shard=(int(k), int(n)),
        first=args.first,
        network=args.network,
    )
    print(f"wrote {wrote} examples to {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    raise SystemExit(main())
