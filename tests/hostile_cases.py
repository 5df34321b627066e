"""A generator of hostile cases: round 2 (issue 56, families 3-7, `cases()`, run by
`tests/test_hostile2.py`) and round 3 (issue 65, families 2-8, `round3()`, run by
`tests/test_hostile3.py`); `python tests/hostile_cases.py` runs both.

`cases()` returns every case as a `Case(name, family, run)`; `run(tmp)` does what a
hostile user would, through the CLI (in process) or the API, in the empty folder `tmp`,
and raises `AssertionError` saying what went wrong: a traceback, an exit code other than
the one expected, an error that is not one line naming the argument or file, a file
written or an input changed. `run_case` turns any other exception into a failure too,
so a case counts as failed whatever breaks.

Nothing here runs for long: whatever a case expects to be refused before the work
starts runs under `no_work()`, which makes every denoiser, the dataset builder and the
trainers raise if they are reached.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import os
import shutil
import struct
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# The bundled weights of the dmd_jax imported (another checkout's, under PYTHONPATH).
BUNDLED = Path(importlib.util.find_spec("dmd_jax").origin).parent / "weights/dmd_small.msgpack"
CLASSIC = ("laplacian", "taubin", "bmd", "nifp", "fefp", "bnf", "gnf", "l0")


class Case(NamedTuple):
    name: str
    family: int
    run: Callable[[Path], None]


class WorkStarted(AssertionError):
    """Raised by `no_work()`'s stand-ins: the work began before the refusal."""


# --------------------------------------------------------------------------------------
# Meshes and helpers
# --------------------------------------------------------------------------------------


def sphere(level: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """An octahedron subdivided `level` times and projected on the unit sphere."""
    v = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    f = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    v = [np.array(p, float) for p in v]
    for _ in range(level):
        mid, nf = {}, []

        def middle(a, b, mid=mid):
            key = (min(a, b), max(a, b))
            if key not in mid:
                mid[key] = len(v)
                v.append((v[a] + v[b]) / 2)
            return mid[key]

        for a, b, c in f:
            ab, bc, ca = middle(a, b), middle(b, c), middle(c, a)
            nf += [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
        f = nf
    v = np.array(v)
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.array(f, np.int64)


V, F = sphere(1)


def write(path: Path, v=V, f=F) -> Path:
    from dmd_jax.io import save_mesh

    save_mesh(path, v, f, overwrite=True)
    return path


def cli(*argv) -> tuple[int, str, str]:
    """`dmd-jax ARGV` in process: `(exit code, stdout, stderr)`; a traceback fails."""
    from dmd_jax.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse
            code = exc.code if isinstance(exc.code, int) else 2
        except WorkStarted:
            raise
        except Exception as exc:
            raise AssertionError(
                f"traceback: {type(exc).__name__}: {exc}\n{traceback.format_exc(limit=-3)}"
            ) from exc
    return code, out.getvalue(), err.getvalue()


def snapshot(folder: Path) -> dict[str, bytes | str]:
    """Every entry under `folder` (not following links): its bytes, or what it is."""
    found = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = Path(root) / name
            rel = str(p.relative_to(folder))
            if p.is_symlink():
                found[rel] = "link -> " + os.readlink(p)
            elif p.is_file() and p.stat().st_size > 1 << 20:
                # A large (sparse) input: its size and time of change, not 3 GB of reading.
                info = p.stat()
                found[rel] = f"{info.st_size} bytes, changed {info.st_mtime_ns}"
            elif p.is_file():
                found[rel] = p.read_bytes()
            else:
                found[rel] = "dir"
    return found


def refused(result, *words, code: int = 2) -> str:
    """Checks a refusal: the exit code, one error line holding every word; returns it."""
    got, _, err = result
    lines = [line for line in err.splitlines() if line.strip()]
    assert got == code, f"exit code {got}, expected {code}; stderr: {err.strip()[:300]!r}"
    errors = [line for line in lines if "error:" in line]
    assert errors, f"no error line: {err.strip()[:300]!r}"
    line = errors[-1]
    for w in words:
        assert w.lower() in line.lower(), f"{w!r} not in the error line {line!r}"
    return line


def refused_quietly(tmp: Path, argv, *words, before=None) -> None:
    """`dmd-jax ARGV` is refused (exit 2, one line naming `words`) before any work, and
    leaves `tmp` as it was."""
    before = snapshot(tmp) if before is None else before
    with no_work():
        result = cli(*argv)
    refused(result, *words)
    after = snapshot(tmp)
    assert after == before, f"files changed: {sorted(set(after) ^ set(before))[:5]}"


@contextlib.contextmanager
def no_work():
    """Every denoiser, the dataset builder and the trainers raise `WorkStarted`."""
    import dmd_jax.api
    import dmd_jax.baselines
    import dmd_jax.baselines.cascaded_regression as cnr
    import dmd_jax.data.dataset
    import dmd_jax.demo
    import dmd_jax.inference
    import dmd_jax.render
    import dmd_jax.train
    import dmd_jax.viewer

    def boom(*args, **kwargs):
        raise WorkStarted("the work started before the refusal")

    targets = [
        (dmd_jax.api, "denoise_with"),
        (dmd_jax.api, "add_noise"),
        (dmd_jax.baselines, "run_baseline"),
        (dmd_jax.inference, "denoise"),
        (dmd_jax.data.dataset, "build_dataset"),
        (dmd_jax.train, "train_and_evaluate"),
        (cnr, "train_main"),
        (dmd_jax.demo, "run_demo"),
        (dmd_jax.render, "render_meshes"),
        (dmd_jax.viewer, "comparison_html"),
    ]
    saved = [(m, n, getattr(m, n)) for m, n in targets]
    try:
        for m, n in targets:
            setattr(m, n, boom)
        yield
    finally:
        for m, n, fn in saved:
            setattr(m, n, fn)


def expect_value_error(fn, *words) -> None:
    """`fn()` raises `ValueError` (or `OSError`) whose message holds every word."""
    try:
        fn()
    except (ValueError, OSError) as exc:
        text = str(exc).lower()
        for w in words:
            assert w.lower() in text, f"{w!r} not in {str(exc)[:200]!r}"
        return
    except WorkStarted:
        raise
    except Exception as exc:
        raise AssertionError(f"{type(exc).__name__} instead of ValueError: {exc}") from exc
    raise AssertionError("no error raised")


# --------------------------------------------------------------------------------------
# Family 3: number formats
# --------------------------------------------------------------------------------------


def _f3_stl_overflow(value: float, axis: int, via: str):
    def run(tmp: Path) -> None:
        v = V.copy()
        v[0, axis] = value
        out = tmp / "big.stl"
        if via == "api":
            from dmd_jax.io import save_mesh

            expect_value_error(lambda: save_mesh(out, v, F), "big.stl", "float32")
            assert not out.exists(), "a file was written"
        else:
            src = write(tmp / "big.obj", v)
            before = snapshot(tmp)
            result = cli("denoise", src, "-o", out, "--method", "laplacian")
            refused(result, "big.stl", "float32")
            assert snapshot(tmp) == before, "a file was written"

    return run


def _f3_offset_classic(method: str, offset: float, axis: int):
    """A detailed unit sphere at a survey-scale offset: the result must be the result at
    the origin, moved (the filters work in the mesh's own frame)."""

    def run(tmp: Path) -> None:
        from dmd_jax import denoise_with

        rng = np.random.default_rng(0)
        v = V + 1e-3 * rng.standard_normal(V.shape)
        shift = np.zeros(3)
        shift[axis] = offset
        at_origin = denoise_with(method, v, F)
        far = denoise_with(method, v + shift, F)
        err = np.abs((far - shift) - at_origin).max()
        # float64 holds ~1e-16 × 1e8 = 1e-8 at these offsets; 1e-6 of the unit size.
        assert err < 1e-6, f"moved by {offset:g}: the result differs by {err:.3g}"

    return run


def _f3_offset_stl(offset: float):
    """Writing an STL (float32) of a mesh far from the origin: refused or exact."""

    def run(tmp: Path) -> None:
        from dmd_jax.io import load_mesh, save_mesh

        v = V * 0.01 + offset  # 1 cm detail at `offset`
        out = tmp / "far.stl"
        try:
            save_mesh(out, v, F)
        except ValueError as exc:
            assert "far.stl" in str(exc) and "float32" in str(exc), str(exc)
            assert not out.exists()
            return
        back, faces = load_mesh(out)
        assert len(back) == len(v), f"float32 merged {len(v) - len(back)} vertices silently"
        err = np.abs(np.sort(back, axis=0) - np.sort(v, axis=0)).max()
        assert err <= 1e-3 * 0.01, f"float32 moved vertices by {err:.3g} (detail 0.01) silently"

    return run


def _ply_with_duplicate(fmt: str, dup: str) -> bytes:
    vprops = ["x", "y", "z"]
    fprop = "vertex_indices"
    vp = vprops + ([dup] if dup in vprops else [])
    fp = [fprop] + ([fprop] if dup == fprop else [])
    head = [
        "ply",
        f"format {fmt} 1.0",
        f"element vertex {len(V)}",
        *[f"property double {p}" for p in vp],
        f"element face {len(F)}",
        *[f"property list uchar int {p}" for p in fp],
        "end_header",
    ]
    text = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        extra = [vprops.index(dup)] if dup in vprops else []
        rows = [" ".join(repr(float(x)) for x in [*p, *p[extra]]) for p in V]
        rows += [" ".join(["3", *map(str, f)] * (2 if dup == fprop else 1)) for f in F]
        return text + ("\n".join(rows) + "\n").encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    body = b""
    for p in V:
        vals = list(p) + ([p[vprops.index(dup)]] if dup in vprops else [])
        body += struct.pack(order + "d" * len(vals), *vals)
    for f in F:
        one = struct.pack(order + "B3i", 3, *map(int, f))
        body += one * (2 if dup == fprop else 1)
    return text + body


def _f3_ply_duplicate(fmt: str, dup: str):
    def run(tmp: Path) -> None:
        from dmd_jax.io import load_mesh

        p = tmp / "dup.ply"
        p.write_bytes(_ply_with_duplicate(fmt, dup))
        expect_value_error(lambda: load_mesh(p), "dup.ply", dup, "twice")

    return run


def _f3_ply_duplicate_element(fmt: str):
    def run(tmp: Path) -> None:
        from dmd_jax.io import load_mesh

        head = (
            f"ply\nformat {fmt} 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
            "property float z\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            "end_header\n"
        )
        if fmt == "ascii":
            body = b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
        else:
            o = "<" if fmt == "binary_little_endian" else ">"
            body = struct.pack(o + "9f", 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack(
                o + "B3i", 3, 0, 1, 2
            )
        p = tmp / "twice.ply"
        p.write_bytes(head.encode() + body)
        expect_value_error(lambda: load_mesh(p), "twice.ply", "vertex", "twice")

    return run


def family3() -> list[Case]:
    out = []
    for value in (3.5e38, 1e39, -1e39, 1e300, -1e300, 1.7e308):
        for axis in range(3):
            out.append(
                Case(
                    f"f3-stl-overflow-api-{value:g}-{'xyz'[axis]}",
                    3,
                    _f3_stl_overflow(value, axis, "api"),
                )
            )
        if abs(value) >= 1e300:  # smoothing keeps such a vertex beyond float32's range
            out.append(Case(f"f3-stl-overflow-cli-{value:g}", 3, _f3_stl_overflow(value, 0, "cli")))
    for method in ("laplacian", "taubin", "bnf", "fefp", "nifp"):
        for offset in (1e5, 1e6, 1e7):
            out.append(
                Case(f"f3-offset-{method}-{offset:g}", 3, _f3_offset_classic(method, offset, 0))
            )
    for offset in (1e4, 1e5, 1e6, 1e7, -1e6):
        out.append(Case(f"f3-offset-stl-{offset:g}", 3, _f3_offset_stl(offset)))
    for fmt in ("ascii", "binary_little_endian", "binary_big_endian"):
        for dup in ("x", "y", "z", "vertex_indices"):
            out.append(Case(f"f3-ply-dup-{dup}-{fmt}", 3, _f3_ply_duplicate(fmt, dup)))
        out.append(Case(f"f3-ply-dup-element-{fmt}", 3, _f3_ply_duplicate_element(fmt)))
    return out


# --------------------------------------------------------------------------------------
# Family 4: nothing the user gave is overwritten
# --------------------------------------------------------------------------------------


def _f4_export_onto_input(how: str, overwrite: bool):
    def run(tmp: Path) -> None:
        src = tmp / "w.msgpack"
        shutil.copy(BUNDLED, src)
        if how == "same":
            out = src
        elif how == "relative":
            out = tmp / "." / "w.msgpack"
        elif how == "hardlink":
            out = tmp / "hard.msgpack"
            os.link(src, out)
        elif how == "symlink":
            out = tmp / "link.msgpack"
            out.symlink_to(src)
        elif how == "policy-from":
            other = tmp / "other.msgpack"
            shutil.copy(BUNDLED, other)
            argv = ["export-weights", other, "-o", src, "--policy-from", src]
            refused_quietly(tmp, argv + (["--overwrite"] if overwrite else []), "w.msgpack")
            return
        argv = ["export-weights", src, "-o", out] + (["--overwrite"] if overwrite else [])
        refused_quietly(tmp, argv, "input")

    return run


def _f4_temp_names(ext: str, complete: bool):
    def run(tmp: Path) -> None:
        folder = tmp / "in"
        folder.mkdir()
        write(folder / f"a{ext}")
        temp = folder / f".a{ext}.k3j9x_2q{ext}"
        if complete:
            write(temp)
        else:
            temp.write_bytes((folder / f"a{ext}").read_bytes()[:40])
        code, _, err = cli("denoise", folder, "--out", tmp / "out", "--method", "laplacian")
        assert code == 0, f"exit {code}: {err.strip()[:300]}"
        written = sorted(p.name for p in (tmp / "out").iterdir())
        assert written == [f"a{ext}"], f"wrote {written}"

    return run


def _f4_own_input(kind: str):
    def run(tmp: Path) -> None:
        src = write(tmp / "in.obj")
        folder = tmp / "meshes"
        folder.mkdir()
        write(folder / "a.obj")
        write(folder / "b.off")
        argvs = {
            "denoise-same": ["denoise", src, "-o", src, "--overwrite", "--method", "laplacian"],
            "denoise-folder": [
                "denoise",
                folder,
                "--out",
                folder,
                "--overwrite",
                "--method",
                "laplacian",
            ],
            "denoise-folder-relative": [
                "denoise",
                folder,
                "--out",
                tmp / "meshes" / ".",
                "--overwrite",
                "--method",
                "laplacian",
            ],
            "add-noise-same": ["add-noise", src, "-o", src, "--overwrite", "--level", "0.1"],
            "add-noise-dotdot": [
                "add-noise",
                src,
                "-o",
                folder / ".." / "in.obj",
                "--overwrite",
                "--level",
                "0.1",
            ],
            "make-dataset-same": [
                "make-dataset",
                "--out",
                folder,
                "--from-folder",
                folder,
                "--overwrite",
            ],
            "make-dataset-parent": [
                "make-dataset",
                "--out",
                tmp,
                "--from-folder",
                folder,
                "--overwrite",
            ],
            "train-cnr-same": [
                "train-cnr",
                "--data",
                folder,
                "--out",
                folder / "a.obj",
                "--overwrite",
            ],
            "demo-weights-inside": [
                "demo",
                "--out",
                tmp,
                "--weights",
                tmp / "clean.obj",
                "--overwrite",
            ],
        }
        if kind == "demo-weights-inside":
            write(tmp / "clean.obj")
        if kind == "denoise-symlink":
            link = tmp / "link.obj"
            link.symlink_to(src)
            argv = ["denoise", src, "-o", link, "--overwrite", "--method", "laplacian"]
        else:
            argv = argvs[kind]
        refused_quietly(tmp, argv)

    return run


def family4() -> list[Case]:
    out = []
    for how in ("same", "relative", "hardlink", "symlink", "policy-from"):
        for overwrite in (False, True):
            out.append(
                Case(
                    f"f4-export-onto-input-{how}-{'ow' if overwrite else 'plain'}",
                    4,
                    _f4_export_onto_input(how, overwrite),
                )
            )
    for ext in (".obj", ".off", ".ply", ".stl"):
        for complete in (False, True):
            out.append(
                Case(
                    f"f4-folder-temp-{ext[1:]}-{'complete' if complete else 'partial'}",
                    4,
                    _f4_temp_names(ext, complete),
                )
            )
    for kind in (
        "denoise-same",
        "denoise-folder",
        "denoise-folder-relative",
        "add-noise-same",
        "add-noise-dotdot",
        "make-dataset-same",
        "make-dataset-parent",
        "train-cnr-same",
        "demo-weights-inside",
        "denoise-symlink",
    ):
        out.append(Case(f"f4-own-input-{kind}", 4, _f4_own_input(kind)))
    return out


# --------------------------------------------------------------------------------------
# Family 5: no traceback
# --------------------------------------------------------------------------------------


def _loop(path: Path) -> Path:
    """A symbolic link that points at itself."""
    path.symlink_to(path.name)
    return path


def _f5_loop_input(command: str):
    def run(tmp: Path) -> None:
        loop = _loop(tmp / "loop.obj")
        good = write(tmp / "good.obj")
        w = tmp / "w.msgpack"
        argvs = {
            "denoise": ["denoise", loop, "-o", tmp / "o.obj", "--method", "laplacian"],
            "add-noise": ["add-noise", loop, "-o", tmp / "o.obj", "--level", "0.1"],
            "evaluate-gt": ["evaluate", "--gt", loop, "--mesh", good],
            "evaluate-mesh": ["evaluate", "--gt", good, "--mesh", loop],
            "render": ["render", loop, "-o", tmp / "o.png"],
            "denoise-out": ["denoise", good, "-o", loop, "--method", "laplacian", "--overwrite"],
            "add-noise-out": ["add-noise", good, "-o", loop, "--level", "0.1", "--overwrite"],
            "render-out": ["render", good, "-o", _loop(tmp / "l.png"), "--overwrite"],
            "export-out": [
                "export-weights",
                BUNDLED,
                "-o",
                _loop(tmp / "l.msgpack"),
                "--overwrite",
            ],
            "info-weights": ["info", "--weights", _loop(w)],
            "denoise-weights": [
                "denoise",
                good,
                "-o",
                tmp / "o.obj",
                "--weights",
                _loop(tmp / "lw.msgpack"),
            ],
            "denoise-folder-out": [
                "denoise",
                good,
                good.with_name("good2.obj"),
                "--out",
                _loop(tmp / "outdir"),
                "--method",
                "laplacian",
            ],
        }
        if command == "denoise-folder-out":
            write(tmp / "good2.obj")
        refused_quietly(tmp, argvs[command], "loop" if "loop" in command else "")

    return run


def _f5_loop_in_folder(kind: str):
    def run(tmp: Path) -> None:
        folder = tmp / "in"
        folder.mkdir()
        write(folder / "a.obj")
        write(folder / "b.ply")
        if kind == "loop":
            _loop(folder / "bad.obj")
        elif kind == "dangling":
            (folder / "bad.obj").symlink_to("nowhere.obj")
        elif kind == "dir":
            (folder / "bad.obj").mkdir()
        elif kind == "fifo":
            os.mkfifo(folder / "bad.obj")
        elif kind == "mutual":
            (folder / "bad.obj").symlink_to("bad2.off")
            (folder / "bad2.off").symlink_to("bad.obj")
        code, _, err = cli("denoise", folder, "--out", tmp / "out", "--method", "laplacian")
        written = sorted(p.name for p in (tmp / "out").iterdir()) if (tmp / "out").exists() else []
        assert written == ["a.obj", "b.ply"], f"wrote {written}; stderr {err.strip()[:300]}"
        assert code == 1, f"exit {code}"
        lines = [line for line in err.splitlines() if "error:" in line]
        assert lines and all("bad" in line for line in lines), err[:300]

    return run


def _f5_meta(text: str):
    def run(tmp: Path) -> None:
        src = tmp / "w.msgpack"
        shutil.copy(BUNDLED, src)
        refused_quietly(
            tmp, ["export-weights", src, "-o", tmp / "o.msgpack", "--meta", text], "--meta"
        )

    return run


def _f5_too_big(ext: str, size: int, budget: str):
    def run(tmp: Path) -> None:
        big = tmp / f"big{ext}"
        with open(big, "wb") as fh:  # sparse: no disk used
            fh.truncate(size)
        import dmd_jax.io

        def read(*args, **kwargs):  # reading a sparse 3 GB file would take 3 GB
            raise WorkStarted("the file was read before its size was checked")

        real, dmd_jax.io.load_mesh = dmd_jax.io.load_mesh, read
        try:
            argv = ["denoise", big, "-o", tmp / f"o{ext}", "--max-memory", budget]
            refused_quietly(tmp, argv, f"big{ext}", "--max-memory")
        finally:
            dmd_jax.io.load_mesh = real

    return run


def family5() -> list[Case]:
    out = []
    for command in (
        "denoise",
        "add-noise",
        "evaluate-gt",
        "evaluate-mesh",
        "render",
        "denoise-out",
        "add-noise-out",
        "render-out",
        "export-out",
        "info-weights",
        "denoise-weights",
        "denoise-folder-out",
    ):
        out.append(Case(f"f5-symlink-loop-{command}", 5, _f5_loop_input(command)))
    for kind in ("loop", "dangling", "dir", "fifo", "mutual"):
        out.append(Case(f"f5-folder-entry-{kind}", 5, _f5_loop_in_folder(kind)))
    for text in ("[1, 2]", "3", '"text"', "null", "true", "[]", '{"a": NaN}', "[{}]"):
        out.append(Case(f"f5-meta-{text}", 5, _f5_meta(text)))
    for ext in (".obj", ".off", ".ply", ".stl"):
        for size, budget in ((3 * 10**9, "1GB"), (2 * 2**30, "1GiB"), (1300 * 10**6, "1GB")):
            out.append(
                Case(f"f5-too-big-{ext[1:]}-{size}-{budget}", 5, _f5_too_big(ext, size, budget))
            )
    return out


# --------------------------------------------------------------------------------------
# Family 6: bounded work
# --------------------------------------------------------------------------------------


def _f6_cli(argv_tail, word):
    def run(tmp: Path) -> None:
        src = write(tmp / "in.obj")
        data = tmp / "data"
        data.mkdir()
        argv = [
            a.format(src=src, tmp=tmp, data=data) if isinstance(a, str) else a for a in argv_tail
        ]
        refused_quietly(tmp, argv, word)

    return run


def _f6_api(method: str, param: str, value):
    def run(tmp: Path) -> None:
        from dmd_jax import baselines

        with no_work():
            patch = _stop_filters()
            try:
                expect_value_error(
                    lambda: baselines.REGISTRY[method](V, F, **{param: value}), param
                )
            finally:
                patch()

    return run


def _f6_denoise_with(method: str, value):
    def run(tmp: Path) -> None:
        import dmd_jax

        with no_work():
            expect_value_error(
                lambda: dmd_jax.denoise_with(method, V, F, iterations=value), "iterations"
            )

    return run


def _stop_filters():
    """Makes every classic filter's mesh work raise `WorkStarted`; returns the undo."""
    import importlib

    names = [
        "smoothing",
        "bilateral_mesh",
        "normal_filtering",
        "robust_projection",
        "l0_minimization",
    ]
    saved = []

    def boom(*args, **kwargs):
        raise WorkStarted("the filter started before its arguments were checked")

    for n in names:
        m = importlib.import_module(f"dmd_jax.baselines.{n}")
        for attr in ("run_in_canonical_frame", "validate_mesh"):
            if hasattr(m, attr):
                saved.append((m, attr, getattr(m, attr)))
                setattr(m, attr, boom)

    def undo():
        for m, attr, fn in saved:
            setattr(m, attr, fn)

    return undo


HUGE = (100_000_000, 10**9, 2**31, 2**63, 10**30)
API_COUNTS = {
    "laplacian": ["iterations"],
    "taubin": ["iterations"],
    "bmd": ["iterations"],
    "fefp": ["normal_iterations", "vertex_iterations"],
    "bnf": ["normal_iterations", "vertex_iterations"],
    "gnf": ["normal_iterations", "vertex_iterations"],
}


def family6() -> list[Case]:
    out = []
    for method in CLASSIC:
        for n in HUGE:
            out.append(
                Case(
                    f"f6-cli-iterations-{method}-{n}",
                    6,
                    _f6_cli(
                        [
                            "denoise",
                            "{src}",
                            "-o",
                            "{tmp}/o.obj",
                            "--method",
                            method,
                            "--iterations",
                            str(n),
                        ],
                        "--iterations",
                    ),
                )
            )
        for n in (10**8, 2**40):
            out.append(Case(f"f6-denoise-with-{method}-{n}", 6, _f6_denoise_with(method, n)))
    for method, params in API_COUNTS.items():
        for param in params:
            for n in (10**8, 2**31, 10**12):
                out.append(Case(f"f6-api-{method}-{param}-{n}", 6, _f6_api(method, param, n)))
    cli_cases = {
        "dmd-iterations": (
            ["denoise", "{src}", "-o", "{tmp}/o.obj", "--iterations", "100000000"],
            "--iterations",
        ),
        "relax": (["denoise", "{src}", "-o", "{tmp}/o.obj", "--relax", "100000000"], "--relax"),
        "presmooth": (
            ["denoise", "{src}", "-o", "{tmp}/o.obj", "--presmooth", "100000000"],
            "--presmooth",
        ),
        "per-category": (
            ["make-dataset", "--out", "{tmp}/ds", "--per-category", "1000000000"],
            "--per-category",
        ),
        "workers": (["make-dataset", "--out", "{tmp}/ds", "--workers", "100000"], "--workers"),
        "max-vertices": (
            ["make-dataset", "--out", "{tmp}/ds", "--max-vertices", "1000000000000"],
            "--max-vertices",
        ),
        "min-vertices": (
            ["make-dataset", "--out", "{tmp}/ds", "--min-vertices", "0"],
            "--min-vertices",
        ),
        "cnr-steps": (
            [
                "train-cnr",
                "--data",
                "{data}",
                "--out",
                "{tmp}/c.msgpack",
                "--steps",
                "1000000000000",
            ],
            "--steps",
        ),
        "cnr-draws": (
            ["train-cnr", "--data", "{data}", "--out", "{tmp}/c.msgpack", "--draws", "1000000000"],
            "--draws",
        ),
        "cnr-stages": (
            ["train-cnr", "--data", "{data}", "--out", "{tmp}/c.msgpack", "--stages", "1000000"],
            "--stages",
        ),
        "cnr-hidden": (
            ["train-cnr", "--data", "{data}", "--out", "{tmp}/c.msgpack", "--hidden", "1000000000"],
            "--hidden",
        ),
        "cnr-faces": (
            [
                "train-cnr",
                "--data",
                "{data}",
                "--out",
                "{tmp}/c.msgpack",
                "--faces-per-mesh",
                "1000000000000",
            ],
            "--faces-per-mesh",
        ),
        "cnr-batch": (
            [
                "train-cnr",
                "--data",
                "{data}",
                "--out",
                "{tmp}/c.msgpack",
                "--batch-size",
                "1000000000000",
            ],
            "--batch-size",
        ),
        "cnr-vertex-iterations": (
            [
                "train-cnr",
                "--data",
                "{data}",
                "--out",
                "{tmp}/c.msgpack",
                "--vertex-iterations",
                "1000000000",
            ],
            "--vertex-iterations",
        ),
        "cnr-eval": (
            ["train-cnr", "--data", "{data}", "--out", "{tmp}/c.msgpack", "--eval-meshes", "-5"],
            "--eval-meshes",
        ),
        "export-max-passes": (
            ["export-weights", str(BUNDLED), "-o", "{tmp}/e.msgpack", "--max-passes", "1000000000"],
            "--max-passes",
        ),
        "export-relax-steps": (
            [
                "export-weights",
                str(BUNDLED),
                "-o",
                "{tmp}/e.msgpack",
                "--relax-steps",
                "1000000000",
            ],
            "--relax-steps",
        ),
        "train-eval-meshes": (
            ["train", "--data", "{data}", "--workdir", "{tmp}/w", "--eval-meshes", "1000000000"],
            "--eval-meshes",
        ),
        "add-noise-seed": (
            ["add-noise", "{src}", "-o", "{tmp}/o.obj", "--level", "0.1", "--seed", str(2**70)],
            "--seed",
        ),
        "add-noise-level": (
            ["add-noise", "{src}", "-o", "{tmp}/o.obj", "--level", "1e300"],
            "--level",
        ),
    }
    for name, (argv, word) in cli_cases.items():
        out.append(Case(f"f6-cli-{name}", 6, _f6_cli(argv, word)))
    return out


# --------------------------------------------------------------------------------------
# Family 7: clear errors, early
# --------------------------------------------------------------------------------------


def _f7_render_view(arg: str, value: str, ext: str):
    def run(tmp: Path) -> None:
        src = write(tmp / "in.obj")
        refused_quietly(tmp, ["render", src, "-o", tmp / f"o{ext}", arg, value], arg)

    return run


def _f7_render_range(low: str, high: str):
    def run(tmp: Path) -> None:
        src = write(tmp / "in.obj")
        refused_quietly(tmp, ["render", src, "-o", tmp / "o.png", "--range", low, high], "--range")

    return run


def _f7_folder_names_file(kind: str):
    def run(tmp: Path) -> None:
        folder = tmp / "in"
        folder.mkdir()
        write(folder / "good.obj")
        bad = folder / "bad.obj"
        if kind == "empty":
            bad.write_text("")
        elif kind == "garbage":
            bad.write_bytes(b"\x00\x01garbage")
        elif kind == "nan":
            bad.write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
        elif kind == "index":
            bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
        elif kind == "degenerate":
            bad.write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")
        elif kind == "one-face":
            bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
        elif kind == "repeated-corner":
            bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 1 2\nf 1 2 3\n")
        elif kind == "huge":
            bad.write_text("v 1e308 0 0\nv -1e308 0 0\nv 0 1e308 0\nf 1 2 3\n")
        code, _, err = cli("denoise", folder, "--out", tmp / "out", "--method", "bnf")
        assert (tmp / "out" / "good.obj").exists(), f"good.obj not written: {err[:300]}"
        errors = [line for line in err.splitlines() if "error:" in line]
        for line in errors:
            assert "bad.obj" in line, f"an error line names no file: {line!r}"
        if not errors:
            assert (tmp / "out" / "bad.obj").exists(), "neither written nor an error"

    return run


def _f7_long_name(command: str, length: int):
    """An output name of `length` bytes: up to the file system's limit (255) it is
    written, past it refused before the work."""

    def run(tmp: Path) -> None:
        src = write(tmp / "in.obj")
        ext = {"render-png": ".png", "render-html": ".html", "export": ".msgpack"}.get(
            command, ".obj"
        )
        long = tmp / ("n" * (length - len(ext)) + ext)
        argvs = {
            "denoise": ["denoise", src, "-o", long, "--method", "laplacian"],
            "add-noise": ["add-noise", src, "-o", long, "--level", "0.1"],
            "render-png": ["render", src, "-o", long],
            "render-html": ["render", src, "-o", long],
            "export": ["export-weights", BUNDLED, "-o", long],
        }
        if length > 255:
            refused_quietly(tmp, argvs[command], "too long")
            return
        code, _, err = cli(*argvs[command])
        assert code == 0, f"exit {code}: {err.strip()[:300]}"
        assert long.is_file(), "not written"
        assert sorted(p.name for p in tmp.iterdir()) == sorted(["in.obj", long.name])

    return run


def _f7_long_folder_name(length: int):
    def run(tmp: Path) -> None:
        folder = tmp / "in"
        folder.mkdir()
        name = "m" * (length - 4) + ".obj"
        (folder / name).write_bytes((write(tmp / "b.obj")).read_bytes())
        (tmp / "b.obj").rename(folder / "b.obj")
        code, _, err = cli("denoise", folder, "--out", tmp / "out", "--method", "laplacian")
        assert code == 0, f"exit {code}: {err.strip()[:300]}"
        assert sorted(p.name for p in (tmp / "out").iterdir()) == sorted(["b.obj", name])

    return run


def _f7_max_memory(value: str):
    def run(tmp: Path) -> None:
        src = write(tmp / "in.obj")
        refused_quietly(
            tmp, ["denoise", src, "-o", tmp / "o.obj", "--max-memory", value], "--max-memory"
        )

    return run


def _f7_numpy_memory(kind: str):
    def run(tmp: Path) -> None:
        import dmd_jax

        value = {
            "int64": np.int64(8 * 10**9),
            "int32": np.int32(2 * 10**9),
            "uint64": np.uint64(8 * 10**9),
            "float32": np.float32(8e9),
        }[kind]
        bundle = dmd_jax.load_pretrained()
        out = dmd_jax.denoise(V, F, bundle, max_memory=value)
        assert np.asarray(out).shape == V.shape

    return run


def _f7_url(command: str, url: str):
    def run(tmp: Path) -> None:
        src = write(tmp / "in.obj")
        argvs = {
            "denoise": ["denoise", src, "-o", tmp / "o.obj", "--weights", url],
            "info": ["info", "--weights", url],
            "demo": ["demo", "--out", tmp / "demo", "--weights", url],
            "policy-from": [
                "export-weights",
                BUNDLED,
                "-o",
                tmp / "e.msgpack",
                "--policy-from",
                url,
            ],
            "export": ["export-weights", url, "-o", tmp / "e.msgpack"],
            "init-from": ["train", "--data", tmp, "--workdir", tmp / "w", "--init-from", url],
        }
        refused_quietly(tmp, argvs[command], "url")

    return run


def _f7_version(value):
    def run(tmp: Path) -> None:
        from flax import serialization

        payload = serialization.msgpack_restore(BUNDLED.read_bytes())
        payload["version"] = value
        w = tmp / "v.msgpack"
        w.write_bytes(serialization.msgpack_serialize(payload))
        src = write(tmp / "in.obj")
        for argv in (
            ["info", "--weights", w],
            ["denoise", src, "-o", tmp / "o.obj", "--weights", w],
        ):
            refused_quietly(tmp, argv, "v.msgpack", "version")

    return run


def _f7_missing_folder(kind: str):
    def run(tmp: Path) -> None:
        good = write(tmp / "good.obj")
        argvs = {
            "one": ["denoise", tmp / "nofolder", "--out", tmp / "out"],
            "one-slash": ["denoise", str(tmp / "nofolder") + "/", "--out", tmp / "out"],
            "among": ["denoise", good, tmp / "nofolder", "--out", tmp / "out"],
            "file-o": ["denoise", tmp / "nofile.obj", "-o", tmp / "o.obj"],
        }
        refused_quietly(tmp, argvs[kind], "nofo" if "folder" in str(argvs[kind][1:]) else "no")

    return run


def _f7_evaluate(kind: str):
    def run(tmp: Path) -> None:
        gt = write(tmp / "gt.obj")
        rng = np.random.default_rng(1)
        noisy = V + 0.01 * rng.standard_normal(V.shape)
        ref = write(tmp / "ref.obj", noisy, F)
        if kind == "faces-reversed-order":
            f = F[::-1]
        elif kind == "faces-shuffled":
            f = F[rng.permutation(len(F))]
        elif kind == "corners-rotated":
            f = np.roll(F, 1, axis=1)
        else:
            f = F
        mesh = write(tmp / "m.obj", noisy, f)
        code, out, err = cli("evaluate", "--gt", gt, "--mesh", ref, mesh, "--json")
        assert code == 0, f"exit {code}: {err.strip()[:300]}"
        rows = json.loads(out)
        for key in rows[0]:
            if key != "mesh":
                assert abs(rows[0][key] - rows[1][key]) <= 1e-9 * max(1, abs(rows[0][key])), (
                    key,
                    rows[0][key],
                    rows[1][key],
                )
        assert "face" in err.lower(), f"no note on the face order: {err.strip()[:300]!r}"

    return run


def _f7_evaluate_zero_area(where: str):
    def run(tmp: Path) -> None:
        v = np.concatenate([V, V[:1]])  # a duplicate of vertex 0 at the end
        f = np.concatenate([F, [[0, len(V), 1]]])  # a face of zero area
        gt = write(tmp / "gt.obj", v, f)
        mesh = write(tmp / "m.obj", v + (0.01 if where == "mesh" else 0.0), f)
        code, out, err = cli("evaluate", "--gt", gt, "--mesh", mesh)
        assert code == 0, f"exit {code}: {err.strip()[:300]}"
        notes = [line for line in err.splitlines() if "zero area" in line]
        assert notes and "gt.obj" in notes[0], f"no note naming gt.obj: {err.strip()[:300]!r}"
        assert "1 of" in notes[0], notes[0]

    return run


def _f7_demo_full_disk(fail_at: int):
    def run(tmp: Path) -> None:
        import errno

        import dmd_jax.io._files as files

        out = tmp / "demo"
        real = files.os.replace
        count = [0]

        def replace(a, b):
            # Only the writes into the output folder (caches elsewhere go on).
            if str(b).startswith(str(out)):
                count[0] += 1
                if count[0] == fail_at:
                    raise OSError(errno.ENOSPC, "No space left on device")
            return real(a, b)

        files.os.replace = replace
        try:
            code, _, err = cli("demo", "--out", out, "--no-render")
        finally:
            files.os.replace = real
        refused((code, "", err), "space")
        left = sorted(p.name for p in out.iterdir()) if out.exists() else []
        assert left == [], f"partial files left: {left}"

    return run


def _f7_concurrent(command: str):
    def run(tmp: Path) -> None:
        from dmd_jax.cli._common import output_lock

        folder = tmp / "in"
        folder.mkdir()
        write(folder / "a.obj")
        out = tmp / "out"
        out.mkdir()
        argvs = {
            "denoise": ["denoise", folder, "--out", out, "--method", "laplacian"],
            "demo": ["demo", "--out", out],
            "make-dataset": ["make-dataset", "--out", out, "--from-folder", folder],
        }
        with output_lock(out):  # what a run writing `out` holds
            refused_quietly(tmp, argvs[command], str(out.name), "another")

    return run


def family7() -> list[Case]:
    out = []
    for arg in ("--elev", "--azim"):
        for value in ("nan", "inf", "-inf", "1e20", "1e300", "-1000"):
            for ext in (".png", ".html"):
                out.append(
                    Case(f"f7-render{arg}-{value}-{ext[1:]}", 7, _f7_render_view(arg, value, ext))
                )
    for low, high in (("nan", "10"), ("0", "inf"), ("-inf", "5"), ("0", "1e300")):
        out.append(Case(f"f7-render-range-{low}-{high}", 7, _f7_render_range(low, high)))
    for kind in (
        "empty",
        "garbage",
        "nan",
        "index",
        "degenerate",
        "one-face",
        "repeated-corner",
        "huge",
    ):
        out.append(Case(f"f7-folder-names-{kind}", 7, _f7_folder_names_file(kind)))
    for command in ("denoise", "add-noise", "render-png", "render-html", "export"):
        for length in (250, 255, 300):
            out.append(Case(f"f7-long-name-{command}-{length}", 7, _f7_long_name(command, length)))
    for length in (250, 255):
        out.append(Case(f"f7-long-folder-name-{length}", 7, _f7_long_folder_name(length)))
    for value in ("1KB", "1", "1000", "1MB", "10MiB", "1e3"):
        out.append(Case(f"f7-max-memory-{value}", 7, _f7_max_memory(value)))
    for kind in ("int64", "int32", "uint64", "float32"):
        out.append(Case(f"f7-numpy-max-memory-{kind}", 7, _f7_numpy_memory(kind)))
    for command in ("denoise", "info", "demo", "policy-from", "export", "init-from"):
        for url in ("https://example.com/w.msgpack", "http://h/w", "s3://bucket/w.msgpack"):
            out.append(Case(f"f7-url-{command}-{url.split(':')[0]}", 7, _f7_url(command, url)))
    for value in ("2", [2], 2.5, None, {"v": 2}, True):
        out.append(Case(f"f7-version-{value!r}", 7, _f7_version(value)))
    for kind in ("one", "one-slash", "among", "file-o"):
        out.append(Case(f"f7-missing-input-{kind}", 7, _f7_missing_folder(kind)))
    for kind in ("faces-reversed-order", "faces-shuffled", "corners-rotated"):
        out.append(Case(f"f7-evaluate-{kind}", 7, _f7_evaluate(kind)))
    for where in ("gt", "mesh"):
        out.append(Case(f"f7-evaluate-zero-area-{where}", 7, _f7_evaluate_zero_area(where)))
    for fail_at in (1, 3, 6):
        out.append(Case(f"f7-demo-full-disk-{fail_at}", 7, _f7_demo_full_disk(fail_at)))
    for command in ("denoise", "demo", "make-dataset"):
        out.append(Case(f"f7-concurrent-{command}", 7, _f7_concurrent(command)))
    return out


def cases() -> list[Case]:
    """Every hostile case, families 3 to 7, in a fixed order."""
    return family3() + family4() + family5() + family6() + family7()


# Cases that run the network or a whole command (seconds each): left out of the quick
# sample the default test suite runs.
SLOW_PREFIXES = ("f7-demo-full-disk", "f7-numpy-max-memory", "f3-offset-")


def run_case(case: Case, tmp: Path) -> str | None:
    """None if `case` passes, else what went wrong (one line)."""
    try:
        case.run(tmp)
    except AssertionError as exc:
        return " ".join(str(exc).split())[:300] or "assertion"
    except Exception as exc:
        return f"{type(exc).__name__}: {' '.join(str(exc).split())[:280]}"
    return None


# --------------------------------------------------------------------------------------
# Round 3 (issue 65): families 2 (number syntax), 3 (line breaks), 4 (arguments outside
# denoise), 5 (nothing to denoise), 6 (folder mode onto itself), 7 (the experiments
# runner), 8 (clear messages). Names start with "r3-".
# --------------------------------------------------------------------------------------

# Number tokens Python's float()/int() read and C strtod/strtol do not (each refused).
BAD_NUMBERS = ("1_0", "1_000.5", "\uff11", "\u0661", "\U0001d7ce", "1\u00a0", "\u00b2", "0_1")


def text_mesh(fmt: str, token: str | None = None, where: str = "coordinate") -> bytes:
    """The tetrahedron `TET` as OBJ, OFF, ASCII PLY or ASCII STL text, with `token` in
    place of its first coordinate (or first face index, `where="index"`)."""
    v = [["0", "0", "0"], ["1", "0", "0"], ["0", "1", "0"], ["0", "0", "1"]]
    f = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    if token is not None and where == "coordinate":
        v[1][0] = token
    idx = [[str(i + (fmt == "obj")) for i in face] for face in f]
    if token is not None and where == "index":
        idx[0][1] = token
    if fmt == "obj":
        rows = [f"v {' '.join(p)}" for p in v] + [f"f {' '.join(t)}" for t in idx]
    elif fmt == "off":
        rows = ["OFF", "4 4 0"] + [" ".join(p) for p in v] + [f"3 {' '.join(t)}" for t in idx]
    elif fmt == "ply":
        rows = [
            "ply",
            "format ascii 1.0",
            "element vertex 4",
            "property float x",
            "property float y",
            "property float z",
            "element face 4",
            "property list uchar int vertex_indices",
            "end_header",
            *[" ".join(p) for p in v],
            *[f"3 {' '.join(t)}" for t in idx],
        ]
    else:  # ASCII STL: a triangle soup
        rows = ["solid t"]
        for face in f:
            rows += ["facet normal 0 0 0", "outer loop"]
            rows += [f"vertex {' '.join(v[i])}" for i in face]
            rows += ["endloop", "endfacet"]
        rows.append("endsolid t")
    return ("\n".join(rows) + "\n").encode("utf-8")


def _r3_number(fmt: str, token: str, where: str, via: str):
    def run(tmp: Path) -> None:
        from dmd_jax.io import load_mesh

        p = tmp / f"n.{fmt}"
        p.write_bytes(text_mesh(fmt, token, where))
        if via == "api":
            expect_value_error(lambda: load_mesh(p), "n." + fmt, "line")
        else:
            refused_quietly(tmp, ["denoise", p, "-o", tmp / "o.obj", "--method", "laplacian"])

    return run


def _r3_good_number(fmt: str, token: str, value: float):
    """A token C strtod reads (hexadecimal, exponent, sign) reads as that value."""

    def run(tmp: Path) -> None:
        from dmd_jax.io import load_mesh

        p = tmp / f"g.{fmt}"
        p.write_bytes(text_mesh(fmt, token))
        v, _ = load_mesh(p)
        assert value in v[:, 0], f"{token!r} read as {sorted(set(v[:, 0]))}, not {value}"

    return run


# Line breaks str.splitlines() takes and the formats do not: a statement after one, in a
# comment, stays in the comment.
BREAKS = ("\u2028", "\u2029", "\x85", "\x0c", "\x0b", "\x1c", "\x1d", "\x1e")


def _r3_break_in_comment(fmt: str, brk: str):
    def run(tmp: Path) -> None:
        from dmd_jax.io import load_mesh

        good = text_mesh(fmt).decode()
        if fmt == "obj":  # a hidden vertex and face would make a fifth vertex
            text = f"# note{brk}v 9 9 9{brk}f 1 2 5\n" + good
        elif fmt == "off":
            text = good.replace("OFF\n", f"OFF\n# note{brk}5 5 0\n", 1)
        else:  # PLY: a hidden `element` line in a header comment
            text = good.replace(
                "format ascii 1.0\n", f"format ascii 1.0\ncomment x{brk}element edge 9\n"
            )
        p = tmp / f"c.{fmt}"
        p.write_bytes(text.encode("utf-8"))
        v, f = load_mesh(p)
        assert v.shape == (4, 3) and f.shape == (4, 3), f"read {v.shape}, {f.shape}"

    return run


def _r3_argument(fn: str, arg: str, value):
    """A public function of the root API refuses a bad argument with one ValueError or
    TypeError naming it, before any work."""

    def run(tmp: Path) -> None:
        import dmd_jax

        calls = {
            "add_noise": lambda **kw: dmd_jax.add_noise(
                kw.get("seed", 0),
                kw.get("vertices", V),
                kw.get("faces", F),
                "scanner" if "view" in kw else "gaussian",
                0.1,
                **({"view": kw["view"]} if "view" in kw else {}),
            ),
            "simulate_scan": lambda **kw: dmd_jax.simulate_scan(
                kw.get("seed", 0),
                kw.get("vertices", V),
                kw.get("faces", F),
                view=kw.get("view"),
                resolution=16,
            ),
            "denoise_with": lambda **kw: dmd_jax.denoise_with(
                "laplacian", kw.get("vertices", V), kw.get("faces", F)
            ),
            "build_mesh_graph": lambda **kw: dmd_jax.build_mesh_graph(kw.get("faces", F), len(V)),
            "save_mesh": lambda **kw: dmd_jax.save_mesh(
                tmp / "o.ply", kw.get("vertices", V), kw.get("faces", F)
            ),
        }
        word = {"vertices": "vert", "faces": "face", "seed": "seed", "view": "view"}[arg]
        try:
            calls[fn](**{arg: value})
        except (ValueError, TypeError) as exc:
            text = str(exc)
            assert "\n" not in text.strip(), f"not one line: {text[:200]!r}"
            assert word in text.lower(), f"{word!r} not named: {text[:200]!r}"
            return
        raise AssertionError(f"{fn}({arg}={value!r}) was taken")

    return run


def _faces_with(kind: str) -> np.ndarray:
    f = F.copy()
    if kind == "negative":
        f[0, 1] = -1
    elif kind == "out-of-range":
        f[0, 1] = len(V)
    elif kind == "uint64-huge":
        f = f.astype(np.uint64)
        f[0, 1] = 2**63 + 1
    elif kind == "fractional":
        f = f + 0.5
    elif kind == "two-columns":
        f = f[:, :2]
    return f


def tetrahedron(regular: bool = True) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    if not regular:
        v = v * [1.0, 0.7, 1.3] + [[0.1, 0, 0], [0, 0.2, 0], [0, 0, -0.1], [0.05, 0, 0]]
    return v, np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])


def icosahedron() -> tuple[np.ndarray, np.ndarray]:
    t = (1 + 5**0.5) / 2
    v = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        float,
    )
    f = [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ]
    return v, np.array(f)


def still_mesh(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Meshes with nothing to denoise (`consistency.still_faces`)."""
    if kind == "tetrahedron":
        return tetrahedron()
    if kind == "irregular-tetrahedron":
        return tetrahedron(regular=False)
    if kind == "octahedron":
        return sphere(0)
    if kind == "icosahedron":
        return icosahedron()
    if kind == "one-triangle":
        return np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]])
    if kind == "collinear":  # every face of zero area: points on one line
        x = np.linspace(0.0, 1.0, 6)
        v = np.stack([x * 0.1, x * 0.3, x * 0.7], 1)
        return v, np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 5], [0, 2, 5]])
    if kind == "two-tetrahedra":
        a, fa = tetrahedron()
        b, _ = tetrahedron(regular=False)
        return np.concatenate([a, b + 5.0]), np.concatenate([fa, fa + 4])
    raise ValueError(kind)


def _r3_still(kind: str, method: str):
    def run(tmp: Path) -> None:
        import dmd_jax

        v, f = still_mesh(kind)
        out = dmd_jax.denoise_with(method, v, f)
        assert np.array_equal(out, v), f"{method} moved {kind} by {np.abs(out - v).max():.3g}"

    return run


def _r3_folder_onto_itself(how: str):
    def run(tmp: Path) -> None:
        folder = tmp / "meshes"
        folder.mkdir()
        write(folder / "a.obj")
        write(folder / "b.off")
        out = {"same": folder, "dot": folder / ".", "dotdot": folder / ".." / "meshes"}[how]
        argv = ["denoise", folder, "--out", out, "--skip-existing", "--method", "laplacian"]
        refused_quietly(tmp, argv, "input")

    return run


def _r3_experiments(command: str, where: str):
    def run(tmp: Path) -> None:
        import subprocess
        import sys

        paths = {
            "missing": tmp / "nothing",
            "empty": tmp / "empty",
            "file": tmp / "file.txt",
            "bad-json": tmp / "bad",
        }
        (tmp / "empty").mkdir()
        (tmp / "file.txt").write_text("x")
        (tmp / "bad").mkdir()
        (tmp / "bad" / "plan.json").write_text("{not json")
        (tmp / "bad" / "p").mkdir()
        (tmp / "bad" / "p" / "summary.json").write_text("[1,")
        before = snapshot(tmp)
        got = subprocess.run(
            [sys.executable, "-m", "experiments", command, str(paths[where])],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
        )
        refused((got.returncode, got.stdout, got.stderr), str(paths[where].name))
        assert "Traceback" not in got.stderr, got.stderr[-300:]
        assert snapshot(tmp) == before, "files changed"

    return run


def _r3_message(kind: str):
    def run(tmp: Path) -> None:
        import gzip

        from dmd_jax.io import load_mesh

        src = write(tmp / "m.off")
        if kind.startswith("gzip"):
            ext = kind.split("-")[1]
            good = write(tmp / f"g.{ext}")
            p = tmp / f"z.{ext}"
            p.write_bytes(gzip.compress(good.read_bytes()))
            expect_value_error(lambda: load_mesh(p), "z." + ext, "gzip")
        elif kind == "off-in-obj":
            p = tmp / "x.obj"
            p.write_bytes(src.read_bytes())
            expect_value_error(lambda: load_mesh(p), "x.obj", "OFF")
        elif kind == "ply-faces-element":
            p = tmp / "x.ply"
            text = text_mesh("ply").replace(b"element face", b"element faces")
            p.write_bytes(text)
            expect_value_error(lambda: load_mesh(p), "x.ply", "'face' element", "faces")
        elif kind.startswith("max-memory"):
            value = kind.split(":", 1)[1]
            word = {"1e3": "1000 bytes", "1e400GB": "more than any", "0.5": "less than one"}
            refused_quietly(
                tmp,
                ["denoise", src, "-o", tmp / "o.obj", "--max-memory", value],
                "--max-memory",
                word[value],
            )
        elif kind == "unwritable":
            ro = tmp / "ro"
            ro.mkdir()
            import dmd_jax.io._files as files

            real = files.tempfile.mkstemp

            def refuse(*args, **kwargs):  # what a read-only or foreign folder does
                if str(kwargs.get("dir", "")).startswith(str(ro)):
                    raise PermissionError(13, "Permission denied")
                return real(*args, **kwargs)

            files.tempfile.mkstemp = refuse
            try:
                argv = ["denoise", src, "-o", ro / "o.obj", "--method", "laplacian"]
                refused_quietly(tmp, argv, "o.obj", "cannot write")
            finally:
                files.tempfile.mkstemp = real

    return run


def round3() -> list[Case]:
    out = []
    for fmt in ("obj", "off", "ply", "stl"):
        for i, token in enumerate(BAD_NUMBERS):
            for via in ("api", "cli") if i < 2 else ("api",):
                out.append(
                    Case(
                        f"r3-f2-{fmt}-coord-{i}-{via}", 2, _r3_number(fmt, token, "coordinate", via)
                    )
                )
        if fmt != "stl":
            for i, token in enumerate(("1_0", "\uff12", "2.0", "0x2", "2e0")):
                out.append(
                    Case(f"r3-f2-{fmt}-index-{i}", 2, _r3_number(fmt, token, "index", "api"))
                )
        for token, value in (("0x1p-2", 0.25), ("+1e0", 1.0), ("1.", 1.0), ("-.5E1", -5.0)):
            out.append(Case(f"r3-f2-{fmt}-good-{token}", 2, _r3_good_number(fmt, token, value)))
    for fmt in ("obj", "off", "ply"):
        for brk in BREAKS:
            out.append(Case(f"r3-f3-{fmt}-{ord(brk):04x}", 3, _r3_break_in_comment(fmt, brk)))
    bad = {
        "seed": (1.5, "1", None, True, np.float64(2.0), 2**64, np.zeros(3, np.uint32)),
        "faces": tuple(
            _faces_with(k)
            for k in ("negative", "out-of-range", "uint64-huge", "fractional", "two-columns")
        ),
        "view": ([0, 0, 0], [np.nan, 0, 1], "up", [1, 2]),
        "vertices": (np.full((4, 3), np.nan), "abc", V[:, :2]),
    }
    takes = {
        "add_noise": ("seed", "faces", "view", "vertices"),
        "simulate_scan": ("seed", "faces", "view", "vertices"),
        "denoise_with": ("faces", "vertices"),
        "build_mesh_graph": ("faces",),
        "save_mesh": ("faces", "vertices"),
    }
    for fn, args in takes.items():
        for arg in args:
            for i, value in enumerate(bad[arg]):
                if fn == "build_mesh_graph" and i == 3:
                    continue  # fractional faces: a graph takes integral floats only too
                out.append(Case(f"r3-f4-{fn}-{arg}-{i}", 4, _r3_argument(fn, arg, value)))
    for kind in (
        "tetrahedron",
        "irregular-tetrahedron",
        "octahedron",
        "icosahedron",
        "one-triangle",
        "collinear",
        "two-tetrahedra",
    ):
        for method in (*CLASSIC, "cnr", "dmd"):
            out.append(Case(f"r3-f5-{kind}-{method}", 5, _r3_still(kind, method)))
    for how in ("same", "dot", "dotdot"):
        out.append(Case(f"r3-f6-{how}", 6, _r3_folder_onto_itself(how)))
    for command in ("aggregate", "index"):
        for where in ("missing", "empty", "file", "bad-json"):
            out.append(Case(f"r3-f7-{command}-{where}", 7, _r3_experiments(command, where)))
    for kind in (
        "gzip-stl",
        "gzip-obj",
        "gzip-ply",
        "gzip-off",
        "off-in-obj",
        "ply-faces-element",
        "max-memory:1e3",
        "max-memory:1e400GB",
        "max-memory:0.5",
        "unwritable",
    ):
        out.append(Case(f"r3-f8-{kind}", 8, _r3_message(kind)))
    return out


if __name__ == "__main__":  # python tests/hostile_cases.py: count the failures
    import sys
    import tempfile

    sys.path.insert(0, str(REPO / "tests"))
    only = sys.argv[1:]
    failed = 0
    every = cases() + round3()
    chosen = [c for c in every if not only or any(c.name.startswith(o) for o in only)]
    for c in chosen:
        with tempfile.TemporaryDirectory() as d:
            why = run_case(c, Path(d))
        if why is not None:
            failed += 1
            print(f"FAIL {c.name}: {why}", flush=True)
    print(f"{failed} of {len(chosen)} cases failed")
