"""`dmd-jax denoise`: one mesh file (-o FILE), or several and folders (--out DIR)."""

from __future__ import annotations

import argparse
import contextlib
import re
import sys
from pathlib import Path

from dmd_jax.cli._common import (
    MESH_SUFFIXES,
    METHODS,
    MIN_MAX_MEMORY,
    WEIGHTED_METHODS,
    _check_output,
    _load_input,
    _make_parent,
    _note,
    check_range,
    check_weights_path,
    output_lock,
)


def _denoise_inputs(args: argparse.Namespace):
    """`[(input, output)]` of a `denoise` call: one file and `-o`, or files and folders
    (their mesh files, not recursive, less `atomic_write`'s temporary files) and
    `--out DIR` (same names there)."""
    import os
    from pathlib import Path

    if args.skip_existing and args.overwrite:
        raise ValueError("--skip-existing and --overwrite contradict each other; pass one")
    for name in args.input:
        # Said first: a missing folder is not "one input file" (the wrong problem).
        if not os.path.lexists(name):
            raise FileNotFoundError(f"{name}: no such file or folder")
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
    from dmd_jax.io import is_temp_name

    files = []
    skipped = 0
    for name in args.input:
        p = Path(name)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.suffix.lower() in MESH_SUFFIXES)
            # An interrupted write's temporary file (`.NAME.XXXXXXXX.obj`) is no input,
            # even where it happens to hold a whole mesh.
            mine = [q for q in found if is_temp_name(q.name)]
            skipped += len(mine)
            found = [q for q in found if not is_temp_name(q.name)]
            if not found:
                raise ValueError(f"{name}: holds no mesh files ({', '.join(MESH_SUFFIXES)})")
            files += found
        else:
            files.append(p)
    if skipped:
        _note(f"left out {skipped} unfinished temporary files of an interrupted write")
    out = Path(args.out)
    if out.is_symlink() and not os.path.exists(out):
        raise ValueError(f"{args.out}: is a symbolic link to nothing (or a loop)")
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
    outputs of an interrupted run are complete files: every write is atomic); an output
    that is an input (`--out` the input folder) is no finished output, and is refused
    as without the flag.
    """
    from pathlib import Path

    from dmd_jax.io import same_file

    sources = [src for src, _ in pairs]
    todo = []
    for src, dst in pairs:
        if args.skip_existing and Path(dst).is_file():
            if any(same_file(s, dst) for s in sources):
                _check_output(dst, sources, args.overwrite, suffixes=MESH_SUFFIXES)  # refuses
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
    if args.method == "dmd":
        from dmd_jax.policy import MAX_PASSES_LIMIT as most
    else:
        from dmd_jax.baselines import MAX_PASSES as most
    check_range("--iterations", args.iterations, 1, most)
    check_weights_path("--weights", args.weights)
    if args.weights is not None and args.method not in WEIGHTED_METHODS:
        raise ValueError(
            f"--weights is for --method {' or '.join(WEIGHTED_METHODS)}; {args.method!r} is a "
            "classic filter with no weights (drop --weights)"
        )
    extra = {}
    if args.max_memory is not None:
        if args.method != "dmd":
            raise ValueError("--max-memory is for --method dmd (the network)")
        from dmd_jax.memory_plan import format_bytes, parse_memory

        extra["max_memory"] = parse_memory(args.max_memory, "--max-memory")
        if extra["max_memory"] < MIN_MAX_MEMORY:
            unitless = re.fullmatch(r"\s*[0-9.eE+-]+\s*", args.max_memory) is not None
            raise ValueError(
                f"--max-memory {args.max_memory} is {format_bytes(extra['max_memory'])}"
                f"{' (a number without a unit counts bytes)' if unitless else ''}, below the "
                f"least the network runs in, {format_bytes(MIN_MAX_MEMORY)} (its compiled "
                "programs and XLA's working memory alone): write e.g. 8GB"
            )
    if args.relax is not None:
        if args.method != "dmd":
            raise ValueError("--relax is for --method dmd (the network)")
        if args.relax < 0:
            raise ValueError(f"--relax must be 0 or more steps, got {args.relax}")
        from dmd_jax.policy import MAX_RELAX_STEPS

        check_range("--relax", args.relax, 0, MAX_RELAX_STEPS)
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
            from dmd_jax.presmooth import MAX_STEPS

            check_range("--presmooth", steps, 0, MAX_STEPS)
            extra["presmooth"] = steps
        else:
            extra["presmooth"] = "rule"
    if args.controller is not None:
        if args.method != "dmd":
            raise ValueError("--controller is for --method dmd (the network)")
        extra["controller"] = args.controller == "on"
    pairs = _denoise_inputs(args)
    if args.out is None:  # one file: refused by its size before the weights are read too
        _check_size(pairs[0][0] if pairs else args.input[0], extra.get("max_memory"))
    with contextlib.ExitStack() as stack:
        if args.out is not None and pairs:
            # Two runs writing one folder at once would replace each other's outputs.
            Path(args.out).mkdir(parents=True, exist_ok=True)
            stack.enter_context(output_lock(args.out))
        weights = args.weights
        if args.method == "dmd":
            from dmd_jax.checkpoints import load_model

            # Once for every mesh, and before any: unreadable weights are refused first.
            weights = load_model(weights)
        t_all = time.perf_counter()
        failed, done = _denoise_all(args, pairs, weights, extra, denoise_with, save_mesh)
    many = args.out is not None
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


def _denoise_all(args, pairs, weights, extra, denoise_with, save_mesh):
    """Runs every pair; `(failed [(input, message)], number written)`."""
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
            if Path(src).name not in message:  # every line names its file
                message = f"{src}: {message}"
            print(f"dmd-jax denoise: error: {message} (going on with the others)", file=sys.stderr)
            failed.append((src, message))
        except KeyboardInterrupt as exc:
            if many:
                exc.hint = (
                    f" after {done} of {len(pairs)} meshes; the finished outputs are complete "
                    "files: rerun the same command with --skip-existing to resume"
                )
            raise
    return failed, done


def _check_size(src, max_memory: int | None) -> None:
    """Refuses, by its size and before reading it, a file larger than the memory budget
    (reading it alone would take more)."""
    import os

    if max_memory is None:
        return
    size = os.stat(src).st_size
    if size > max_memory:
        from dmd_jax.memory_plan import format_bytes

        raise ValueError(
            f"{src}: the file is {format_bytes(size)}, more than the --max-memory budget of "
            f"{format_bytes(max_memory)} (reading it alone would exceed it)"
        )


def _denoise_one(args, src, dst, weights, extra, denoise_with, save_mesh) -> int:
    """Denoises one file into `dst` and prints its line; returns 1."""
    import time

    _check_size(src, extra.get("max_memory"))
    vertices, faces = _load_input(src)
    if args.parents:
        _make_parent(dst)
    compiles = _compiled_so_far(args.method)
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
    if info is not None and info.controller:
        how += f" [{info.controller}]"
    print(
        f"denoised {src} ({len(vertices)} vertices, {len(faces)} faces) with "
        f"{args.method}{how} in {elapsed:.2f} s -> {dst}"
    )
    _note_compiles(args, compiles)
    return 1


def _compiled_so_far(method: str) -> int | None:
    """How many network programs this process compiled so far (None: not the network)."""
    if method != "dmd":
        return None
    from dmd_jax.forward import COMPILED

    return len(COMPILED)


def _note_compiles(args, before: int | None) -> None:
    """Once per process: says that the call compiled the network for this mesh's size,
    and that `dmd-jax warmup` compiles it for every size once."""
    if before is None or getattr(args, "_noted_compile", False):
        return
    from dmd_jax.forward import COMPILED
    from dmd_jax.warmup import DEFAULT_MAX_FACES, DEFAULT_MIN_FACES

    seconds = sum(s for name, s in COMPILED[before:] if name == "predict")
    if seconds:
        args._noted_compile = True
        _note(
            f"compiled the network for meshes of this size ({seconds:.1f} s of the time "
            f"above, kept in the cache for the next run); `dmd-jax warmup` compiles it "
            f"for every size from {DEFAULT_MIN_FACES:,d} to {DEFAULT_MAX_FACES:,d} faces once"
        )


def add_parser(sub) -> None:
    """Registers the subcommand on `sub`, the parser's subparsers."""
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
        help="uniform Laplacian steps before the network (default, or 'rule': the "
        "roughness rule stored with the weights' policy; 0: none)",
    )
    p.add_argument(
        "--controller",
        choices=("on", "off"),
        default=None,
        help="on: the learned smoothing controller stored with the weights chooses the "
        "pre-smoothing, passes and vertex update per mesh; off: the policy's rules "
        "(default: as the weights' policy says)",
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
