"""What every format shares: the reader's result, text decoding, fan triangulation, the
row writer of the text formats, and the checked read and atomic write of a file."""

from __future__ import annotations

import os
import re
import stat
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

_BOM = b"\xef\xbb\xbf"  # the UTF-8 byte-order mark


class _MeshText(NamedTuple):
    """What a reader found: vertices, triangulated faces and how many were polygons."""

    vertices: np.ndarray  # [n_vertex, 3] float64
    faces: np.ndarray  # [n_face, 3] int64
    n_polygons: int


def _fan(corners: list[int], out: list[int]) -> None:
    """Appends the fan triangulation `(c0, c_i, c_i+1)` of one face to a flat list."""
    c0 = corners[0]
    for i in range(1, len(corners) - 1):
        out += (c0, corners[i], corners[i + 1])


def _text_of(data: bytes, name: str) -> str:
    """The text of an OBJ or OFF file; NUL bytes mean it is not text at all."""
    if b"\0" in data:
        raise ValueError(f"{name}: binary data in a text mesh format (corrupt file?)")
    # Numbers are ASCII; anything else can only sit in comments and names, so bytes that
    # are not UTF-8 (a Latin-1 comment, say) must not stop the file from loading.
    # Windows editors start UTF-8 files with a byte-order mark: glued to the first
    # keyword it would hide that statement (an OBJ's first `v` line, say).
    return data.removeprefix(_BOM).decode("utf-8", errors="replace")


# Compressed files and archives, by their leading bytes: read as a mesh they would be
# "corrupt" in a way that hides what they are.
_COMPRESSED = (
    (b"\x1f\x8b", "gzip-compressed", "gunzip it"),
    (b"PK\x03\x04", "a ZIP archive", "unzip it"),
    (b"BZh", "bzip2-compressed", "bunzip2 it"),
    (b"\xfd7zXZ\x00", "xz-compressed", "unxz it"),
    (b"\x28\xb5\x2f\xfd", "zstd-compressed", "unzstd it"),
    (b"7z\xbc\xaf\x27\x1c", "a 7-Zip archive", "extract it"),
)


def compressed(data: bytes) -> tuple[str, str] | None:
    """`(what, how to undo it)` when `data` starts like a compressed file or archive."""
    for magic, what, undo in _COMPRESSED:
        if data.startswith(magic):
            return what, undo
    return None


def check_not_compressed(data: bytes, name: str) -> None:
    """Refuses a compressed file or archive under a mesh name, saying what it is.

    Raises:
      ValueError: `X: is gzip-compressed, not a mesh file; gunzip it first`.
    """
    found = compressed(data)
    if found is not None:
        what, undo = found
        kind = what if what.startswith("a ") else f"a {what} file"
        raise ValueError(f"{name}: is {kind}, not a mesh file; {undo} first")


def sniff_format(data: bytes) -> str | None:
    """The mesh format `data` looks like by its first statement (`"PLY"`, `"OFF"`,
    `"STL"`, `"OBJ"`), or None: for error messages only, never to read a file."""
    head = data.removeprefix(_BOM)[:4096]
    first = head.lstrip(b" \t\r\n\v\f").split(None, 1)[:1]
    word = first[0].decode("ascii", "replace") if first else ""
    if word == "ply":
        return "PLY"
    if word.upper().endswith("OFF") and len(word) <= 6:
        return "OFF"
    if word.lower() == "solid":
        return "STL"
    text = head.decode("ascii", "replace")
    if any(line.lstrip(" \t").startswith(("v ", "f ", "vn ", "vt ")) for line in text.split("\n")):
        return "OBJ"
    return None


def not_this_format(data: bytes, name: str, expected: str, problem: str) -> None:
    """Refuses a file its reader cannot read, saying which format it looks like instead.

    Raises:
      ValueError: `X: PROBLEM: not an EXPECTED file (it looks like OFF: rename it to .off)`.
    """
    other = sniff_format(data)
    hint = f" (it looks like {other}: rename it to .{other.lower()})" if other else ""
    if other == expected:
        hint = ""
    raise ValueError(f"{name}: {problem}: not an {expected} file{hint}")


def check_readable_file(path, what: str = "mesh file") -> None:
    """Refuses, with the reason, a path that is not a regular file one can read.

    Says which of the look-alikes of "no such file" it is: a directory, a FIFO or
    device (reading one could block for ever), a symlink loop or a dangling symlink.
    `what` names the expected file in the messages.

    Raises:
      FileNotFoundError: nothing there, or a symlink to nothing.
      ValueError: a directory, or not a regular file.
      OSError: the path cannot be examined (a symlink loop, no permission).
    """
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        if path.is_symlink():
            raise FileNotFoundError(
                f"{path}: a symbolic link to {os.readlink(path)}, which does not exist"
            ) from None
        raise FileNotFoundError(f"{path}: no such {what}") from None
    except OSError as exc:  # ELOOP (a symlink loop), EACCES on a folder, ENAMETOOLONG
        raise OSError(exc.errno, f"{path}: cannot open it ({exc.strerror})") from None
    if stat.S_ISDIR(info.st_mode):
        raise ValueError(f"{path}: is a directory, not a {what}")
    if not stat.S_ISREG(info.st_mode):
        kind = "a FIFO (named pipe)" if stat.S_ISFIFO(info.st_mode) else "not a regular file"
        raise ValueError(f"{path}: is {kind}; save the {what} to a regular file first")


# mkstemp's random part: 8 characters of this alphabet (CPython's tempfile).
_TEMP_NAME = re.compile(r"\.(?P<head>.*)\.[a-z0-9_]{8}(?P<suffix>\.[^.]*)?", re.IGNORECASE)


def name_max(folder) -> int:
    """The longest file name, in bytes, the file system of `folder` takes (255 if unknown)."""
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def temp_prefix(path: Path) -> str:
    """The prefix of `atomic_write`'s temporary file for `path`: `.NAME.`, with NAME cut
    so the temporary name (prefix, 8 random characters, suffix) fits the file system's
    limit: any name the system takes can be written."""
    room = name_max(path.parent if path.parent.is_dir() else ".") - 2 - 8 - len(path.suffix)
    name = path.name
    while len(name.encode("utf-8", "surrogateescape")) > room:
        name = name[:-1]
    return f".{name}."


def is_temp_name(name: str) -> bool:
    """Whether `name` is (or looks like) a temporary file of `atomic_write`: what an
    interrupted run can leave, never a finished output (folder mode skips them)."""
    m = _TEMP_NAME.fullmatch(name)
    if m is None:
        return False
    head, suffix = m.group("head"), m.group("suffix") or ""
    # `.NAME.XXXXXXXX.SUF` where NAME ends in .SUF, or was cut to fit the file system.
    # A cut NAME leaves the temporary name within a character of the limit (255).
    return head.lower().endswith(suffix.lower()) or len(name.encode("utf-8", "replace")) >= 250


def same_file(a, b) -> bool:
    """Whether paths `a` and `b` name the same file: the same path once links are
    followed, or hard links to one file. Never raises (a symlink loop is just a path)."""
    try:
        if os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b):
            return True
    except OSError:
        pass
    # os.path.realpath never raises on a loop (Path.resolve does before Python 3.13).
    return os.path.realpath(a) == os.path.realpath(b)


def check_writable(path) -> None:
    """Refuses, naming `path`, an output its folder will not take: a temporary file is
    created there and removed (a read-only file system, `/proc`, a full inode table and
    permissions other than the mode bits show only then), and an existing file in a
    sticky folder (`/tmp`) owned by another user cannot be replaced.

    Raises:
      PermissionError or OSError: `X: cannot write in FOLDER (reason)`.
    """
    path = Path(path)
    folder = path.parent
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=path.suffix, dir=folder)
    except OSError as exc:
        raise type(exc)(exc.errno, f"{path}: cannot write in {folder} ({exc.strerror})") from None
    os.close(fd)
    os.unlink(tmp)
    try:
        info, there = folder.stat(), path.lstat()
    except OSError:
        return
    uid = os.geteuid()
    if info.st_mode & stat.S_ISVTX and uid not in (0, info.st_uid, there.st_uid):
        raise PermissionError(
            f"{path}: cannot replace it (another user's file in a sticky folder, {folder})"
        )


def _named(exc: OSError, what: str) -> OSError:
    """`exc` said of the output (`what`), keeping its type, errno and reason."""
    reason = exc.strerror or str(exc)
    if exc.errno is None:
        return type(exc)(f"{what} ({reason})")
    return type(exc)(exc.errno, f"{what} ({reason})")


def atomic_write(path, write_fn, *, overwrite: bool = False, protect=()) -> Path:
    """Writes a file by `write_fn(tmp_path)` then renames it into place.

    Args:
      path: destination.
      write_fn: callable that writes the whole file to the temporary path it is given.
      overwrite: replace an existing file; without it an existing file is an error.
      protect: paths that must never be written (the user's inputs).
    """
    path = Path(path)
    for p in protect:
        if same_file(p, path):
            raise ValueError(f"{path}: refusing to overwrite the input file")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists (pass overwrite=True / --overwrite)")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path.parent}: output directory does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=path.suffix, dir=path.parent)
    except OSError as exc:  # named by the output, not by a hidden temporary name
        raise _named(exc, f"{path}: cannot write in {path.parent}") from None
    os.close(fd)
    try:
        write_fn(tmp)
        # mkstemp creates 0600 files; give the result the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise _named(exc, f"{path}: cannot write it") from None
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_text_atomic(path, text: str) -> Path:
    """Replaces `path` with `text` atomically (a report, a log summary, a JSON file).

    Args:
      path: destination; its folder must exist. An existing file is replaced.
      text: the whole content.
    """
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text), overwrite=True)


# Rows per formatting call of the text writers: big enough that the per-call overhead
# vanishes, small enough that the text of one block stays a few tens of MB.
_WRITE_BLOCK = 1 << 18


def _write_rows(fh, row: str, rows: np.ndarray) -> None:
    """Writes `row % tuple(r)` for every row, a block at a time.

    `%r` of a Python float is its shortest repr, which reads back as the same float64
    (every finite value, 1e-300 and 1e300 alike); one `%` over a whole block keeps the
    formatting in C.
    """
    for s in range(0, len(rows), _WRITE_BLOCK):
        block = rows[s : s + _WRITE_BLOCK]
        fh.write((row * len(block)) % tuple(block.ravel().tolist()))
