"""Shared fixtures: float64 JAX, a PRNG key, and the public meshes of ../shared."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import numpy as np
import pytest

# The suite never writes compiled programs into the user's cache directory: the cache is
# off unless a run sets DMD_JAX_COMPILE_CACHE (tests/test_compile_cache.py gives its
# processes temporary directories). Set before any dmd_jax module configures JAX.
os.environ.setdefault("DMD_JAX_COMPILE_CACHE", "0")

from dmd_jax.protocol import SHARED_MESHES_ENV, shared_meshes_dir  # noqa: E402

jax.config.update("jax_enable_x64", True)

REPO = Path(__file__).resolve().parents[1]
# $DMD_JAX_SHARED_MESHES, else ../shared/meshes (`dmd_jax.protocol.shared_meshes_dir`).
SHARED_MESHES = shared_meshes_dir()
# Every skip for want of the shared meshes gives a reason that starts with this, so the
# end of the run can count them (`pytest_terminal_summary`).
NEEDS_SHARED = "needs the shared meshes"


def shared_meshes_state(environ=None, folder: Path | None = None) -> str:
    """Where the shared meshes were looked for and what is there, in words, true in
    every case: the variable set, set but empty, or unset (and the old name); the
    folder found with its mesh count, holding no mesh, not a folder, or absent.

    Args:
      environ: the environment to describe (default `os.environ`).
      folder: the folder it leads to (default `shared_meshes_dir()` of the present one).
    """
    from dmd_jax.io import SUPPORTED_EXTENSIONS

    env = os.environ if environ is None else environ
    folder = shared_meshes_dir() if folder is None else Path(folder)
    old = "DMD_SHARED_MESHES"  # the deprecated name `shared_meshes_dir` still reads
    if env.get(SHARED_MESHES_ENV):
        source = f"from ${SHARED_MESHES_ENV}"
    elif env.get(old):
        source = f"from ${old}, the deprecated name of ${SHARED_MESHES_ENV}"
    elif SHARED_MESHES_ENV in env:
        source = f"the default beside the checkout: ${SHARED_MESHES_ENV} is set but empty"
    else:
        source = f"the default beside the checkout: ${SHARED_MESHES_ENV} is unset"
    if folder.is_dir():
        n = sum(1 for p in folder.iterdir() if p.suffix.lower() in SUPPORTED_EXTENSIONS)
        found = (
            f"{folder} found, {n} mesh file{'s' * (n != 1)}"
            if n
            else f"{folder} holds no mesh file"
        )
    elif folder.exists():
        found = f"{folder} is not a folder"
    else:
        found = f"{folder} does not exist"
    return f"{found} ({source})"


def skip_without_shared(missing: Path):
    """Skips the calling test: `missing` (a file or folder of the shared meshes) is absent."""
    pytest.skip(f"{NEEDS_SHARED}: {missing} is absent; {shared_meshes_state()}")


@pytest.hookimpl(hookwrapper=True)
def pytest_terminal_summary(terminalreporter):
    """After the run's summary (just above its counts): how many tests skipped for want of
    the shared meshes, and why."""
    yield
    skipped = terminalreporter.stats.get("skipped", [])
    n = sum(
        1
        for report in skipped
        if isinstance(report.longrepr, tuple) and NEEDS_SHARED in str(report.longrepr[2])
    )
    terminalreporter.write_line(
        f"{n} tests skipped for want of the shared meshes: {shared_meshes_state()}"
    )


@pytest.fixture
def key():
    return jax.random.PRNGKey(0)


@pytest.fixture
def shared_meshes() -> Path:
    if not SHARED_MESHES.is_dir():
        skip_without_shared(SHARED_MESHES)
    return SHARED_MESHES


def shared_mesh_path(name: str) -> Path:
    """Path of a file in ../shared/meshes, skipping the test when it is absent."""
    path = SHARED_MESHES / name
    if not path.is_file():
        skip_without_shared(path)
    return path


def rules_only(bundle):
    """`bundle` without a smoothing controller: its network and its fixed rules, what
    a test of the rules runs whether or not the bundled weights carry a controller."""
    return bundle._replace(controller=None, policy=bundle.policy.replace(controller=False))


def tetrahedron() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], dtype=np.int32)
    return v, f


def icosphere(subdivisions: int = 2, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int32)


def crop_mesh(v: np.ndarray, f: np.ndarray, centre, radius: float):
    """The faces whose centroid lies within `radius` of `centre`, re-indexed: `(v, f)`."""
    keep = np.linalg.norm(v[f].mean(axis=1) - centre, axis=1) < radius
    fk = f[keep]
    used = np.unique(fk)
    remap = np.full(v.shape[0], -1)
    remap[used] = np.arange(used.size)
    return v[used], remap[fk].astype(np.int32)
