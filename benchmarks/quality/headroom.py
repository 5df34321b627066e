"""Headroom of DMD-Net's normal-first head: how much error is design ceiling, how much learning gap.

For every mesh and noise condition of the quality table (`dmd_jax.protocol`: the
benchmark's Gaussian levels, heavy and impulsive noise, and whatever conditions the
protocol lists besides, such as scanner noise and simulated scans), the noisy mesh in
the bundled model's frame is moved by the vertex update onto four sets of face normals:

(a) `gt`: the clean mesh's face normals (what the update alone can reach);
(b) `oracle`: per face, the candidate normal of the network's input closest to the clean
    one (`encoding.local_features`: the noisy normal, the pre-filtered and Taubin
    fields the head mixes);
(c) `field`: the best single candidate field of the mesh (one field for every face);
(d) `network`: the bundled network as `dmd_jax.denoise` runs it by default (its policy's
    passes and pre-smoothing), the sota-lite `DMD-Net` row;

each through the bundled model's update (`jacobi`: Sun et al.'s, `vertex_iterations`
steps) and through the converged one (`solve`: `dmd_jax.vertex_update`, default
settings; for (d) the bundled config switched to `vertex_update="solve"`). Errors are
sota-lite's: mean angle between corresponding face normals, degrees
(`metrics.mesh_metrics`' `normal_deg`). A diagnostic: nothing in `denoise` reads it.

With `--others CSV` (a sota-lite report), the `network` columns are also rated per shape
against the best other library denoiser of each case (`protocol.is_rival`), as
sota-lite's per-shape table does: the measurement that decides which update the bundled
weights should run until weights trained through the solve ship.

```bash
python benchmarks/quality/headroom.py                     # make headroom: shared + val
python benchmarks/quality/headroom.py --sets val --others benchmarks/results/sota_lite.csv
```
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
import warnings
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `benchmarks` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import (  # noqa: E402
    BUNDLED,
    RESULTS_DIR,
    command_line,
    environment,
    markdown_table,
    write_csv,
    write_report,
)
from dmd_jax import comparison, protocol  # noqa: E402

UPDATES = ("jacobi", "solve")
SOURCES = ("gt", "oracle", "field", "network")
CSV_HEADER = (
    "set",
    "mesh",
    "n_face",
    "condition",
    "seed",
    "noisy",
    *(f"{s}_{u}" for u in UPDATES for s in SOURCES),
    "field_jacobi_index",
    "field_solve_index",
)


def conditions() -> tuple:
    """The quality table's conditions: `QUALITY_CONDITIONS` and every other list of the
    protocol's (scanner noise, simulated scans) that exists in this checkout."""
    out = list(protocol.QUALITY_CONDITIONS)
    for name in ("SCANNER_CONDITIONS", "SCAN_CONDITIONS"):
        out += list(getattr(protocol, name, ()))
    return tuple(out)


def case_mesh(clean, faces, condition, seed):
    """`(clean, noisy, faces)` of one case (`protocol.condition_mesh` where it exists)."""
    make = getattr(protocol, "condition_mesh", None)
    if make is not None:
        return make(clean, faces, condition, seed)
    return clean, protocol.condition_noise(clean, faces, condition, seed), faces


class Runner:
    """The bundled model's pieces, compiled once per padded size."""

    def __init__(self, bundle):
        import jax
        import jax.numpy as jnp

        from dmd_jax import encoding, geometry
        from dmd_jax.vertex_update import solve_vertices_to_normals

        self.bundle = bundle
        self.cfg = cfg = bundle.config.model
        if cfg.head != "normal" or cfg.encoding != "local":
            raise ValueError("headroom needs a normal-first model with the local encoding")
        self.solve_bundle = bundle.with_vertex_update("solve")

        def candidates(x, graph):
            return encoding.local_features(
                x,
                graph,
                filter_iterations=cfg.filter_iterations,
                taubin_iterations=cfg.taubin_iterations,
                filter_sigmas=cfg.filter_sigmas,
            )[2]

        def jacobi(x, faces, normals):
            corner_face = jnp.repeat(jnp.arange(faces.shape[0], dtype=faces.dtype), 3)
            free = jnp.ones(x.shape[0], x.dtype)
            return geometry.fit_vertices_to_normals(
                x, faces, normals, faces.reshape(-1), corner_face, free, cfg.vertex_iterations
            )

        def solve(x, faces, normals):
            return solve_vertices_to_normals(
                x,
                faces,
                normals,
                tolerance=cfg.vertex_tolerance,
                max_iterations=cfg.vertex_max_iterations,
                normal_weight=cfg.vertex_normal_weight,
                tangent_weight=cfg.vertex_tangent_weight,
            )

        self.candidates = jax.jit(candidates)
        self.update = {"jacobi": jax.jit(jacobi), "solve": jax.jit(solve)}

    def case(self, clean, noisy, faces, network_only: bool = False) -> dict:
        """Every error of one case, degrees; `field_*_index`: the best field's index.
        With `network_only`, only `noisy` and `network_*` (the others NaN)."""
        import jax
        import jax.numpy as jnp

        from dmd_jax.encoding import mesh_frame
        from dmd_jax.graph import pad_vertex_array, undirected_vertex_edges
        from dmd_jax.inference import denoise, whole_mesh_graph
        from dmd_jax.mesh import face_normals_np
        from dmd_jax.metrics import face_normal_errors_deg

        def err(v):
            # sota-lite's normal error (`mesh_metrics`: zero-area clean faces left out),
            # without its chamfer search, which would cost more than the case.
            angles = face_normal_errors_deg(
                np.asarray(v, np.float64), clean, faces, undefined=np.nan
            )
            return float(np.nanmean(angles))

        n, nf = noisy.shape[0], faces.shape[0]
        graph = whole_mesh_graph(faces, n, "segment_sum")
        frame = mesh_frame(self.cfg.encoding, noisy, faces, edges=undirected_vertex_edges(graph))
        graph = jax.tree.map(jnp.asarray, graph)
        xp = jnp.asarray(pad_vertex_array(frame.apply(noisy).astype(np.float32), graph.n_vertex))
        pad_faces = graph.faces

        def moved(normals_np, update):
            padded = np.zeros((pad_faces.shape[0], 3), np.float32)
            padded[:nf] = normals_np
            out = self.update[update](xp, pad_faces, jnp.asarray(padded))
            return frame.invert(np.asarray(out[:n], np.float64))

        row = {"noisy": err(noisy)}
        if network_only:
            for update in UPDATES:
                bundle = self.bundle if update == "jacobi" else self.solve_bundle
                row[f"network_{update}"] = err(denoise(noisy, faces, bundle))
                for s in ("gt", "oracle", "field"):
                    row[f"{s}_{update}"] = np.nan
                row[f"field_{update}_index"] = -1
            return row
        gt = face_normals_np(np.asarray(clean, np.float64), faces)
        cands = np.asarray(self.candidates(xp, graph))[:nf]  # [nf, k, 3]
        dots = np.einsum("fkc,fc->fk", cands, gt)
        oracle = cands[np.arange(nf), np.argmax(dots, axis=1)]
        for update in UPDATES:
            row[f"gt_{update}"] = err(moved(gt, update))
            row[f"oracle_{update}"] = err(moved(oracle, update))
            fields = [err(moved(cands[:, k], update)) for k in range(cands.shape[1])]
            best = int(np.argmin(fields))
            row[f"field_{update}"], row[f"field_{update}_index"] = fields[best], best
            bundle = self.bundle if update == "jacobi" else self.solve_bundle
            row[f"network_{update}"] = err(denoise(noisy, faces, bundle))
        return row


def evaluate(
    runner, path, mesh_set: str, conds, max_faces: int, network_only=False, echo=print
) -> list[list]:
    """Rows (`CSV_HEADER` order) of one mesh file under every condition."""
    from dmd_jax.io import load_mesh

    path = Path(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        clean, faces = load_mesh(path)
    clean, faces = protocol.crop(np.asarray(clean, np.float64), faces, max_faces)
    rows = []
    for condition in conds:
        seed = protocol.condition_seed(path.name, condition)
        c, noisy, f = case_mesh(clean, faces, condition, seed)
        c, noisy, f = np.asarray(c, np.float64), np.asarray(noisy, np.float64), np.asarray(f)
        got = runner.case(c, noisy, f, network_only)
        rows.append(
            [mesh_set, path.name, int(f.shape[0]), condition.label, int(seed)]
            + [got[h] for h in CSV_HEADER[5:]]
        )
        echo(
            f"  {path.name} {condition.label}: noisy {got['noisy']:.2f}  "
            + "  ".join(
                f"{u}: gt {got[f'gt_{u}']:.2f} oracle {got[f'oracle_{u}']:.2f} "
                f"field {got[f'field_{u}']:.2f} network {got[f'network_{u}']:.2f}"
                for u in UPDATES
            )
        )
    return rows


def means_table(rows) -> str:
    """Means over meshes per set and condition of every column."""
    col = {h: i for i, h in enumerate(CSV_HEADER)}
    groups: dict[tuple, list] = {}
    for r in rows:
        groups.setdefault((r[0], r[3]), []).append(r)
    out = []
    for (mesh_set, cond), group in groups.items():
        cells = [mesh_set, cond, len(group), f"{np.mean([r[col['noisy']] for r in group]):.2f}"]
        for update in UPDATES:
            cells += [f"{np.mean([r[col[f'{s}_{update}']] for r in group]):.2f}" for s in SOURCES]
        out.append(cells)
    headers = ["set", "condition", "meshes", "noisy"] + [
        f"{s} ({u})" for u in UPDATES for s in SOURCES
    ]
    return markdown_table(headers, out)


def gaps_table(rows) -> str:
    """Per set and condition: the design ceiling (gt), what a better choice among the
    candidates could win (oracle, best field) and the network's learning gap, per update."""
    col = {h: i for i, h in enumerate(CSV_HEADER)}
    groups: dict[tuple, list] = {}
    for r in rows:
        groups.setdefault((r[0], r[3]), []).append(r)
    out = []
    for (mesh_set, cond), group in groups.items():
        for update in UPDATES:

            def mean(s, group=group, update=update):
                return float(np.mean([r[col[f"{s}_{update}"]] for r in group]))

            out.append(
                [
                    mesh_set,
                    cond,
                    update,
                    f"{mean('gt'):.2f}",
                    f"{mean('oracle') - mean('gt'):+.2f}",
                    f"{mean('network') - mean('oracle'):+.2f}",
                    f"{mean('network') - mean('field'):+.2f}",
                ]
            )
    headers = [
        "set",
        "condition",
        "update",
        "ceiling: gt normals",
        "oracle − gt",
        "network − oracle",
        "network − best field",
    ]
    return markdown_table(headers, out)


def read_others(csv_path) -> dict[tuple, float]:
    """`{(set, mesh, condition label): best other library denoiser's error}` of a
    sota-lite CSV (rows of `protocol.is_rival` methods)."""
    best: dict[tuple, float] = {}
    with open(csv_path) as fh:
        for r in csv.DictReader(fh):
            if not protocol.is_rival(r["method"]):
                continue
            cond = protocol.NoiseCondition(r.get("noise") or "gaussian", float(r["level"]))
            key = (r["set"], r["mesh"], cond.label)
            best[key] = min(best.get(key, np.inf), float(r["normal_deg"]))
    return best


def decision_table(rows, others: dict[tuple, float]) -> str:
    """Per set and condition: the default `denoise` call with each update over the best
    other library denoiser, per mesh (geometric mean, share within 5 %, worst ratio)."""
    col = {h: i for i, h in enumerate(CSV_HEADER)}
    every: dict[tuple, list] = {}
    for r in rows:
        if (r[0], r[1], r[3]) in others:
            every.setdefault((r[0], r[3]), []).append(r)
    for mesh_set in dict.fromkeys(k[0] for k in list(every)):
        every[(mesh_set, "all")] = [r for k, g in every.items() if k[0] == mesh_set for r in g]
    out = []
    for (mesh_set, cond), group in every.items():
        cells = [mesh_set, cond, len(group)]
        for update in UPDATES:
            ratios = {
                (r[1], r[3]): r[col[f"network_{update}"]] / others[(r[0], r[1], r[3])]
                for r in group
            }
            worst = max(ratios, key=ratios.get)
            within = sum(v <= comparison.WITHIN for v in ratios.values())
            where = worst[0] if cond != "all" else f"{worst[0]}, {worst[1]}"
            cells += [
                f"{comparison.geometric_mean(list(ratios.values())):.3f}",
                f"{within} of {len(ratios)}",
                f"{ratios[worst]:.2f} ({where})",
            ]
        wins = sum(r[col["network_solve"]] < r[col["network_jacobi"]] for r in group)
        cells.append(f"{wins} of {len(group)}")
        out.append(cells)
    headers = ["set", "condition", "cases"]
    for update in UPDATES:
        headers += [f"{update}: geometric mean", f"{update}: within 5 %", f"{update}: worst"]
    headers.append("solve better")
    return markdown_table(headers, out)


def run(
    sets=("shared", "val"),
    *,
    mesh_dir=None,
    val_dir=None,
    conds=None,
    meshes=(),
    max_faces: int = protocol.MAX_FACES,
    others=None,
    weights=None,
    network_only: bool = False,
    name: str = "headroom",
    out_dir=RESULTS_DIR,
    echo=print,
):
    """Runs the report and writes `<out_dir>/<name>.md` and `.csv`."""
    from dmd_jax.checkpoints import load_model

    conds = conditions() if conds is None else tuple(conds)
    files = []
    if "shared" in sets:
        files += [("shared", p) for p in protocol.mesh_files(mesh_dir)]
    if "val" in sets:
        files += [("val", p) for p in protocol.validation_files(val_dir)]
    if meshes:
        files = [(s, p) for s, p in files if p.name in set(meshes)]
    if not files:
        raise ValueError("no mesh to run (check --sets and --meshes)")
    bundle = load_model(weights)
    runner = Runner(bundle)
    start = time.perf_counter()
    rows = []
    env = environment(packages=("dmd_jax", "jax", "jaxlib", "numpy"))
    for i, (mesh_set, path) in enumerate(files, 1):
        echo(f"[{i}/{len(files)}] {mesh_set}: {path.name}")
        rows += evaluate(runner, path, mesh_set, conds, max_faces, network_only, echo)
        # The report so far after every mesh: a long run stopped early keeps its rows.
        env["wall time"] = f"{time.perf_counter() - start:.0f} s, {i} of {len(files)} meshes"
        path_md = _write(rows, env, bundle, others, max_faces, weights, name, out_dir)
    echo(f"wrote {path_md}")
    return path_md


def _write(rows, env, bundle, others, max_faces, weights, name, out_dir):
    """Writes `<name>.md` and `.csv` from the rows so far."""
    env["model"] = (
        f"preset {bundle.config.name}: jacobi = {bundle.config.model.vertex_iterations} "
        f"iterations; solve = tolerance {bundle.config.model.vertex_tolerance:g}, at most "
        f"{bundle.config.model.vertex_max_iterations} iterations, normal weight "
        f"{bundle.config.model.vertex_normal_weight:g}, tangent weight "
        f"{bundle.config.model.vertex_tangent_weight:g}"
    )
    env["policy"] = bundle.policy.describe("=")
    sections = [
        ("Where the error is, means over meshes (°)", gaps_table(rows)),
        ("Means over meshes (°)", means_table(rows)),
    ]
    if others is not None:
        sections.insert(
            0,
            (
                "The default call per shape against the best other library denoiser",
                decision_table(rows, read_others(others)),
            ),
        )
    detail = markdown_table(
        list(CSV_HEADER),
        [[f"{x:.2f}" if isinstance(x, float) else x for x in r] for r in rows],
    )
    sections.append(("Per mesh (°)", detail))
    intro = (
        "Mean angle between corresponding face normals, degrees, after moving the noisy "
        "mesh onto (a) the clean face normals (`gt`), (b) per face the network's candidate "
        "normal closest to the clean one (`oracle`), (c) the best single candidate field "
        "(`field`; its index in `encoding.local_features`' candidates in the CSV), (d) the "
        "bundled network as the default `denoise` call runs it (`network`, its policy "
        "included: sota-lite's DMD-Net row), each through the bundled model's update "
        "(`jacobi`) and the converged one (`solve`, `dmd_jax.vertex_update`; for (d) the "
        'bundled config with `vertex_update="solve"`). '
        "`oracle − gt` is what the candidates lack, `network − oracle` what the network's "
        "choice among them loses. Conditions: `dmd_jax.protocol`; meshes above "
        f"{max_faces:,} faces cropped as sota-lite does (`protocol.crop`). A diagnostic: "
        "nothing in `denoise` reads it."
    )
    write_csv(Path(out_dir) / f"{name}.csv", CSV_HEADER, rows)
    path = write_report(
        Path(out_dir) / f"{name}.md",
        title="Headroom: design ceiling and learning gap of the normal-first head",
        env=env,
        sections=sections,
        intro=intro,
        command=command_line(),
        weights=BUNDLED if weights is None else weights,
    )
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", nargs="+", default=["shared", "val"], choices=("shared", "val"))
    parser.add_argument("--meshes", nargs="*", default=[], help="only these file names")
    parser.add_argument(
        "--conditions",
        nargs="*",
        default=None,
        help="conditions as protocol.parse_condition reads them (default: every one)",
    )
    parser.add_argument("--max-faces", type=int, default=protocol.MAX_FACES)
    parser.add_argument("--others", default=None, help="a sota-lite CSV: rate denoise per shape")
    parser.add_argument("--weights", default=None, help="weights file (default: bundled)")
    parser.add_argument(
        "--network-only",
        action="store_true",
        help="only the default call with either update (the per-shape rating), no headroom",
    )
    parser.add_argument("--name", default="headroom", help="report file stem")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="report folder")
    args = parser.parse_args(argv)
    conds = None
    if args.conditions:
        conds = [protocol.parse_condition(c) for c in args.conditions]
    run(
        args.sets,
        conds=conds,
        meshes=args.meshes,
        max_faces=args.max_faces,
        others=args.others,
        weights=args.weights,
        network_only=args.network_only,
        name=args.name,
        out_dir=args.out_dir,
    )


if __name__ == "__main__":
    main()
