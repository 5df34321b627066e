"""The skip line of `make test` (issue 66 item 5): what it says about the shared meshes
is true whether the variable is unset, set, set but empty, or the old name, and whether
the folder holds meshes, holds none, is a file or is absent."""

from __future__ import annotations

from conftest import shared_meshes_state

from dmd_jax.protocol import SHARED_MESHES_ENV


def test_every_case_is_told_as_it_is(tmp_path):
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "a.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    (meshes / "README.md").write_text("not a mesh")
    empty = tmp_path / "empty"
    empty.mkdir()
    a_file = tmp_path / "file.txt"
    a_file.write_text("")
    missing = tmp_path / "missing"
    var = f"${SHARED_MESHES_ENV}"
    cases = [
        (
            {},
            missing,
            f"{missing} does not exist (the default beside the checkout: {var} is unset)",
        ),
        (
            {},
            meshes,
            f"{meshes} found, 1 mesh file (the default beside the checkout: {var} is unset)",
        ),
        (
            {SHARED_MESHES_ENV: ""},
            missing,
            f"{missing} does not exist (the default beside the checkout: {var} is set but empty)",
        ),
        ({SHARED_MESHES_ENV: str(missing)}, missing, f"{missing} does not exist (from {var})"),
        ({SHARED_MESHES_ENV: str(empty)}, empty, f"{empty} holds no mesh file (from {var})"),
        ({SHARED_MESHES_ENV: str(a_file)}, a_file, f"{a_file} is not a folder (from {var})"),
        ({SHARED_MESHES_ENV: str(meshes)}, meshes, f"{meshes} found, 1 mesh file (from {var})"),
        (
            {"DMD_SHARED_MESHES": str(meshes)},
            meshes,
            f"{meshes} found, 1 mesh file (from $DMD_SHARED_MESHES, the deprecated name of {var})",
        ),
    ]
    for environ, folder, expected in cases:
        assert shared_meshes_state(environ, folder) == expected
    # No case claims the variable points elsewhere when it is unset.
    assert "elsewhere" not in shared_meshes_state({}, missing)
