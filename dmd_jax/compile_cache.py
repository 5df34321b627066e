"""The on-disk compilation cache: compiled programs kept between processes.

A fresh process that runs the network must otherwise trace, lower and compile it again
(seconds on CPU: `docs/cold-start.md`). Two stores share one bounded directory:

* **Executables** of the network's programs (`dmd_jax.forward`), keyed by the program,
  its model config, its input shapes and dtypes, the package's source, JAX's version
  and the machine. A hit is loaded without tracing, lowering or compiling
  (`executable`).
* **JAX's persistent compilation cache** (opt-in: `DMD_JAX_COMPILE_CACHE_XLA=1`, see
  `ENV_XLA`) for every other jitted program (the small
  eager ones of the frame, the policy, the weights' check), with no minimum compile
  time, so the small programs are kept too. JAX keys those by their lowered module:
  tracing still runs, compiling does not.

Where: `$DMD_JAX_COMPILE_CACHE` when it names a directory; otherwise the platform's
user cache directory (`platformdirs.user_cache_dir("dmd_jax")`: `$XDG_CACHE_HOME/dmd_jax`
or `~/.cache/dmd_jax` on Linux) plus `jax/`. `DMD_JAX_COMPILE_CACHE=0` (or `off`,
`false`, `no`) switches both stores off: every process compiles afresh, nothing is
written. Results are the same either way (the same compiled program runs).

Bounded: after each write, the oldest entries (least recently read or written) go until
the directory holds at most `$DMD_JAX_COMPILE_CACHE_MAX_MB` MiB (default
`DEFAULT_MAX_MB`). Several processes may share the directory: every entry is written
to a temporary file and renamed into place (readers see a whole entry or none), and an
entry that vanishes under a reader (another process evicted it) is a miss. Every entry
carries a checksum: a damaged one (a full disk, a killed writer on a filesystem without
atomic rename, bit rot) is deleted and the program compiled again, never loaded.

Trusted: entries are executables (the network's are `pickle`d by
`jax.experimental.serialize_executable`, the only way JAX reloads an executable without
tracing), so anyone who can write there can run code as you. The store therefore creates
its directories with mode 0o700, and reads or writes an entry only while the entry's
directory (`programs/`, `xla/`) and the entry file itself are owned by the current user
(`os.getuid()`) and not writable by group or others. Otherwise it warns once per
directory (`UserWarning`, naming the directory and the reason) and the call compiles as
with the cache off; results are the same. Checking the entry's own directory suffices: a
directory this user owns and no one else may write cannot have its entries replaced,
and one swapped in by someone else is not owned by this user. On platforms without
`os.getuid` (Windows) neither check runs and the directories get the platform's default
permissions (the user's cache directory is private there by default).

The JAX side is configured when `dmd_jax.forward` is imported (no file is touched
then), so `import dmd_jax` stays light; a process that set
`jax_compilation_cache_dir` itself keeps its own JAX cache.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import platform
import re
import stat
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import NamedTuple

# The environment variable that moves (a directory) or switches off (`0`) the cache.
ENV = "DMD_JAX_COMPILE_CACHE"
# The environment variable bounding the cache directory, in MiB.
ENV_MAX_MB = "DMD_JAX_COMPILE_CACHE_MAX_MB"
# JAX's own persistent cache (`xla/`) is opt-in: with jaxlib 0.10.2 a program JAX loaded
# from it and then serialised again fails at run time ("Function ... not found"), which
# several concurrent runs here hit, and caching the small programs saved no measurable time
# (docs/cold-start.md). `DMD_JAX_COMPILE_CACHE_XLA=1` turns it on.
ENV_XLA = "DMD_JAX_COMPILE_CACHE_XLA"
# The default bound: the bundled model's whole-mesh and patch programs for a few dozen
# shape buckets (about 2-5 MiB each, measured in docs/cold-start.md).
DEFAULT_MAX_MB = 512
_OFF = frozenset({"0", "off", "false", "no"})
_ON = frozenset({"", "1", "on", "true", "yes"})
# Entry layout: magic, 16-byte BLAKE2b digest of the payload, payload.
_MAGIC = b"DMDJC01\n"
_DIGEST = 16
_SUFFIX = ".bin"
# `jax.monitoring` events of `executable`: an executable loaded from the store, or not
# found there (then compiled and stored).
HIT_EVENT = "/dmd_jax/compile_cache/executable_hit"
MISS_EVENT = "/dmd_jax/compile_cache/executable_miss"
# Bumped when the executable payload's layout changes.
_FORMAT = 1


class Settings(NamedTuple):
    """The cache's directory (None: off) and its bound in bytes."""

    path: Path | None
    max_bytes: int


def default_dir() -> Path:
    """The platform's user cache directory for the compiled programs."""
    import platformdirs

    return Path(platformdirs.user_cache_dir("dmd_jax", appauthor=False)) / "jax"


def settings() -> Settings:
    """The cache's settings, read from the environment now.

    Raises:
      ValueError: a `DMD_JAX_COMPILE_CACHE_MAX_MB` that is not a positive number.
    """
    raw_max = os.environ.get(ENV_MAX_MB, "").strip()
    if raw_max:
        try:
            max_mb = float(raw_max)
        except ValueError:
            max_mb = -1.0
        if not max_mb > 0:
            raise ValueError(f"{ENV_MAX_MB} must be a positive number of MiB, got {raw_max!r}")
    else:
        max_mb = DEFAULT_MAX_MB
    max_bytes = int(max_mb * 2**20)
    raw = os.environ.get(ENV, "").strip()
    if raw.lower() in _OFF:
        return Settings(None, max_bytes)
    if raw.lower() in _ON:
        return Settings(default_dir(), max_bytes)
    return Settings(Path(raw).expanduser(), max_bytes)


def _uid() -> int | None:
    """The current user's id; None where the platform has none (Windows: no checks)."""
    getuid = getattr(os, "getuid", None)
    return None if getuid is None else getuid()


def _stat(target: Path | int) -> os.stat_result:
    """`os.stat` of a directory or of an open entry's file descriptor (the trust checks'
    only look at ownership and mode)."""
    return os.stat(target)


def _distrust(st: os.stat_result, uid: int, what: str) -> str | None:
    """Why `st` (of `what`) is not trusted by user `uid`, or None when it is."""
    if st.st_uid != uid:
        return f"{what} is owned by uid {st.st_uid}, not by the current user (uid {uid})"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"{what} is writable by group or others (mode {stat.S_IMODE(st.st_mode):o})"
    return None


_warned: set[str] = set()
_warn_lock = threading.Lock()


def _warn_once(path: Path, reason: str) -> None:
    """One `UserWarning` per directory and process: the cache is not used there."""
    with _warn_lock:
        if str(path) in _warned:
            return
        _warned.add(str(path))
    warnings.warn(
        f"dmd_jax compile cache: not using {path}: {reason}; compiling without the cache "
        f"(make it private, `chmod 700`, or set {ENV} to another directory or to 0)",
        UserWarning,
        stacklevel=3,
    )


def _private_dir(path: Path) -> None:
    """Creates `path` and its missing parents with mode 0o700 (existing ones untouched).

    Raises:
      OSError: a directory could not be created.
    """
    missing = []
    while not os.path.lexists(path) and path.parent != path:
        missing.append(path)
        path = path.parent
    for folder in reversed(missing):
        try:
            folder.mkdir(mode=0o700)
        except FileExistsError:  # another process made it meanwhile: checked on use
            continue
        if _uid() is not None:
            os.chmod(folder, 0o700)  # the umask may narrow mkdir's mode, never widen it


class EntryStore:
    """A bounded directory of checksummed entries, shared safely between processes.

    Entries are read and written only while the directory (and, to read, the entry
    file) belongs to the current user and no one else may write it (`trusted`).

    Args:
      path: the directory (created with mode 0o700 on the first write).
      max_bytes: the bound on the entries' total size.
    """

    def __init__(self, path: Path, max_bytes: int):
        self.path = Path(path)
        self.max_bytes = int(max_bytes)

    def problem(self) -> str | None:
        """Why the directory is not trusted, or None (trusted, absent, or no `os.getuid`).

        An absent directory is trusted: the store creates it private.
        """
        uid = _uid()
        if uid is None:
            return None
        try:
            st = _stat(self.path)
        except FileNotFoundError:
            return None
        except OSError as err:
            return f"the directory cannot be checked ({err.strerror})"
        if not stat.S_ISDIR(st.st_mode):
            return "it is not a directory"
        return _distrust(st, uid, "the directory")

    def trusted(self) -> bool:
        """Whether entries may be read and written here; warns once when not."""
        reason = self.problem()
        if reason is not None:
            _warn_once(self.path, reason)
        return reason is None

    def _file(self, key: str) -> Path:
        if not key or not all(c.isalnum() or c in "-_" for c in key):
            raise ValueError(f"a cache key is letters, digits, '-' and '_', got {key!r}")
        return self.path / f"{key}{_SUFFIX}"

    def get(self, key: str) -> bytes | None:
        """The payload stored under `key`, or None: absent, damaged (then deleted), or
        not trusted (the directory, or the entry owned by another user or writable by
        group or others: left alone, with a warning)."""
        file = self._file(key)
        if not self.trusted():
            return None
        try:
            fd = os.open(file, os.O_RDONLY | getattr(os, "O_BINARY", 0))
        except (FileNotFoundError, IsADirectoryError, PermissionError):
            return None
        with os.fdopen(fd, "rb") as fh:
            uid = _uid()
            # The open file's own status: the entry checked is the entry read.
            reason = None if uid is None else _distrust(_stat(fd), uid, f"entry {file.name}")
            if reason is not None:
                _warn_once(self.path, reason)
                return None
            try:
                data = fh.read()
            except IsADirectoryError:
                return None
        head = len(_MAGIC) + _DIGEST
        payload = data[head:]
        if (
            len(data) < head
            or data[: len(_MAGIC)] != _MAGIC
            or hashlib.blake2b(payload, digest_size=_DIGEST).digest() != data[len(_MAGIC) : head]
        ):
            self._remove(file)
            return None
        try:
            os.utime(file)  # the eviction order: least recently used first
        except OSError:
            pass
        return payload

    def put(self, key: str, payload: bytes) -> None:
        """Stores `payload` under `key` (atomically), then evicts beyond the bound.

        A payload larger than the whole bound is not stored, nor one for a directory
        that is not `trusted`. Write errors (a read-only or full disk) are ignored: the
        cache only saves time. Entries are created with mode 0o600 (`mkstemp`).
        """
        file = self._file(key)
        if len(payload) + len(_MAGIC) + _DIGEST > self.max_bytes:
            return
        digest = hashlib.blake2b(payload, digest_size=_DIGEST).digest()
        tmp = None
        try:
            _private_dir(self.path)
            if not self.trusted():  # checked once it exists: someone else's is refused
                return
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=self.path)
            with os.fdopen(fd, "wb") as out:
                out.write(_MAGIC + digest + payload)
            os.replace(tmp, file)  # atomic: readers see the old entry or the new one
            tmp = None
        except OSError:
            return
        finally:
            if tmp is not None:
                self._remove(Path(tmp))
        self.evict()

    def entries(self) -> list[tuple[float, int, Path]]:
        """`(last use, size in bytes, file)` of every entry, oldest first."""
        out = []
        try:
            files = list(self.path.iterdir())
        except OSError:
            return out
        for file in files:
            if not file.name.endswith(_SUFFIX):
                continue
            try:
                st = file.stat()
            except OSError:  # evicted by another process meanwhile
                continue
            out.append((st.st_mtime, st.st_size, file))
        out.sort()
        return out

    def size(self) -> int:
        """The entries' total size in bytes."""
        return sum(size for _, size, _ in self.entries())

    def evict(self) -> None:
        """Deletes the oldest entries until the rest fit `max_bytes`; also temporary
        files an hour old (a writer killed before its rename)."""
        entries = self.entries()
        total = sum(size for _, size, _ in entries)
        for _, size, file in entries:
            if total <= self.max_bytes:
                break
            self._remove(file)
            total -= size
        now = time.time()
        try:
            stale = [f for f in self.path.glob(".tmp-*") if now - f.stat().st_mtime > 3600]
        except OSError:
            stale = []
        for file in stale:
            self._remove(file)

    @staticmethod
    def _remove(file: Path) -> None:
        try:
            file.unlink()
        except OSError:  # already gone (another process), or not ours to delete
            pass


_lock = threading.Lock()
_jax_configured = False


def store() -> EntryStore | None:
    """The executables' store under the current settings, or None when switched off or
    not trusted (`EntryStore.trusted`, which warns once): then calls compile as with the
    cache off."""
    s = settings()
    if s.path is None:
        return None
    entries = EntryStore(s.path / "programs", s.max_bytes)
    return entries if entries.trusted() else None


def configure_jax() -> bool:
    """Points JAX's persistent compilation cache at `settings()`' directory, once.

    Every program is kept however fast it compiled (the cold call runs dozens of small
    ones). The directory is JAX's, bounded and checked by an `EntryStore`; no file is
    touched before JAX's first compile.

    Returns:
      Whether this call (or an earlier one) turned JAX's cache on here; False when the
      cache is off, `DMD_JAX_COMPILE_CACHE_XLA` is not set to 1 (`ENV_XLA`), its
      `xla/` directory is not trusted (`EntryStore.trusted`, which warns), or the
      process had set `jax_compilation_cache_dir` itself.
    """
    global _jax_configured
    with _lock:
        if _jax_configured:
            return True
        s = settings()
        if s.path is None or os.environ.get(ENV_XLA, "").strip().lower() not in _ON - {""}:
            return False
        import jax

        if jax.config.jax_compilation_cache_dir:  # the caller's own cache: keep it
            return False
        xla = EntryStore(s.path / "xla", s.max_bytes)
        # Checked here too: where JAX's internals differ (`_install_jax_store`), JAX's own
        # cache reads the directory without the store's checks.
        if not xla.trusted():
            return False
        jax.config.update("jax_compilation_cache_dir", str(s.path / "xla"))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        _install_jax_store(xla)
        _jax_configured = True
        return True


def _install_jax_store(entries: EntryStore) -> None:
    """Makes JAX read and write its persistent cache through `entries`.

    JAX's own file cache writes entries in place (a reader may see half of one) and
    bounds its size only with the `filelock` package; when JAX's internals differ from
    what is expected here, its own cache is left in place (still on, unbounded).
    """
    try:
        from jax._src import compilation_cache as cc
        from jax._src.compilation_cache_interface import CacheInterface
    except ImportError:
        return
    if not all(
        hasattr(cc, n) for n in ("_cache", "_cache_initialized", "_cache_initialized_mutex")
    ):
        return

    class _JaxEntries(CacheInterface):
        def __init__(self):
            self._path = entries.path

        def get(self, key: str):
            return entries.get(_safe_key(key))

        def put(self, key: str, value: bytes):
            entries.put(_safe_key(key), value)

    with cc._cache_initialized_mutex:
        if cc._cache is None:
            cc._cache = _JaxEntries()
            cc._cache_initialized = True


def _safe_key(key: str) -> str:
    """A JAX cache key as a file name (they are `jit_<name>-<hex>`; names may hold dots)."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in key)


_fingerprint: str | None = None
# The modules whose code a stored executable may run: these and every `dmd_jax` module
# they import, at any depth (`program_sources`).
_PROGRAM_ROOTS = ("dmd_jax.forward", "dmd_jax.model")
# `import a, b` or `from m import a, (b, c)`, at the start of a line (any indent).
_IMPORT = re.compile(
    r"^[ \t]*(?:from[ \t]+(?P<module>[\w.]+)[ \t]+)?import[ \t]+(?P<names>\([^)]*\)|[^\n]*)",
    re.M,
)


def program_sources() -> list[Path]:
    """The source files of `_PROGRAM_ROOTS` and of every `dmd_jax` module they import
    (anywhere in their source, function bodies too), found by reading the source.

    An edit to any of them may change a compiled program, so all are in the key; an
    edit elsewhere in the package (the CLI, training) keeps the stored programs.
    """
    root = Path(__file__).resolve().parent

    def file_of(name: str) -> Path | None:
        parts = name.split(".")[1:]
        if not parts:  # the package itself: its __init__ imports lazily, by name
            return root / "__init__.py"
        rel = Path(*parts)
        for cand in (root / rel.with_suffix(".py"), root / rel / "__init__.py"):
            if cand.is_file():
                return cand
        return None

    seen: dict[str, Path] = {}
    todo = list(_PROGRAM_ROOTS)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        file = file_of(name)
        if file is None:
            continue
        seen[name] = file
        package = name if file.name == "__init__.py" else name.rpartition(".")[0]
        # Import statements by pattern, not `ast` (a tenth of a second per process on
        # every cold start): a line that only looks like one adds a file to the key,
        # never drops one.
        for m in _IMPORT.finditer(file.read_text(encoding="utf-8")):
            names = [
                n.split()[0]
                for n in re.sub(r"#[^\n]*", "", m["names"]).strip("()").split(",")
                if n.strip()
            ]
            if m["module"] is None:
                found = names
            else:
                level = len(m["module"]) - len(m["module"].lstrip("."))
                target = m["module"].lstrip(".")
                if level:
                    base = package.split(".")[: len(package.split(".")) - level + 1]
                    target = ".".join(base + ([target] if target else []))
                found = [target] + [f"{target}.{n}" for n in names]
            todo += [n for n in found if n == "dmd_jax" or n.startswith("dmd_jax.")]
    return sorted(set(seen.values()))


def fingerprint() -> str:
    """What every stored executable depends on besides its program and shapes.

    The source of the modules a program may run (`program_sources`), JAX's and
    jaxlib's versions, the platform and its version, the CPU's flags (an executable is
    compiled for the host's instruction set), `XLA_FLAGS` and JAX's float64 mode.
    """
    global _fingerprint
    import jax

    if _fingerprint is None:
        import jaxlib

        h = hashlib.sha256()
        root = Path(__file__).resolve().parent
        for file in program_sources():
            h.update(str(file.relative_to(root)).encode())
            h.update(file.read_bytes())
        backend = jax.devices()[0].client
        h.update(
            repr(
                (
                    _FORMAT,
                    jax.__version__,
                    jaxlib.__version__,
                    backend.platform,
                    backend.platform_version,
                    platform.machine(),
                    _cpu_flags(),
                    os.environ.get("XLA_FLAGS", ""),
                )
            ).encode()
        )
        _fingerprint = h.hexdigest()
    return f"{_fingerprint}:{bool(jax.config.jax_enable_x64)}"


def _cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def signature(args) -> tuple:
    """The tree structure, shapes and dtypes of `args` (what selects a compiled program)."""
    import jax
    import numpy as np

    leaves, tree = jax.tree.flatten(args)
    return (
        tree,
        tuple(
            (tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False)))
            if hasattr(x, "dtype")
            else (tuple(np.shape(x)), str(np.result_type(x)), True)  # a Python scalar
            for x in leaves
        ),
    )


def executable(name: str, jitted, args, identity: str):
    """`jitted`'s compiled program for `args`' shapes: loaded from the store or compiled.

    Args:
      name: the program's kind (part of the key, readable in logs).
      jitted: a `jax.jit` function.
      args: its positional arguments (arrays or `jax.ShapeDtypeStruct`s).
      identity: what else selects the program (its model config, its options).

    Returns:
      A `jax.stages.Compiled`; stored for the next process when the store is on and the
      program can be serialised.
    """
    return lookup(name, jitted, args, identity)[0]


def _key(name: str, args, identity: str) -> str:
    """The store's key of program `name` for `args`' signature."""
    tree, shapes = signature(args)
    key = hashlib.sha256(
        repr((name, identity, str(tree), shapes, fingerprint())).encode()
    ).hexdigest()
    return f"{name}-{key[:40]}"


def stored(name: str, args, identity: str):
    """The executable `executable` would load for `args`, or None: not in the store,
    the store off or refused. Never compiles (`forward.Program.preload` runs it in a
    background thread, on a guess of the shapes).
    """
    entries = store()
    if entries is None:
        return None
    loaded = _load(entries, _key(name, args, identity))
    if loaded is not None:
        from jax import monitoring

        monitoring.record_event(HIT_EVENT)
    return loaded


def lookup(name: str, jitted, args, identity: str):
    """`executable`, and whether it was loaded from the store: `(compiled, loaded)`."""
    entries = store()
    if entries is None:
        return jitted.lower(*args).compile(), False
    key = _key(name, args, identity)
    from jax import monitoring

    loaded = _load(entries, key)
    if loaded is not None:
        monitoring.record_event(HIT_EVENT)
        return loaded, True
    monitoring.record_event(MISS_EVENT)
    # Compiled here, not loaded from JAX's persistent cache: XLA:CPU cannot serialise
    # again an executable it deserialised (the copy fails at run time, "Function ...
    # not found"; jaxlib 0.10.2), and the store keeps this program anyway.
    with _without_jax_cache():
        compiled = jitted.lower(*args).compile()
    _save(entries, key, compiled)
    return compiled, False


def _without_jax_cache():
    """A context in which JAX neither reads nor writes its persistent cache."""
    try:
        from jax._src.config import enable_compilation_cache

        return enable_compilation_cache(False)
    except (ImportError, TypeError):
        import contextlib

        return contextlib.nullcontext()


def remembered(name: str, identity: str, compute):
    """A small JSON value about a program, computed once and kept with the executables.

    For what a fresh process would otherwise compile (or trace) a program to learn, such
    as XLA's memory analysis of the network (`memory_plan.network_bytes_per_vertex`).
    Keyed like `executable` (the package's program sources, JAX, the machine).

    Args:
      name: what the value is (part of the key).
      identity: what selects it (the model config).
      compute: `() -> value`, a JSON-serialisable value, run on a miss.
    """
    import json

    entries = store()
    if entries is None:
        return compute()
    digest = hashlib.sha256(repr((name, identity, fingerprint())).encode()).hexdigest()
    key = f"{name}-{digest[:40]}"
    payload = entries.get(key)
    if payload is not None:
        try:
            return json.loads(payload)
        except ValueError:  # checksummed, so only a foreign writer: compute again
            pass
    value = compute()
    entries.put(key, json.dumps(value).encode())
    return value


def _load(entries: EntryStore, key: str):
    # `entries.get` returns a payload only from a trusted directory and entry file: the
    # one place this package unpickles, and only what `_save` below pickled.
    payload = entries.get(key)
    if payload is None:
        return None
    try:
        from jax.experimental.serialize_executable import deserialize_and_load

        serialized, in_tree, out_tree = pickle.loads(payload)
        return deserialize_and_load(serialized, in_tree, out_tree)
    except Exception:  # noqa: BLE001 - a stale or foreign entry: compile instead
        entries._remove(entries._file(key))
        return None


def _save(entries: EntryStore, key: str, compiled) -> None:
    try:
        from jax.experimental.serialize_executable import serialize

        payload = pickle.dumps(serialize(compiled), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # noqa: BLE001 - not serialisable (constants, callbacks): not kept
        return
    entries.put(key, payload)
