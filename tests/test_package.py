"""The package as a whole: its public names, a light `import dmd_jax`, and no import cycles.

The import graph is read from the source with `ast`, every `import` and `from ... import`
of a `dmd_jax` module counted, those inside functions and `TYPE_CHECKING` blocks too: a
deferred import hides a cycle from Python but not from a reader.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import dmd_jax

PACKAGE_DIR = Path(dmd_jax.__file__).resolve().parent


def module_names() -> dict[str, Path]:
    """Dotted name -> file of every module of the package (packages by `__init__`)."""
    out = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def imports_of(name: str, path: Path, modules: set[str]) -> set[str]:
    """The `dmd_jax` modules that module `name` imports anywhere in its source."""
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target in modules:
                out.add(target)
            # `from dmd_jax import ops` imports the module `dmd_jax.ops`.
            out |= {f"{target}.{a.name}" for a in node.names} & modules
    out.discard(name)
    return out


def import_graph() -> dict[str, set[str]]:
    modules = module_names()
    return {name: imports_of(name, path, set(modules)) for name, path in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected components with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(frozenset(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_cycle_finder_sees_direct_and_longer_cycles():
    graph = {"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"a"}}
    assert set(cycles(graph)) == {frozenset("ab"), frozenset("cde")}
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_import_graph_reads_every_kind_of_import():
    graph = import_graph()
    assert "dmd_jax.graph" in graph["dmd_jax.ops"]  # from dmd_jax.graph import ...
    assert "dmd_jax.model" in graph["dmd_jax.checkpoints"]  # inside a function
    assert "dmd_jax.baselines._common" in graph["dmd_jax.baselines.bilateral_mesh"]


def test_no_import_cycles_inside_dmd_jax():
    found = [sorted(c) for c in cycles(import_graph())]
    assert not found, f"import cycles inside dmd_jax: {found}"


def test_parallel_places_devices_and_knows_no_training():
    graph = import_graph()
    assert not graph["dmd_jax.parallel"], graph["dmd_jax.parallel"]
    assert "dmd_jax.parallel" in graph["dmd_jax.train"]


def test_graph_io_and_mesh_sit_below_the_model():
    """The host-side modules never import JAX-side ones (they stay usable without JAX)."""
    graph = import_graph()
    # dmd_jax.io is a package of one module per format: each of them sits as low.
    io = {name for name in graph if name == "dmd_jax.io" or name.startswith("dmd_jax.io.")}
    assert len(io) > 1, io
    for low in ("dmd_jax.graph", "dmd_jax.mesh", *sorted(io)):
        assert graph[low] <= {"dmd_jax.graph", "dmd_jax.mesh", "dmd_jax.topology"} | io, (
            low,
            graph[low],
        )


def test_topology_is_the_bottom_layer():
    """Edges, adjacency and boundary: NumPy/SciPy only, no other `dmd_jax` module."""
    assert not import_graph()["dmd_jax.topology"]


def test_config_imports_no_model_code():
    """A config is read, checked and written without the model: the names and sizes it
    validates against live in `dmd_jax.constants`, which imports nothing of `dmd_jax`."""
    graph = import_graph()
    config = sorted(m for m in graph if m == "dmd_jax.config" or m.startswith("dmd_jax.config."))
    assert config == [
        "dmd_jax.config",
        "dmd_jax.config.codec",
        "dmd_jax.config.frozen",
        "dmd_jax.config.presets",
        "dmd_jax.config.sections",
    ], config
    for name in config:
        assert graph[name] <= {"dmd_jax.constants", *config}, (name, graph[name])
    assert not graph["dmd_jax.constants"], graph["dmd_jax.constants"]
    code = (
        "import sys, dmd_jax.config; "
        "print(sorted(m for m in sys.modules if m.startswith('dmd_jax')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(["dmd_jax", *config, "dmd_jax.constants"])


def private_baseline_uses(name: str, path: Path) -> list[str]:
    """Where module `name` reaches into `dmd_jax.baselines`' private names.

    Counted: importing a module of `dmd_jax.baselines` whose dotted path has a part with a
    leading underscore (`baselines._common`), importing a leading-underscore name from
    any of them, and reading `alias._name` off a name bound to one of them.
    """
    is_package = path.name == "__init__.py"
    found, aliases = [], set()

    def private(dotted: str) -> bool:
        return any(part.startswith("_") for part in dotted.split("."))

    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("dmd_jax.baselines"):
                    if private(a.name):
                        found.append(f"import {a.name}")
                    aliases.add(a.asname or a.name)
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            for a in node.names:
                target = f"{module}.{a.name}"
                if not target.startswith("dmd_jax.baselines"):
                    continue
                if private(target):
                    found.append(f"from {module} import {a.name}")
                aliases.add(a.asname or a.name)
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
            and isinstance(node.value, ast.Name)
            and node.value.id in aliases
        ):
            found.append(f"{node.value.id}.{node.attr}")
    return found


def test_private_baseline_uses_are_seen(tmp_path):
    code = (
        "from dmd_jax.baselines._common import umbrella_weights\n"
        "from dmd_jax.baselines import _ALL, laplacian\n"
        "import dmd_jax.baselines._common as c\n"
        "from dmd_jax import baselines\n"
        "baselines._ALL, baselines.REGISTRY, laplacian.__name__\n"
    )
    path = tmp_path / "m.py"
    path.write_text(code)
    found = private_baseline_uses("dmd_jax.m", path)
    assert found == [
        "from dmd_jax.baselines._common import umbrella_weights",
        "from dmd_jax.baselines import _ALL",
        "import dmd_jax.baselines._common",
        "baselines._ALL",
    ], found


def test_core_modules_use_no_private_name_of_the_baselines():
    """The shipped denoiser never depends on the comparison methods' internals: what
    both need (topology, geometry) lives below them."""
    bad = {
        name: uses
        for name, path in module_names().items()
        if not (name == "dmd_jax.baselines" or name.startswith("dmd_jax.baselines."))
        and (uses := private_baseline_uses(name, path))
    }
    assert not bad, bad


def test_public_names_resolve_and_are_listed():
    assert "denoise" in dmd_jax.__all__
    for name in dmd_jax.__all__:
        assert getattr(dmd_jax, name) is not None, name
    assert set(dmd_jax.__all__) <= set(dir(dmd_jax))
    from dmd_jax.checkpoints import load_pretrained
    from dmd_jax.inference import denoise

    assert dmd_jax.denoise is denoise and dmd_jax.load_pretrained is load_pretrained
    assert dmd_jax.preset("test").name == "test"
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        dmd_jax.nonexistent  # noqa: B018


def test_import_dmd_jax_loads_neither_jax_nor_flax():
    code = "import sys, dmd_jax; print(sorted({'jax', 'flax', 'numpy'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
