"""What the subcommands share: reading an input mesh the CLI's way, checking an output
before any work, the help formatter and the `note:` line."""

from __future__ import annotations

import argparse
import sys

# METHODS: every denoiser `--method` accepts, the names of `dmd_jax.denoise_with`;
# MESH_SUFFIXES: the files `dmd_jax.io` reads (both import only NumPy, so `--help`
# stays quick).
from dmd_jax.api import METHODS as METHODS
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
    """Faces of zero area, each judged against its own edges (`metrics.zero_area_faces`):
    a test against the whole mesh's extent would call every face of a small part far
    from the rest zero-area."""
    from dmd_jax.metrics import zero_area_faces

    return int(zero_area_faces(vertices, faces).sum())


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


def _check_output(output, inputs, overwrite: bool, *, parents: bool = False, suffixes=None) -> None:
    """Everything that would make writing `output` fail, checked before any work.

    The format (`suffixes`), `-` (no stdout output), the input itself, through links or
    a hard link (with or without --overwrite), a symbolic link to nothing, a directory,
    an existing file without --overwrite, a missing folder (created later with
    `parents`, see `_make_parent`), a name too long for the file system, and a folder
    one may not write in.
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
    from dmd_jax.io import name_max, same_file

    for src in [inputs] if isinstance(inputs, (str, Path)) else inputs:
        # The same path once links are followed, or a hard link to the input.
        if same_file(src, out):
            raise ValueError(f"{output}: the output path is the input file; choose another")
    if out.is_symlink() and not os.path.exists(out):
        raise ValueError(f"{output}: is a symbolic link to nothing (or a loop); remove it first")
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
            if folder.is_symlink():
                raise ValueError(f"{folder}: is a symbolic link to nothing (or a loop)")
            folder = folder.parent
        if not folder.is_dir():
            raise NotADirectoryError(f"{folder}: is not a directory")
    # Checked now, not found by the write after the work: the file system's limit on a
    # name (an atomic write's temporary name is cut to fit it, see dmd_jax.io).
    size, limit = len(out.name.encode("utf-8", "surrogateescape")), name_max(folder)
    if size > limit:
        raise ValueError(
            f"{output}: the file name is too long ({size} bytes; the file system takes at "
            f"most {limit})"
        )
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"{output}: cannot write in {folder} (permission denied)")
    if out.parent.is_dir():  # a folder --parents creates later is new and ours
        from dmd_jax.io._files import check_writable

        check_writable(out)


def _make_parent(output) -> None:
    """Creates the folders above `output` (`--parents`), just before writing it."""
    from pathlib import Path

    Path(output).parent.mkdir(parents=True, exist_ok=True)


def _in_gt_order(v, f, gt_v, gt_f, path, gt_path):
    """The vertices of `path` in the ground truth's vertex order, or a clear error.

    The metrics compare vertex i with vertex i. A mesh with the ground truth's faces is
    taken as it is, and so, with a note, is one listing the same faces in another order
    (or with their corners rotated); one with the same number of faces but another vertex
    numbering (an STL output, which renumbers its vertices, or a mesh reordered by another
    tool) is matched through its faces, corner by corner, or else through identical
    positions, with a note; anything else is refused, naming what differs.
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
        # The same triangles listed in another order, or with their corners rotated or
        # reversed: the metrics go vertex by vertex over the ground truth's faces, so the
        # vertices are taken as they are; a note says what differed.
        if np.array_equal(
            np.unique(np.sort(f, axis=1), axis=0), np.unique(np.sort(gt_f, axis=1), axis=0)
        ):
            _note(
                f"{path}: the same faces as {gt_path} in another order (or with their "
                "corners rotated or reversed); scored vertex by vertex on the ground truth's faces"
            )
            return v
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


# --------------------------------------------------------------------------------------
# Bounds and refusals shared by the subcommands (docs/refusals.md lists every one)
# --------------------------------------------------------------------------------------

# `--max-memory` below this is refused: the network's compiled programs and XLA's
# working memory alone take about this much (`memory_plan.RUNTIME_BYTES`, measured).
MIN_MAX_MEMORY = 512 * 2**20
# `add-noise --level`: a thousand times the bounding box (or the mean edge) wipes out any
# mesh already; past it the noise only overflows float64.
MAX_NOISE_LEVEL = 1000.0
# `render`: panels side by side (inputs, plus the ground truth).
MAX_PANELS = 32
# Counts of `make-dataset`, `train`, `train-cnr`: far above every preset and study, low
# enough that a typo (an extra three zeros) is refused rather than run for days.
MAX_PER_CATEGORY = 10_000
MAX_WORKERS = 256
MIN_VERTICES = 4  # a tetrahedron
MAX_VERTICES = 10_000_000
MAX_EVAL_MESHES = 10_000
MAX_CNR = {
    "--steps": 10_000_000,
    "--draws": 1_000,
    "--faces-per-mesh": 1_000_000,
    "--batch-size": 1_000_000,
    "--stages": 16,
    "--vertex-iterations": 10_000,
    "--eval-meshes": MAX_EVAL_MESHES,
    "--max-meshes": 1_000_000,
}
MAX_CNR_HIDDEN = (16, 4096)  # layers, units per layer


def check_range(flag: str, value, low, high) -> None:
    """Refuses `value` outside `[low, high]` (NaN included), naming `flag`.

    Raises:
      ValueError: `"{flag} must be from {low} to {high}, got {value}"`.
    """
    import math

    if value is None:
        return
    number = float(value)
    if math.isnan(number) or not low <= number <= high:

        def shown(x):
            return f"{x:g}" if isinstance(x, float) else str(x)

        raise ValueError(f"{flag} must be from {shown(low)} to {shown(high)}, got {shown(value)}")


def check_local_path(flag: str, value) -> None:
    """Refuses a URL where a local file or folder is expected (`--weights` etc.): the
    message says so, instead of "no such file"."""
    import re

    if value is not None and re.match(r"[A-Za-z][A-Za-z0-9+.-]*://", str(value)):
        raise ValueError(
            f"{flag} {value}: is a URL; dmd_jax reads local files only (download it first, "
            "e.g. with curl -LO, and pass the file)"
        )


def check_weights_path(flag: str, value) -> None:
    """A `--weights`-like argument, checked before any work: not a URL, and, unless it
    is a checkpoint folder, a regular file one can read (a symlink loop, a FIFO or a
    missing file is named now, not after the mesh was read)."""
    from pathlib import Path

    from dmd_jax.io import check_readable_file

    if value is None:
        return
    check_local_path(flag, value)
    p = Path(value)
    if not p.is_dir():
        check_readable_file(p, "weights file")


class output_lock:  # noqa: N801  (used as a function: `with output_lock(folder):`)
    """Holds an exclusive lock on the folder a run writes (`flock` on the folder
    itself: nothing is written, and the lock goes with the process however it ends).

    A second run that would write the same folder at the same time is refused.

    Raises:
      ValueError: another process holds the lock.
    """

    def __init__(self, folder):
        self.folder = folder
        self.fd = None

    def __enter__(self):
        import fcntl
        import os

        self.fd = os.open(self.folder, os.O_RDONLY)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self.fd)
            self.fd = None
            raise ValueError(
                f"{self.folder}: another dmd-jax run is writing this folder now; wait for it "
                "to finish or choose another output folder"
            ) from None
        return self

    def __exit__(self, *exc):
        import os

        if self.fd is not None:
            os.close(self.fd)  # releases the lock
            self.fd = None
        return False
