"""The `dmd-jax` command line.

Each subcommand lives in its own `_cmd_*` function; `main` turns any `ValueError` or
`OSError` (missing file, existing output, a directory or unwritable path) into a
one-line error and exit code 2.
"""

from __future__ import annotations

import argparse
import sys

# METHODS: every denoiser `--method` accepts, the names of `dmd_jax.denoise_with`;
# MESH_SUFFIXES: the files `dmd_jax.io` reads (both import only NumPy, so `--help`
# stays quick).
from dmd_jax.api import METHODS
from dmd_jax.io import SUPPORTED_EXTENSIONS as MESH_SUFFIXES

# The methods that read `--weights`: DMD-Net and the learned CNR baseline.
WEIGHTED_METHODS = ("dmd", "cnr")


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Defaults after each option's help (not for None/False, nor when the help names
    its default itself); the epilog's examples keep their line breaks."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default is None or action.default is False or "default" in text:
            return text
        return super()._get_help_string(action)


def _note(message: str) -> None:
    """A remark that is not an error, on stderr (stdout stays clean for `--json`)."""
    print(f"note: {message}", file=sys.stderr)


def _ply_element_counts(path) -> dict[str, int]:
    """`{element: count}` of a PLY header, read as `load_mesh` reads it.

    `{}` when the header is unreadable: `load_mesh` then says what is wrong with it (a
    header this function parsed more leniently than the reader could hide its faces
    and pass for a point cloud).
    """
    from dmd_jax.io import read_ply_header

    with open(path, "rb") as fh:
        head = fh.read(1 << 20)
    try:
        return read_ply_header(head, str(path)).counts()
    except ValueError:
        return {}


def _zero_area_faces(vertices, faces) -> int:
    """Faces of zero area, to rounding (1e-12 of the squared longest bounding-box side)."""
    import numpy as np

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    # Scaled to at most 1 first: coordinates near 1e300 (or 1e-300) would overflow (or
    # underflow) in the cross products, with a NumPy warning per operation.
    largest = float(np.abs(v).max()) if v.size else 0.0
    if largest == 0.0:
        return len(f)
    v = v / largest
    doubled = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    side = float(np.ptp(v, axis=0).max())
    return int(np.count_nonzero(doubled <= 1e-12 * side * side))


def _load_input(path):
    """`load_mesh` for a file the user named, with the CLI's plainer words.

    A directory or a point-cloud PLY is refused with a message that says so; polygon
    triangulation and zero-area faces each become one `note:` line on stderr instead of
    a raw Python warning, or silence.
    """
    import warnings
    from pathlib import Path

    from dmd_jax.io import load_mesh

    p = Path(path)
    if p.is_dir():
        found = sorted(q.name for q in p.iterdir() if q.suffix.lower() in MESH_SUFFIXES)
        hint = f"; it holds {len(found)} mesh files, e.g. {found[0]}" if found else ""
        raise ValueError(
            f"{path}: is a directory, not a mesh file ({', '.join(MESH_SUFFIXES)}){hint}"
        )
    from dmd_jax.io import check_readable_file

    check_readable_file(p)  # a FIFO would block the header read below
    if p.suffix.lower() == ".ply":
        counts = _ply_element_counts(p)
        if counts.get("vertex", 0) > 0 and not counts.get("face"):
            raise ValueError(
                f"{path}: is a point cloud ({counts['vertex']} vertices, no faces); "
                "denoising needs a triangle mesh (reconstruct a surface first)"
            )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vertices, faces = load_mesh(p)
    for w in caught:
        text = str(w.message)
        if "triangulated" in text:
            text += "; every output of this command is a triangle mesh"
        _note(text)
    zero = _zero_area_faces(vertices, faces)
    if zero:
        _note(
            f"{path}: {zero} of {len(faces)} faces have zero area; their normals are "
            "undefined (the normal error leaves them out)"
        )
    return vertices, faces


def _cmd_info(args: argparse.Namespace) -> int:
    import jax

    import dmd_jax

    print(f"dmd_jax {dmd_jax.__version__}, jax {jax.__version__}, devices {jax.devices()}")
    if getattr(args, "preset", None) is not None:
        from dmd_jax.config import preset, variant_config
        from dmd_jax.model import param_count, param_counts_by_module

        model = preset(args.preset).model
        if args.variant is not None:
            model = variant_config(model, args.variant)
        print(
            f"preset {args.preset}, variant {model.variant}, width {model.width}, "
            f"depth {model.depth}"
        )
        for name, count in param_counts_by_module(model).items():
            print(f"  {name:<18} {count:>12,d} parameters")
        print(f"  {'total':<18} {param_count(model):>12,d} parameters")
        if args.preset == "paper":
            print("  (the paper says about 30 M; dmd_jax.config explains the difference)")
    elif getattr(args, "variant", None) is not None:
        raise ValueError("--variant needs --preset")
    if getattr(args, "weights", None) is not None:
        from dmd_jax.checkpoints import load_model
        from dmd_jax.model import param_count

        bundle = load_model(None if args.weights == "bundled" else args.weights)
        model = bundle.config.model
        print(
            f"weights {args.weights}: preset {bundle.config.name}, width {model.width}, "
            f"{param_count(model):,d} parameters, encoding {model.encoding}, head {model.head}"
        )
        print("  policy: " + bundle.policy.describe())
    return 0


def _denoise_inputs(args: argparse.Namespace):
    """`[(input, output)]` of a `denoise` call: one file and `-o`, or files and folders
    (their mesh files, not recursive) and `--out DIR` (same names there)."""
    from pathlib import Path

    if args.skip_existing and args.overwrite:
        raise ValueError("--skip-existing and --overwrite contradict each other; pass one")
    many = len(args.input) > 1 or Path(args.input[0]).is_dir()
    if not many:
        if args.out is not None:
            raise ValueError("one input file takes -o/--output FILE; --out DIR is for several")
        if args.output is None:
            raise ValueError("give -o/--output FILE for the denoised mesh")
        pairs = [(args.input[0], args.output)]
        return _unfinished(pairs, args)
    if args.output is not None:
        raise ValueError("several inputs (or a folder) take --out DIR, not -o/--output")
    if args.out is None:
        raise ValueError("several inputs (or a folder) need --out DIR for the results")
    files = []
    for name in args.input:
        p = Path(name)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.suffix.lower() in MESH_SUFFIXES)
            if not found:
                raise ValueError(f"{name}: holds no mesh files ({', '.join(MESH_SUFFIXES)})")
            files += found
        else:
            files.append(p)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{args.out}: exists and is not a directory")
    names = [f.name for f in files]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"two inputs share the file name {twice[0]}; their outputs would collide")
    pairs = [(str(f), str(out / f.name)) for f in files]
    # --out DIR is created when missing (like `mkdir -p`): it names a folder of results,
    # so there is nothing to mistype into an unintended place but the folder itself.
    args.parents = True
    return _unfinished(pairs, args)


def _unfinished(pairs, args):
    """The `(input, output)` pairs still to run, every output checked before any work.

    With --skip-existing, pairs whose output exists are left out with a note (the
    outputs of an interrupted run are complete files: every write is atomic).
    """
    from pathlib import Path

    todo = []
    for src, dst in pairs:
        if args.skip_existing and Path(dst).is_file():
            continue
        _check_output(dst, src, args.overwrite, parents=args.parents, suffixes=MESH_SUFFIXES)
        todo.append((src, dst))
    if len(todo) < len(pairs):
        _note(f"--skip-existing: {len(pairs) - len(todo)} of {len(pairs)} outputs exist already")
    return todo


def _cmd_denoise(args: argparse.Namespace) -> int:
    import time

    from dmd_jax.api import denoise_with
    from dmd_jax.io import save_mesh

    if args.iterations is not None and args.iterations < 1:
        raise ValueError(f"--iterations must be at least 1, got {args.iterations}")
    if args.method not in METHODS:
        raise ValueError(f"unknown --method {args.method!r}; choose one of: {', '.join(METHODS)}")
    if args.weights is not None and args.method not in WEIGHTED_METHODS:
        raise ValueError(
            f"--weights is for --method {' or '.join(WEIGHTED_METHODS)}; {args.method!r} is a "
            "classic filter with no weights (drop --weights)"
        )
    extra = {}
    if args.max_memory is not None:
        if args.method != "dmd":
            raise ValueError("--max-memory is for --method dmd (the network)")
        from dmd_jax.memory_plan import parse_memory

        extra["max_memory"] = parse_memory(args.max_memory)
    if args.relax is not None:
        if args.method != "dmd":
            raise ValueError("--relax is for --method dmd (the network)")
        if args.relax < 0:
            raise ValueError(f"--relax must be 0 or more steps, got {args.relax}")
        extra["relax"] = args.relax
    if args.presmooth is not None:
        if args.method != "dmd":
            raise ValueError("--presmooth is for --method dmd (the network)")
        if args.presmooth != "rule":
            try:
                steps = int(args.presmooth)
            except ValueError:
                steps = -1
            if steps < 0:
                raise ValueError(
                    f"--presmooth must be 0 or more steps, or 'rule', got {args.presmooth!r}"
                )
            extra["presmooth"] = steps
        else:
            extra["presmooth"] = "rule"
    pairs = _denoise_inputs(args)
    weights = args.weights
    if args.method == "dmd" and args.out is not None:
        from dmd_jax.checkpoints import load_model

        weights = load_model(weights)  # once for every mesh
    t_all = time.perf_counter()
    many = args.out is not None  # folder mode: one bad file does not stop the others
    failed: list[tuple[str, str]] = []
    done = 0
    for src, dst in pairs:
        try:
            done += _denoise_one(args, src, dst, weights, extra, denoise_with, save_mesh)
        except (ValueError, OSError) as exc:
            if not many:
                raise
            # One bad file must not cost the rest of a folder: say so, go on, sum up.
            message = " ".join(str(exc).split()) or type(exc).__name__
            print(f"dmd-jax denoise: error: {message} (going on with the others)", file=sys.stderr)
            failed.append((src, message))
        except KeyboardInterrupt as exc:
            if many:
                exc.hint = (
                    f" after {done} of {len(pairs)} meshes; the finished outputs are complete "
                    "files: rerun the same command with --skip-existing to resume"
                )
            raise
    if many:
        minutes = max(time.perf_counter() - t_all, 1e-9) / 60
        print(
            f"{done} meshes in {minutes * 60:.1f} s ({done / minutes:.1f} meshes "
            "per minute, reading and writing included)"
        )
    if failed:
        names = ", ".join(src.replace("\\", "/").rsplit("/", 1)[-1] for src, _ in failed[:5])
        more = f" and {len(failed) - 5} more" if len(failed) > 5 else ""
        print(
            f"dmd-jax denoise: {len(failed)} of {len(pairs)} meshes failed ({names}{more}); "
            + ("the others were written" if done else "no output was written"),
            file=sys.stderr,
        )
        return 1
    return 0


def _denoise_one(args, src, dst, weights, extra, denoise_with, save_mesh) -> int:
    """Denoises one file into `dst` and prints its line; returns 1."""
    import time

    vertices, faces = _load_input(src)
    if args.parents:
        _make_parent(dst)
    t0 = time.perf_counter()
    # One call for the network and every baseline, as in Python (dmd_jax.denoise_with).
    out = denoise_with(
        args.method,
        vertices,
        faces,
        weights=weights,
        iterations=args.iterations,
        **({"return_info": True} if args.method == "dmd" else {}),
        **extra,
    )
    out, info = out if args.method == "dmd" else (out, None)
    elapsed = time.perf_counter() - t0
    save_mesh(dst, out, faces, overwrite=args.overwrite, protect=[src])
    how = ""
    if info is not None and info.presmooth_steps:
        how = f" after {info.presmooth_steps} Laplacian steps"
    if info is not None and info.passes > 1:
        how += f" ({info.passes} passes)"
    if info is not None and info.path == "patches":
        how += f" in {info.patches} patches of {info.patch_size:,} vertices"
    if info is not None and info.route is not None:
        who = (
            "its review of the network's result took" if info.reviewed else "its learned choice ran"
        )
        how += f" ({who} the network-free route {info.route})"
    if info is not None and info.cascade is not None:
        how += f" (its review ran {info.cascade} on the network's result)"
    print(
        f"denoised {src} ({len(vertices)} vertices, {len(faces)} faces) with "
        f"{args.method}{how} in {elapsed:.2f} s -> {dst}"
    )
    return 1


def _check_output(output, inputs, overwrite: bool, *, parents: bool = False, suffixes=None) -> None:
    """Everything that would make writing `output` fail, checked before any work.

    The format (`suffixes`), `-` (no stdout output), the input itself or a hard link to
    it, a directory, an existing file without --overwrite, a missing folder (created
    later with `parents`, see `_make_parent`), and a folder one may not write in.
    """
    import os
    from pathlib import Path

    if str(output) == "-":
        raise ValueError("-o -: meshes are not written to stdout; give a file name")
    out = Path(output)
    if suffixes is not None and out.suffix.lower() not in suffixes:
        raise ValueError(
            f"{output}: unknown mesh format {out.suffix!r}; use one of {', '.join(suffixes)}"
        )
    for src in [inputs] if isinstance(inputs, (str, Path)) else inputs:
        same = Path(src).resolve() == out.resolve()
        if not same and out.exists() and Path(src).exists():
            same = os.path.samefile(src, out)  # a hard link to the input
        if same:
            raise ValueError(f"{output}: the output path is the input file; choose another")
    if out.is_dir():
        raise ValueError(f"{output}: is a directory; give a file name")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{output}: already exists (pass --overwrite to replace it)")
    folder = out.parent
    if not folder.is_dir():
        if folder.exists():
            raise NotADirectoryError(f"{folder}: is not a directory")
        if not parents:
            raise FileNotFoundError(
                f"{folder}: output directory does not exist (pass --parents to create it)"
            )
        while not folder.exists():  # the folder that will hold the new ones
            folder = folder.parent
        if not folder.is_dir():
            raise NotADirectoryError(f"{folder}: is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"{output}: cannot write in {folder} (permission denied)")


def _make_parent(output) -> None:
    """Creates the folders above `output` (`--parents`), just before writing it."""
    from pathlib import Path

    Path(output).parent.mkdir(parents=True, exist_ok=True)


def _cmd_add_noise(args: argparse.Namespace) -> int:
    import numpy as np

    from dmd_jax.api import add_noise
    from dmd_jax.io import save_mesh

    _check_output(
        args.output, args.input, args.overwrite, parents=args.parents, suffixes=MESH_SUFFIXES
    )
    vertices, faces = _load_input(args.input)
    # The same noise as dmd_jax.add_noise(seed, ...) in Python, whatever JAX's x64 mode.
    noisy = add_noise(
        args.seed,
        vertices,
        faces,
        args.kind,
        args.level,
        units=args.units,
        direction=args.direction,
    )
    if not np.isfinite(noisy).all():
        # Not the output file's fault: the noise itself left float64's range.
        raise ValueError(
            f"--level {args.level:g} ({args.units} units) moves {args.input}'s vertices "
            "beyond float64's range; give a smaller level"
        )
    if args.parents:
        _make_parent(args.output)
    save_mesh(args.output, noisy, faces, overwrite=args.overwrite, protect=[args.input])
    print(
        f"added {args.kind} noise, level {args.level} ({args.units} units, seed {args.seed}) "
        f"-> {args.output}"
    )
    return 0


def _in_gt_order(v, f, gt_v, gt_f, path, gt_path):
    """The vertices of `path` in the ground truth's vertex order, or a clear error.

    The metrics compare vertex i with vertex i. A mesh with the ground truth's faces is
    taken as it is; one with the same number of faces but another vertex numbering (an
    STL output, which renumbers its vertices, or a mesh reordered by another tool) is
    matched through its faces, corner by corner, or else through identical positions,
    with a note; anything else is refused, naming what differs.
    """
    import numpy as np

    if v.shape == gt_v.shape and f.shape == gt_f.shape and (f == gt_f).all():
        return v
    counts = f"{len(v)} vs {len(gt_v)} vertices, {len(f)} vs {len(gt_f)} faces"
    if f.shape == gt_f.shape and len(v) == len(gt_v):
        # Faces in the same order, vertices renumbered: face i corner j is the same
        # point in both, so the faces themselves give the vertex map.
        perm = np.full(len(gt_v), -1, np.int64)
        perm[gt_f.ravel()] = f.ravel()
        if (perm[gt_f] == f).all() and (np.sort(perm) == np.arange(len(v))).all():
            _note(f"{path}: vertices matched to {gt_path} through the faces (another vertex order)")
            return v[perm]
        # Or the very same points, listed in another order (and faces with them).
        order_v, order_gt = np.lexsort(v.T[::-1]), np.lexsort(gt_v.T[::-1])
        if (v[order_v] == gt_v[order_gt]).all() and len(np.unique(v, axis=0)) == len(v):
            perm = np.empty(len(v), np.int64)
            perm[order_gt] = order_v
            ours = np.unique(np.sort(np.argsort(perm)[f], axis=1), axis=0)
            if np.array_equal(ours, np.unique(np.sort(gt_f, axis=1), axis=0)):
                _note(f"{path}: vertices matched to {gt_path} by position (another order)")
                return v[perm]
        raise ValueError(
            f"{path}: the counts match {gt_path} ({counts}) but the vertex order does not "
            "(an STL output renumbers vertices; evaluate the OBJ, OFF or PLY output, "
            "which keeps the input's order)"
        )
    raise ValueError(f"{path}: vertex/face correspondence with {gt_path} is required ({counts})")


def _cmd_evaluate(args: argparse.Namespace) -> int:
    import json
    import math

    from dmd_jax.metrics import mesh_metrics, metrics_table

    gt_v, gt_f = _load_input(args.gt)
    rows = []
    for path in args.mesh:
        v, f = _load_input(path)
        v = _in_gt_order(v, f, gt_v, gt_f, path, args.gt)
        m = mesh_metrics(v, gt_v, gt_f)
        if math.isnan(m["normal_deg"]):
            raise ValueError(
                f"{args.gt}: no face of the ground truth has a non-zero area, so the normal "
                "error is undefined (a degenerate mesh cannot be a ground truth)"
            )
        bad = [k for k, x in m.items() if not math.isfinite(x)]
        if bad:
            raise ValueError(
                f"{path}: its {bad[0]} error overflows float64 (the mesh lies astronomically "
                f"far from {args.gt}: another unit or a corrupt file?)"
            )
        rows.append({"mesh": str(path), **{k: float(x) for k, x in m.items()}})
    if args.json:
        # allow_nan=False: never the non-JSON `Infinity`/`NaN` (refused above).
        print(json.dumps(rows, indent=2, allow_nan=False))
    else:
        print(metrics_table({r["mesh"]: r for r in rows}, style="text"), end="")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from pathlib import Path

    from dmd_jax.render import render_meshes, resolve_up, sharpest_face

    kind = Path(args.output).suffix.lower()
    if kind not in (".png", ".html"):
        raise ValueError(f"{args.output}: write a .png (static picture) or .html (3-D page)")
    if args.range is not None and not args.range[0] < args.range[1]:
        raise ValueError(f"--range needs LOW < HIGH, got {args.range[0]:g} {args.range[1]:g}")
    from dmd_jax.render import MAX_PANEL_SIZE

    if not 0 < args.panel_size <= MAX_PANEL_SIZE:  # NaN fails too
        raise ValueError(
            f"--panel-size must be in (0, {MAX_PANEL_SIZE:g}] inches, got {args.panel_size:g}"
        )
    _check_output(
        args.output,
        args.inputs + ([args.gt] if args.gt else []),
        args.overwrite,
        parents=args.parents,
    )
    meshes = [_load_input(p) for p in args.inputs]
    if args.parents:
        _make_parent(args.output)
    titles = args.titles.split(",") if args.titles else [Path(p).stem for p in args.inputs]
    values = None
    if args.gt:
        from dmd_jax.metrics import face_normal_errors_deg

        gt_v, gt_f = _load_input(args.gt)
        values = []
        for i, (path, (v, f)) in enumerate(zip(args.inputs, meshes, strict=True)):
            # evaluate's correspondence: renumbered vertices (an STL) matched, else refused.
            v = _in_gt_order(v, f, gt_v, gt_f, path, args.gt)
            meshes[i] = (v, gt_f)
            values.append(face_normal_errors_deg(v, gt_v, gt_f))
        # The clean mesh is the last panel, with no error of its own.
        meshes.append((gt_v, gt_f))
        values.append(None)
        stem = Path(args.gt).stem
        if len(titles) == len(args.inputs):
            titles.append(stem if stem == "clean" else f"{stem} (clean)")
    if len(titles) != len(meshes):
        raise ValueError(f"--titles gives {len(titles)} titles for {len(meshes)} panels")
    if args.gt:
        # Each title gets its mesh's mean normal error: `evaluate`'s normal (°) column.
        import math

        import numpy as np

        from dmd_jax.metrics import NORMAL, face_normal_errors_deg, format_metric

        for i, (v, _) in enumerate(meshes[: len(args.inputs)]):
            mean = np.nanmean(face_normal_errors_deg(v, gt_v, gt_f, undefined=math.nan))
            titles[i] += f"\n{NORMAL.name} {format_metric(NORMAL, mean)}{NORMAL.unit}"
    view = dict(
        titles=titles,
        face_values=values,
        value_range=None if args.range is None else tuple(args.range),
        elev=args.elev,
        azim=args.azim,
        up=resolve_up(args.up, meshes),
    )
    if kind == ".html":
        from dmd_jax.viewer import comparison_html

        comparison_html(
            meshes,
            args.output,
            overwrite=args.overwrite,
            panel_px=round(130 * args.panel_size),
            **view,
        )
    else:
        crop = None
        if not args.no_zoom:
            # Zoom on the sharpest feature of the clean mesh (or of the first input).
            ref_v, ref_f = meshes[-1]
            if all(f.shape == ref_f.shape and (f == ref_f).all() for _, f in meshes):
                crop = sharpest_face(ref_v, ref_f, elev=args.elev, azim=args.azim, up=view["up"])
        render_meshes(
            meshes,
            args.output,
            shaded_row=True,
            crop_face=crop,
            panel_size=args.panel_size,
            overwrite=args.overwrite,
            **view,
        )
    print(f"wrote {args.output}")
    return 0


def _cmd_make_dataset(args: argparse.Namespace) -> int:
    import time

    from dmd_jax.data.dataset import build_dataset

    def names(text):
        # None: the option was not given; "" gives (): e.g. --test-inter "" holds out nothing.
        return None if text is None else tuple(x.strip() for x in text.split(",") if x.strip())

    start = time.perf_counter()
    ds = build_dataset(
        args.out,
        from_folder=args.from_folder,
        per_category=args.per_category,
        categories=names(args.categories),
        test_inter=names(args.test_inter),
        remesh=args.remesh,
        seed=args.seed,
        intra_fraction=args.intra_fraction,
        workers=args.workers,
        min_vertices=args.min_vertices,
        max_vertices=args.max_vertices,
        progress=not args.no_progress,
        overwrite=args.overwrite,
    )
    counts = ds.counts()
    skipped = len(ds.manifest.get("skipped", []))
    print(
        f"wrote {len(ds)} meshes to {args.out} in {time.perf_counter() - start:.1f} s: "
        f"train {counts['train']}, test_intra {counts['test_intra']}, "
        f"test_inter {counts['test_inter']} ({', '.join(ds.test_inter_categories) or 'none'})"
        + (f"; {skipped} skipped (see manifest.json)" if skipped else "")
    )
    return 0


def _parse_edits(items: list[str]) -> dict:
    """`["train.steps=10", "loss.vertex=50"]` -> nested dict (values parsed as JSON)."""
    import json

    edits: dict = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set takes SECTION.FIELD=VALUE, got {item!r}")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        if isinstance(value, list):
            value = tuple(value)
        node = edits
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return edits


def _distributed_args(args: argparse.Namespace) -> dict | None:
    """`jax.distributed.initialize` keywords from the multi-host flags, or None if unset.

    Raises:
      ValueError: only some of the three flags, bad values, or no --data-parallel.
    """
    flags = {
        "--coordinator": args.coordinator,
        "--num-processes": args.num_processes,
        "--process-id": args.process_id,
    }
    given = [k for k, v in flags.items() if v is not None]
    if not given:
        return None
    if len(given) != len(flags):
        missing = ", ".join(k for k in flags if k not in given)
        raise ValueError(
            f"multi-host training needs --coordinator, --num-processes and --process-id "
            f"together; missing {missing}"
        )
    host, sep, port = args.coordinator.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"--coordinator takes HOST:PORT, got {args.coordinator!r}")
    if args.num_processes < 1:
        raise ValueError(f"--num-processes must be at least 1, got {args.num_processes}")
    if not 0 <= args.process_id < args.num_processes:
        raise ValueError(
            f"--process-id must be in 0..{args.num_processes - 1}, got {args.process_id}"
        )
    if not args.data_parallel:
        raise ValueError("--coordinator, --num-processes and --process-id need --data-parallel")
    return {
        "coordinator_address": args.coordinator,
        "num_processes": args.num_processes,
        "process_id": args.process_id,
    }


def _train_config(args: argparse.Namespace):
    """The run's `ExperimentConfig`: the preset, its `--set` edits, then the flags that
    set config fields (`--data`, and `--eval-meshes`, `--real-meshes`, `--init-from`
    when given)."""
    from dmd_jax.config import preset

    cfg = preset(args.preset).with_edits(_parse_edits(args.set or []))
    data = {"dataset_dir": args.data}
    if args.eval_meshes is not None:
        data["eval_meshes_per_split"] = args.eval_meshes
    if args.real_meshes:
        data["real_root"] = args.real_meshes
    edits = {"data": data}
    if args.init_from is not None:
        edits["train"] = {"init_from": args.init_from}
    return cfg.with_edits(edits)


def _cmd_train(args: argparse.Namespace) -> int:
    import json

    import jax

    # Before anything touches a device: the device list then spans every process.
    distributed = _distributed_args(args)
    if distributed is not None:
        jax.distributed.initialize(**distributed)

    from dmd_jax.train import train_and_evaluate

    result = train_and_evaluate(
        _train_config(args),
        args.workdir,
        pad=args.pad,
        data_parallel=args.data_parallel,
        progress=not args.no_progress,
        verbose=True,
    )
    result.pop("state", None)
    if jax.process_index() == 0:
        print(json.dumps(result, indent=2) if args.json else _train_summary(result))
    return 0


def _train_summary(result: dict) -> str:
    """One line: the trained model's mean normal error against its noisy input's, per
    evaluation set, e.g. `test_intra normal error 9.5° vs noisy 20.1° (-53 %)`."""
    parts = []
    for key in sorted(k for k in result if k.endswith("/normal_deg") and "/noisy_" not in k):
        split = key.split("/")[0]
        model, noisy = result[key], result.get(f"{split}/noisy_normal_deg")
        if noisy is None:
            continue
        change = 100.0 * (model - noisy) / noisy if noisy else 0.0
        parts.append(f"{split} normal error {model:.1f}° vs noisy {noisy:.1f}° ({change:+.0f} %)")
    head = f"step {result['step']}, {result['wall_time_s']:.0f} s"
    if not parts:
        return f"{head}: no evaluation set, nothing to compare"
    return f"{head}: " + "; ".join(parts)


def _cmd_export_weights(args: argparse.Namespace) -> int:
    import json
    import platform
    from pathlib import Path

    from dmd_jax.checkpoints import load_params, load_weights, save_weights
    from dmd_jax.policy import trained_policy

    source = Path(args.checkpoint)
    if source.is_file():
        # A weights file: the same params with a newly fitted inference policy.
        bundle = load_weights(source)
        params, cfg, meta = bundle.params, bundle.config, dict(bundle.meta)
        policy = bundle.policy
        step = meta.get("step")
        meta["exported_from"] = str(args.checkpoint)
    else:
        params, cfg = load_params(source)
        policy = trained_policy(cfg)
        step = _latest_step(source)
        meta = {"source": str(args.checkpoint), "platform": platform.platform()}
        if step is not None:
            meta["step"] = step
    if args.policy_from is not None:
        # A fine-tune keeps the policy fitted for the weights it started from; the
        # edits below still apply on top of it.
        policy = load_weights(args.policy_from).policy
        meta["policy_from"] = str(args.policy_from)
    policy = _edited_policy(policy, args)
    if args.meta:
        meta.update(json.loads(args.meta))
    path = save_weights(args.output, params, cfg, meta, policy=policy, overwrite=args.overwrite)
    print(
        f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB): "
        + (f"step {step}" if step is not None else "the newest step")
        + f" of {args.checkpoint}, preset {cfg.name}"
    )
    return 0


def _edited_policy(policy, args: argparse.Namespace):
    """`policy` with export-weights' --pass-tolerance, --max-passes, --presmooth and
    --relax-steps applied (a tolerance on a one-pass policy without --max-passes gets
    `policy.LEGACY_AUTO_MAX_PASSES`, the cap such weights always had)."""
    from dmd_jax.policy import LEGACY_AUTO_MAX_PASSES

    edits = {}
    if args.pass_tolerance is not None:
        edits["pass_tolerance"] = args.pass_tolerance
        if args.pass_tolerance > 0 and policy.max_passes == 1:
            edits["max_passes"] = LEGACY_AUTO_MAX_PASSES
    if args.max_passes is not None:
        edits["max_passes"] = args.max_passes
    if args.presmooth is not None:
        # An explicit rule is the one to run: it replaces a learned choice.
        policy = policy.with_presmooth_rule()
        edits["presmooth_start"], edits["presmooth_per_step"] = args.presmooth
    if args.relax_steps is not None:
        edits["relax_steps"] = args.relax_steps
    return policy.with_edits(edits)


def _latest_step(checkpoint_dir) -> int | None:
    """The step `load_params` reads: the newest checkpoint of an Orbax manager directory."""
    from pathlib import Path

    import orbax.checkpoint as ocp

    return ocp.CheckpointManager(Path(checkpoint_dir).absolute()).latest_step()


def _cmd_demo(args: argparse.Namespace) -> int:
    from dmd_jax.demo import run_demo

    run_demo(args.out, weights=args.weights, overwrite=args.overwrite, render=not args.no_render)
    return 0


def _cmd_train_cnr(args: argparse.Namespace) -> int:
    import shlex

    from dmd_jax.baselines.cascaded_regression import train_main

    train_main(args, "dmd-jax " + " ".join(shlex.quote(a) for a in sys.argv[1:]))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dmd-jax", description="DMD-Net mesh denoising in JAX (see README.md)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="versions, devices, presets and parameter counts")
    p.add_argument(
        "--preset",
        choices=("paper", "small", "test"),
        help="print the parameter count of a preset's model",
    )
    p.add_argument("--variant", help="structure-ablation variant, e.g. FGT-3 or fgt3")
    p.add_argument(
        "--weights",
        default=None,
        help="also describe these weights (a file, a checkpoint directory, or 'bundled'): "
        "the network and the denoising policy stored with it",
    )
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser(
        "denoise",
        help="denoise mesh files",
        description="Denoise one mesh file (-o FILE) or several and folders (--out DIR). "
        "Every output is checked before any work starts. A folder run goes on past a file "
        "it cannot read or denoise, names it, and exits with 1 and a summary at the end; "
        "after Ctrl-C or SIGTERM, rerun it with --skip-existing to resume.",
    )
    p.add_argument(
        "input", nargs="+", help="noisy mesh (.obj .off .ply .stl), or several, or folders"
    )
    p.add_argument("-o", "--output", help="where to write the result (one input file)")
    p.add_argument("--out", help="folder for the results of several inputs (same file names)")
    p.add_argument(
        "--weights",
        default=None,
        help="weights file or checkpoint directory (default: bundled model)",
    )
    p.add_argument(
        "--method",
        default="dmd",
        metavar="METHOD",
        help="'dmd' (the network) or another denoiser of dmd_jax.baselines: "
        + ", ".join(METHODS[1:])
        + " (cnr is learned: it takes --weights too; the others are classic filters)",
    )
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="passes of the denoiser (default: 1 for a classic filter; for dmd the pass rule "
        "stored with the weights: `dmd-jax info --weights W` shows it)",
    )
    p.add_argument(
        "--max-memory",
        default=None,
        help="memory budget of the network, e.g. 8GB or 6GiB; larger meshes run in "
        "patches (default: half the memory available)",
    )
    p.add_argument(
        "--relax",
        type=int,
        default=None,
        metavar="STEPS",
        help="steps of crease-preserving tangential relaxation after the network, for "
        "noise that is not along the normals, e.g. 3 (default: the weights' policy)",
    )
    p.add_argument(
        "--presmooth",
        default=None,
        metavar="STEPS",
        help="uniform Laplacian steps before the network (default: the weights' policy "
        "chooses, from what the noisy mesh looks like; 0: none; 'rule': the roughness "
        "rule stored with the weights, in place of the learned choice)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument(
        "--skip-existing",
        action="store_true",
        help="leave out inputs whose output exists: resumes an interrupted folder run "
        "(outputs are written atomically, so an existing one is complete)",
    )
    p.add_argument(
        "--parents",
        action="store_true",
        help="create -o's missing folders (--out DIR is always created when missing)",
    )
    p.set_defaults(func=_cmd_denoise)

    p = sub.add_parser("add-noise", help="add synthetic noise to a mesh file")
    p.add_argument("input", help="clean mesh (.obj .off .ply .stl)")
    p.add_argument("-o", "--output", required=True, help="where to write the noisy mesh")
    p.add_argument(
        "--kind",
        default="gaussian",
        choices=["gaussian", "uniform", "gamma", "impulse"],
        help="noise distribution per coordinate (dmd_jax.noise explains each)",
    )
    p.add_argument(
        "--level",
        type=float,
        required=True,
        help="noise level in --units: σ for gaussian, the amplitude for the other kinds",
    )
    p.add_argument(
        "--units",
        default="canonical",
        choices=["canonical", "edge"],
        help="canonical: fraction of the longest bbox side; edge: × mean edge length",
    )
    p.add_argument(
        "--direction",
        choices=("isotropic", "normal"),
        default="isotropic",
        help="isotropic: per coordinate; normal: one draw per vertex along its normal "
        "(the benchmark protocol)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed; same seed, same noise")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--parents", action="store_true", help="create -o's missing folders")
    p.set_defaults(func=_cmd_add_noise)

    p = sub.add_parser("evaluate", help="vertex / normal / chamfer metrics against a ground truth")
    p.add_argument(
        "--gt",
        required=True,
        help="ground-truth mesh: the same vertices as each --mesh, in the same order (a "
        "mesh whose faces match but whose vertices were renumbered, e.g. an STL output, is "
        "matched through its faces)",
    )
    p.add_argument("--mesh", required=True, nargs="+", help="meshes to score")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser(
        "render", help="meshes side by side: a PNG picture or an interactive HTML page"
    )
    p.add_argument("inputs", nargs="+", help="meshes to show (.obj .off .ply .stl)")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        help=".png: shaded, zoomed and error rows; .html: one self-contained 3-D page",
    )
    p.add_argument(
        "--gt",
        default=None,
        help="clean mesh: colour faces by normal error against it, shown as the last panel",
    )
    p.add_argument("--titles", default=None, help="comma-separated panel titles")
    p.add_argument("--elev", type=float, default=20.0, help="camera elevation, degrees")
    p.add_argument("--azim", type=float, default=-60.0, help="camera azimuth, degrees")
    p.add_argument(
        "--up",
        default="auto",
        choices=["auto", "y", "z"],
        help="the models' up axis; auto: z if the meshes stand on a flat base under z, "
        "else y (the convention of scans; dmd_jax.render.guess_up_axis)",
    )
    p.add_argument(
        "--panel-size", type=float, default=3.2, help="inches per panel (HTML: × 130 px)"
    )
    p.add_argument(
        "--range",
        type=float,
        nargs=2,
        metavar=("LOW", "HIGH"),
        default=None,
        help="error colour range in degrees (default: 0 to the best panel's 95th "
        "percentile, rounded up)",
    )
    p.add_argument("--no-zoom", action="store_true", help="PNG: no zoom on the sharpest edge")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--parents", action="store_true", help="create -o's missing folders")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser(
        "make-dataset", help="generate procedural training meshes, or convert a mesh folder"
    )
    p.add_argument("--out", required=True, help="output directory (must be empty)")
    p.add_argument("--per-category", type=int, default=None, help="shapes per category")
    p.add_argument("--seed", type=int, default=0, help="shape and split seed")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--min-vertices", type=int, default=1000, help="smallest vertex count")
    p.add_argument("--max-vertices", type=int, default=6000, help="largest vertex count")
    p.add_argument(
        "--test-inter",
        default=None,
        help='comma-separated categories held out whole; "" holds out none (default: '
        "fastener,bottle,metaballs for procedural data, none for folders)",
    )
    p.add_argument("--categories", default=None, help="comma-separated subset of categories")
    p.add_argument("--intra-fraction", type=float, default=0.2, help="test-intra share")
    p.add_argument(
        "--from-folder", default=None, help="convert a category/*.obj|off|ply folder instead"
    )
    p.add_argument("--remesh", action="store_true", help="remesh folder meshes into the range")
    p.add_argument("--overwrite", action="store_true", help="allow a non-empty --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_make_dataset)

    p = sub.add_parser("train", help="train DMD-Net on a dataset made by make-dataset")
    p.add_argument("--data", required=True, help="dataset directory (make-dataset output)")
    p.add_argument("--workdir", required=True, help="checkpoints, log.jsonl, loss_curve.png")
    p.add_argument("--preset", default="small", help="paper, small or test")
    p.add_argument(
        "--set",
        nargs="*",
        metavar="SECTION.FIELD=VALUE",
        help="config edits, e.g. train.steps=3000 loss.vertex=50",
    )
    p.add_argument(
        "--eval-meshes",
        type=int,
        default=None,
        help="sets data.eval_meshes_per_split: meshes of each test split used for "
        "periodic evaluation (default: the config's, 8 of each)",
    )
    p.add_argument(
        "--init-from",
        default=None,
        help="sets train.init_from: checkpoint directory or weights file to fine-tune from "
        "(the same parameter shapes; settings that hold no parameters, such as "
        "vertex_iterations, may differ)",
    )
    p.add_argument(
        "--real-meshes",
        default=None,
        metavar="DIR",
        help="sets data.real_root: folder of real meshes (e.g. ../shared/meshes/train): "
        "its training split is added as connected patches, its fixed validation split "
        "(dmd_jax.data.real) is evaluated as 'val' with the benchmark noise and picks the "
        "best checkpoint (patch sizes: data.real_* fields, e.g. --set "
        "data.real_patch_faces=4000)",
    )
    p.add_argument(
        "--pad",
        choices=("auto", "bucket", "largest"),
        default="auto",
        help="bucket: each batch padded to its own vertex bucket (one compiled program per "
        "bucket, least padding); largest: every batch to the largest the data can form (one "
        "program); auto: largest for runs of at most 500 steps "
        "(dmd_jax.train.AUTO_PAD_MAX_STEPS)",
    )
    p.add_argument(
        "--json", action="store_true", help="print the final evaluation as JSON, not one line"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--data-parallel",
        action="store_true",
        help="split each global batch over every device (train.batch_size >= devices)",
    )
    p.add_argument(
        "--coordinator",
        default=None,
        metavar="HOST:PORT",
        help="multi-host: address of process 0 (with --num-processes, --process-id)",
    )
    p.add_argument(
        "--num-processes", type=int, default=None, help="multi-host: number of processes"
    )
    p.add_argument("--process-id", type=int, default=None, help="multi-host: this process, 0..N-1")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("export-weights", help="checkpoint directory -> one weights file")
    p.add_argument(
        "checkpoint",
        help="an Orbax checkpoint directory (e.g. RUN/checkpoints/best), or a weights file "
        "to rewrite with a new --pass-tolerance / --presmooth",
    )
    p.add_argument("-o", "--output", required=True, help="weights file to write (.msgpack)")
    p.add_argument("--meta", default=None, help="JSON object of provenance to store")
    p.add_argument(
        "--pass-tolerance",
        type=float,
        default=None,
        help="store this pass tolerance in the weights' policy: passes repeat while the last "
        "moved the mesh by more than it, in mean edges (fit it with `make calibrate`; "
        "0: every one of --max-passes)",
    )
    p.add_argument(
        "--max-passes",
        type=int,
        default=None,
        help="store this most network passes in the weights' policy",
    )
    p.add_argument(
        "--relax-steps",
        type=int,
        default=None,
        help="store this many tangential relaxation steps in the weights' policy",
    )
    p.add_argument(
        "--presmooth",
        type=float,
        nargs=2,
        default=None,
        metavar=("START", "PER_STEP"),
        help="store this pre-smoothing rule in the weights' policy (degrees of roughness: "
        "round((roughness - START) / PER_STEP) steps; fit it with `make calibrate`; "
        "START 0 turns it off), in place of a learned pre-smoothing choice",
    )
    p.add_argument(
        "--policy-from",
        default=None,
        metavar="WEIGHTS",
        help="take the inference policy (learned pre-smoothing, rules) from this weights "
        "file instead of the checkpoint's trained policy, e.g. the weights a fine-tune "
        "started from; the options above still edit it",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cmd_export_weights)

    # Further subcommands are registered below, one block each.
    p = sub.add_parser(
        "demo", help="denoise a generated noisy CAD part; print metrics, write meshes and a PNG"
    )
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument(
        "--weights",
        default=None,
        help="weights file or checkpoint directory (default: bundled model)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--no-render", action="store_true", help="skip before_after.png")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser(
        "train-cnr", help="train the CNR baseline (dmd_jax.baselines.cascaded_regression)"
    )
    p.add_argument("--data", required=True, help="dataset directory (make-dataset output)")
    p.add_argument("--out", required=True, help="weights file to write (.msgpack)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--max-meshes", type=int, default=None, help="first N train meshes only")
    p.add_argument("--draws", type=int, default=1, help="noisy copies per mesh")
    p.add_argument("--faces-per-mesh", type=int, default=512, help="faces sampled per copy")
    p.add_argument("--steps", type=int, default=2000, help="Adam steps per stage")
    p.add_argument("--batch-size", type=int, default=1024, help="faces per Adam step")
    p.add_argument("--lr", type=float, default=2e-3, help="Adam learning rate")
    p.add_argument("--seed", type=int, default=0, help="noise and sampling seed")
    p.add_argument("--stages", type=int, default=2, help="cascade length")
    p.add_argument(
        "--hidden", type=int, nargs="+", default=[128, 128, 64], help="MLP hidden widths"
    )
    p.add_argument(
        "--vertex-iterations", type=int, default=20, help="vertex update passes per stage"
    )
    p.add_argument("--eval-meshes", type=int, default=8, help="test-intra meshes checked")
    p.set_defaults(func=_cmd_train_cnr)

    # Every subcommand's help shows the defaults and an example (dmd-jax CMD --help).
    parser.formatter_class = _HelpFormatter
    parser.epilog = "examples: dmd-jax demo --out out/demo; dmd-jax COMMAND --help"
    for name, p in sub.choices.items():
        p.formatter_class = _HelpFormatter
        p.epilog = "example:\n  " + "\n  ".join(EXAMPLES[name])
    return parser


# One or two example command lines per subcommand, shown by `dmd-jax CMD --help`.
EXAMPLES = {
    "info": ["dmd-jax info --preset small"],
    "denoise": [
        "dmd-jax denoise scan.ply -o scan_dmd.ply",
        "dmd-jax denoise scan.ply -o scan_bnf.ply --method bnf",
        "dmd-jax denoise scans/ --out scans_dmd/ --max-memory 8GB",
    ],
    "add-noise": ["dmd-jax add-noise part.obj -o part_noisy.obj --level 0.2 --units edge"],
    "evaluate": ["dmd-jax evaluate --gt part.obj --mesh part_noisy.obj part_dmd.obj"],
    "render": [
        "dmd-jax render part_noisy.obj part_dmd.obj --gt part.obj -o cmp.png",
        "dmd-jax render part_noisy.obj part_dmd.obj --gt part.obj -o cmp.html",
    ],
    "make-dataset": [
        "dmd-jax make-dataset --out data/procedural --per-category 40",
        "dmd-jax make-dataset --out data/tiny --per-category 2   # 38 meshes, ~16 s",
    ],
    "train": [
        "dmd-jax train --data data/procedural --workdir runs/small --preset small",
        "dmd-jax train --data data/tiny --workdir runs/tiny --preset test   # a first run",
    ],
    "export-weights": ["dmd-jax export-weights runs/small/checkpoints/best -o mine.msgpack"],
    "demo": ["dmd-jax demo --out out/demo"],
    "train-cnr": ["dmd-jax train-cnr --data data/procedural --out cnr.msgpack"],
}


class _Terminated(KeyboardInterrupt):
    """SIGTERM (`timeout`, schedulers, `docker stop`), raised like Ctrl-C so that every
    cleanup runs: an atomic write removes its temporary file."""


def _on_sigterm(signum, frame):
    raise _Terminated()


def main(argv: list[str] | None = None) -> int:
    import signal
    import threading

    parser = build_parser()
    args = parser.parse_args(argv)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return _run(args)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError) as exc:
        # One line whatever the message holds (some library errors span several lines).
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"dmd-jax {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, _Terminated)
        what = "terminated" if terminated else "interrupted"
        print(f"dmd-jax {args.command}: {what}{getattr(exc, 'hint', '')}", file=sys.stderr)
        return 143 if terminated else 130


if __name__ == "__main__":
    sys.exit(main())
