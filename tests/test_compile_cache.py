"""The on-disk compilation cache (`dmd_jax.compile_cache`, `dmd_jax.forward.Program`).

The store is checked directly (checksums, atomic writes, the bound), and end to end in
fresh processes, the way a user meets it: a first process compiles and stores, a second
loads, both give the same bits as a process without the cache; two processes writing
at once, and damaged entries, leave a cache that still works. The trust boundary is
checked on the store with a tiny jitted function: private directories, and no entry
loaded from a directory or file another user owns or may write.

The test suite runs with the cache off (`tests/conftest.py` sets
`DMD_JAX_COMPILE_CACHE=0`); every process here gets its own temporary directory.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmd_jax import compile_cache
from dmd_jax.compile_cache import ENV, ENV_MAX_MB, EntryStore

REPO = Path(__file__).resolve().parents[1]

# One fresh process: the test preset's network (small: compiles in seconds) through
# `forward.predictor` on an icosphere, twice in a row (the second call must not load or
# compile again), then (with a second argument) the patch program through
# `.lower().compile()` as `memory_plan` uses it. Prints the cache events and writes the
# outputs.
PROGRAM = r"""
import collections, json, sys
import jax, numpy as np, trimesh
from jax import monitoring
from dmd_jax import compile_cache, forward
from dmd_jax.config import preset
from dmd_jax.graph import build_mesh_graph, pad_mesh_graph, padded_sizes_for, with_ell_layout
from dmd_jax.model import init_params

events = collections.Counter()
monitoring.register_event_listener(lambda e, **kw: events.__setitem__(e, events[e] + 1))
cfg = preset("test").model
params = init_params(cfg, jax.random.PRNGKey(0))
s = trimesh.creation.icosphere(subdivisions=2)
v, f = np.asarray(s.vertices, np.float32), np.asarray(s.faces, np.int32)
graph = with_ell_layout(pad_mesh_graph(build_mesh_graph(f, len(v)), padded_sizes_for(
    build_mesh_graph(f, len(v)))))
noisy = np.zeros((graph.n_vertex, 3), np.float32)
noisy[: len(v)] = v + 0.01 * np.sin(7 * v)
predict = forward.predictor(cfg)
out = np.asarray(predict(params, noisy, graph))
again = np.asarray(predict(params, noisy, graph))
patch = len(sys.argv) > 2
if patch:
    compiled = forward.patch_predictor(cfg).lower(params, noisy, graph, {}).compile()
np.save(sys.argv[1], np.stack([out, again]))
print(json.dumps({
    "hit": events[compile_cache.HIT_EVENT],
    "miss": events[compile_cache.MISS_EVENT],
    "jax_hit": events["/jax/compilation_cache/cache_hits"],
    "has_memory": patch and compiled.memory_analysis() is not None,
}))
"""


def run_program(
    tmp_path: Path, name: str, cache, *, extra_env=None, wait: bool = True, patch: bool = False
):
    """Runs `PROGRAM` in a fresh process with `DMD_JAX_COMPILE_CACHE=cache` (None: unset).

    Returns the `Popen` when `wait` is False, else `(events, outputs)`.
    """
    env = {k: v for k, v in os.environ.items() if k not in (ENV, ENV_MAX_MB)}
    env.update({"XDG_CACHE_HOME": str(tmp_path / "xdg"), "HOME": str(tmp_path / "home")})
    if cache is not None:
        env[ENV] = str(cache)
    env.update(extra_env or {})
    out = tmp_path / f"{name}.npy"
    script = tmp_path / "program.py"
    script.write_text(PROGRAM)
    proc = subprocess.Popen(
        [sys.executable, str(script), str(out), *(["patch"] if patch else [])],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    if not wait:
        return proc, out
    return finish(proc, out)


def finish(proc, out: Path):
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr[-3000:]
    return json.loads(stdout.strip().splitlines()[-1]), np.load(out)


def entries(path: Path) -> list[Path]:
    return sorted(path.rglob("*.bin")) if path.exists() else []


# ---------------------------------------------------------------- settings, the store


def test_settings_read_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv(ENV_MAX_MB, raising=False)
    for off in ("0", "off", "False", " no "):
        monkeypatch.setenv(ENV, off)
        assert compile_cache.settings().path is None
        assert compile_cache.store() is None
    monkeypatch.setenv(ENV, str(tmp_path / "here"))
    assert compile_cache.settings() == (tmp_path / "here", compile_cache.DEFAULT_MAX_MB * 2**20)
    # Unset: the platform's user cache directory ($XDG_CACHE_HOME on Linux).
    monkeypatch.delenv(ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert compile_cache.settings().path == tmp_path / "xdg" / "dmd_jax" / "jax"
    monkeypatch.setenv(ENV_MAX_MB, "1.5")
    assert compile_cache.settings().max_bytes == int(1.5 * 2**20)
    for bad in ("0", "-3", "lots"):
        monkeypatch.setenv(ENV_MAX_MB, bad)
        with pytest.raises(ValueError, match=ENV_MAX_MB):
            compile_cache.settings()


def test_store_round_trip_and_damaged_entries(tmp_path):
    store = EntryStore(tmp_path / "s", 10_000)
    assert store.get("absent") is None
    store.put("a", b"payload one")
    assert store.get("a") == b"payload one"
    store.put("a", b"payload two")  # replaced whole
    assert store.get("a") == b"payload two"
    (file,) = entries(tmp_path)
    for damage in (
        lambda b: b[:-1] + bytes([b[-1] ^ 1]),  # a flipped bit in the payload
        lambda b: b[: len(b) // 2],  # a truncated write
        lambda b: b"",  # an empty file
        lambda b: b"garbage" + b[7:],  # a foreign header
    ):
        store.put("a", b"payload two")
        file.write_bytes(damage(file.read_bytes()))
        assert store.get("a") is None  # a miss: the program is compiled again
        assert not file.exists()  # and the damaged entry is gone
    with pytest.raises(ValueError, match="cache key"):
        store.get("../escape")
    assert not list((tmp_path / "s").glob(".tmp-*"))  # no temporary file left behind


def test_store_is_bounded_oldest_first(tmp_path):
    store = EntryStore(tmp_path, 3 * 1024 + 3 * 24)  # three 1 KiB entries and headers
    for k, name in enumerate("abc"):
        store.put(name, bytes([k]) * 1024)
        os.utime(tmp_path / f"{name}.bin", (1000 + k, 1000 + k))
    assert store.get("a") is not None  # reading "a" makes "b" the oldest
    store.put("d", b"d" * 1024)
    assert [p.stem for p in entries(tmp_path)] == ["a", "c", "d"]
    assert store.size() <= store.max_bytes
    store.put("huge", b"x" * 10_000)  # larger than the bound: not stored, nothing evicted
    assert [p.stem for p in entries(tmp_path)] == ["a", "c", "d"]


def test_remembered_values_are_computed_once(monkeypatch, tmp_path):
    calls = []

    def compute():
        calls.append(1)
        return {"bytes": 123}

    monkeypatch.setenv(ENV, str(tmp_path))
    assert compile_cache.remembered("probe", "config-a", compute) == {"bytes": 123}
    assert compile_cache.remembered("probe", "config-a", compute) == {"bytes": 123}
    assert len(calls) == 1
    compile_cache.remembered("probe", "config-b", compute)  # another identity: its own
    assert len(calls) == 2
    monkeypatch.setenv(ENV, "0")  # off: computed every time, nothing written
    compile_cache.remembered("probe", "config-a", compute)
    assert len(calls) == 3
    assert len(entries(tmp_path)) == 2


@pytest.mark.slow
def test_memory_plan_measure_is_kept(monkeypatch, tmp_path):
    from dmd_jax import memory_plan
    from dmd_jax.config import preset

    cfg = preset("test").model
    measured = memory_plan._measured_bytes_per_vertex(cfg)
    monkeypatch.setenv(ENV, str(tmp_path))
    memory_plan.network_bytes_per_vertex.cache_clear()
    assert memory_plan.network_bytes_per_vertex(cfg) == measured
    assert any(p.name.startswith("network-bytes-") for p in entries(tmp_path))
    memory_plan.network_bytes_per_vertex.cache_clear()
    monkeypatch.setattr(memory_plan, "_measured_bytes_per_vertex", lambda c: 1 / 0)
    assert memory_plan.network_bytes_per_vertex(cfg) == measured  # read, not measured
    memory_plan.network_bytes_per_vertex.cache_clear()


def test_the_weights_check_reads_the_param_shapes_it_remembered(monkeypatch, tmp_path):
    from dmd_jax import checkpoints

    path = checkpoints.pretrained_path()
    config = checkpoints.load_model(path).config
    traced = {
        jax_keystr: (tuple(x.shape), np.dtype(x.dtype).name)
        for jax_keystr, x in _flat(checkpoints.abstract_params(config))
    }
    monkeypatch.setenv(ENV, str(tmp_path))
    assert checkpoints.expected_params(config) == traced
    assert any(p.name.startswith("param-shapes-") for p in entries(tmp_path))
    # A second process: read, not traced; and a wrong file is still refused.
    monkeypatch.setattr(checkpoints, "abstract_params", lambda c: 1 / 0)
    bundle = checkpoints.load_model(path)
    assert checkpoints.expected_params(bundle.config) == traced
    params = dict(bundle.params)
    name = next(iter(params))
    params[name] = {**params[name], "extra": np.zeros(2, np.float32)}
    with pytest.raises(ValueError, match="do not match their config"):
        checkpoints.check_params(params, bundle.config, "weights")


def _flat(tree):
    import jax

    return [(jax.tree_util.keystr(p), x) for p, x in jax.tree_util.tree_flatten_with_path(tree)[0]]


# ---------------------------------------------------------------- the trust boundary

posix_only = pytest.mark.skipif(
    not hasattr(os, "getuid"), reason="no os.getuid: the trust checks do not run"
)


def mode(path: Path) -> int:
    return path.stat().st_mode & 0o777


def tiny_program():
    """A small jitted function, its argument and its output (a fresh trace each call)."""
    import jax
    import jax.numpy as jnp

    x = np.linspace(0.0, 1.0, 7, dtype=np.float32)
    jitted = jax.jit(lambda v: jnp.sin(v) * 2.0 + 1.0)
    return jitted, x, np.asarray(jitted(x))


def spy_loads(monkeypatch) -> list:
    """Records every `_load` (an entry read from the store, then deserialised)."""
    loads = []
    real = compile_cache._load

    def load(entries, key):
        loads.append(real(entries, key))
        return loads[-1]

    monkeypatch.setattr(compile_cache, "_load", load)
    return loads


def test_preload_loads_in_the_background_and_never_compiles(monkeypatch, tmp_path):
    # `Program.preload` (what `denoise` starts on a guess of the whole-mesh shapes):
    # on a miss the thread ends without compiling and the call compiles as before; on a
    # hit the call runs the executable the thread loaded, with no second load.
    import jax
    import jax.numpy as jnp

    from dmd_jax import forward

    monkeypatch.setenv(ENV, str(tmp_path / "cache"))
    x = np.linspace(0.0, 1.0, 7, dtype=np.float32)

    def program():
        return forward.Program("tiny", lambda v: jnp.sin(v) * 2.0 + 1.0, "preload-test")

    first = program()
    thread = first.preload(jax.ShapeDtypeStruct(x.shape, x.dtype))
    assert thread is not None
    thread.join()
    assert first._compiled == {} and not entries(tmp_path / "cache" / "programs")
    compiled = len(forward.COMPILED)
    want = np.asarray(first(x))  # compiled and stored by the call
    assert len(forward.COMPILED) == compiled + 1 and first.prepare(x) == "ready"
    assert first.preload(x) is None  # already in this process

    loads = spy_loads(monkeypatch)
    second = program()  # a new process's program
    thread = second.preload(jax.ShapeDtypeStruct(x.shape, x.dtype))
    thread.join()
    assert len(loads) == 1 and loads[0] is not None
    np.testing.assert_array_equal(np.asarray(second(x)), want)
    assert len(loads) == 1 and len(forward.COMPILED) == compiled + 1
    assert second.prepare(x) == "ready"

    monkeypatch.setenv(ENV, "0")  # the cache off: nothing to load
    assert program().preload(x) is None


def cache_warnings(record, where: Path) -> list[str]:
    return [
        str(w.message)
        for w in record
        if issubclass(w.category, UserWarning) and str(where) in str(w.message)
    ]


@posix_only
def test_directories_are_created_private(tmp_path):
    (tmp_path / "home").mkdir(mode=0o755)
    os.chmod(tmp_path / "home", 0o755)
    root = tmp_path / "home" / "new" / "cache"
    for part in ("programs", "xla"):
        EntryStore(root / part, 10_000).put("k", b"payload")
        assert mode(root / part) == 0o700
        assert mode(root / part / "k.bin") == 0o600  # mkstemp's mode, kept by the rename
    assert mode(root) == mode(root.parent) == 0o700  # every level the store made
    assert mode(tmp_path / "home") == 0o755  # an existing parent is left as it was
    old = os.umask(0o002)  # a permissive umask does not widen the mode
    try:
        EntryStore(tmp_path / "wide" / "programs", 10_000).put("k", b"payload")
    finally:
        os.umask(old)
    assert mode(tmp_path / "wide") == mode(tmp_path / "wide" / "programs") == 0o700


@posix_only
@pytest.mark.parametrize("shared", [0o770, 0o707])
def test_group_or_world_writable_directory_is_refused(monkeypatch, tmp_path, shared):
    root = tmp_path / "cache"
    monkeypatch.setenv(ENV, str(root))
    jitted, x, want = tiny_program()
    loads = spy_loads(monkeypatch)
    compile_cache.executable("tiny", jitted, (x,), "trust")  # stored
    compile_cache.executable("tiny", jitted, (x,), "trust")  # and loadable
    assert len(loads) == 2 and loads[0] is None and loads[1] is not None
    programs = root / "programs"
    (entry,) = entries(programs)
    before = entry.read_bytes(), entry.stat().st_mtime_ns
    os.chmod(programs, shared)
    loads.clear()
    with pytest.warns(UserWarning) as record:
        assert compile_cache.store() is None  # the network's programs: as with the cache off
        compiled = compile_cache.executable("tiny", jitted, (x,), "trust")
        np.testing.assert_array_equal(np.asarray(compiled(x)), want)
        store = EntryStore(programs, 10_000)
        assert store.get(entry.stem) is None  # the store itself refuses to read
        store.put("other", b"payload")  # and to write
    assert loads == []  # nothing was loaded
    assert (entry.read_bytes(), entry.stat().st_mtime_ns) == before
    assert [p.name for p in programs.iterdir()] == [entry.name]
    (message,) = cache_warnings(record, programs)  # once, naming the directory
    assert f"writable by group or others (mode {shared:o})" in message


@posix_only
def test_entry_of_another_user_is_not_loaded(monkeypatch, tmp_path):
    root = tmp_path / "cache"
    monkeypatch.setenv(ENV, str(root))
    jitted, x, want = tiny_program()
    loads = spy_loads(monkeypatch)
    compile_cache.executable("tiny", jitted, (x,), "owner")
    (entry,) = entries(root / "programs")
    real_stat = compile_cache._stat

    def other_users_entry(target):
        st = real_stat(target)
        if isinstance(target, int):  # the open entry file (the directory is a path)
            fields = list(st)
            fields[4] = os.getuid() + 1  # st_uid
            return os.stat_result(fields)
        return st

    monkeypatch.setattr(compile_cache, "_stat", other_users_entry)
    loads.clear()
    with pytest.warns(UserWarning) as record:
        for _ in range(2):
            compiled = compile_cache.executable("tiny", jitted, (x,), "owner")
            np.testing.assert_array_equal(np.asarray(compiled(x)), want)
    assert loads == [None, None]  # read, refused, compiled instead: never deserialised
    (message,) = cache_warnings(record, root / "programs")
    assert f"entry {entry.name} is owned by uid {os.getuid() + 1}" in message
    # A group-writable entry (the directory private) is refused the same way.
    monkeypatch.setattr(compile_cache, "_stat", real_stat)
    monkeypatch.setattr(compile_cache, "_warned", set())
    (entry,) = entries(root / "programs")  # rewritten by this user: loads again
    assert compile_cache.executable("tiny", jitted, (x,), "owner") is not None
    assert loads[-1] is not None
    os.chmod(entry, 0o660)
    with pytest.warns(UserWarning, match="is writable by group or others"):
        compile_cache.executable("tiny", jitted, (x,), "owner")
    assert loads[-1] is None


@posix_only
def test_directory_of_another_user_is_refused(monkeypatch, tmp_path):
    root = tmp_path / "cache"
    monkeypatch.setenv(ENV, str(root))
    calls = []
    assert compile_cache.remembered("v", "id", lambda: calls.append(1) or 7) == 7
    monkeypatch.setattr(compile_cache, "_uid", lambda: os.getuid() + 1)
    with pytest.warns(UserWarning, match="is owned by uid") as record:
        assert compile_cache.store() is None
        assert compile_cache.remembered("v", "id", lambda: calls.append(1) or 7) == 7
    assert len(calls) == 2  # computed again: the stored value was not read
    assert len(cache_warnings(record, root / "programs")) == 1
    # JAX's persistent cache is not pointed at an untrusted `xla/` either (checked where
    # this process has no JAX cache of its own: the suite's default, the cache off).
    import jax

    if jax.config.jax_compilation_cache_dir:
        return
    (root / "xla").mkdir(mode=0o700)
    updates = []
    monkeypatch.setattr(jax.config, "update", lambda *a: updates.append(a))
    monkeypatch.setattr(compile_cache, "_jax_configured", False)
    monkeypatch.setenv(compile_cache.ENV_XLA, "1")
    with pytest.warns(UserWarning, match="xla"):
        assert compile_cache.configure_jax() is False
    assert updates == []


@pytest.mark.parametrize("value", [None, "", "0", "no"])
def test_jax_persistent_cache_is_opt_in(tmp_path, monkeypatch, value):
    """JAX's own cache stays off unless DMD_JAX_COMPILE_CACHE_XLA=1 (docs/cold-start.md)."""
    import jax

    monkeypatch.setenv(compile_cache.ENV, str(tmp_path / "cache"))
    if value is None:
        monkeypatch.delenv(compile_cache.ENV_XLA, raising=False)
    else:
        monkeypatch.setenv(compile_cache.ENV_XLA, value)
    updates = []
    monkeypatch.setattr(jax.config, "update", lambda *a: updates.append(a))
    monkeypatch.setattr(compile_cache, "_jax_configured", False)
    assert compile_cache.configure_jax() is False
    assert updates == [] and not (tmp_path / "cache" / "xla").exists()


def test_program_sources_cover_the_network():
    names = {p.name for p in compile_cache.program_sources()}
    assert {"forward.py", "model.py", "ops.py", "geometry.py", "graph.py"} <= names
    folders = {p.parent.name for p in compile_cache.program_sources()}
    assert "train.py" not in names and "cli" not in folders


def _imports_by_ast(file: Path, package: str) -> set[str]:
    import ast

    found = set()
    for node in ast.walk(ast.parse(file.read_bytes())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            target = node.module or ""
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            found |= {target} | {f"{target}.{a.name}" for a in node.names}
    return {n for n in found if n == "dmd_jax" or n.startswith("dmd_jax.")}


def test_program_sources_match_a_walk_of_the_syntax_trees():
    import dmd_jax

    root = Path(dmd_jax.__file__).parent

    def file_of(name):
        rel = Path(*name.split(".")[1:]) if "." in name else Path("__init__")
        for cand in (root / rel.with_suffix(".py"), root / rel / "__init__.py"):
            if cand.is_file():
                return cand
        return None

    seen, todo = {}, ["dmd_jax.forward", "dmd_jax.model"]
    while todo:
        name = todo.pop()
        file = None if name in seen else file_of(name)
        if file is not None:
            seen[name] = file
            package = name if file.name == "__init__.py" else name.rpartition(".")[0]
            todo += sorted(_imports_by_ast(file, package))
    assert compile_cache.program_sources() == sorted(set(seen.values()))


# ---------------------------------------------------------------- fresh processes


@pytest.mark.slow
def test_second_process_loads_and_results_are_bit_identical(tmp_path):
    cache = tmp_path / "cache"
    plain_events, plain = run_program(tmp_path, "plain", "0", patch=True)
    assert plain_events["miss"] == plain_events["hit"] == 0
    assert not (tmp_path / "xdg").exists() and not (tmp_path / "home").exists()  # opt-out
    first_events, first = run_program(tmp_path, "first", cache, patch=True)
    assert first_events["miss"] == 2 and first_events["hit"] == 0  # predict and patch
    assert first_events["has_memory"]
    stored = entries(cache / "programs")
    assert len(stored) == 2
    # JAX's own cache is opt-in (DMD_JAX_COMPILE_CACHE_XLA): nothing of it is written.
    assert not (cache / "xla").exists() or not entries(cache / "xla")
    second_events, second = run_program(tmp_path, "second", cache, patch=True)
    assert second_events["hit"] == 2 and second_events["miss"] == 0
    assert second_events["has_memory"]  # memory_plan's measure works on a loaded program
    # The same bits with and without the cache, loaded or compiled, first call or second.
    for out in (first, second):
        np.testing.assert_array_equal(out, plain)
    np.testing.assert_array_equal(plain[0], plain[1])


@pytest.mark.slow
def test_default_directory_is_the_user_cache(tmp_path):
    events, _ = run_program(tmp_path, "default", None)
    assert events["miss"] == 1
    where = tmp_path / "xdg" / "dmd_jax" / "jax"
    if sys.platform.startswith("linux"):
        assert len(entries(where / "programs")) == 1


@pytest.mark.slow
def test_concurrent_processes_and_damaged_entries(tmp_path):
    cache = tmp_path / "cache"
    _, plain = run_program(tmp_path, "plain", "0")
    # Two processes fill one empty cache at the same time.
    running = [run_program(tmp_path, f"p{k}", cache, wait=False) for k in range(2)]
    for proc, out in running:
        _, result = finish(proc, out)
        np.testing.assert_array_equal(result, plain)
    assert not list(cache.rglob(".tmp-*"))
    events, result = run_program(tmp_path, "after", cache)
    assert events["hit"] == 1 and events["miss"] == 0  # whole entries, loadable
    np.testing.assert_array_equal(result, plain)
    # Every entry damaged: recompiled (not fatal), and written again whole.
    for file in entries(cache):
        data = file.read_bytes()
        file.write_bytes(data[: len(data) // 2])
    events, result = run_program(tmp_path, "damaged", cache)
    assert events["miss"] == 1 and events["hit"] == 0
    np.testing.assert_array_equal(result, plain)
    events, result = run_program(tmp_path, "healed", cache)
    assert events["hit"] == 1 and events["miss"] == 0
    assert events["jax_hit"] > 0
    np.testing.assert_array_equal(result, plain)


@pytest.mark.slow
def test_bound_holds_across_processes(tmp_path):
    cache = tmp_path / "cache"
    # A bound below one network executable: the small programs are kept, bounded; the
    # network is compiled each time and its results do not change.
    _, plain = run_program(tmp_path, "plain", "0")
    for name in ("one", "two"):
        events, result = run_program(tmp_path, name, cache, extra_env={ENV_MAX_MB: "0.05"})
        assert events["hit"] == 0 and events["miss"] == 1
        np.testing.assert_array_equal(result, plain)
        for part in ("programs", "xla"):
            assert sum(p.stat().st_size for p in entries(cache / part)) <= 0.05 * 2**20
